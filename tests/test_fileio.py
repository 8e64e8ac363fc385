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
    from blockloc.errors import BlocklocError
    from blockloc.fileio import atomic_dir
    from blockloc.outdir import MARKER_NAME

    out = tmp_path / "session"
    with atomic_dir(out, "simulated dataset") as tmp:
        (tmp / "sim.json").write_text("1")
    with pytest.raises(RuntimeError):
        with atomic_dir(out, "simulated dataset") as tmp:
            (tmp / "b").write_text("2")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in out.iterdir()) == [MARKER_NAME, "sim.json"]
    with atomic_dir(out, "simulated dataset") as tmp:
        (tmp / "metrics.json").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == [MARKER_NAME, "metrics.json"]
    with pytest.raises(BlocklocError, match="it is blockloc's simulated dataset"):  # another kind
        with atomic_dir(out, "map store") as tmp:
            pass
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
        with atomic_dir(mine, "map store") as tmp:
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


def test_a_marker_is_proven_by_its_content_not_its_name(tmp_path):
    """manifest.json / metrics.json / a marker file of another content prove nothing."""
    from blockloc.errors import BlocklocError
    from blockloc.outdir import MARKER_NAME, check_replaceable, owner

    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.tex").write_text("years of work")
    for name, text in (("manifest.json", "not json"), ("manifest.json", '{"version": 1}'),
                       ("metrics.json", '{"accuracy": 0.9}'), (MARKER_NAME, '{"kind": "map store"}'),
                       (MARKER_NAME, "blockloc")):
        (d / name).write_text(text)
        assert owner(d) is None, (name, text)
        with pytest.raises(BlocklocError, match="did not make"):
            check_replaceable(d)
        (d / name).unlink()


def test_a_blockloc_folder_holding_a_foreign_file_is_not_replaced(tmp_path):
    from blockloc.errors import BlocklocError
    from blockloc.fileio import atomic_dir

    out = tmp_path / "store"
    with atomic_dir(out, "map store") as tmp:
        (tmp / "000.pcd").write_text("x")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(BlocklocError, match=r"holds files blockloc did not write \(notes.txt\)"):
        with atomic_dir(out, "map store") as tmp:
            pass
    assert (out / "notes.txt").read_text() == "mine" and (out / "000.pcd").exists()


def test_stores_written_before_markers_are_proven_by_their_format(tmp_path):
    """A pre-marker map store (manifest with version/kind/entries+sha256) and results folder
    (metrics.json with frames/processed/estimated) stay replaceable; their foreign files do not."""
    import json

    from blockloc.errors import BlocklocError
    from blockloc.outdir import check_replaceable, owner

    store = tmp_path / "store"
    store.mkdir()
    (store / "000.pcd").write_text("x")
    (store / "manifest.json").write_text(json.dumps({"version": 1, "kind": "block", "entries": [
        {"file": "000.pcd", "sha256": "00"}]}))
    assert owner(store) == ("map store", {"manifest.json", "000.pcd", "CentroidCloud.pcd",
                                          "pointcloud_map_metadata.yaml"})
    check_replaceable(store, "--out", ("map store",))
    (store / "thesis.tex").write_text("mine")
    with pytest.raises(BlocklocError, match="thesis.tex"):
        check_replaceable(store, "--out", ("map store",))
    res = tmp_path / "res"
    res.mkdir()
    (res / "metrics.json").write_text(json.dumps({"frames": 3, "processed": 3, "estimated": 3}))
    (res / "poses.tum").write_text("")
    (res / "changes.json").write_text("{}")  # map changes / track --detect-changes write it there
    check_replaceable(res, "--out", ("results folder",))
    with pytest.raises(BlocklocError, match="not a map store .it is blockloc's results folder"):
        check_replaceable(res, "--out", ("map store",), "a map store")


def test_output_lock_names_a_live_holder_and_takes_over_a_dead_one(tmp_path):
    import subprocess
    import sys

    from blockloc.errors import BlocklocError
    from blockloc.outdir import OutputLock

    out = tmp_path / "res"
    # a live holder that runs blockloc (its command line says so)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; print(1, flush=True); time.sleep(60)",
                               "blockloc"], stdout=subprocess.PIPE)
    try:
        holder.stdout.readline()  # it runs (exec done: its command line is its own)
        (tmp_path / ".res.blockloc-lock").write_text(f"pid {holder.pid}\n")
        with pytest.raises(BlocklocError, match=f"in use by another blockloc run .process {holder.pid}"):
            OutputLock(out).acquire()
    finally:
        holder.kill()
        holder.wait()
    with OutputLock(out) as lock:  # its process is gone: taken over
        assert lock.holder() == os.getpid()
    assert not (tmp_path / ".res.blockloc-lock").exists()


def test_free_space_and_writability_are_checked(tmp_path):
    from blockloc.errors import BlocklocError
    from blockloc.outdir import check_free_space, check_writable

    check_writable(tmp_path / "a" / "b")
    check_free_space(tmp_path / "a", 1)
    with pytest.raises(BlocklocError, match=r"--out .*MiB free on its file system, the run needs about"):
        check_free_space(tmp_path / "a", 2**62)


