from blockloc.cache import cache_root, fingerprint


def test_fingerprint_follows_code_and_params(tmp_path, monkeypatch):
    pkg = tmp_path / "fp_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    first = fingerprint("fp_pkg", params=(1, 2))
    assert fingerprint("fp_pkg", params=(1, 2)) == first
    assert fingerprint("fp_pkg", params=(1, 3)) != first
    (pkg / "a.py").write_text("X = 2\n")
    assert fingerprint("fp_pkg", params=(1, 2)) != first


def test_cache_root_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    assert cache_root() == tmp_path
