"""The live node against ``track`` on the same session and map (issue 39).

    python -m bench.live                          # 1x and 3x, the whole small loc session; docs/bench/live.md
    python -m bench.live --frames 300 --rates 1,3
    python -m bench.live --preset campus --minutes 10 --rates 0.5 --data /work/data2/node   # its own section

``blockloc play`` publishes the cached small world's loc session (its first scans written once in
NCLT layout: the simulator renders too slowly to play live) at each rate into ``blockloc
node`` (both as subprocesses, DDS on loopback with multicast off); a third participant here
listens to the node's /blockloc/pose and /diagnostics. A last run at 1x sends an /initialpose
10 m and 90 degrees wrong half-way (``--no-initialpose``: not). Then ``blockloc track`` runs the
same frames in the same map. Both start from the same global init around the demo's noisy hint
(``--init-pose``). Reported: ATE (position RMSE against the ground truth at each pose stamp, no
alignment: both are in the map frame), poses published against scans played, scans the node
dropped and caught up on after its global init, latency from a scan's stamp (its sweep's end in
the player's pace, ``play --pace-file``) to its pose received here, and from its arrival at the
node to its pose being published (the node's own ``latency_ms`` in /diagnostics), CPU seconds per
scan (user + system of the whole process, from wait4) and peak RSS (ru_maxrss), beside track's;
the time from the wrong /initialpose to the verified pose that follows it.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _env() -> dict:
    from blockloc.ros2.dds import cyclone_config

    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
                CYCLONEDDS_URI=cyclone_config("localhost"), ROS_DOMAIN_ID=str(90 + os.getpid() % 40))


def _start(args: list[str], env: dict, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "blockloc.cli", *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=open(log, "w"), cwd=ROOT)


def _reap(proc: subprocess.Popen) -> tuple[int, float, float]:
    """(exit code, CPU seconds user+system, peak RSS MB) of a finished child."""
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024.0


def _ate(poses_tum: Path, gt) -> tuple[float, int]:
    if not poses_tum.exists():  # the run ended before a pose (e.g. no verified global init)
        return float("nan"), 0
    d = np.loadtxt(poses_tum, ndmin=2)
    if not len(d):
        return float("nan"), 0
    inside = (d[:, 0] >= gt.stamps[0]) & (d[:, 0] <= gt.stamps[-1])
    d = d[inside]
    e = np.linalg.norm(d[:, 1:4] - gt.interpolate(d[:, 0])[:, :3, 3], axis=1)
    return float(np.sqrt(np.mean(e ** 2))), len(d)


def _counters(out: Path) -> dict:
    """Failures (tracking lost), recoveries, block switches and rejected scans of a run folder's metrics."""
    import json

    try:
        m = json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError):
        return {}
    return {k: m.get(k) for k in ("failures", "recoveries", "switches", "rejected")}


def _due(anchor: dict, stamp: float, sweep_end_s: float) -> float:
    """CLOCK_MONOTONIC second a scan stamped ``stamp`` was due at the node: the end of its sweep
    (``stamp`` + its last point's offset, when a real driver could publish it) in the player's
    pace (``play --pace-file``)."""
    return anchor["monotonic"] + (stamp + sweep_end_s - anchor["stamp"]) / anchor["rate"]


