"""The simulator: a procedural world ray-cast by an HDL-32E model, with IMU and ground truth.

- ``generate_dataset(preset, seed, out, fmt="nclt")`` writes every session (NCLT layout or bags).
- ``blockloc.sim.stream.open_sim_sequence(preset, session, seed)`` streams one session.

Submodules: presets, seeds; the world: terrain, meshes, layout, movables, world (``build_world``);
trajectory, scene (ray casting), lidar, stream (``SimSequence``), parallel (worker processes),
writer, render.
"""

from __future__ import annotations

from pathlib import Path


def generate_dataset(preset: str, seed: int, out: Path, fmt: str = "nclt", **kwargs) -> Path:
    """Write all sessions of ``preset`` (small | campus) for ``seed`` under ``out``; see
    ``blockloc.sim.writer.generate_dataset``."""
    from blockloc.sim.writer import generate_dataset as _gen

    return _gen(preset, seed, Path(out), fmt, **kwargs)


def open_sim_sequence(preset: str, session: str, seed: int, **overrides):
    """Stream a simulated session; see ``blockloc.sim.stream.open_sim_sequence``."""
    from blockloc.sim.stream import open_sim_sequence as _open

    return _open(preset, session, seed, **overrides)


__all__ = ["generate_dataset", "open_sim_sequence"]
