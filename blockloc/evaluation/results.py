"""A tracking run's results: the metrics of a run and the results folder, written as it goes.

:func:`run_metrics` turns what a session collected (per-frame diagnostics, counters, the
estimated trajectory, ground truth) into the flat dict saved as ``metrics.json``.

:class:`RunWriter` is a run observer (``start`` / ``frame`` / ``finish``) that fills a results
folder: ``poses.tum`` (time s, T_map_body) and ``diagnostics.csv`` are appended and flushed after
every frame, so a crash or a kill still leaves every pose computed so far; ``config.yaml`` is
written at the start; ``poses_kitti.txt`` (+ times), ``metrics.json`` and the plots at the end;
then a ``latest`` link beside the folder points at it. ``metrics.json`` is also what marks a
folder as blockloc's own (see :func:`blockloc.fileio.is_blockloc_output`).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blockloc.fileio import atomic_write_text, to_jsonable
from blockloc.geometry import Trajectory
from blockloc.resources import peak_rss_mb

log = logging.getLogger(__name__)

#: The files a results folder holds (the first two grow during the run).
RESULT_FILES = ("poses.tum", "diagnostics.csv", "config.yaml", "poses_kitti.txt", "poses_kitti.times.txt",
                "metrics.json", "trajectories.png", "errors.png", "error_breakdown.png")


def _q(values: Sequence[float], q: float) -> float | None:
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(np.percentile(a, q)) if len(a) else None


def run_metrics(*, diagnostics: list[dict], counters: dict, trajectory: Trajectory,
                ground_truth: Trajectory | None, evaluation: dict | None = None,
                plot_dir: Path | None = None, **facts: Any) -> dict:
    """The metrics of a run, JSON-ready.

    diagnostics: one dict per frame (the tracker's fields plus index, stamp; status
    ``skipped`` for frames that could not be read). counters: the tracker's and the session's
    counts. trajectory: the estimate (T_map_body). ground_truth: or None (no accuracy figures).
    evaluation: keywords of :func:`~blockloc.evaluation.report.evaluate_trajectories` (align,
    max_time_diff_s, rpe_deltas_m); plot_dir: where its plots go (None: no plots). facts:
    anything else to record (sequence, map, backend, init, timings, map_stats, ...).
    """
    d = [x for x in diagnostics if x.get("status") != "skipped"]
    tracked = [x for x in d if x["status"] != "uninitialized"]
    upd = [x["update_ms"] for x in tracked]
    m: dict[str, Any] = dict(facts)
    m.update({
        "frames": len(diagnostics), "processed": len(d), "estimated": len(trajectory), **counters,
        "update_ms_median": _q(upd, 50), "update_ms_mean": float(np.mean(upd)) if upd else None,
        "update_ms_p99": _q(upd, 99), "update_ms_max": float(np.max(upd)) if upd else None,
        "switch_update_ms_p99": _q([x["update_ms"] for x in d if x.get("switched")], 99),
        "fitness_median": _q([x["fitness"] for x in d], 50),
        "window_size_min": int(min((x["window_size"] for x in d), default=0)),
        "window_size_max": int(max((x["window_size"] for x in d), default=0)),
        "peak_rss_mb": peak_rss_mb(),
    })
    for key in ("deskew_ms", "registration_ms", "smoother_ms", "map_ms"):
        m[f"{key}_median"] = _q([x[key] for x in d if key in x], 50)
    if ground_truth is not None and len(trajectory) > 1:
        from blockloc.errors import EvaluationError
        from blockloc.evaluation.report import evaluate_trajectories

        if plot_dir is not None:
            Path(plot_dir).mkdir(parents=True, exist_ok=True)
        try:
            m.update(evaluate_trajectories(ground_truth, trajectory, plot_dir=plot_dir, interpolate=True,
                                           **(evaluation or {})))
        except EvaluationError as exc:  # e.g. no estimate overlaps the ground truth
            log.warning("no accuracy figures: %s", exc)
            m["evaluation_error"] = str(exc)
    return to_jsonable(m)


#: Bytes a results folder keeps allocated while a run writes (``.reserve``), freed when the disk
#: fills or the run ends, so that its metrics, KITTI poses and report still fit.
RESERVE_BYTES = 2**20
RESERVE_NAME = ".reserve"


class RunWriter:
    """Run observer that writes the results folder ``out`` (see the module docstring). Rows are
    appended whole (:class:`blockloc.fileio.RowFile`); a file that cannot be written raises
    :class:`~blockloc.errors.OutputWriteError` naming it (the run stops; ``finish`` still writes
    the metrics of what was done, into the space :data:`RESERVE_BYTES` kept free)."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)
        self._poses = None
        self._diag = None
        self._diag_fields: list[str] | None = None
        self._reserve: Path | None = None
        self._stamps: list[float] = []
        self._T: list[np.ndarray] = []

    def start(self, info) -> None:
        import yaml

        from blockloc.errors import OutputWriteError
        from blockloc.fileio import RowFile, reserve_space
        from blockloc.outdir import RESULTS, write_marker
        from blockloc.trajectory_io import TUM_HEADER

        try:
            self.out.mkdir(parents=True, exist_ok=True)
            write_marker(self.out, RESULTS)  # first: what follows is blockloc's, a kill or not
            (self.out / "metrics.json").unlink(missing_ok=True)  # an earlier run's: not this one's
            self._reserve = reserve_space(self.out / RESERVE_NAME, RESERVE_BYTES)
            atomic_write_text(self.out / "config.yaml", yaml.safe_dump(to_jsonable(info.config), sort_keys=False))
        except OSError as exc:
            raise OutputWriteError.of(getattr(exc, "filename", None) or self.out, exc) from None
        self._poses = RowFile(self.out / "poses.tum")
        self._poses.write(TUM_HEADER + "\n")
        self._diag = RowFile(self.out / "diagnostics.csv")

    def frame(self, event) -> None:
        from blockloc.trajectory_io import tum_lines

        try:
            # the frame's diagnostics row first, then its pose: a run killed between the two writes
            # leaves a diagnostics row without its pose, never a pose without its row
            if self._diag is not None:
                row = {"index": event.index, "stamp": f"{event.stamp:.9f}", "status": event.status,
                       **{k: v for k, v in event.diagnostics.items() if k != "status"}}
                text = ""
                if self._diag_fields is None:
                    self._diag_fields = list(row)
                    text = _csv_row(self._diag_fields)
                text += _csv_row([row.get(k, "") for k in self._diag_fields])
                self._diag.write(text)
            if event.T_map_body is not None and self._poses is not None:
                self._poses.write(tum_lines([event.stamp], event.T_map_body[None])[0] + "\n")
                self._stamps.append(float(event.stamp))
                self._T.append(np.asarray(event.T_map_body))
        except BaseException:
            from blockloc.fileio import release_space

            release_space(self._reserve)  # the disk is full: make room for the metrics
            self._reserve = None
            raise

    def finish(self, metrics: dict) -> None:
        from blockloc.errors import OutputWriteError
        from blockloc.fileio import release_space
        from blockloc.trajectory_io import write_kitti

        release_space(self._reserve)
        self._reserve = None
        for fh in (self._poses, self._diag):
            if fh is not None:
                fh.close()
        self._poses = self._diag = None
        try:
            atomic_write_text(self.out / "metrics.json", json.dumps(to_jsonable(metrics), indent=2))
            if self._T:
                write_kitti(self.out / "poses_kitti.txt", Trajectory(np.asarray(self._stamps), np.asarray(self._T)))
        except OSError as exc:
            raise OutputWriteError.of(getattr(exc, "filename", None) or self.out / "metrics.json", exc) from None
        _point_latest(self.out)


def _csv_row(values) -> str:
    """One CSV row (csv module quoting), with its newline."""
    import io

    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(values)
    return buf.getvalue()


def _point_latest(out: Path) -> None:
    """``latest`` beside ``out`` -> ``out``, only when ``latest`` is absent or a link blockloc
    made (it points at a results folder beside it: :func:`blockloc.outdir.is_blockloc_link`); a
    user's own ``latest`` (a link elsewhere, a file, a directory) is left alone, with a warning."""
    import os

    from blockloc.outdir import is_blockloc_link

    latest = out.parent / "latest"
    try:
        if latest.is_symlink() and not is_blockloc_link(latest):
            log.warning("%s: not updated (a link blockloc did not make: it points at %s)", latest,
                        os.readlink(latest))
        elif latest.is_symlink() or not latest.exists():
            tmp = out.parent / f".latest.{os.getpid()}.tmp"
            if tmp.is_symlink():
                tmp.unlink()
            tmp.symlink_to(out.name)
            tmp.replace(latest)
    except OSError as exc:  # e.g. a file system without symlinks
        log.info("no 'latest' link: %s", exc)