def test_to_jsonable_makes_numpy_and_nan_valid_json():
    import json

    import numpy as np

    from blockloc.fileio import to_jsonable

    got = to_jsonable({1: np.float32(0.5), "a": (np.int64(3), np.array([1.0, np.nan])), "b": float("inf")})
    assert got == {"1": 0.5, "a": [3, [1.0, None]], "b": None}
    json.dumps(got, allow_nan=False)


def test_array_reads_take_turns_parsing_headers(tmp_path, monkeypatch):
    """numpy parses .npy headers with ast.literal_eval, which CPython 3.11 cannot run in two
    threads at once (python/cpython#106905): blockloc's readers must never overlap there."""
    import ast
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    from blockloc.fileio import load_array, load_arrays

    np.save(tmp_path / "a.npy", np.arange(6.0).reshape(2, 3))
    np.savez_compressed(tmp_path / "b.npz", x=np.ones(3), y=np.zeros((2, 2)))
    inside, most, lock = [0], [0], threading.Lock()
    literal_eval = ast.literal_eval

    def watched(src):
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.002)  # long enough for another thread to come in if nothing stops it
        try:
            return literal_eval(src)
        finally:
            with lock:
                inside[0] -= 1

    monkeypatch.setattr(ast, "literal_eval", watched)

    def read(i):
        if i % 2:
            return float(load_array(tmp_path / "a.npy", mmap_mode="r").sum())
        z = load_arrays(tmp_path / "b.npz")
        return float(z["x"].sum() + z["y"].sum())

    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(read, range(40)))
    assert got == [15.0 if i % 2 else 3.0 for i in range(40)]
    assert most[0] == 1


def test_the_package_reads_arrays_only_through_the_turn_taking_readers():
    import re
    from pathlib import Path

    import blockloc

    root = Path(blockloc.__file__).parent
    direct = [f"{p.relative_to(root)}:{n}" for p in root.rglob("*.py") if p.name != "fileio.py"
              for n, line in enumerate(p.read_text().splitlines(), 1) if re.search(r"\bnp\.load\(", line)]
    assert direct == []


def test_on_pythons_with_the_ast_bug_every_parse_takes_turns():
    """python/cpython#106905 (before 3.11.8, and 3.12.0): ``blockloc`` makes ast.parse take one
    lock, so a thread's parse waits while another holds it (numpy headers, tracebacks, numba)."""
    import ast
    import sys
    import threading

    import blockloc

    if not (sys.version_info[:3] < (3, 11, 8) or sys.version_info[:3] == (3, 12, 0)):
        # a Python that parses safely in threads is left as it is
        assert not getattr(ast.parse, "_blockloc_guarded", False)
        return
    assert ast.parse._blockloc_guarded
    done = threading.Event()
    with blockloc.AST_LOCK:
        t = threading.Thread(target=lambda: (ast.parse("x = 1"), done.set()))
        t.start()
        assert not done.wait(0.3)  # waits for the lock
    t.join(5)
    assert done.is_set()


def test_the_umask_is_read_by_one_thread_at_a_time(monkeypatch):
    """Reading the umask sets it to 0 and back: two threads at once could each read the other's 0
    (a world-writable file) and leave the process at 0. Atomic writes run in worker threads."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from blockloc import fileio

    state = {"mask": 0o022, "inside": 0, "most": 0}
    lock = threading.Lock()

    def umask(new):
        with lock:
            state["inside"] += 1
            state["most"] = max(state["most"], state["inside"])
            old, state["mask"] = state["mask"], new
        time.sleep(0.001)  # long enough for another thread to come in if nothing stops it
        with lock:
            state["inside"] -= 1
        return old

    monkeypatch.setattr(fileio.os, "umask", umask)
    with ThreadPoolExecutor(4) as pool:
        seen = list(pool.map(lambda _: fileio._umask(), range(40)))
    assert seen == [0o022] * 40 and state["mask"] == 0o022


@pytest.mark.parametrize("fmt", ["png", "pdf", "svg", "jpg", "tif", "webp", "eps"])
def test_saved_figures_carry_blockloc_s_mark_and_others_do_not(tmp_path, fmt):
    """map plot replaces a file at its --out only when it carries the mark (a user's figure is kept)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from blockloc.fileio import is_blockloc_figure, save_figure

    fig = plt.figure()
    plt.plot([0, 1])
    save_figure(fig, tmp_path / f"ours.{fmt}")
    fig = plt.figure()
    plt.plot([0, 1])
    fig.savefig(tmp_path / f"theirs.{fmt}")
    plt.close(fig)
    assert is_blockloc_figure(tmp_path / f"ours.{fmt}")
    assert not is_blockloc_figure(tmp_path / f"theirs.{fmt}")
    assert not is_blockloc_figure(tmp_path / "absent.png")
