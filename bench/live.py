"""The live node against ``track`` on the same session and map (issue 39).

    python -m bench.live                          # 1x and 3x, the whole small loc session; docs/bench/live.md
    python -m bench.live --frames 300 --rates 1,3

``blockloc play`` publishes the cached small world's loc session (its first scans written once in
NCLT layout: the simulator renders too slowly to play live) at each rate into ``blockloc
node`` (both as subprocesses, DDS on loopback with multicast off); a third participant here
listens to the node's /blockloc/pose and /diagnostics. Then ``blockloc track`` runs the same
frames in the same map. Both start from the same global init around the demo's noisy hint
(``--init-pose``). Reported: ATE (position RMSE against the ground truth at each pose stamp, no
alignment: both are in the map frame), poses published against scans played, scans the node
dropped, latency from a scan's arrival at the node to its pose being published (median, p99,
the node's own ``latency_ms`` in /diagnostics), CPU seconds per scan (user + system of the
whole process, from wait4) and peak RSS (ru_maxrss), beside track's.
"""

from __future__ import annotations

import argparse
import os
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
    d = np.loadtxt(poses_tum, ndmin=2)
    if not len(d):
        return float("nan"), 0
    inside = (d[:, 0] >= gt.stamps[0]) & (d[:, 0] <= gt.stamps[-1])
    d = d[inside]
    e = np.linalg.norm(d[:, 1:4] - gt.interpolate(d[:, 0])[:, :3, 3], axis=1)
    return float(np.sqrt(np.mean(e ** 2))), len(d)


