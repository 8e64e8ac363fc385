"""A tracking run's folder as change detection reads it: poses and which frames are trusted.

A run folder (``blockloc track --out``) holds ``poses.tum`` (time s, T_map_body) and
``diagnostics.csv`` (index, stamp, status, ...; ``blockloc.evaluation.results``). Statuses
(``blockloc.viz.events.STATUSES``, set by ``blockloc.tracking.estimator`` and ``blockloc.app.session``):
``ok`` (scan registered and accepted), ``rejected``, ``imu_only``, ``lost``, ``recovered`` (just
relocalized), ``uninitialized``; ``skipped`` (unreadable frame). Only ``ok`` frames that follow at
least ``settle_frames`` ``ok`` frames are trusted: a frame right after a loss, a rejection or a
relocalization is not (its pose has not been confirmed by the scans after it yet).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blockloc.errors import BlocklocError

TRUSTED_STATUS = "ok"


class RunError(BlocklocError):
    """A run folder that cannot be read for change detection."""


@dataclass
class RunPoses:
    """A run's trusted frames. index: (N,) frame index; stamps: (N,) s; T_map_body: (N, 4, 4);
    statuses: every diagnostics row's status by frame index; sequence: the ``--seq`` the run was
    made from (metrics.json's ``sequence_arg``, else its ``sequence`` name), or None; map: the
    map it was tracked in (metrics.json's ``map_path``, absolute, else its ``map`` as given to
    track), or None; map_id: that map's identity (``map_id``,
    :func:`blockloc.maps.changes.versions.map_identity`), or None (runs from before it was recorded);
    poses: the trajectory file the sequence was given (``--poses``, metrics.json's ``poses_arg``,
    absolute), or None."""

    path: Path
    index: np.ndarray
    stamps: np.ndarray
    T_map_body: np.ndarray
    statuses: dict
    sequence: str | None
    map: str | None = None
    map_id: str | None = None
    poses: str | None = None

    def __len__(self) -> int:
        return len(self.index)

    @property
    def num_frames(self) -> int:
        """Frames of its sequence the run went through: the last diagnostics row's index + 1 (0
        for a run without rows)."""
        return max(self.statuses) + 1 if self.statuses else 0


class TrustedFrames:
    """The rule of the module docstring one frame at a time: ``trusted(status)`` is True for an
    ``ok`` frame that follows at least ``settle_frames`` ``ok`` frames (call it with every frame's
    status in order, skipped and lost frames included). What ``track`` and the node feed the
    change detector while they run, and what :func:`trusted_mask` applies to a finished run."""

    def __init__(self, settle_frames: int = 10) -> None:
        self.settle_frames = int(settle_frames)
        self._ok_before = 0  # consecutive ok frames right before the next one

    def __call__(self, status: str) -> bool:
        ok = status == TRUSTED_STATUS
        trusted = ok and self._ok_before >= self.settle_frames
        self._ok_before = self._ok_before + 1 if ok else 0
        return trusted


def trusted_mask(statuses: list[str], settle_frames: int) -> np.ndarray:
    """(N,) bool: status ``ok`` with the ``settle_frames`` frames before it ``ok`` too
    (:class:`TrustedFrames` over the statuses in order)."""
    rule = TrustedFrames(settle_frames)
    return np.array([rule(s) for s in statuses], dtype=bool)


def read_run(run_dir: str | Path, settle_frames: int = 10) -> RunPoses:
    """The trusted frames of the run folder ``run_dir`` (module docstring)."""
    from blockloc.trajectory_io import read_tum

    run_dir = Path(run_dir)
    poses_path, diag_path = run_dir / "poses.tum", run_dir / "diagnostics.csv"
    for p in (poses_path, diag_path):
        if not p.is_file():
            raise RunError(f"--run {run_dir}: no {p.name} (expected a folder written by blockloc track)")
    with open(diag_path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    try:
        idx = np.array([int(r["index"]) for r in rows], dtype=np.int64)
        stamps = np.array([float(r["stamp"]) for r in rows])
        status = [r["status"] for r in rows]
    except (KeyError, ValueError) as exc:
        raise RunError(f"{diag_path}: expected columns index, stamp, status ({exc})") from None
    trusted = trusted_mask(status, settle_frames)
    traj = read_tum(poses_path)
    # a pose belongs to the frame with its stamp (poses.tum writes the frame's stamp)
    j = np.searchsorted(traj.stamps, stamps)
    j = np.clip(j, 0, max(len(traj.stamps) - 1, 0))
    has = len(traj.stamps) > 0
    match = has & (np.abs(traj.stamps[j] - stamps) < 1e-4) if has else np.zeros(len(stamps), bool)
    keep = trusted & match
    doc = {}
    metrics = run_dir / "metrics.json"
    if metrics.is_file():
        try:
            doc = json.loads(metrics.read_text())
        except (OSError, ValueError):
            doc = {}
    doc = doc if isinstance(doc, dict) else {}

    def text(*keys: str) -> str | None:
        return next((str(doc[k]) for k in keys if isinstance(doc.get(k), str) and doc[k]), None)

    # the --seq the run was given (since 2026-12-07), else its display name (a sim name opens again)
    return RunPoses(run_dir, idx[keep], stamps[keep], traj.poses[j[keep]] if has else np.zeros((0, 4, 4)),
                    dict(zip(idx.tolist(), status)), text("sequence_arg", "sequence"),
                    map=text("map_path", "map"), map_id=text("map_id"), poses=text("poses_arg"))
