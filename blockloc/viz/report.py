"""``write_report``: a run's ``report.html``, one self-contained page (no fetch at view time).

The page holds: the headline figures and the whole metrics table; an interactive top view of the
map (subsampled points, block/tile outlines, ground-truth and estimated paths, the robot at the
chosen time with its served block highlighted; pan by dragging, zoom with the wheel, layers
toggled, a time slider that plays the run); per-scan time and fitness over time with the frames
that were not ``ok`` shaded; the PNG plots embedded as data URIs; the config used.
Everything is inline: the data as JSON (arrays as base64), the script and style from
:mod:`blockloc.viz._report_assets`.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from blockloc.fileio import atomic_write_text, to_jsonable
from blockloc.viz.events import VizError
from blockloc.viz.ros_messages import outline_xy

log = logging.getLogger(__name__)

MAP_POINTS_MAX = 150_000
PATH_POINTS_MAX = 20_000
STATUS_CODES = {"ok": 0, "recovered": 1, "rejected": 2, "imu_only": 3, "lost": 4, "uninitialized": 5}
# Per-frame series drawn over time, if the diagnostics have them: (key, label, colour).
TIME_SERIES = (("update_ms", "whole update", "#d62728"), ("registration_ms", "registration", "#2ca02c"),
               ("smoother_ms", "smoother", "#9467bd"), ("map_ms", "map provider", "#8c564b"),
               ("deskew_ms", "deskew", "#ff7f0e"))
FITNESS_SERIES = (("fitness", "fitness", "#1f77b4"),)
HEADLINE = (("ate_trans_rmse_m", "ATE RMSE", "m"), ("ate_trans_max_m", "ATE max", "m"),
            ("ate_rot_rmse_deg", "rotation RMSE", "deg"), ("err_along_mean_m", "along-track mean", "m"),
            ("err_cross_rms_m", "cross-track RMS", "m"), ("err_time_shift_s", "best time shift", "s"),
            ("frames", "frames", ""),
            ("estimated", "estimated", ""), ("failures", "failures", ""), ("recoveries", "recoveries", ""),
            ("switches", "switches", ""), ("update_ms_median", "update median", "ms"),
            ("update_ms_p99", "update p99", "ms"), ("path_length_m", "path", "m"), ("duration_s", "duration", "s"))


def _b64(a: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _stride(n: int, cap: int) -> int:
    return max(1, math.ceil(n / cap))


def _fmt(v: Any) -> str:
    """A metrics value as table text."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    if isinstance(v, str):
        return v
    text = json.dumps(to_jsonable(v), separators=(", ", ": "))
    return text if len(text) <= 400 else text[:400] + " …"


def _flatten(metrics: dict, prefix: str = "") -> list[tuple[str, Any]]:
    rows = []
    for k, v in metrics.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and len(prefix) < 40:
            rows += _flatten(v, key + ".")
        else:
            rows.append((key, v))
    return rows


def _series(diagnostics: list[dict], key: str) -> np.ndarray | None:
    vals = [d.get(key) for d in diagnostics]
    if not any(isinstance(v, (int, float, np.number)) and not isinstance(v, bool) for v in vals):
        return None
    return np.array([float(v) if isinstance(v, (int, float, np.number)) else np.nan for v in vals])


def _config_text(config: dict) -> str:
    import yaml

    try:
        return yaml.safe_dump(to_jsonable(config), sort_keys=False, default_flow_style=False, width=100)
    except yaml.YAMLError:
        return json.dumps(to_jsonable(config), indent=2)


def _png_uri(path: Path) -> str:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise VizError(f"report: image {path} cannot be read ({exc.strerror})") from None
    if not data.startswith(b"\x89PNG"):
        raise VizError(f"report: image {path} is not a PNG")
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def report_data(*, metrics: dict, estimate, ground_truth, diagnostics: list[dict], map_xy: np.ndarray,
                map_entries: list[dict], title: str) -> dict:
    """The page's data (JSON-able): paths, map, outlines and per-frame series, times relative to t0."""
    stamps_all = [float(d["stamp"]) for d in diagnostics if d.get("stamp") is not None]
    t0 = min([*stamps_all, *(estimate.stamps[:1] if len(estimate) else [])], default=0.0)
    est_idx = np.arange(0, len(estimate), _stride(len(estimate), PATH_POINTS_MAX))
    est_T = estimate.poses[est_idx]
    yaw = np.arctan2(est_T[:, 1, 0], est_T[:, 0, 0]) if len(est_T) else np.zeros(0)
    data: dict[str, Any] = {
        "title": title, "t0": t0,
        "est_t": _b64(estimate.stamps[est_idx] - t0, np.float64),
        "est_xy": _b64(est_T[:, :2, 3], np.float64), "est_yaw": _b64(yaw, np.float32),
        "gt_xy": "", "gt_t": "",
        "map_xy": _b64(np.asarray(map_xy, float).reshape(-1, 2)[::_stride(len(map_xy), MAP_POINTS_MAX)], np.float32),
        "entries": [{"id": str(e["id"]), "outline": outline_xy(e).round(3).tolist(),
                     "centroid": [round(float(c), 3) for c in np.asarray(e["centroid"], float)[:2]]}
                    for e in map_entries],
    }
    if ground_truth is not None and len(ground_truth):
        gi = np.arange(0, len(ground_truth), _stride(len(ground_truth), PATH_POINTS_MAX))
        data["gt_xy"] = _b64(ground_truth.positions[gi, :2], np.float64)
        data["gt_t"] = _b64(ground_truth.stamps[gi] - t0, np.float64)
    frames = [d for d in diagnostics if d.get("stamp") is not None]
    data["frames"] = {
        "t": _b64(np.array([float(d["stamp"]) for d in frames]) - t0, np.float64),
        "status": [STATUS_CODES.get(str(d.get("status")), 2) for d in frames],
        "block": [None if d.get("block_id") is None else str(d["block_id"]) for d in frames],
        "active": [list(map(str, d["active_entries"])) if isinstance(d.get("active_entries"), (list, tuple))
                   else None for d in frames],
        "series": {},
    }
    for key, label, color in TIME_SERIES + FITNESS_SERIES:
        s = _series(frames, key)
        if s is not None:
            data["frames"]["series"][key] = {"label": label, "color": color, "values": _b64(s, np.float32)}
    data["status_names"] = list(STATUS_CODES)
    return data


