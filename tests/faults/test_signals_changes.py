"""``blockloc track --detect-changes`` stopped by Ctrl-C keeps what the detector accumulated while
tracking: ``changes.json`` from the frames tracked before the stop, saying so in its params."""

from __future__ import annotations

import json
import signal

from .cases import case
from .conftest import Running


@case(2, "SIGINT to `track --detect-changes` while it tracks and detects",
      "exit 130; the run is written, and changes.json from the frames tracked before the stop, its params "
      "saying so")
def test_track_detect_changes_stopped_writes_changes_of_the_frames_before(tiny_world, tmp_path):
    out = tmp_path / "res"
    run = Running("track", "--seq", tiny_world["long"], "--map", tiny_world["map"], "--init", "gt",
                  "--config", tiny_world["config"], "--out", out, "--detect-changes", "--changes-stride", "2")
    # past the 10 settling frames, so some frames are trusted and used
    run.wait_for(lambda: (out / "poses.tum").is_file() and len((out / "poses.tum").read_text().splitlines()) > 16)
    r = run.signal(signal.SIGINT)
    assert r.code == 130 and "Traceback" not in r.err, r.err[-800:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"] is True and m["frames"] < 120
    doc = json.loads((out / "changes.json").read_text())
    assert doc["params"]["interrupted"] is True and "interrupted" in doc["params"]["note"]
    assert doc["during"] == "track --detect-changes" and doc["cost"]["frames_tracked"] == m["frames"]
    # the frames fed: every frame tracked, the trusted ones after 10 ok frames, every 2nd used
    assert 1 <= doc["frames_trusted"] <= m["frames"] - 10 and doc["scans_used"] == (doc["frames_trusted"] + 1) // 2
    assert f"changes.json written from the {doc['frames_trusted']} trusted frames before the stop" in r.err
    assert "interrupted by SIGINT" in r.err
    assert not list(out.glob("*.partial")) and not list(out.glob(".changes.json*"))
