"""Map builds on Dask (blockloc.maps.build_plan + distributed): the serial and the distributed
build write the same bytes, drives merge the same in any order, a killed worker's tasks are rerun,
a failed task leaves nothing behind."""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from blockloc.cli import app
from blockloc.maps.build_plan import Drive, build_map_from_drives
from blockloc.maps.distributed import ProcessCluster, open_executor
from blockloc.maps.store import open_map

from .slow_sequences import FailingSequence, SlowSequence
from .synthetic import MemorySequence, route, world_points

TESTS = Path(__file__).resolve().parents[1]
runner = CliRunner()
KW = dict(block_size_m=30.0, tile_size_m=10.0, voxel_size_m=0.3, keyframe_distance_m=2.0)


@pytest.fixture(autouse=True)
def _reproducible(monkeypatch):
    # manifests carry their creation time; a fixed one makes two builds byte-comparable
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")


def store_files(path) -> dict[str, bytes]:
    """Every file of a store directory: name -> bytes."""
    return {p.name: p.read_bytes() for p in sorted(Path(path).iterdir())}


def leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if ".building-" in p.name)


@pytest.fixture(scope="module")
def world():
    return world_points(extent=(-40, 160), seed=5, density=0.25)


def two_drives(world, cls=MemorySequence, **kw):
    """Out along y = 0 and, a minute later, back along a parallel road 8 m away: the second
    drive merges into and skips the first's blocks."""
    out = route([[0, 0], [110, 0]], speed=4.0, t0=100.0)
    back = route([[110, 8], [0, 8], [0, 40]], speed=4.0, t0=200.0)
    return [Drive.of(cls(world, out, radius=22.0, name="out", **kw)),
            Drive.of(cls(world, back, radius=22.0, name="back", **kw))]


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """A scheduler and two single-threaded workers on 127.0.0.1, each its own process started by
    the dask command lines; stopped by PID at the end."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    cluster = ProcessCluster(2, tmp_path_factory.mktemp("dask"), env=env)
    yield cluster
    pids = cluster.worker_pids + [cluster.scheduler.pid]
    cluster.stop()
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


@pytest.mark.parametrize("kind", ["block", "grid"])
def test_drives_merge_the_same_in_either_order(tmp_path, world, kind):
    a = build_map_from_drives(two_drives(world), kind, tmp_path / "ab", **KW)
    b = build_map_from_drives(two_drives(world)[::-1], kind, tmp_path / "ba", **KW)
    assert store_files(tmp_path / "ab") == store_files(tmp_path / "ba")
    assert a.params["sequence"] == "out + back" == b.params["sequence"]
    assert [d["sequence"] for d in a.params["drives"]] == ["out", "back"]
    one = build_map_from_drives(two_drives(world)[:1], kind, tmp_path / "a", **KW)
    assert a.params["num_keyframes"] > one.params["num_keyframes"]
    assert a.total_points > one.total_points  # the second drive's road is in the map
    if kind == "block":
        ev = a.params["events"]
        assert ev["merge"] + ev["skip"] + ev["tail"] >= 1  # the way back repeats the way out
        kf = np.concatenate([e.keyframes for e in a.entries])
        assert len(np.unique(kf, axis=0)) == a.params["num_keyframes"]


@pytest.mark.parametrize("kind", ["block", "grid"])
def test_running_scheduler_writes_the_serial_bytes(tmp_path, world, dask_cluster, kind):
    build_map_from_drives(two_drives(world), kind, tmp_path / "serial", **KW)
    with open_executor(dask_cluster.address) as ex:
        build_map_from_drives(two_drives(world), kind, tmp_path / "dask", executor=ex, **KW)
    assert store_files(tmp_path / "serial") == store_files(tmp_path / "dask")
    assert leftovers(tmp_path) == []


def test_a_calibrated_build_on_the_cluster_writes_the_serial_bytes(tmp_path, world, dask_cluster):
    """The mounting estimate is a task too: the same estimate, and the same store, from any worker."""
    serial = build_map_from_drives(two_drives(world), "block", tmp_path / "serial", calibrate_mounting=True, **KW)
    with open_executor(dask_cluster.address) as ex:
        build_map_from_drives(two_drives(world), "block", tmp_path / "dask", executor=ex,
                              calibrate_mounting=True, **KW)
    assert sorted(serial.params["mounting"]) == ["back", "out"]
    assert store_files(tmp_path / "serial") == store_files(tmp_path / "dask")
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["block", "grid"])
def test_failed_task_writes_no_manifest(tmp_path, world, dask_cluster, kind):
    drives = two_drives(world, FailingSequence, fail_after=60)
    with open_executor(dask_cluster.address) as ex, pytest.raises(OSError, match="unplugged"):
        build_map_from_drives(drives, kind, tmp_path / "m", executor=ex, **KW)
    assert list(tmp_path.iterdir()) == []  # no store, no temporary build directory
    with pytest.raises(Exception):
        open_map(tmp_path / "m")


def test_killed_worker_build_completes_with_the_same_bytes(tmp_path, world, dask_cluster):
    from distributed import Client

    build_map_from_drives(two_drives(world), "block", tmp_path / "serial", **KW)
    result: dict = {}

    def build():
        try:
            with open_executor(dask_cluster.address) as ex:
                result["store"] = build_map_from_drives(two_drives(world, SlowSequence, delay_s=0.1),
                                                        "block", tmp_path / "dask", executor=ex, **KW)
        except BaseException as exc:  # reported below
            result["error"] = exc

    thread = threading.Thread(target=build)
    thread.start()
    killed = None
    with Client(dask_cluster.address) as client:
        pids = client.run(os.getpid)
        deadline = time.monotonic() + 120
        while killed is None and thread.is_alive() and time.monotonic() < deadline:
            for worker, keys in client.processing().items():
                if any(str(k).startswith("candidate-") for k in keys):
                    killed = pids[worker]
                    os.kill(killed, signal.SIGKILL)
                    break
            time.sleep(0.05)
    thread.join(300)
    assert killed is not None, "no worker was seen working on a candidate block"
    assert "error" not in result, result.get("error")
    assert store_files(tmp_path / "serial") == store_files(tmp_path / "dask")
    assert leftovers(tmp_path) == []
    dask_cluster.add_worker()  # the fixture's other tests expect two workers
    dask_cluster.wait_for_workers(2)


def test_ctrl_c_during_a_dask_build_keeps_the_previous_map(tmp_path, world, dask_cluster):
    """SIGINT (a real one, to this process) while a Dask build replaces a map: the build's tasks
    are cancelled and none runs on afterwards, its temporary directory is gone, and the previous
    map at --out is byte for byte what it was."""
    out = tmp_path / "m"
    full: list[tuple[int, int]] = []
    build_map_from_drives(two_drives(world), "block", out, progress=lambda n, t: full.append((n, t)),
                          **KW)  # the map the build replaces
    before = store_files(out)
    seen: list[tuple[int, int]] = []

    def interrupt() -> None:  # Ctrl-C once a few tasks are done
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not seen or seen[-1][0] < 3):
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)

    with open_executor(dask_cluster.address) as ex:
        threading.Thread(target=interrupt, daemon=True).start()
        with pytest.raises(KeyboardInterrupt):
            build_map_from_drives(two_drives(world, SlowSequence, delay_s=0.1), "block", out,
                                  executor=ex, overwrite=True, progress=lambda n, t: seen.append((n, t)),
                                  **KW)
        assert 3 <= max(n for n, _ in seen) < full[-1][1]  # stopped part way
        running = [k for ks in ex.client.processing().values() for k in ks]
        assert not [k for k in running if str(k).split("-")[0] in ("run", "candidate", "merge", "write")]
    assert store_files(out) == before
    assert leftovers(tmp_path) == []


def test_ctrl_c_stops_a_cli_build_on_the_cluster(tmp_path, dask_cluster):
    """`blockloc map build --cluster ADDR --overwrite` sent SIGINT by its PID mid-build: exit 130
    with one line after the progress lines, the map it was replacing intact, no temporary
    directory left."""
    import subprocess
    import sys

    from tests.faults import tiny

    sess = tiny.write_tiny_session(tmp_path / "sess", n_frames=400, max_points=2000)
    cfg = tiny.write_config(tmp_path / "cfg.yaml")
    out = tmp_path / "map"
    common = ["map", "build", "--seq", str(sess), "--config", str(cfg), "--out", str(out)]
    res = runner.invoke(app, [*common, "--voxel", "0.5"])  # another map than the build's: a replacement shows
    assert res.exit_code == 0, res.output
    before = store_files(out)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS.parent), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-m", "blockloc.cli", *common, "--overwrite",
                             "--cluster", dask_cluster.address], stderr=subprocess.PIPE, text=True, env=env)
    lines = []
    for line in proc.stderr:  # piped: one progress line per 10% of the tasks
        lines.append(line.rstrip("\n"))
        m = re.match(r"block map build tasks: (\d+)/(\d+) ", line)
        if m and int(m[1]) >= 1 and int(m[2]) >= 10:
            proc.send_signal(signal.SIGINT)
            break
    rest = proc.communicate(timeout=120)[1]
    lines += rest.splitlines()
    assert proc.returncode == 130, lines
    assert lines[-1] == "interrupted (SIGINT)" and "Traceback" not in rest, lines
    assert store_files(out) == before
    assert leftovers(tmp_path) == []


def small_world_drives():
    """Two slices of the small world's mapping drive as two drives (scans ray-cast on the fly)."""
    import functools

    from blockloc.sim.stream import open_sim_sequence

    opener = functools.partial(open_sim_sequence, "small", "map", 1)
    return [Drive(f"sim:small/map@1[{a}:{b}]", opener, "sim-small-map-1", a, b)
            for a, b in ((0, 150), (150, 300))]


