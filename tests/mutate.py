#!/usr/bin/env python
"""Planted-bug checks: does the suite catch one-line bugs in the formulas, frames and thresholds?

Each mutation below is (name, file, the exact old snippet, its replacement, the tests to run). For
each one the repository (``git ls-files``: tracked and untracked-but-not-ignored files, never
``.git``) is copied to a temporary directory, the snippet is replaced there, and the listed tests
run in the copy with ``PYTHONPATH`` pointing at it. ``caught``: the tests failed (or errored);
``SURVIVED``: they passed with the bug in; ``STALE``: the snippet no longer occurs exactly once
(the code moved: update the mutation, never let it pass silently). Before the mutations, the
union of the listed tests runs once on the unmodified copy (``--no-baseline`` skips it): a
failure there makes every "caught" meaningless, so the script stops.

    python tests/mutate.py                       # all mutations, one at a time
    python tests/mutate.py --only ndt_constants_res_power --only block_skip_band
    python tests/mutate.py --jobs 2 --record     # 2 in parallel; write the table into mutations.md
    python tests/mutate.py --list

Exit status 0 when every mutation is caught, 1 otherwise (any survivor, stale snippet or error).
This file is a script, not a test module: ``tests/conftest.py`` keeps pytest from collecting it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RECORD = Path(__file__).resolve().parent / "mutations.md"
BEGIN, END = "<!-- mutate.py results begin -->", "<!-- mutate.py results end -->"
TIMEOUT_S = 1200


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str
    old: str
    new: str
    tests: tuple[str, ...]


def M(name, file, old, new, *tests):
    return Mutation(name, file, old, new, tuple(tests))


T_NDT = "tests/registration/test_ndt.py"
T_FACTORS = "tests/tracking/test_factors.py"
T_BLOCKS = "tests/maps/test_block_maps.py"
T_GRID = "tests/maps/test_grid_tiles.py"
T_EVAL = "tests/evaluation"

MUTATIONS: list[Mutation] = [
    # --- the three that survived the suite before issue 20
    M("ndt_info_adjoint_side", "blockloc/tracking/factors.py",
      "A = adjoint(inv_T(T_body_lidar))", "A = adjoint(T_body_lidar)", T_FACTORS),
    M("ndt_constants_res_power", "blockloc/registration/ndt.py",
      "c2 = outlier_ratio / resolution**3", "c2 = outlier_ratio / resolution**2",
      f"{T_NDT}::test_ndt_constants_match_magnusson"),
    M("block_skip_band", "blockloc/maps/block_maps.py",
      "if d > 0.1 * S:", "if d > 0.05 * S:", T_BLOCKS),
    M("block_merge_lower_bound", "blockloc/maps/block_maps.py",
      "if d > 0.1 * S:", "if d > 0.2 * S:", T_BLOCKS),
    # --- the seventeen caught ones (as far as it names them) and their kin
    M("ndt_gradient_sign", "blockloc/registration/ndt.py",
      "return NdtEvaluation(score, inliers, b, Hgn", "return NdtEvaluation(score, inliers, -b, Hgn",
      f"{T_NDT}::test_gradient_and_hessian_match_finite_differences"),
    M("ndt_hessian_not_psd_projected", "blockloc/registration/ndt.py",
      "H = ev.H if lam[0] >= 0.0 else (V * np.maximum(lam, 0.0)) @ V.T", "H = ev.H",
      f"{T_NDT}::test_result_H_is_psd_projection_of_exact_hessian"),
    M("ndt_inlier_threshold", "blockloc/registration/ndt.py",
      "INLIER_MAHALANOBIS_SQ = 11.345", "INLIER_MAHALANOBIS_SQ = 7.815",
      f"{T_NDT}::test_score_and_inliers_match_numpy_reference"),
    M("window_drops_schur_prior", "blockloc/tracking/window.py",
      "                self.add_factor(f)\n", "                pass\n",
      "tests/tracking/test_window.py"),
    M("window_switch_size_swapped", "blockloc/tracking/window.py",
      "size_on_switch if switched else self.max_size", "self.max_size if switched else size_on_switch",
      "tests/tracking/test_window.py"),
    M("window_one_iteration_always", "blockloc/tracking/window.py",
      "                opt.optimize()  # goes on from the first iteration's estimate\n", "                pass\n",
      "tests/tracking/test_window.py"),
    M("ndt_prediction_never_falls_back", "blockloc/registration/ndt.py",
      "if not (converged and acc[1] > 0 and moved_m <= 0.25 * fine.resolution):", "if False:",
      f"{T_NDT}::test_align_from_prediction_far_start_falls_back_to_align"),
    M("tracker_wrong_side_transform", "blockloc/tracking/estimator.py",
      "T_ndt = np.asarray(res.T_target_source) @ self.T_lidar_body",
      "T_ndt = self.T_lidar_body @ np.asarray(res.T_target_source)",
      "tests/tracking/test_tracker_branches.py"),
    M("tracker_min_fitness_ignored", "blockloc/tracking/results.py",
      "not fitness >= min_fitness", "not fitness >= 0.0",
      "tests/tracking/test_tracker_branches.py"),
    M("tracker_innovation_gate_widened", "blockloc/tracking/results.py",
      "if inn_m > gates[0] or", "if inn_m > 100 * gates[0] or",
      "tests/tracking/test_tracker_branches.py"),
    M("deskew_velocity_sign", "blockloc/tracking/imu_tracker.py",
      "T_pred[:3, 3] + v_pred[None] * (table_t - stamp)[:, None]",
      "T_pred[:3, 3] - v_pred[None] * (table_t - stamp)[:, None]",
      "tests/tracking/test_tracker_branches.py"),
    M("deskew_table_inverted", "blockloc/deskew.py",
      "return inv_T(T_ref)[None] @ T_map_lidar", "return inv_T(T_map_lidar) @ T_ref[None]",
      "tests/tracking/test_deskew.py"),
    M("imu_extrinsic_inverted", "blockloc/tracking/imu.py",
      "p.setBodyPSensor(gtsam.Pose3(np.asarray(T_body_imu, dtype=np.float64)))",
      "p.setBodyPSensor(gtsam.Pose3(np.asarray(T_body_imu, dtype=np.float64)).inverse())",
      "tests/tracking/test_imu.py"),
    M("ndt_info_no_floor", "blockloc/tracking/factors.py",
      "cov = (U / np.maximum(w, eps)) @ U.T + np.diag(floor)", "cov = (U / np.maximum(w, eps)) @ U.T",
      T_FACTORS),
    M("ndt_info_weak_not_downweighted", "blockloc/tracking/factors.py",
      "w = np.where(weak, w * params.weak_factor, w)", "w = np.where(weak, w, w)", T_FACTORS),
    M("block_new_threshold", "blockloc/maps/block_maps.py",
      "if d >= 0.5 * S:", "if d >= 0.6 * S:", T_BLOCKS),
    M("keyframe_distance_threshold", "blockloc/maps/mapping.py",
      "if d > distance_m or a > max_angle:", "if d > 2 * distance_m or a > max_angle:", T_BLOCKS),
    M("tile_names_off_by_1_5", "blockloc/maps/grid_tiles.py",
      'return f"{(ix + 0.5) * s:.{d}f}_{(iy + 0.5) * s:.{d}f}"',
      'return f"{(ix + 1.5) * s:.{d}f}_{(iy + 0.5) * s:.{d}f}"', T_GRID),
    M("grid_window_widens_backward", "blockloc/maps/grid_tiles.py",
      "x1 += k if dx > 0 else 0", "x1 += k if dx < 0 else 0", T_GRID),
    M("heading_sector_floor", "blockloc/maps/grid_tiles.py",
      "return int(round(angle / (math.pi / 4))) % 8", "return int(angle / (math.pi / 4)) % 8", T_GRID),
    M("srt_radius_to_tile_centre", "blockloc/maps/policies.py",
      "nearest = np.clip(p, self.cell_min, self.cell_max)",
      "nearest = 0.5 * (self.cell_min + self.cell_max)",
      "tests/maps/test_provider.py::test_srt_radius_and_rebuild_triggers"),
    M("store_checksum_always_passes", "blockloc/maps/store.py",
      "if digest != e.sha256:", "if False:",
      "tests/maps/test_store.py::test_checksum_mismatch_and_truncation"),
    M("store_point_count_unchecked", "blockloc/maps/store.py",
      "if len(points) != e.num_points:", "if False:",
      "tests/maps/test_store.py::test_point_count_mismatch_names_the_file"),
    M("pyramid_bound_not_admissible", "blockloc/global_init/pyramid.py",
      "np.maximum(cur[:-half], prev[half:], out=cur[:-half])",
      "np.minimum(cur[:-half], prev[half:], out=cur[:-half])",
      "tests/global_init/test_pyramid.py"),
    M("bnb_angle_step_too_coarse", "blockloc/global_init/bnb.py",
      "return math.acos(1.0 - resolution**2 / (2.0 * d**2))",
      "return math.acos(1.0 - resolution**2 / (0.5 * d**2))",
      "tests/global_init/test_bnb.py"),
    M("bnb_prunes_at_s0", "blockloc/global_init/bnb.py",
      "found again by the search.\n    threshold = max(threshold, int(s0_ratio * best) - 1)",
      "found again by the search.\n    threshold = max(threshold, int(best) + 1)",
      "tests/global_init/test_bnb.py"),
    M("tum_quaternion_order", "blockloc/trajectory_io.py",
      "poses[:, :3, :3] = quat_xyzw_to_R(data[:, 4:8])",
      "poses[:, :3, :3] = quat_xyzw_to_R(data[:, [7, 4, 5, 6]])",
      f"{T_EVAL}/test_eval_trajectory_io.py"),
    M("kitti_row_order", "blockloc/trajectory_io.py",
      "poses[:, :3, :] = data.reshape(-1, 3, 4)",
      "poses[:, :3, :] = data.reshape(-1, 4, 3).transpose(0, 2, 1)[:, :3, :]",
      f"{T_EVAL}/test_eval_trajectory_io.py"),
    M("umeyama_translation_without_rotation", "blockloc/evaluation/metrics.py",
      "T[:3, 3] = mu_d - R @ mu_s", "T[:3, 3] = mu_d - mu_s",
      f"{T_EVAL}/test_eval_properties.py"),
    M("umeyama_scaled", "blockloc/evaluation/metrics.py",
      "    T[:3, :3] = R\n",
      "    T[:3, :3] = R * np.sqrt(((dst - mu_d) ** 2).sum() / ((src - mu_s) ** 2).sum())\n",
      f"{T_EVAL}/test_eval_metrics_vs_evo.py::test_umeyama_recovers_transform_and_matches_evo"),
    M("rpe_relative_in_world_frame", "blockloc/evaluation/metrics.py",
      "G_rel = inv_T(G[i]) @ G[j]", "G_rel = G[j] @ inv_T(G[i])",
      f"{T_EVAL}/test_eval_metrics_vs_evo.py"),
    M("rotation_angle_atan2_swapped", "blockloc/evaluation/metrics.py",
      "return np.arctan2(sin, cos)", "return np.arctan2(cos, sin)",
      f"{T_EVAL}/test_eval_metrics_vs_evo.py"),
    M("nclt_gt_roll_pitch_swap", "blockloc/datasets/nclt.py",
      "poses = xyzrpy_to_T(*data[:, 1:].T)", "poses = xyzrpy_to_T(*data[:, [1, 2, 3, 5, 4, 6]].T)",
      "tests/datasets/test_nclt_fixed_rows.py"),
    M("nclt_ms25_mag_as_accel", "blockloc/datasets/nclt.py",
      "data[:, 0], data[:, 4:7], data[:, 7:10]", "data[:, 0], data[:, 1:4], data[:, 7:10]",
      "tests/datasets/test_nclt_fixed_rows.py"),
    M("nclt_point_scale", "blockloc/datasets/nclt.py",
      "NCLT_POINT_SCALE = 0.005", "NCLT_POINT_SCALE = 0.004",
      "tests/datasets/test_nclt_fixed_rows.py"),
    M("rpy_pitch_sign", "blockloc/geometry.py",
      "R[..., 2, 0] = -sp", "R[..., 2, 0] = sp", "tests/test_geometry.py"),
    M("nclt_gt_writer_roll_pitch_swap", "blockloc/datasets/nclt.py",
      "xyzrpy = T_to_xyzrpy(traj.poses)", "xyzrpy = T_to_xyzrpy(traj.poses)[:, [0, 1, 2, 4, 3, 5]]",
      "tests/datasets/test_nclt_fixed_rows.py"),
    M("tum_writer_scalar_first", "blockloc/trajectory_io.py",
      "for t, (x, y, z), (qx, qy, qz, qw) in zip(np.asarray(stamps), poses[:, :3, 3], q)]",
      "for t, (x, y, z), (qw, qx, qy, qz) in zip(np.asarray(stamps), poses[:, :3, 3], q)]",
      f"{T_EVAL}/test_eval_trajectory_io.py"),
    M("ndt_information_scale_ignored", "blockloc/tracking/factors.py",
      "H = 0.5 * (H + H.T) * params.information_scale", "H = 0.5 * (H + H.T)", T_FACTORS),
    # --- the LiDAR mounting estimate (issue 15)
    M("mounting_hand_eye_sides", "blockloc/maps/mounting.py",
      "b.compose(Xi).compose(a).compose(X)", "b.compose(X).compose(a).compose(Xi)",
      "tests/maps/test_mounting.py"),
    M("mounting_not_applied", "blockloc/maps/build_plan.py",
      'drives = [remounted(p.drive, m["T_body_lidar"]) for p, m in zip(plans, found)]',
      'drives = [p.drive for p in plans]', "tests/maps/test_mounting.py"),
    M("restart_sweep_without_rotation", "blockloc/tracking/imu_tracker.py",
      "early = table_t[0] < t_prev - 1e-9 and abs(stamp - t_prev) < 1e-4", "early = False",
      "tests/node/test_session_live.py"),
    M("restart_not_refined", "blockloc/tracking/restart.py",
      "return None if reason else T_ndt", "return None", "tests/global_init/test_kidnap.py"),
    M("backlog_drops_the_oldest", "blockloc/node/buffer.py",
      "if not (self.backlog or self._catching_up) or len(self._items) < 3:", "if True:",
      "tests/node/test_buffer.py"),
]


@dataclass
class Outcome:
    name: str
    file: str
    result: str  # caught | SURVIVED | STALE | ERROR
    seconds: float
    detail: str = ""


def repo_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         cwd=REPO, check=True, capture_output=True).stdout
    return [f for f in out.decode().split("\0") if f]


def sync_copy(dst: Path, files: list[str]) -> None:
    """Make ``dst`` hold the repository's files as they are (mtimes kept, so compiled caches of
    unchanged modules in ``dst`` stay valid between mutations)."""
    for rel in files:
        src = REPO / rel
        if not src.is_file():  # deleted in the work tree
            continue
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target)


def shared_data_env() -> str:
    env = os.environ.get("BLOCKLOC_SHARED_DATA")
    return env if env else str(REPO.parent / "shared" / "data")


def run_pytest(cwd: Path, tests: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(cwd) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    # the copy is not beside ../shared/data: point it at the repository's
    env["BLOCKLOC_SHARED_DATA"] = shared_data_env()
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-n", "0", "-p", "no:cacheprovider", *tests]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


def mutate_one(m: Mutation, slot: Path, files: list[str]) -> Outcome:
    t0 = time.perf_counter()
    text = (REPO / m.file).read_text()
    count = text.count(m.old)
    if count != 1:
        return Outcome(m.name, m.file, "STALE", 0.0, f"snippet found {count} times")
    sync_copy(slot, files)
    (slot / m.file).write_text(text.replace(m.old, m.new))
    try:
        proc = run_pytest(slot, list(m.tests))
    except subprocess.TimeoutExpired:
        return Outcome(m.name, m.file, "caught", time.perf_counter() - t0, f"timeout {TIMEOUT_S} s")
    finally:
        (slot / m.file).write_text(text)
    dt = time.perf_counter() - t0
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr.strip()[-200:]
    if proc.returncode == 0:
        return Outcome(m.name, m.file, "SURVIVED", dt, tail)
    if proc.returncode in (1, 2, 3):  # tests failed, collection/import error, internal error
        return Outcome(m.name, m.file, "caught", dt, tail)
    return Outcome(m.name, m.file, "ERROR", dt, f"pytest exit {proc.returncode}: {tail}")


def table(outcomes: list[Outcome]) -> str:
    lines = ["| mutation | file | result | seconds | tests' last line |", "|---|---|---|---|---|"]
    for o in outcomes:
        detail = o.detail.replace("|", "/")[:90]
        lines.append(f"| {o.name} | {o.file} | {o.result} | {o.seconds:.0f} | {detail} |")
    return "\n".join(lines)


def record(outcomes: list[Outcome], header: str) -> None:
    text = RECORD.read_text() if RECORD.exists() else f"{BEGIN}\n{END}\n"
    a, b = text.index(BEGIN), text.index(END)
    RECORD.write_text(text[:a + len(BEGIN)] + "\n" + header + "\n\n" + table(outcomes) + "\n"
                      + text[b:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", action="append", default=[], help="run only this mutation (repeatable)")
    ap.add_argument("--jobs", type=int, default=1, help="mutations run in parallel (default 1)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run")
    ap.add_argument("--record", action="store_true", help=f"write the table into {RECORD.name}")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copies")
    args = ap.parse_args(argv)

    names = [m.name for m in MUTATIONS]
    if len(set(names)) != len(names):
        print("duplicate mutation names", file=sys.stderr)
        return 2
    chosen = MUTATIONS
    if args.only:
        unknown = sorted(set(args.only) - set(names))
        if unknown:
            print(f"unknown mutation(s): {', '.join(unknown)}", file=sys.stderr)
            return 2
        chosen = [m for m in MUTATIONS if m.name in args.only]
    if args.list:
        for m in chosen:
            print(f"{m.name:40s} {m.file:40s} {' '.join(m.tests)}")
        return 0

    files = repo_files()
    jobs = max(1, args.jobs)
    root = Path(tempfile.mkdtemp(prefix="blockloc-mutate-"))
    slots = [root / f"copy{k}" for k in range(jobs)]
    t_start = time.perf_counter()
    try:
        for slot in slots:
            sync_copy(slot, files)
        if not args.no_baseline:
            tests = sorted({t for m in chosen for t in m.tests})
            t0 = time.perf_counter()
            proc = run_pytest(slots[0], tests)
            print(f"baseline (unmutated, {len(tests)} test paths): exit {proc.returncode}, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
            if proc.returncode != 0:
                print(proc.stdout[-3000:], proc.stderr[-2000:], sep="\n", file=sys.stderr)
                print("the listed tests fail without any mutation: fix them first", file=sys.stderr)
                return 1
        free = list(slots)
        lock = threading.Lock()

        def work(m: Mutation) -> Outcome:
            with lock:
                slot = free.pop()
            try:
                o = mutate_one(m, slot, files)
            finally:
                with lock:
                    free.append(slot)
            print(f"{o.result:9s} {o.seconds:6.0f} s  {o.name}  ({o.detail})", flush=True)
            return o

        with ThreadPoolExecutor(max_workers=jobs) as pool:
            outcomes = list(pool.map(work, chosen))
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
        else:
            print(f"copies kept in {root}")
    total = time.perf_counter() - t_start
    n_caught = sum(o.result == "caught" for o in outcomes)
    print()
    print(table(outcomes))
    summary = f"{n_caught} of {len(outcomes)} caught, {total:.0f} s in total (--jobs {jobs})"
    print("\n" + summary)
    if args.record:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                                text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True).stdout.strip()
        header = (f"Run on commit {commit}{' (with uncommitted changes)' if dirty else ''}, "
                  f"{time.strftime('%Y-%m-%d')}: {summary}.")
        record(outcomes, header)
    return 0 if n_caught == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