def run_node(world, hint: str, rate: float, frames: int, work: Path, env: dict) -> dict:
    from blockloc.ros2 import dds as d
    from blockloc.ros2 import messages as m

    out = work / f"node_{rate:g}x"
    node = _start(["node", "--map", str(world.block_map), "--config", "sim", "--init-pose", hint, "--out", str(out)],
                  env, work / f"node_{rate:g}x.log")
    os.environ.update({k: env[k] for k in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")})
    listener = d.Dds()
    diags: list = []
    poses: list = []
    listener.reader("/diagnostics", m.DiagnosticArray, diags.append, d.RELIABLE)
    listener.reader("/blockloc/pose", m.PoseWithCovarianceStamped, poses.append, d.RELIABLE)
    try:
        t0 = time.monotonic()
        while "listening on" not in (work / f"node_{rate:g}x.log").read_text():
            if node.poll() is not None or time.monotonic() - t0 > 300:
                raise SystemExit(f"the node did not start: {(work / f'node_{rate:g}x.log').read_text()[-2000:]}")
            time.sleep(0.2)
        play = _start(["play", "--seq", world.session, "--config", "sim", "--rate", f"{rate:g}", "--max-frames",
                       str(frames)], env, work / f"play_{rate:g}x.log")
        t_play = time.monotonic()
        play_code, _, _ = _reap(play)
        play_s = time.monotonic() - t_play
        time.sleep(3.0)  # the node finishes its queue
        node.send_signal(signal.SIGINT)
        code, cpu_s, rss_mb = _reap(node)
    finally:
        if node.poll() is None:
            node.kill()
        listener.close()
    values = [{kv.key: kv.value for kv in x.status[0].values} for x in diags]
    scans = [v for v in values if "latency_ms" in v]
    latency = np.array([float(v["latency_ms"]) for v in scans])
    last = values[-1] if values else {}
    ate, n = _ate(out / "poses.tum", world_gt(world))
    processed = int(last.get("scans_processed", 0))
    return {"rate": rate, "play_exit": play_code, "node_exit": code, "play_s": play_s, "ate_m": ate,
            "poses": len(poses), "poses_file": n, "scans_received": int(last.get("scans_received", 0)),
            "processed": processed, "dropped": int(last.get("dropped_scans", 0)),
            "latency_ms_median": float(np.median(latency)) if len(latency) else float("nan"),
            "latency_ms_p99": float(np.percentile(latency, 99)) if len(latency) else float("nan"),
            "cpu_s": cpu_s, "cpu_ms_per_scan": 1e3 * cpu_s / max(processed, 1), "peak_rss_mb": rss_mb}


def recorded_session(world, frames: int) -> Path:
    """The first ``frames`` scans of the small loc session written once in NCLT layout (cached):
    the simulator renders a scan in ~1-3 s, too slow to play at 10 Hz, and ``track`` then reads
    the same files as the player."""
    from blockloc.cache import cache_root
    from blockloc.app.catalog import open_sequence
    from blockloc.datasets.base import ImuData
    from blockloc.datasets.nclt import write_session

    out = cache_root() / "bench" / f"live_small_loc1_{frames}"
    if (out / "done").exists():
        return out
    seq = open_sequence(world.loc)
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
    return {"exit": code, "wall_s": wall, "ate_m": ate, "poses": n, "cpu_s": cpu_s,
            "cpu_ms_per_scan": 1e3 * cpu_s / max(frames, 1), "peak_rss_mb": rss_mb}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.live")
    ap.add_argument("--frames", type=int, default=None, help="scans to play (default: the whole session)")
    ap.add_argument("--rates", default="1,3")
    ap.add_argument("--no-fragment", action="store_true")
    a = ap.parse_args(argv)
    from blockloc.app.runs import noisy_hint, prepare_small_world
    from blockloc.app.catalog import open_sequence

    world, cfg = prepare_small_world()
    seq = open_sequence(world.loc, dataset_cfg=cfg.dataset)
    frames = min(a.frames or len(seq), len(seq))
    world.session = str(recorded_session(world, frames))
    x, y, _ = noisy_hint(seq)
    hint = f"{x:.2f},{y:.2f}"
    env = _env()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        work = Path(tmp)
        nodes = []
        for rate in [float(r) for r in a.rates.split(",")]:
            nodes.append(run_node(world, hint, rate, frames, work, env))
            print(nodes[-1], flush=True)
        track = run_track(world, hint, frames, work, env)
        print({"track": track}, flush=True)
    if a.no_fragment:
        return 0
    from bench.__main__ import FRAGMENTS, machine
    from blockloc.fileio import atomic_write_text

    cmd = "python -m bench.live" + (f" --frames {a.frames}" if a.frames else "") + \
        (f" --rates {a.rates}" if a.rates != "1,3" else "")
    lines = ["## The live node (ROS 2 over DDS) against track", "",
             f"`{cmd}`, {started}, on {machine()} (load average {os.getloadavg()[0]:.1f} at the end; the machine "
             "is shared). The small world's loc session (`sim:small/loc@1`, seed 1, written once in NCLT layout), its cached block map, "
             f"{frames} scans played by `blockloc play` into `blockloc node` over loopback DDS; both start from "
             f"global init around `--init-pose {hint}` (the demo's noisy hint). ATE: position RMSE against "
             "ground truth, no alignment. Latency: the scan's arrival at the node to its pose published "
             "(the node's `latency_ms`). CPU: user + system seconds of the whole process over the scans it "
             "processed; RSS: peak.", "",
             "| run | play took [s] | scans played / received / processed / dropped | poses | ATE [m] | latency median / p99 [ms] | CPU per scan [ms] | peak RSS [MB] |",
             "|---|---|---|---|---|---|---|---|"]
    for r in nodes:
        lines.append(f"| node at {r['rate']:g}x | {r['play_s']:.0f} | {frames} / {r['scans_received']} / {r['processed']} / "
                     f"{r['dropped']} | {r['poses']} | "
                     f"{r['ate_m']:.3f} | {r['latency_ms_median']:.0f} / {r['latency_ms_p99']:.0f} | "
                     f"{r['cpu_ms_per_scan']:.0f} | {r['peak_rss_mb']:.0f} |")
    lines.append(f"| track | - ({track['wall_s']:.0f} wall) | {frames} / {frames} / {frames} / 0 | {track['poses']} | "
                 f"{track['ate_m']:.3f} | - | "
                 f"{track['cpu_ms_per_scan']:.0f} | {track['peak_rss_mb']:.0f} |")
    lines += ["", "One run each (no repeats): the figures move with the machine's load. Scans played but not "
              "received were overwritten in the node's DDS reader (best effort, keep last 5) while its process "
              "did not get the CPU; the node counts only the scans it dropped itself."]
    atomic_write_text(FRAGMENTS / "live.md", "\n".join(lines) + "\n\n")
    print(FRAGMENTS / "live.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
