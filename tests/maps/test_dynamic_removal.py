"""Our dynamic-point remover: voxel scan evidence over one drive, no prior map."""

import numpy as np

from blockloc.maps.dynamic_removal import DynamicParams, dynamic_voxels, scan_evidence, static_mask


def _scene(n_scans=12, walker_scans=3):
    """A drive along x (sensor 1.7 m above the ground, z up) past a wall at y = 10 and the ground;
    a walker stands at (5, 5) in the first scans and is gone later (rays to the wall behind now
    pass where it stood). Returns [(origin, points, dynamic)]."""
    xs, zs = np.meshgrid(np.arange(-10, 20, 0.1), np.arange(0.0, 3.0, 0.1))
    wall = np.stack([xs.ravel(), np.full(xs.size, 10.0), zs.ravel()], axis=1)
    gx, gy = np.meshgrid(np.arange(-10, 20, 0.2), np.arange(1.0, 10.0, 0.2))
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    wz, wa = np.meshgrid(np.arange(0.05, 1.75, 0.05), np.linspace(0, 2 * np.pi, 16, endpoint=False))
    walker = np.stack([5 + 0.25 * np.cos(wa.ravel()), 5 + 0.25 * np.sin(wa.ravel()), wz.ravel()], axis=1)
    out = []
    for k in range(n_scans):
        origin = np.array([k * 1.0, 0.0, 1.7])
        pts = [wall, ground] + ([walker] if k < walker_scans else [])
        dyn = [np.zeros(len(wall), bool), np.zeros(len(ground), bool)] + (
            [np.ones(len(walker), bool)] if k < walker_scans else [])
        out.append((origin, np.concatenate(pts), np.concatenate(dyn)))
    return out


def test_walker_left_out_wall_and_ground_kept():
    scans = _scene()
    p = DynamicParams(voxel_m=0.4, margin_m=0.5)
    ev = scan_evidence(((o, pts) for o, pts, _ in scans), p, up=np.array([0.0, 0.0, 1.0]))
    assert ev.scans == len(scans)
    keys = dynamic_voxels(ev, p)
    pts = np.concatenate([s[1] for s in scans])
    dyn = np.concatenate([s[2] for s in scans])
    keep = static_mask(pts, keys, p.voxel_m)
    assert keep[~dyn].mean() > 0.99  # the wall and the ground stay
    # the walker goes, but for its feet in the ground's voxels (voxel 0.4 m: the lowest 0.4 m);
    # without growing, the voxels next to the ground's (0.4-0.8 m) would stay too
    assert (~keep[dyn]).mean() > 0.7
    walker = pts[dyn]
    assert (~keep[dyn][walker[:, 2] > 0.4]).all()


def test_nothing_removed_from_a_static_scene():
    scans = _scene(walker_scans=0)
    p = DynamicParams()
    ev = scan_evidence(((o, pts) for o, pts, _ in scans), p, up=np.array([0.0, 0.0, 1.0]))
    keys = dynamic_voxels(ev, p)
    pts = np.concatenate([s[1] for s in scans])
    assert static_mask(pts, keys, p.voxel_m).mean() > 0.995


def test_one_scan_never_decides():
    scans = _scene(n_scans=1, walker_scans=0)
    p = DynamicParams(min_free=2)
    ev = scan_evidence(((o, pts) for o, pts, _ in scans), p)
    assert not len(dynamic_voxels(ev, p))


def test_static_masks_filter_only_the_own_scans_with_the_others_as_evidence():
    """What `map build --remove-dynamic` does per task: the walker is seen in scan 0 only; the
    scans after it (evidence, not filtered) see through where it stood, so scan 0 loses the
    walker and keeps the wall; asked for scan 0 alone as evidence, nothing can decide."""
    from blockloc.maps.dynamic_removal import static_masks

    scans = _scene(n_scans=8, walker_scans=1)
    up = np.array([0.0, 0.0, 1.0])
    (keep,) = static_masks([(o, p) for o, p, _ in scans], [0], DynamicParams(), up)
    dyn = scans[0][2]
    assert len(keep) == len(scans[0][1])
    assert keep[~dyn].mean() > 0.99 and (~keep[dyn]).mean() > 0.7
    (alone,) = static_masks([(scans[0][0], scans[0][1])], [0], DynamicParams(), up)
    assert alone.all()


def test_dynamic_filter_takes_the_context_inside_the_drive():
    """A task's evidence: its keyframes and up to 8 on each side, never past the drive's ends."""
    from types import SimpleNamespace

    from blockloc.maps.build_tasks import DYNAMIC_CONTEXT_KEYFRAMES, dynamic_filter

    T = np.tile(np.eye(4), (30, 1, 1))
    T[:, 0, 3] = np.arange(30.0)
    plan = SimpleNamespace(frames=np.arange(100, 130), T_map_lidar=T)
    f = dynamic_filter(plan, np.arange(3, 11), DynamicParams())
    assert f.frames == tuple(range(100, 111 + DYNAMIC_CONTEXT_KEYFRAMES))
    assert np.allclose(f.origins[:, 0], np.arange(0, 11 + DYNAMIC_CONTEXT_KEYFRAMES))
    f = dynamic_filter(plan, np.arange(24, 30), DynamicParams())
    assert f.frames == tuple(range(124 - DYNAMIC_CONTEXT_KEYFRAMES, 130))