def write_report(path: str | Path, *, metrics: dict, estimate, ground_truth, diagnostics: list[dict],
                 config: dict, map_xy: np.ndarray, map_entries: list[dict], images: dict[str, Path],
                 title: str | None = None) -> Path:
    """Write the run's ``report.html`` to ``path`` (atomically); returns the path.

    metrics: the run's flat metrics dict (``metrics.json``). estimate, ground_truth:
    :class:`blockloc.geometry.Trajectory` of ``T_map_body`` (ground truth may be None).
    diagnostics: one dict per frame with at least ``stamp`` and ``status`` (as ``diagnostics.csv``;
    optional ``active_entries``). config: the config used (plain dict). map_xy: (K, 2) map points,
    map frame x/y metres, already subsampled (more than 150k are strided down). map_entries: as
    ``RunInfo.map_entries``. images: caption -> PNG path, embedded as data URIs.
    """
    from blockloc.viz._report_assets import SCRIPT, STYLE

    path = Path(path)
    title = title or str(metrics.get("sequence") or "blockloc run")
    data = report_data(metrics=metrics, estimate=estimate, ground_truth=ground_truth, diagnostics=diagnostics,
                       map_xy=map_xy, map_entries=map_entries, title=title)
    esc = html.escape
    heads = "".join(
        f'<div class="fig"><div class="v">{esc(_fmt(metrics[k]))}<small>{esc(unit)}</small></div>'
        f'<div class="k">{esc(label)}</div></div>'
        for k, label, unit in HEADLINE if metrics.get(k) is not None)
    rows = "".join(f'<div class="row"><span class="k">{esc(k)}</span><span class="v">{esc(_fmt(v))}</span></div>'
                   for k, v in _flatten(metrics))
    figures = "".join(f'<figure><img alt="{esc(name)}" src="{_png_uri(p)}"><figcaption>{esc(name)}</figcaption></figure>'
                      for name, p in images.items())
    notes = "".join(f"<li>{esc(str(n))}</li>" for n in metrics.get("notes") or [])
    payload = json.dumps(to_jsonable(data), separators=(",", ":")).replace("</", "<\\/")
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'">
<title>{esc(title)} · blockloc report</title>
<style>{STYLE}</style></head>
<body>
<header><h1>{esc(title)}</h1>
<p class="sub">blockloc localization run · {esc(str(metrics.get("backend") or ""))} map
{esc(str(metrics.get("map") or ""))}</p>
<div class="figs">{heads}</div>{f'<ul class="notes">{notes}</ul>' if notes else ''}</header>
<main>
<section id="top"><h2>Top view</h2>
<div class="toolbar" id="layers"></div>
<div class="view"><canvas id="topview" tabindex="0" aria-label="top view of the map and paths"></canvas>
<div class="readout" id="readout"></div></div>
<div class="player"><button id="play" type="button">play</button>
<input id="slider" type="range" min="0" max="0" value="0" aria-label="time">
<span id="now"></span></div>
<p class="hint">Drag to pan, wheel to zoom, double-click to fit. The orange outline is the block
served at the chosen time; red marks frames that were rejected, IMU-only or lost.</p></section>
<section id="time"><h2>Over time</h2>
<canvas id="timing" class="chart" aria-label="per-scan time"></canvas>
<canvas id="fitness" class="chart" aria-label="fitness"></canvas></section>
<section id="metrics"><h2>Metrics</h2><div class="metrics">{rows}</div></section>
{f'<section id="plots"><h2>Plots</h2><div class="plots">{figures}</div></section>' if figures else ''}
<section id="config"><h2>Config used</h2><pre>{esc(_config_text(config))}</pre></section>
</main>
<script type="application/json" id="run-data">{payload}</script>
<script>{SCRIPT}</script>
</body></html>
"""
    try:
        atomic_write_text(path, page)
    except OSError as exc:
        raise VizError(f"report {path}: cannot write ({exc.strerror})") from None
    log.info("report: %s (%.1f MB)", path, len(page) / 1e6)
    return path
