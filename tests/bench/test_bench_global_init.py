"""The global-init benchmark end to end on the tiny session: a scan the search refuses to start from
(global init raises, e.g. too few occupied cells in the height band) is a failure of that frame, as
a session goes on to the next scan, not the end of the benchmark."""

from __future__ import annotations

import pytest

from tests.faults import tiny


def test_a_refused_scan_is_a_failed_frame_not_the_end_of_the_run(tmp_path, monkeypatch):
    from bench import global_init as bench
    from blockloc.errors import GlobalInitError
    from blockloc.global_init.relocalize import GlobalLocalizer

    sess = tiny.write_tiny_session(tmp_path / "sess", n_frames=40)
    tiny.build_tiny_map(sess, tmp_path / "map")
    real = GlobalLocalizer.localize
    calls = []

    def localize(self, *args, **kw):
        calls.append(len(calls))
        if len(calls) in (1, 4):  # the first hinted frame and the first no-hint one
            raise GlobalInitError("scan has 3 occupied cells in the height band (0.3, 3.0) m: expected at least 50")
        return real(self, *args, **kw)

    monkeypatch.setattr(GlobalLocalizer, "localize", localize)
    out = tmp_path / "gi.md"
    res = bench.run(["--seq", str(sess), "--map", str(tmp_path / "map"), "--frames", "3", "--reloc-frames", "3",
                      "--methods", "hinted", "--out", str(out)])
    assert len(calls) >= 6
    assert res["methods"]["hinted"]["frames"] == 3 and res["reloc"]["place index"]["frames"] == 3
    assert res["methods"]["hinted"]["success"] <= 2 / 3 and res["reloc"]["place index"]["success"] <= 2 / 3
    assert [name for name in res["refused"]] == ["hinted", "place index"]
    text = out.read_text()
    assert "refused to start from" in text and "3 occupied cells" in text
