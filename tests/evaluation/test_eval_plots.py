"""``evaluation/plots.py`` directly: PNGs of the size asked for, drawn where the data says, written
atomically (no temp file beside them, an old file replaced whole)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from blockloc.evaluation.plots import plot_errors_over_time, plot_trajectories


def _read(path):
    from matplotlib.image import imread

    return imread(path)[..., :3]


def test_plot_trajectories(tmp_path):
    t = np.linspace(0, 2 * np.pi, 200)
    gt = np.c_[20 * np.cos(t), 10 * np.sin(t)]
    est = gt[::2] + 0.1
    err = np.linspace(0.0, 0.5, len(est))
    path = tmp_path / "traj.png"
    path.write_bytes(b"old")
    assert plot_trajectories(path, gt, est, err, title="a title") == path
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.png"]
    img = _read(path)
    assert img.shape[:2] == (6 * 120, 7 * 120)  # figsize (7, 6) at 120 dpi
    # the ground truth line is grey 0.6; viridis' ends (dark purple, yellow) mark the errors
    grey = np.all(np.abs(img - 0.6) < 0.02, axis=-1).mean()
    yellow = np.all(np.abs(img - [0.993, 0.906, 0.144]) < 0.06, axis=-1).mean()
    assert grey > 1e-3 and yellow > 1e-4


def test_plot_errors_over_time(tmp_path):
    stamps = 1e9 + np.arange(100) * 0.1
    trans = np.abs(np.sin(np.arange(100) / 10.0))
    rot = np.linspace(0, 2, 100)
    path = plot_errors_over_time(tmp_path / "err.png", stamps, trans, rot)
    img = _read(path)
    assert img.shape[:2] == (5 * 120, 8 * 120)
    c0 = np.array([0x1F, 0x77, 0xB4]) / 255  # C0: translation, C1: rotation, C3: the RMSE line
    c1 = np.array([0xFF, 0x7F, 0x0E]) / 255
    c3 = np.array([0xD6, 0x27, 0x28]) / 255
    top, bottom = img[: img.shape[0] // 2], img[img.shape[0] // 2:]

    def share(part, rgb):
        return np.all(np.abs(part - rgb) < 0.05, axis=-1).mean()

    assert share(top, c0) > 1e-3 and share(bottom, c0) < 1e-4
    assert share(bottom, c1) > 1e-3 and share(top, c1) < 1e-4
    assert np.all(np.abs(top - c3) < 0.15, axis=-1).mean() > 1e-4  # thin, dashed


def test_failed_plot_leaves_the_old_file(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    def disk_full(self, fname, **kw):
        Path(fname).write_bytes(b"partial")
        raise OSError("No space left on device")

    monkeypatch.setattr(Figure, "savefig", disk_full)
    path = tmp_path / "traj.png"
    path.write_bytes(b"old")
    with pytest.raises(OSError, match="No space"):
        plot_trajectories(path, np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3))
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.png"]
