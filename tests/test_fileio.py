import os

import pytest

from blockloc.fileio import atomic_path, atomic_write_bytes, atomic_write_text


def test_atomic_write_replaces_and_uses_normal_permissions(tmp_path):
    path = tmp_path / "sub" / "a.txt"
    atomic_write_text(path, "one")
    atomic_write_bytes(path, b"two")
    assert path.read_bytes() == b"two"
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    assert [p.name for p in path.parent.iterdir()] == ["a.txt"]


def test_failed_write_leaves_the_old_file_and_no_temp(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_dir_replaces_whole_or_not_at_all(tmp_path):
    from blockloc.fileio import atomic_dir

    out = tmp_path / "session"
    with atomic_dir(out) as tmp:
        (tmp / "sim.json").write_text("1")  # blockloc's own output carries a marker
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as tmp:
            (tmp / "b").write_text("2")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in out.iterdir()) == ["sim.json"]
    with atomic_dir(out) as tmp:
        (tmp / "metrics.json").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["session"]


def test_a_directory_blockloc_did_not_make_is_never_replaced(tmp_path):
    from blockloc.errors import BlocklocError
    from blockloc.fileio import atomic_dir, check_replaceable, is_blockloc_output

    mine = tmp_path / "thesis"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    assert not is_blockloc_output(mine) and is_blockloc_output(tmp_path / "nothing") is False
    with pytest.raises(BlocklocError, match=r"--out .*thesis: a directory blockloc did not make"):
        check_replaceable(mine)
    with pytest.raises(BlocklocError, match="did not make"):
        with atomic_dir(mine) as tmp:
            (tmp / "manifest.json").write_text("{}")
    assert (mine / "thesis.tex").read_text() == "years of work"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["thesis"]  # the temp dir is gone too
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    with pytest.raises(BlocklocError, match="not a directory"):
        check_replaceable(a_file)
    empty = tmp_path / "empty"
    empty.mkdir()
    check_replaceable(empty)  # an empty directory may be written into


def test_to_jsonable_makes_numpy_and_nan_valid_json():
    import json

    import numpy as np

    from blockloc.fileio import to_jsonable

    got = to_jsonable({1: np.float32(0.5), "a": (np.int64(3), np.array([1.0, np.nan])), "b": float("inf")})
    assert got == {"1": 0.5, "a": [3, [1.0, None]], "b": None}
    json.dumps(got, allow_nan=False)