def run_node(world, hint: str, rate: float, frames: int, work: Path, env: dict, sweep_end: dict,
             initialpose_after: int | None = None, detect: bool = False, stride: int = 1) -> dict:
    """One ``blockloc play`` into ``blockloc node`` at ``rate``; with ``initialpose_after``, an
    /initialpose 10 m and 90 degrees off the ground truth is sent once the node published that many poses."""
    import json
    import threading

    from blockloc.geometry import rpy_to_R
    from blockloc.ros2 import convert
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m
    from blockloc.ros2.messages import time_to_stamp

    tag = f"{rate:g}x" + ("_initialpose" if initialpose_after is not None else "") + ("_detect" if detect else "")
    out = work / f"node_{tag}"
    node = _start(["node", "--map", str(world.block_map), "--config", "sim", "--init-pose", hint, "--out", str(out)]
                  + (["--detect-changes", "--changes-stride", str(stride)] if detect else []), env, work / f"node_{tag}.log")
    os.environ.update({k: env[k] for k in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")})
    listener = d.Dds()
    diags: list = []
    poses: list = []  # (CLOCK_MONOTONIC s received, message)
    truth: list = []
    listener.reader("/diagnostics", m.DiagnosticArray, lambda x: diags.append((time.monotonic(), x)), d.RELIABLE)
    listener.reader("/blockloc/pose", m.PoseWithCovarianceStamped, lambda x: poses.append((time.monotonic(), x)),
                    d.RELIABLE)
    listener.reader("/blockloc/ground_truth", m.Odometry, truth.append, d.RELIABLE)
    initialpose = listener.writer("/initialpose", m.PoseWithCovarianceStamped, d.RELIABLE)
    sent: list = []

    def send_initialpose() -> None:
        if not truth:
            return
        T = convert.matrix_of(truth[-1].pose.pose.position, truth[-1].pose.pose.orientation)
        wrong = T.copy()
        heading = T[:2, 0] / np.linalg.norm(T[:2, 0])
        wrong[:2, 3] += 10.0 * np.array([-heading[1], heading[0]])  # 10 m to the robot's left
        wrong[:3, :3] = rpy_to_R(0.0, 0.0, np.pi / 2) @ T[:3, :3]  # and turned 90 degrees
        sent.append(time.monotonic())
        initialpose.write(convert.pose_with_covariance(wrong, None, 0.0, "map"))

    pace = work / f"pace_{tag}.json"
    try:
        t0 = time.monotonic()
        while "listening on" not in (work / f"node_{tag}.log").read_text():
            if node.poll() is not None or time.monotonic() - t0 > 300:
                raise SystemExit(f"the node did not start: {(work / f'node_{tag}.log').read_text()[-2000:]}")
            time.sleep(0.2)
        play = _start(["play", "--seq", world.session, "--config", "sim", "--rate", f"{rate:g}", "--max-frames",
                       str(frames), "--pace-file", str(pace)], env, work / f"play_{tag}.log")
        t_play = time.monotonic()
        done = threading.Event()

        def when_tracking() -> None:
            while not done.is_set() and len(poses) < initialpose_after:
                time.sleep(0.01)
            if not done.is_set():
                send_initialpose()

        if initialpose_after is not None:
            threading.Thread(target=when_tracking, daemon=True).start()
        play_code, _, _ = _reap(play)
        play_s = time.monotonic() - t_play
        done.set()
        time.sleep(3.0)  # the node finishes its queue
        # SIGTERM (the node ends it as Ctrl-C, exit 143): a bench started in the background by a
        # shell has SIGINT ignored, and so have its children
        node.send_signal(signal.SIGTERM)
        code, cpu_s, rss_mb = _reap(node)
    finally:
        if node.poll() is None:
            node.kill()
        listener.close()
    anchor = json.loads(pace.read_text())
    values = [(t, {kv.key: kv.value for kv in x.status[0].values}) for t, x in diags]
    scans = [v for _, v in values if "latency_ms" in v]
    steady = {round(float(v["stamp"]), 6) for v in scans if v.get("catching_up") == "False"
              and v.get("state") == "ok"}
    latency = np.array([float(v["latency_ms"]) for v in scans])
    # stamp -> pose: the sweep's end in the player's pace to the pose received here
    stamp_ms = np.array([1e3 * (t - _due(anchor, s, sweep_end[round(s, 6)]))
                         for t, x in poses for s in [time_to_stamp(x.header.stamp)] if round(s, 6) in steady])
    last = values[-1][1] if values else {}
    gt = world_gt(world)
    ate, n = _ate(out / "poses.tum", gt)
    processed = int(last.get("scans_processed", 0))
    s0 = next(iter(sweep_end))  # the first scan's: from when it was due to the first pose
    first_pose_s = poses[0][0] - _due(anchor, s0, sweep_end[s0]) if poses else float("nan")
    res = {**_counters(out), "rate": rate, "play_exit": play_code, "node_exit": code, "play_s": play_s, "ate_m": ate,
           "poses": len(poses), "poses_file": n, "scans_received": int(last.get("scans_received", 0)),
           "processed": processed, "dropped": int(last.get("dropped_scans", 0)),
           "caught_up": int(last.get("caught_up_scans", 0)), "first_pose_s": first_pose_s,
           "latency_ms_median": float(np.median(latency)) if len(latency) else float("nan"),
           "latency_ms_p99": float(np.percentile(latency, 99)) if len(latency) else float("nan"),
           "stamp_latency_ms_median": float(np.median(stamp_ms)) if len(stamp_ms) else float("nan"),
           "stamp_latency_ms_p99": float(np.percentile(stamp_ms, 99)) if len(stamp_ms) else float("nan"),
           "stamp_latency_n": int(len(stamp_ms)),
           "cpu_s": cpu_s, "cpu_ms_per_scan": 1e3 * cpu_s / max(processed, 1), "peak_rss_mb": rss_mb}
    if initialpose_after is not None:
        res.update(_initialpose_outcome(sent, values, poses, gt))
    if detect:
        res["detect"] = True
        if (out / "changes.json").is_file():
            doc = json.loads((out / "changes.json").read_text())
            res["changes"] = {k: doc[k] for k in ("frames_trusted", "scans_used", "scans_rejected")}
            res["changes"].update({k: doc["cost"][k] for k in ("per_scan_cpu_ms", "per_scan_wall_ms", "scans_dropped",
                                                                "max_scans_waiting", "node_hook_cpu_ms", "load_1min")})
    return res


def _initialpose_outcome(sent: list, values: list, poses: list, gt) -> dict:
    """Seconds from the /initialpose to the first pose of the global init it started (verified),
    and the largest error of any pose published after it."""
    from blockloc.ros2.messages import time_to_stamp

    if not sent:
        return {"initialpose_sent": False}
    t_sent = sent[0]
    inits = [v for t, v in values if t > t_sent and int(v.get("verified_inits", 0)) >= 2 and v.get("state") == "ok"]
    first = None
    if inits:
        s0 = float(inits[0]["stamp"])
        first = next((t for t, x in poses if abs(time_to_stamp(x.header.stamp) - s0) < 1e-6), None)
    after = [x for t, x in poses if t > t_sent]
    err = [float(np.linalg.norm(np.array([x.pose.pose.position.x, x.pose.pose.position.y, x.pose.pose.position.z])
                                - gt.interpolate(np.array([time_to_stamp(x.header.stamp)]))[0][:3, 3])) for x in after]
    return {"initialpose_sent": True, "initialpose_verified_s": (first - t_sent) if first is not None else float("nan"),
            "initialpose_max_err_m": max(err) if err else float("nan"), "initialpose_poses_after": len(after)}


def sweep_ends(session: Path, frames: int) -> dict:
    """{round(stamp, 6): the last point's time offset, s} of the first ``frames`` scans (cached beside them)."""
    cache = session / "sweep_end.npy"
    if cache.exists():
        a = np.load(cache)
    else:
        from blockloc.datasets.nclt import NcltSequence

        seq = NcltSequence(session)
        a = np.array([(f.stamp, float(np.max(f.time_offsets))) for f in seq.frames(0, frames)])
        np.save(cache, a)
    return {round(float(s), 6): float(e) for s, e in a[:frames]}


def run_setup(seq, session: Path, frames: int) -> tuple:
    """What a node run and its track run share: the sweeps' end stamps of the recorded ``session``,
    the noisy ``X,Y`` hint both start from, the loopback DDS environment, the start time and load."""
    from blockloc.app.runs import noisy_hint

    x, y, _ = noisy_hint(seq)
    return (sweep_ends(session, frames), f"{x:.2f},{y:.2f}", _env(),
            time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), os.getloadavg()[0])


def recorded_session(seq_name: str, frames: int, tag: str, root: Path | None = None) -> Path:
    """The first ``frames`` scans of ``seq_name`` written once in NCLT layout (cached under
    ``root``, default the cache's bench folder): the simulator renders a scan in ~0.05-3 s, too
    slow to play at 10 Hz, and ``track`` then reads the same files as the player."""
    from blockloc.cache import cache_root
    from blockloc.app.catalog import open_sequence
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import write_session

    out = (root or cache_root() / "bench") / f"live_{tag}_{frames}"
    if (out / "done").exists():
        return out
    seq = open_sequence(seq_name)
    stamps = np.asarray(seq.frame_stamps())[:frames]
    imu = seq.imu()
    keep = (imu.t >= stamps[0] - 1.0) & (imu.t <= stamps[-1] + 0.5)
    info = seq.info
    write_session(out, date="2026-01-01", frames=seq.frames(0, frames), imu=ImuData(imu.t[keep], imu.acc[keep],
                  imu.gyro[keep]), ground_truth=seq.ground_truth(), T_body_lidar=info.T_body_lidar,
                  T_body_imu=info.T_body_imu, gravity_map=info.gravity_map)
    (out / "done").write_text("")
    return out


def world_gt(world):
    from blockloc.app.catalog import open_sequence

    return open_sequence(world.session).ground_truth()


def run_track(world, hint: str, frames: int, work: Path, env: dict) -> dict:
    out = work / "track"
    t0 = time.monotonic()
    proc = _start(["track", "--seq", world.session, "--map", str(world.block_map), "--config", "sim", "--init-pose", hint,
                   "--max-frames", str(frames), "--out", str(out), "--no-record"], env, work / "track.log")
    code, cpu_s, rss_mb = _reap(proc)
    wall = time.monotonic() - t0
    ate, n = _ate(out / "poses.tum", world_gt(world))
    return {**_counters(out), "exit": code, "wall_s": wall, "ate_m": ate, "poses": n, "cpu_s": cpu_s,
            "cpu_ms_per_scan": 1e3 * cpu_s / max(frames, 1), "peak_rss_mb": rss_mb}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.live")
    ap.add_argument("--frames", type=int, default=None, help="scans to play (default: the whole session)")
    ap.add_argument("--rates", default="1,3")
    ap.add_argument("--no-initialpose", action="store_true", help="skip the run with a wrong /initialpose")
    ap.add_argument("--no-fragment", action="store_true")
    ap.add_argument("--preset", choices=("small", "campus"), default="small",
                    help="campus: the campus world's loc session for --minutes of sensor time at --rates (one rate)")
    ap.add_argument("--minutes", type=float, default=10.0, help="campus: minutes of sensor time played")
    ap.add_argument("--seed", type=int, default=1, help="campus: the world's seed")
    ap.add_argument("--map", default=None, help="campus: block map (default: built once with the defaults, cached)")
    ap.add_argument("--data", default=None, help="campus: where the recorded session goes (default: the cache)")
    ap.add_argument("--detect-changes", action="store_true",
                    help="each rate twice, the node without and with --detect-changes (no /initialpose, no track); "
                         "its own section")
    ap.add_argument("--changes-stride", type=int, default=1, help="--detect-changes: the node's --changes-stride")
    a = ap.parse_args(argv)
    if a.preset == "campus":
        return main_campus(a)
    from blockloc.app.runs import prepare_small_world
    from blockloc.app.catalog import open_sequence

    world, cfg = prepare_small_world()
    seq = open_sequence(world.loc, dataset_cfg=cfg.dataset)
    frames = min(a.frames or len(seq), len(seq))
    session = recorded_session(world.loc, frames, "small_loc1")
    world.session = str(session)
    sweep_end, hint, env, started, load_start = run_setup(seq, session, frames)
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        work = Path(tmp)
        nodes = []
        if a.detect_changes:
            for rate in [float(r) for r in a.rates.split(",")]:
                for detect in (False, True):
                    nodes.append(run_node(world, hint, rate, frames, work, env, sweep_end, detect=detect,
                                          stride=a.changes_stride))
                    print(nodes[-1], flush=True)
            return 0 if a.no_fragment else _detect_section(a, nodes, frames, hint, started, load_start)
        for rate in [float(r) for r in a.rates.split(",")]:
            nodes.append(run_node(world, hint, rate, frames, work, env, sweep_end))
            print(nodes[-1], flush=True)
        reinit = None
        if not a.no_initialpose:
            # while tracking: once the node published poses for a third of the scans
            reinit = run_node(world, hint, 1.0, frames, work, env, sweep_end, initialpose_after=frames // 3)
            print({"initialpose": reinit}, flush=True)
        track = run_track(world, hint, frames, work, env)
        print({"track": track}, flush=True)
    if a.no_fragment:
        return 0
    from bench.__main__ import machine

    cmd = "python -m bench.live" + (f" --frames {a.frames}" if a.frames else "") + \
        (f" --rates {a.rates}" if a.rates != "1,3" else "") + (" --no-initialpose" if a.no_initialpose else "")
    lines = ["## The live node (ROS 2 over DDS) against track", "",
             f"`{cmd}`, {started}, on {machine()} (1-min load average {load_start:.1f} at the start, "
             f"{os.getloadavg()[0]:.1f} at the end; the machine is shared). The small world's loc session "
             "(`sim:small/loc@1`, seed 1, written once in NCLT layout), its cached block map, "
             f"{frames} scans played by `blockloc play` into `blockloc node` over loopback DDS; both start from "
             f"global init around `--init-pose {hint}` (the demo's noisy hint). ATE: position RMSE against "
             "ground truth, no alignment. Latency from the stamp: from the end of the scan's sweep (its stamp, "
             "the sweep's start, + its last point's time offset: the moment a driver can publish it) in the "
             "player's pace (`play --pace-file`: the CLOCK_MONOTONIC second a stamp was due) to its pose "
             "received on /blockloc/pose by a third process, over the scans tracked in step (not those that "
             "waited through the first global init and were caught up on: their count is the caught-up "
             "column); it includes the player's own lateness. Latency from arrival: the node's `latency_ms`. "
             "First pose: from the first scan's sweep end to the first pose received (the global init "
             "included). CPU: user + system seconds of the whole process over the scans it processed "
             "(wait4); RSS: peak.", "",
             "| run | play took [s] | scans played / received / processed / dropped / caught up | poses | ATE [m] "
             "| first pose [s] | latency from stamp median / p99 [ms] (scans) | latency from arrival median / p99 [ms] "
             "| CPU per scan [ms] | peak RSS [MB] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in nodes + ([reinit] if reinit is not None else []):
        name = f"node at {r['rate']:g}x" + (" + /initialpose" if r.get("initialpose_sent") is not None else "")
        lines.append(f"| {name} | {r['play_s']:.0f} | {frames} / {r['scans_received']} / {r['processed']} / "
                     f"{r['dropped']} / {r['caught_up']} | {r['poses']} | {r['ate_m']:.3f} | {r['first_pose_s']:.1f} | "
                     f"{r['stamp_latency_ms_median']:.0f} / {r['stamp_latency_ms_p99']:.0f} ({r['stamp_latency_n']}) | "
                     f"{r['latency_ms_median']:.0f} / {r['latency_ms_p99']:.0f} | "
                     f"{r['cpu_ms_per_scan']:.0f} | {r['peak_rss_mb']:.0f} |")
    lines.append(f"| track | - ({track['wall_s']:.0f} wall) | {frames} / {frames} / {frames} / 0 / - | {track['poses']} | "
                 f"{track['ate_m']:.3f} | - | - | - | "
                 f"{track['cpu_ms_per_scan']:.0f} | {track['peak_rss_mb']:.0f} |")
    if reinit is not None:
        lines += ["", f"/initialpose 10 m to the robot's left and turned 90 degrees, sent once the node had published "
                  f"{frames // 3} poses (1x): "
                  + (f"the node's first pose from the global init around it was received "
                     f"{reinit['initialpose_verified_s']:.2f} s after it was sent (issue 39: within 3 s); the largest "
                     f"error of the {reinit['initialpose_poses_after']} poses published after it: "
                     f"{reinit['initialpose_max_err_m']:.3f} m." if reinit.get("initialpose_sent") else
                     "not sent (no ground truth received).")]
    lines += ["", "One run each (no repeats): the figures move with the machine's load. Scans played but not "
              "received were overwritten in the node's DDS reader (best effort; its history holds 40 scans and "
              "2000 IMU samples) while its process did not get the CPU; the node counts only the scans it dropped "
              "itself. With `play took` above the scans' 0.1 s x count / rate, the player itself ran late: the "
              "latency from the stamp then measures the machine, not the node."]
    print(write_section(lines))
    return 0


CAMPUS_TITLE = "## The live node on the campus world against track"


def _detect_section(a, nodes: list, frames: int, hint: str, started: str, load_start: float) -> int:
    """docs/bench/live.md: the node's latency without and with ``--detect-changes`` (issue 43)."""
    from bench.__main__ import machine

    cmd = f"python -m bench.live --detect-changes --frames {frames} --rates {a.rates}" + \
        (f" --changes-stride {a.changes_stride}" if a.changes_stride != 1 else "")
    lines = [f"## The live node with --detect-changes --changes-stride {a.changes_stride} (issue 43)", "",
             f"`{cmd}`, {started}, on {machine()} (1-min load average {load_start:.1f} at the start, "
             f"{os.getloadavg()[0]:.1f} at the end; the machine is shared). The small world's loc session "
             f"(`sim:small/loc@1`, seed 1), its cached block map (unchanged: the detector finds little, its cost is "
             f"the point), {frames} scans played into `blockloc node --init-pose {hint}`, once without and once "
             f"with `--detect-changes --changes-stride {a.changes_stride}`. Latency from arrival: the node's `latency_ms` (scan arrival to "
             "pose published), over every scan (those that waited through the first global init and were caught up "
             "on included: the p99); latency from the stamp: the sweep's end in the player's pace to the pose "
             "received by a third process, over the scans tracked in step (their count in brackets); CPU: user + system of the whole node process per scan processed. Detector: its "
             "own thread's CPU and wall time per scan used (changes.json `cost`), the scans dropped for "
             "detection (queue of 40) and the node thread's CPU time in the hook.", "",
             "| run | scans received / processed / dropped | poses | ATE [m] | latency from arrival median / p99 "
             "[ms] | latency from stamp median / p99 [ms] (scans) | CPU per scan [ms] | detector per scan CPU p50 / p99 [ms] | wall p50 / p99 [ms] "
             "| scans used / dropped for detection | hook CPU p50 [ms] |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in nodes:
        c = r.get("changes")
        det = (f"{c['per_scan_cpu_ms']['p50']:.0f} / {c['per_scan_cpu_ms']['p99']:.0f} | "
               f"{c['per_scan_wall_ms']['p50']:.0f} / {c['per_scan_wall_ms']['p99']:.0f} | "
               f"{c['scans_used']} / {c['scans_dropped']} | {c['node_hook_cpu_ms']['p50']:.3f}") if c else \
            ("no changes.json | - | - | -" if r.get("detect") else "- | - | - | -")
        lines.append(f"| node at {r['rate']:g}x{' --detect-changes' if r.get('detect') else ''} | "
                     f"{r['scans_received']} / {r['processed']} / {r['dropped']} | {r['poses']} | {r['ate_m']:.3f} | "
                     f"{r['latency_ms_median']:.0f} / {r['latency_ms_p99']:.0f} | {r['stamp_latency_ms_median']:.0f} / "
                     f"{r['stamp_latency_ms_p99']:.0f} ({r['stamp_latency_n']}) | {r['cpu_ms_per_scan']:.0f} | {det} |")
    lines += ["", "One run each (no repeats): the figures move with the machine's load."]
    print(write_section(lines))
    return 0


def write_section(lines: list[str]) -> Path:
    """docs/bench/live.md with the section ``lines`` (its first line the title) in place of the
    one with that title, the other section kept (the small world and the campus are run apart)."""
    from bench.__main__ import FRAGMENTS
    from blockloc.fileio import atomic_write_text

    path = FRAGMENTS / "live.md"
    old = path.read_text() if path.exists() else ""
    sections = [x.rstrip() for x in re.split(r"(?m)^(?=## )", old) if x.strip()]
    titles = [x.splitlines()[0] for x in sections]
    text = "\n".join(lines).rstrip()
    if lines[0] in titles:
        sections[titles.index(lines[0])] = text
    else:
        sections.append(text)
    sections.sort(key=lambda x: x.startswith(CAMPUS_TITLE))  # the small world's first
    atomic_write_text(path, "\n\n".join(sections) + "\n\n")
    return path


def main_campus(a) -> int:
    """The campus world's loc session for ``a.minutes`` of sensor time through the node at one rate,
    against ``track`` on the same frames and map (issue 39: block switches included)."""
    from types import SimpleNamespace

    from bench.campus import default_map_dir, ensure_map
    from bench.__main__ import machine
    from blockloc.app.catalog import open_sequence
    from blockloc.config import load_config
    from blockloc.maps.store import open_map

    rate = float(a.rates.split(",")[0]) if a.rates != "1,3" else 1.0
    seq_name = f"sim:campus/loc@{a.seed}"
    cfg = load_config("sim", overrides={"map": {"block_size_m": 100.0}})
    map_path = Path(a.map) if a.map else default_map_dir("campus", a.seed, cfg.map)
    built_s = ensure_map("campus", a.seed, map_path, cfg.map)
    store = open_map(map_path)
    seq = open_sequence(seq_name)
    period = float(np.median(np.diff(np.asarray(seq.frame_stamps())[:50])))
    frames = min(len(seq), a.frames or int(round(a.minutes * 60.0 / period)))
    session = recorded_session(seq_name, frames, f"campus_loc{a.seed}", Path(a.data) if a.data else None)
    world = SimpleNamespace(block_map=map_path, session=str(session))
    sweep_end, hint, env, started, load_start = run_setup(seq, session, frames)
    with tempfile.TemporaryDirectory(prefix="bench-live-campus-") as tmp:
        work = Path(tmp)
        node = run_node(world, hint, rate, frames, work, env, sweep_end)
        print(node, flush=True)
        track = run_track(world, hint, frames, work, env)
        print({"track": track}, flush=True)
    if a.no_fragment:
        return 0
    cmd = f"python -m bench.live --preset campus --minutes {a.minutes:g}" + (f" --rates {a.rates}" if a.rates != "1,3"
                                                                              else "") + \
        (f" --seed {a.seed}" if a.seed != 1 else "") + (f" --map {a.map}" if a.map else "") + \
        (f" --data {a.data}" if a.data else "")
    sensor_min = frames * period / 60.0
    lines = [CAMPUS_TITLE, "",
             f"`{cmd}`, {started}, on {machine()} (1-min load average {load_start:.1f} at the start, "
             f"{os.getloadavg()[0]:.1f} at the end; the machine is shared). `{seq_name}`: its first {frames} scans "
             f"({sensor_min:.1f} minutes of sensor time) written once in NCLT layout, played by `blockloc play` at "
             f"{rate:g}x into `blockloc node --config sim` over loopback DDS; `blockloc track` on the same frames. "
             f"Map: `{map_path}` ({len(store.entries)} blocks of {store.params.get('block_size_m', 100):g} m, "
             + (f"built in {built_s:.0f} s" if built_s else "built before with the defaults") + "). Both start from "
             f"global init around `--init-pose {hint}`. ATE: position RMSE against ground truth, no alignment. "
             "Failures, recoveries, block switches and rejected scans: each run folder's metrics.json.", "",
             "| run | play took [s] | scans played / processed / dropped | poses | ATE [m] | failures | recoveries "
             "| block switches | rejected | latency from stamp median / p99 [ms] | CPU per scan [ms] | peak RSS [MB] |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|",
             f"| node at {rate:g}x | {node['play_s']:.0f} | {frames} / {node['processed']} / {node['dropped']} | "
             f"{node['poses']} | {node['ate_m']:.3f} | {node.get('failures')} | {node.get('recoveries')} | "
             f"{node.get('switches')} | {node.get('rejected')} | {node['stamp_latency_ms_median']:.0f} / "
             f"{node['stamp_latency_ms_p99']:.0f} | {node['cpu_ms_per_scan']:.0f} | {node['peak_rss_mb']:.0f} |",
             f"| track | - ({track['wall_s']:.0f} wall) | {frames} / {frames} / 0 | {track['poses']} | "
             f"{track['ate_m']:.3f} | {track.get('failures')} | {track.get('recoveries')} | {track.get('switches')} | "
             f"{track.get('rejected')} | - | {track['cpu_ms_per_scan']:.0f} | {track['peak_rss_mb']:.0f} |", "",
             "One run (no repeats). Below 1x the node gets more time per scan than a robot would give it: say the "
             "rate beside any figure taken from here."]
    print(write_section(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
