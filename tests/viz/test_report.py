"""report.html: self-contained, and rendered by a real headless Chromium without console errors."""

from __future__ import annotations

import html.parser
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from blockloc.viz.events import VizError
from blockloc.viz.report import write_report
from tests.viz.chromium import chromium_binary, render
from tests.viz.report_fixture import report_inputs


class _Refs(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs, self.tags = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for k, v in attrs:
            if k in ("src", "href", "srcset", "data", "action") and v is not None:
                self.refs.append((tag, k, v))


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    inputs = report_inputs(out)
    return write_report(out / "report.html", **inputs), inputs


def test_self_contained(report):
    path, inputs = report
    text = path.read_text()
    parser = _Refs()
    parser.feed(text)
    assert parser.refs, "the PNG plots are embedded as images"
    assert all(v.startswith("data:image/png;base64,") for _, _, v in parser.refs), parser.refs
    assert "link" not in parser.tags and not re.search(r"<script[^>]*\bsrc=", text)
    assert not re.search(r"(fetch|XMLHttpRequest|import\s*\()", text.split('id="run-data"')[1])
    assert "default-src 'none'" in text  # and the page forbids any fetch itself


def test_data_holds_the_run(report):
    path, inputs = report
    text = path.read_text()
    data = json.loads(text.split('<script type="application/json" id="run-data">')[1].split("</script>")[0])
    import base64

    est = np.frombuffer(base64.b64decode(data["est_xy"]), np.float64).reshape(-1, 2)
    assert np.allclose(est, inputs["estimate"].positions[:, :2])
    assert len(np.frombuffer(base64.b64decode(data["map_xy"]), np.float32)) == 2 * len(inputs["map_xy"])
    assert [e["id"] for e in data["entries"]] == [e["id"] for e in inputs["map_entries"]]
    assert len(data["frames"]["status"]) == len(inputs["diagnostics"])
    assert set(data["frames"]["series"]) >= {"fitness", "update_ms", "registration_ms"}
    for key in ("ate_trans_rmse_m", "switches", "map_stats.loads", "init.mode"):
        assert f'<span class="k">{key}</span>' in text
    assert "tracking:\n  window_size: 20" in text  # the config, as YAML


def test_without_ground_truth_or_images(tmp_path):
    inputs = report_inputs(tmp_path, with_gt=False, with_images=False)
    path = write_report(tmp_path / "r.html", **inputs)
    text = path.read_text()
    assert '"gt_xy":""' in text and "<figure>" not in text


def test_bad_image_is_a_viz_error(tmp_path):
    inputs = report_inputs(tmp_path, with_images=False)
    (tmp_path / "x.png").write_text("not a png")
    with pytest.raises(VizError, match="not a PNG"):
        write_report(tmp_path / "r.html", **dict(inputs, images={"x": tmp_path / "x.png"}))


needs_chromium = pytest.mark.skipif(chromium_binary() is None,
                                    reason="Chromium not installed (Debian: apt-get install -y chromium)")


@needs_chromium
def test_renders_in_headless_chromium(report, tmp_path):
    from PIL import Image

    path, inputs = report
    shot = tmp_path / "report.png"
    scripts = {
        "ready": "window.blocklocReport && window.blocklocReport.ready === true",
        "drawn": "window.blocklocReport.drawn",
        "map_off": "document.getElementById('layer-map').click(); window.blocklocReport.drawn.map",
        "map_on": "document.getElementById('layer-map').click(); window.blocklocReport.drawn.map",
        "zoom": """(function () { var c = document.getElementById('topview'), r = c.getBoundingClientRect();
                     var s0 = window.blocklocReport.view.scale;
                     c.dispatchEvent(new WheelEvent('wheel', {deltaY: -400, clientX: r.left + r.width / 2,
                                                              clientY: r.top + r.height / 2, bubbles: true, cancelable: true}));
                     var s1 = window.blocklocReport.view.scale;
                     c.dispatchEvent(new MouseEvent('dblclick', {bubbles: true}));
                     return [s0, s1, window.blocklocReport.view.scale]; })()""",
        "slider": """(function () { var s = document.getElementById('slider'); s.value = 15;
                       s.dispatchEvent(new Event('input')); return document.getElementById('now').textContent; })()""",
    }
    res = render(path.as_uri(), shot, scripts=scripts)
    keep = os.environ.get("BLOCKLOC_VIZ_SCREENSHOTS")
    if keep:  # to look at it
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(keep) / "report.png")
    assert res.errors == []
    assert all(u == path.as_uri() or u.startswith("data:") for u in res.requests), res.requests
    assert res.values["ready"] is True
    drawn = res.values["drawn"]
    assert drawn["map"] > 10_000 and drawn["entries"] == 4 and drawn["bad"] >= 12
    assert res.values["map_off"] == 0 and res.values["map_on"] == drawn["map"]
    s0, s1, s2 = res.values["zoom"]
    assert s1 > 1.5 * s0 and s2 == pytest.approx(s0)
    assert res.values["slider"].startswith("t = 1.5 s · frame 15 · ok · served block_")

    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape[0] > 1500 and img.shape[1] == 1280  # the whole page, not a blank viewport
    assert img.std() > 30
    colours = np.unique((img[::4, ::4] // 16).reshape(-1, 3), axis=0)
    assert len(colours) > 200
    # The top view's canvas is dark with drawn content: map, outlines, paths.
    top = img[300:900, 60:1220]
    assert (top.mean(axis=2) < 40).mean() > 0.4 and (top.max(axis=2) > 150).mean() > 0.005


@needs_chromium
def test_a_run_that_never_localized_renders(tmp_path):
    """No pose, no ground truth, no map points, no plots: the page still renders without errors."""
    from blockloc.geometry import Trajectory

    diagnostics = [{"index": i, "stamp": 100.0 + 0.1 * i, "status": "uninitialized", "fitness": float("nan")}
                   for i in range(20)]
    path = write_report(tmp_path / "report.html", metrics={"frames": 20, "estimated": 0},
                        estimate=Trajectory(np.zeros(0), np.zeros((0, 4, 4))), ground_truth=None,
                        diagnostics=diagnostics, config={}, map_xy=np.zeros((0, 2)), map_entries=[], images={})
    res = render(path.as_uri(), tmp_path / "shot.png",
                 scripts={"ready": "window.blocklocReport.ready === true", "now": "document.getElementById('now').textContent"})
    assert res.errors == [] and res.values["ready"] is True
    assert "uninitialized" in res.values["now"]
