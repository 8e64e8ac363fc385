"""``blockloc demo``: the whole system on the `small` simulated world, from nothing, in minutes.

Steps: build the block map of the world's mapping session (simulated on the fly: only its
keyframes are rendered; cached where ``blockloc track --seq sim:small/loc`` looks for it),
initialize on the localization session by branch-and-bound from a noisy position hint (yaw
unknown), track it with the sliding window while it is simulated scan by scan, evaluate against
ground truth and write the results folder (poses, metrics, plots, report.html, a Foxglove
recording). Nothing but the map is written to disk: a full-density session would be gigabytes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger("blockloc")

PRESET = "small"
SEED = 1
HINT_NOISE_M = 4.0  # the hint is this far (each axis, uniform) from the truth; yaw is not given


@dataclass
class SmallWorld:
    """The demo's world: its mapping and localization sessions (``--seq`` names, simulated on the
    fly) and the block map built from the first (a cache entry keyed by the code that made it)."""

    mapping: str
    loc: str
    block_map: Path

    @classmethod
    def default(cls, preset: str = PRESET, seed: int = SEED, map_cfg=None) -> "SmallWorld":
        """The block map is the default map of ``sim:<preset>/loc@<seed>`` for the block settings
        of ``map_cfg`` (default: the sim preset's)."""
        from blockloc.commands.common import map_params
        from blockloc.datasets.refs import SequenceRef

        if map_cfg is None:
            from blockloc.config import load_config

            map_cfg = load_config("sim").map
        loc = f"sim:{preset}/loc@{seed}"
        ref = SequenceRef.parse(loc)
        return cls(ref.mapping_source(), loc, ref.default_map_path("block", map_params=map_params(map_cfg, "block")))


def ensure_block_map(world: SmallWorld, cfg, say: Callable[[str], None] = log.info) -> Path:
    """The block map of the mapping session (built once, reused)."""
    from blockloc.commands.common import progress
    from blockloc.datasets import open_sequence
    from blockloc.errors import MapError
    from blockloc.maps.build_plan import build_block_map_from_sequence
    from blockloc.maps.store import open_map

    try:
        store = open_map(world.block_map)
        say(f"block map: cached at {world.block_map} ({len(store)} blocks)")
        return world.block_map
    except MapError:
        pass
    say(f"block map: simulating the keyframes of {world.mapping} and stitching blocks of "
        f"{cfg.map.block_size_m:g} m ...")
    t0 = time.perf_counter()
    seq = open_sequence(world.mapping, dataset_cfg=cfg.dataset)
    with progress("block map build tasks") as report:
        store = build_block_map_from_sequence(seq, block_size_m=cfg.map.block_size_m,
                                              keyframe_distance_m=cfg.map.keyframe_distance_m,
                                              keyframe_angle_deg=cfg.map.keyframe_angle_deg,
                                              voxel_size_m=cfg.map.voxel_size_m, out=world.block_map,
                                              overwrite=True, progress=report)
    say(f"block map: {len(store)} blocks in {time.perf_counter() - t0:.0f} s")
    return world.block_map


def prepare_small_world(cfg=None, say: Callable[[str], None] = log.info):
    """The `small` world and its (cached) block map: (SmallWorld, Config used, default the sim preset)."""
    from blockloc.config import load_config

    cfg = cfg or load_config("sim")
    world = SmallWorld.default(map_cfg=cfg.map)
    ensure_block_map(world, cfg, say=say)
    return world, cfg


def noisy_hint(seq, seed: int = SEED, noise_m: float = HINT_NOISE_M) -> tuple[float, float, None]:
    """A position hint near the first ground-truth pose (as a user clicking on a map would give)."""
    gt = seq.ground_truth()
    p = gt.interpolate(np.array([seq.frame_stamps()[0]]))[0][:3, 3]
    rng = np.random.default_rng(seed)
    dx, dy = rng.uniform(-noise_m, noise_m, 2)
    return float(p[0] + dx), float(p[1] + dy), None


def demo_session(cfg=None, *, out: Path | None = None, observers=(), say: Callable[[str], None] = log.info,
                 keep_estimates: bool = False):
    """(Session on the small world's localization session in its block map, the hint)."""
    from blockloc.datasets import open_sequence
    from blockloc.maps.store import open_map
    from blockloc.session import Session

    world, cfg = prepare_small_world(cfg, say=say)
    seq = open_sequence(world.loc, dataset_cfg=cfg.dataset)
    session = Session.from_config(cfg, seq, open_map(world.block_map), backend="block", observers=observers,
                                  out_dir=out, keep_estimates=keep_estimates,
                                  facts={"map": str(world.block_map)})
    return session, noisy_hint(seq)


def demo_command(out: Path | None, max_frames: int | None, record: bool = True) -> None:
    from blockloc.commands.common import check_results_dir, console, results_dir, track_bytes
    from blockloc.commands.init import compile_note
    from blockloc.commands.track import (print_track_summary, print_where, run_observers, run_tracking,
                                         write_run_report)

    con = console()
    out_dir = results_dir(out, "demo")
    check_results_dir(out_dir, track_bytes(max_frames or 1, record))

    def say(msg: str) -> None:
        con.print(f"[bold cyan]demo[/] {msg}")

    session, hint = demo_session(out=out_dir, observers=run_observers(out_dir, record=record), say=say)
    say(f"global init: branch-and-bound around the hint ({hint[0]:.1f}, {hint[1]:.1f}), yaw unknown")
    ok = False
    try:
        res = run_tracking(session, mode="pose", hint=hint, out_dir=out_dir, max_frames=max_frames)
        ok = True
    finally:
        if session.result is not None:
            write_run_report(session, session.result, out_dir, quiet=not ok)
    init = res.metrics.get("init") or {}
    if init.get("time_s") is not None:
        say(f"global init: {init.get('error_m', float('nan')):.2f} m from the truth in {init['time_s']:.2f} s"
            f"{compile_note(init)}")
    print_track_summary(con, res.metrics, res.out_dir)
    print_where(con, out_dir)
