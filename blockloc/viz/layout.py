"""The Foxglove layout for a blockloc run, and how to open a run's recording or live view.

The layout is built with foxglove-sdk's typed layout model (``foxglove.layouts``): a 3D panel in
the ``map`` frame following ``base_link`` (local map, aligned scan, block outlines, paths, pose
with covariance, TF), plots of the registration fitness and of the per-scan times, and the
diagnostics table of ``/diagnostics``. Import it in Foxglove with Layouts > Import from file.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from urllib.parse import quote

from blockloc.fileio import atomic_write_text
from blockloc.viz.events import VizError
from blockloc.viz.ros_codec import DIAG_HARDWARE_ID, DIAG_NAME, FRAME_BASE, FRAME_MAP

log = logging.getLogger(__name__)

RECORDING_NAME = "run.mcap"
LAYOUT_NAME = "foxglove_layout.json"
LIVE_NAME = "live.json"
REPORT_NAME = "report.html"
APP_URL = "https://app.foxglove.dev/~/view"

# Plot series: (diagnostics key, label, colour).
FITNESS_SERIES = (("fitness", "fitness (NDT)", "#1f77b4"),)
TIMING_SERIES = (("update_ms", "update (whole scan)", "#d62728"), ("registration_ms", "registration", "#2ca02c"),
                 ("smoother_ms", "smoother", "#9467bd"), ("map_ms", "map provider", "#8c564b"),
                 ("deskew_ms", "deskew", "#ff7f0e"))


def diagnostics_path(key: str) -> str:
    """Foxglove message path of one ``/diagnostics`` value (KeyValue text, plotted as a number)."""
    return f'/diagnostics.status[0].values[:]{{key=="{key}"}}.value'


def build_layout():
    """The layout as a ``foxglove.layouts.Layout``."""
    import foxglove.layouts as fl

    def series(rows):
        return [fl.PlotSeries(value=diagnostics_path(k), label=label, color=color, enabled=True)
                for k, label, color in rows]

    three_d = fl.ThreeDeePanel(title="map, scan and pose", config=fl.ThreeDeeConfig(
        fixed_frame=FRAME_MAP, follow_tf=FRAME_BASE, follow_mode="follow-position",
        camera_state=fl.ThreeDeeCameraState(distance=80.0, perspective=True, phi=50.0, theta_offset=45.0),
        scene=fl.BaseRendererSceneSettings(background_color="#15171c",
                                           transforms=fl.BaseRendererTransforms(show_label=True, axis_size=2.0)),
        layers={"grid": fl.BaseRendererGridLayerSettings(frame_id=FRAME_MAP, size=200.0, divisions=20,
                                                         color="#ffffff30", label="grid 10 m")},
        topics={
            "/map/local": fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=1.5, color_mode="colormap", color_map="turbo", color_field="z",
                explicit_alpha=0.6),
            "/points/aligned": fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=3.0, color_mode="flat", flat_color="#ff2d55"),
            "/map/blocks": fl.BaseRendererRosMarkerTopicSettings(visible=True),
            "/localization/path": fl.BaseRendererPosesTopicSettings(visible=True, type="line", line_width=0.4,
                                                                    gradient=("#ffd60a", "#ffd60a")),
            "/ground_truth/path": fl.BaseRendererPosesTopicSettings(visible=True, type="line", line_width=0.25,
                                                                    gradient=("#8e8e93", "#8e8e93")),
            "/localization/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#ffd60a",
                                                                   show_covariance=True,
                                                                   covariance_color="#ffd60a60"),
        }))
    fitness = fl.PlotPanel(title="registration fitness", config=fl.PlotConfig(
        paths=series(FITNESS_SERIES), show_legend=True, legend_display="floating", y_axis_label="fitness"))
    timing = fl.PlotPanel(title="per-scan time [ms]", config=fl.PlotConfig(
        paths=series(TIMING_SERIES), show_legend=True, legend_display="floating", y_axis_label="ms",
        min_y_value=0.0))
    diag = fl.DiagnosticsDetailPanel(title="diagnostics", config=fl.DiagnosticsDetailConfig(
        topic_to_render="/diagnostics", selected_hardware_id=DIAG_HARDWARE_ID, selected_name=DIAG_NAME,
        numeric_precision=3))
    right = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=1, content=fitness), fl.SplitItem(proportion=1, content=timing),
        fl.SplitItem(proportion=1.3, content=diag)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(proportion=1, content=right)]))


def layout_json() -> str:
    """The layout as indented JSON text."""
    return json.dumps(json.loads(build_layout().to_json()), indent=2) + "\n"


def write_layout(path: str | Path) -> Path:
    """Write the layout to ``path`` (atomically); returns the path."""
    path = Path(path)
    try:
        atomic_write_text(path, layout_json())
    except OSError as exc:
        raise VizError(f"Foxglove layout {path}: cannot write ({exc.strerror})") from None
    return path


def websocket_app_urls(ws_url: str) -> tuple[str, str]:
    """(web app link, ``foxglove://`` desktop link) that open a Foxglove WebSocket address."""
    q = f"ds=foxglove-websocket&ds.url={quote(ws_url, safe=':/')}"
    return f"{APP_URL}?{q}", f"foxglove://open?{q}"


def _serving(pid) -> bool:
    """Whether the process that wrote live.json still runs (checked without connecting: a bare
    TCP probe would make the server log a failed handshake)."""
    try:
        os.kill(int(pid), 0)
        return True
    except (OSError, TypeError, ValueError):
        return False


def _recording_summary(path: Path) -> str:
    """'N messages on T topics, S s of sensor time' from the file's summary (or why not)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as exc:  # a truncated file has no summary; say so rather than fail
        return f"no summary ({type(exc).__name__}); read it with mcap's stream reader or `mcap recover`"
    if summary is None or summary.statistics is None:
        return "no summary"
    st = summary.statistics
    span = (st.message_end_time - st.message_start_time) / 1e9
    return f"{st.message_count} messages on {st.channel_count} topics, {span:.1f} s of sensor time"


def view_instructions(run_dir: str | Path) -> str:
    """How to look at a results folder (or one ``.mcap`` file): the recording in Foxglove with the
    layout, the live server if one is running for it, and the HTML report. Raises VizError when
    there is nothing to view."""
    run_dir = Path(run_dir)
    if run_dir.is_file() and run_dir.suffix == ".mcap":
        recording, run_dir = run_dir.resolve(), run_dir.resolve().parent
    elif run_dir.is_dir():
        run_dir = run_dir.resolve()
        recording = run_dir / RECORDING_NAME
        if not recording.exists():
            found = sorted(run_dir.glob("*.mcap"))
            recording = found[0] if found else recording
    else:
        raise VizError(f"view {run_dir}: no such results folder or .mcap file")
    partial = recording.with_name(recording.name + ".partial")
    layout, report, live = run_dir / LAYOUT_NAME, run_dir / REPORT_NAME, run_dir / LIVE_NAME
    lines: list[str] = []
    if recording.exists() or partial.exists():
        rec = recording if recording.exists() else partial
        size_mb = rec.stat().st_size / 1e6
        state = "" if rec is recording else " (interrupted run: the recording was never finished)"
        lines += [f"Recording: {rec}{state}", f"  {size_mb:.1f} MB, {_recording_summary(rec)}",
                  "  Open it in Foxglove (desktop app, or https://app.foxglove.dev in Chrome): "
                  "Open local file(s)... (Ctrl+O) and pick it, or drag it onto the window.",
                  f"  Served over HTTP(S) with CORS and range requests it opens from a link: "
                  f"{APP_URL}?ds=remote-file&ds.url=<URL of {rec.name}>"]
        if rec is partial:
            lines.append("  Foxglove may refuse a file without summary: run `mcap recover` on it first.")
    if layout.exists():
        lines += [f"Layout: {layout}", "  In Foxglove: Layouts > Import from file... and pick it "
                  "(3D view of map, scan, blocks and paths; fitness and per-scan time plots; diagnostics)."]
    if live.exists():
        try:
            announced = json.loads(live.read_text())
            url, pid = announced["url"], announced.get("pid")
        except (OSError, ValueError, KeyError):
            url = pid = None
        if url and _serving(pid):
            web, desktop = websocket_app_urls(url)
            lines += [f"Live: {url} (serving now)", f"  {web}", f"  {desktop}"]
        elif url:
            lines.append(f"Live: {url} was announced but does not answer (the run has ended).")
    if report.exists():
        lines += [f"Report: {report}", f"  {report.as_uri()} (self-contained; any browser, offline)"]
    if not lines:
        raise VizError(f"view {run_dir}: no {RECORDING_NAME}, {LAYOUT_NAME}, {LIVE_NAME} or {REPORT_NAME} there "
                       f"(was the run made with --no-record?)")
    return "\n".join(lines)
