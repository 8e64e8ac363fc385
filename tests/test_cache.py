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


def test_disk_memo_builds_once_then_loads_and_rebuilds_a_damaged_entry(tmp_path, monkeypatch):
    import pickle

    from blockloc.cache import disk_memo

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    calls = []

    def build():
        calls.append(1)
        return {"a": list(range(5))}

    assert disk_memo("thing", "k1", build, min_build_s=0.0) == {"a": [0, 1, 2, 3, 4]}
    path = tmp_path / "memo" / "thing-k1.pkl"
    assert path.is_file() and pickle.loads(path.read_bytes()) == {"a": [0, 1, 2, 3, 4]}
    assert disk_memo("thing", "k1", build, min_build_s=0.0) == {"a": [0, 1, 2, 3, 4]} and len(calls) == 1
    assert disk_memo("thing", "k2", build, min_build_s=0.0) and len(calls) == 2  # another key
    path.write_bytes(b"not a pickle")
    assert disk_memo("thing", "k1", build, min_build_s=0.0) == {"a": [0, 1, 2, 3, 4]} and len(calls) == 3
    assert pickle.loads(path.read_bytes()) == {"a": [0, 1, 2, 3, 4]}  # replaced by the rebuilt one
    # quick builds are not written
    disk_memo("quick", "k", lambda: 1, min_build_s=60.0)
    assert not (tmp_path / "memo" / "quick-k.pkl").exists()


def test_a_world_from_the_disk_cache_is_the_world_built_from_its_seed(tmp_path, monkeypatch):
    import pickle

    from blockloc.cache import disk_memo
    from blockloc.sim.presets import get_preset
    from blockloc.sim.world import build_world

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    p = get_preset("small")
    disk_memo("world", "t", lambda: build_world(p, 3), min_build_s=0.0)
    loaded = disk_memo("world", "t", lambda: (_ for _ in ()).throw(AssertionError("rebuilt")), min_build_s=0.0)
    fresh = build_world(p, 3)
    assert _same(loaded, fresh)
    fresh.terrain.waves = fresh.terrain.waves + 1e-9  # the comparison sees a change
    assert not _same(loaded, fresh)


def _same(a, b) -> bool:
    """Structural equality: arrays by value (NaN equal), objects by their attributes."""
    import numpy as np

    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype
                and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dict__") and not callable(a):
        return _same(vars(a), vars(b))
    if hasattr(a, "__slots__"):
        return all(_same(getattr(a, k), getattr(b, k)) for k in a.__slots__)
    return a == b


def test_disk_memo_removes_only_entries_of_its_name_under_older_keys(tmp_path, monkeypatch):
    from blockloc.cache import disk_memo

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    memo = tmp_path / "memo"
    memo.mkdir()
    stale = memo / "world-city-1-0123456789.pkl"
    others = [memo / "world-city-12-0123456789.pkl",  # another name (seed 12)
              memo / "world-city-1-notakey.pkl",      # not a fingerprint
              memo / "world-city-1-0123456789.txt",   # not an entry
              memo / "notes.pkl"]
    for f in [stale, *others]:
        f.write_bytes(b"x")
    assert disk_memo("world-city-1", "abcdef0123", lambda: 42, min_build_s=0.0) == 42
    assert (memo / "world-city-1-abcdef0123.pkl").is_file()
    assert not stale.exists()
    assert all(f.exists() for f in others)
    # loading an entry removes nothing
    stale.write_bytes(b"x")
    assert disk_memo("world-city-1", "abcdef0123", lambda: 0, min_build_s=0.0) == 42
    assert stale.exists()


def test_disk_tiles_keep_arrays_and_drop_only_older_keys_of_their_name(tmp_path, monkeypatch):
    import numpy as np

    from blockloc.cache import DiskTiles

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    memo = tmp_path / "memo"
    old = memo / "material-city-1-0123456789"
    other = memo / "material-city-12-0123456789"  # another name (seed 12), not older code
    mine = memo / "notes-0123456789"  # a directory blockloc did not name this way
    for d in (old, other, mine):
        d.mkdir(parents=True)
    tiles = DiskTiles("material-city-1", "abcdefabcd")
    assert tiles.get("0_0") is None
    a = np.arange(12, dtype=np.uint8).reshape(3, 4)
    tiles.put("0_0", a)
    assert np.array_equal(DiskTiles("material-city-1", "abcdefabcd").get("0_0"), a)
    assert not old.exists() and other.exists() and mine.exists()


def test_a_second_process_asking_for_the_demo_map_waits_for_the_first_builder(tmp_path):
    """ensure_block_map's lock: while one holder builds, another waits (and says so) instead of
    building the same map at the same time; it goes on when the first lets go."""
    import threading
    import time

    from blockloc.app.runs import _build_lock

    path = tmp_path / "maps" / "small_1_block-abc"
    said: list[str] = []
    events: list[str] = []

    def second():
        with _build_lock(path, said.append):
            events.append("second in")

    with _build_lock(path, said.append):
        t = threading.Thread(target=second)
        t.start()
        time.sleep(0.3)
        events.append("first out")
    t.join(5)
    assert events == ["first out", "second in"]
    assert len(said) == 1 and "another process is building" in said[0] and str(path) in said[0]
