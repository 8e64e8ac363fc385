"""The Foxglove layout (panels, topics, plot paths that resolve on the recorded /diagnostics) and
``view_instructions``."""

from __future__ import annotations

import json
import re

import pytest

from blockloc.viz.events import VizError
from blockloc.viz.layout import diagnostics_path, layout_json, view_instructions, websocket_app_urls, write_layout
from blockloc.viz.ros_messages import TOPICS


def panels(node):
    if node.get("type") == "panel":
        yield node
    for item in node.get("items", []):
        yield from panels(item["content"])
    for tab in node.get("tabs", []):
        yield from panels(tab["content"])


def test_layout_panels_and_topics():
    layout = json.loads(layout_json())
    assert layout["version"] == 1
    by_type = {}
    for p in panels(layout["content"]):
        by_type.setdefault(p["panelType"], []).append(p)
    (three_d,) = by_type["ThreeDee"]
    cfg = three_d["config"]
    assert cfg["fixedFrame"] == "map" and cfg["followTf"] == "base_link"
    assert set(cfg["topics"]) <= set(TOPICS)
    assert {"/map/local", "/points/aligned", "/map/blocks", "/localization/path"} <= set(cfg["topics"])
    plots = {p["title"]: [s["value"] for s in p["config"]["paths"]] for p in by_type["Plot"]}
    assert diagnostics_path("fitness") in plots["registration fitness"]
    assert diagnostics_path("update_ms") in plots["per-scan time [ms]"]
    (diag,) = by_type["DiagnosticsDetail"]
    assert diag["config"]["topicToRender"] == "/diagnostics"


def test_plot_paths_name_keys_of_the_recorded_diagnostics(decoded):
    """Each plotted key is a KeyValue of every localized frame's status and parses as a number."""
    layout = json.loads(layout_json())
    keys = {m.group(1) for p in panels(layout["content"]) if p["panelType"] == "Plot"
            for s in p["config"]["paths"] for m in [re.search(r'key=="(\w+)"', s["value"])]}
    assert keys >= {"fitness", "update_ms"}
    for _, msg in decoded["/diagnostics"]:
        values = {kv.key: kv.value for kv in msg.status[0].values}
        for k in keys:
            float(values[k])


def test_view_instructions_for_a_recording(recording, tmp_path):
    path, _ = recording
    text = view_instructions(path.parent)
    assert str(path) in text and "foxglove_layout.json" in text and "Import from file" in text
    assert re.search(r"\d+ messages on 9 topics, 2\d\.\d s of sensor time", text)
    assert view_instructions(path) == text  # the .mcap itself works too


def test_view_instructions_live_and_report(tmp_path):
    from blockloc.viz.live import LiveServer
    from tests.viz.synthetic import make_run

    run = make_run(duration_s=1.0, scan_points=10, out_dir=tmp_path)
    (tmp_path / "report.html").write_text("<html></html>")
    srv = LiveServer(port=0)
    try:
        srv.start(run.info)
        for ev in run.events:
            srv.frame(ev)
        for _ in range(200):
            if (tmp_path / "live.json").exists():
                break
            import time
            time.sleep(0.05)
        text = view_instructions(tmp_path)
        web, desktop = websocket_app_urls(srv.url)
        assert f"Live: {srv.url} (serving now)" in text and web in text and desktop in text
        assert "ds=foxglove-websocket" in web and desktop.startswith("foxglove://open?")
        assert (tmp_path / "report.html").as_uri() in text
        assert (tmp_path / "foxglove_layout.json").exists()
    finally:
        srv.finish({})
    assert not (tmp_path / "live.json").exists()  # the server is gone: no stale address


def test_view_instructions_errors(tmp_path):
    with pytest.raises(VizError, match="no such results folder"):
        view_instructions(tmp_path / "missing")
    with pytest.raises(VizError, match="no run.mcap"):
        view_instructions(tmp_path)


def test_write_layout_is_atomic_json(tmp_path):
    p = write_layout(tmp_path / "sub" / "layout.json")
    assert json.loads(p.read_text())["content"]["type"] == "split"
    assert [f.name for f in p.parent.iterdir()] == ["layout.json"]