def test_local2_matches_serial_on_the_small_world(tmp_path):
    kw = dict(block_size_m=12.0, tile_size_m=10.0, keyframe_distance_m=1.5)
    for kind in ("block", "grid"):
        build_map_from_drives(small_world_drives(), kind, tmp_path / f"{kind}_serial", **kw)
    with open_executor("local:2") as ex:
        assert len(ex.client.scheduler_info()["workers"]) == 2
        for kind in ("block", "grid"):
            build_map_from_drives(small_world_drives(), kind, tmp_path / f"{kind}_local2",
                                  executor=ex, **kw)
    for kind in ("block", "grid"):
        serial = store_files(tmp_path / f"{kind}_serial")
        assert serial == store_files(tmp_path / f"{kind}_local2")
        store = open_map(tmp_path / f"{kind}_local2")
        assert store.total_points > 50_000 and len(store) >= 2
    assert leftovers(tmp_path) == []


def test_cli_on_a_running_scheduler(tmp_path, dask_cluster):
    common = ["map", "build", "--seq", "sim:small/map[0:150]", "--seq", "sim:small/map[150:300]",
              "--kind", "block", "--block-size", "12"]
    res = runner.invoke(app, [*common, "--out", str(tmp_path / "serial")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, [*common, "--out", str(tmp_path / "dask"), "--cluster", dask_cluster.address])
    assert res.exit_code == 0, res.output
    assert store_files(tmp_path / "serial") == store_files(tmp_path / "dask")
    assert open_map(tmp_path / "dask").params["sequence"] == "sim:small/map[0:150] + sim:small/map[150:300]"


def test_cli_bad_cluster_and_poses_are_one_line(tmp_path):
    from blockloc.errors import MapError

    res = runner.invoke(app, ["map", "build", "--seq", "sim:small/map", "--out", str(tmp_path / "m"),
                              "--cluster", "lokal:2"])
    assert isinstance(res.exception, MapError) and "local:N" in str(res.exception)
    res = runner.invoke(app, ["map", "build", "--seq", "sim:small/map", "--seq", "sim:small/map",
                              "--poses", "x.tum", "--out", str(tmp_path / "m")])
    assert isinstance(res.exception, MapError) and "one --poses per --seq" in str(res.exception)
    assert not (tmp_path / "m").exists()


def test_cli_drive_slices_with_poses_files(tmp_path):
    """`--seq DIR[A:B]` twice, with one `--poses` each: a trajectory file moved 100 m east for the
    first drive and '-' (the session's own poses) for the second. Each drive is mapped with its
    own poses: the first drive's keyframes move, the second's stay."""
    write_session = pytest.importorskip("blockloc.datasets.nclt").write_session
    from blockloc.datasets.base import ImuData
    from blockloc.trajectory_io import write_tum
    from blockloc.geometry import Trajectory

    world = world_points(extent=(-30, 200), seed=9, density=0.1)
    traj = route([[0, 0], [60, 0], [60, 30]], speed=4.3)  # not a whole number of keyframe steps
    seq = MemorySequence(world, traj, radius=20.0)
    imu = ImuData(traj.stamps, np.zeros((len(traj), 3)), np.zeros((len(traj), 3)))
    try:
        write_session(tmp_path / "sess", date="2012-01-15", frames=seq.frames(), imu=imu, ground_truth=traj)
    except TypeError as exc:  # the writer's signature is the datasets stage's to choose
        pytest.skip(f"write_session signature differs: {exc}")
    moved = traj.poses.copy()
    moved[:, 0, 3] += 100.0
    write_tum(tmp_path / "moved.tum", Trajectory(traj.stamps, moved))
    n = int(np.argmax(traj.poses[:, 0, 3] >= 60.0))  # the turn: drive 1 goes east, drive 2 north
    drives = ["--seq", f"{tmp_path / 'sess'}[0:{n}]", "--seq", f"{tmp_path / 'sess'}[{n}:]"]
    common = ["map", "build", *drives, "--kind", "block", "--block-size", "25"]
    res = runner.invoke(app, [*common, "--out", str(tmp_path / "own")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, [*common, "--poses", str(tmp_path / "moved.tum"), "--poses", "-",
                              "--out", str(tmp_path / "moved")])
    assert res.exit_code == 0, res.output
    own, mv = open_map(tmp_path / "own"), open_map(tmp_path / "moved")
    assert [d["sequence"] for d in own.params["drives"]] == [drives[1], drives[3]]
    # keyframe positions recorded with the blocks (a closing keyframe is in two blocks: unique)
    kf_own = np.unique(np.concatenate([e.keyframes for e in own.entries]), axis=0)
    kf_mv = np.unique(np.concatenate([e.keyframes for e in mv.entries]), axis=0)
    east = kf_own[:, 0] < 60.0  # drive 1's keyframes (before the turn) in the own-poses map
    assert east.sum() >= 20 and (kf_mv[:, 0] > 99.0).sum() == east.sum()
    np.testing.assert_allclose(kf_mv[kf_mv[:, 0] > 99.0] - [100.0, 0, 0], kf_own[east], atol=2e-3)
    north = kf_own[~east]
    np.testing.assert_allclose(kf_mv[kf_mv[:, 0] < 99.0], north, atol=1e-3)


def _raycast_threads_env():
    from blockloc.threads import RAYCAST_THREADS_ENV

    return os.environ.get(RAYCAST_THREADS_ENV)


def test_workers_cast_rays_in_one_thread_unless_told_otherwise(dask_cluster, monkeypatch):
    from distributed import Client

    from blockloc.maps.distributed import _spawn_environ, _worker_environ
    from blockloc.threads import RAYCAST_THREADS_ENV

    with Client(dask_cluster.address) as client:
        assert set(client.run(_raycast_threads_env).values()) == {"1"}
    monkeypatch.delenv(RAYCAST_THREADS_ENV, raising=False)
    assert _spawn_environ()[RAYCAST_THREADS_ENV] == "1"  # a LocalCluster's nannies' workers
    assert _worker_environ({RAYCAST_THREADS_ENV: "2"}) == {}  # the user's value wins


def test_located_tasks_prefer_the_worker_owning_their_share_of_the_build():
    # Neighbouring runs of a drive go to one worker (a soft preference: Dask may move them), so
    # that workers do not each build every scene window of every drive.
    from blockloc.maps.distributed import DaskExecutor

    class Client:
        def __init__(self):
            self.calls = []

        def scheduler_info(self):
            return {"workers": {"tcp://b:2": {}, "tcp://a:1": {}}}

        def submit(self, fn, *args, **kw):
            self.calls.append(kw)
            return kw

    c = Client()
    ex = DaskExecutor(c, "test")
    ex.submit(len, "x", key="k0", locality=0.0)
    ex.submit(len, "x", key="k1", locality=0.49)
    ex.submit(len, "x", key="k2", locality=0.5)
    ex.submit(len, "x", key="k3", locality=0.999)
    ex.submit(len, "x", key="k4")
    assert [kw.get("workers") for kw in c.calls] == [["tcp://a:1"], ["tcp://a:1"], ["tcp://b:2"], ["tcp://b:2"], None]
    assert all(kw["allow_other_workers"] for kw in c.calls[:4])


def _task_clock_name():
    from blockloc.maps.build_tasks import _cpu_clock

    return _cpu_clock().__name__


def test_task_cpu_counts_the_threads_a_task_starts_when_it_runs_alone(dask_cluster):
    # One task at a time (a serial build, a one-thread worker): the process clock, so open3d's
    # ray-cast threads are charged to the task (the thread clock missed them in serial builds);
    # tasks side by side in one process: each its own thread's clock.
    from distributed import Client, LocalCluster

    assert _task_clock_name() == "process_time"
    with Client(dask_cluster.address) as client:
        assert client.submit(_task_clock_name, pure=False).result() == "process_time"
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as lc, \
            Client(lc) as client:
        assert client.submit(_task_clock_name, pure=False).result() == "thread_time"
