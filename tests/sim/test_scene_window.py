"""A windowed scene (large worlds) renders a scan the same whichever scans the process cast
before: a map build on several workers renders each keyframe in whichever process runs it."""

from __future__ import annotations

import numpy as np

from blockloc.sim.presets import get_preset
from blockloc.sim.stream import SimSequence

HALF_M = 12.0  # the window's half size: cells of 8.4 m, the tiny drive crosses several


def _xy(seq, index: int) -> np.ndarray:
    return seq.trajectory.T_world_flu(np.array([index * seq.period_s]))[0][:2, 3]


def test_a_windowed_scan_does_not_depend_on_the_scans_cast_before():
    preset = get_preset("tiny", scene_window_m=HALF_M)
    fresh = SimSequence(preset, "map", 1)
    near = len(fresh) // 3
    # a frame 2..4 m before: the window the scene had before would still have been in use there
    before = next(j for j in range(near - 1, 0, -1)
                  if 2.0 < np.abs(_xy(fresh, j) - _xy(fresh, near)).max() < 4.0)
    a = fresh.frame(near)
    other = SimSequence(preset, "map", 1)
    other.frame(len(other) - 1)
    other.frame(before)
    b = other.frame(near)
    assert len(a.points) > 100
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.intensity, b.intensity)


def test_windows_hold_no_terrain_and_share_the_worlds_terrain_scene():
    """The terrain is cast in one scene per world: a window holds only what lies in it (in a
    city the terrain was 96% of each window, ~140 MB of BVH per window, four kept per drive)."""
    from blockloc.sim.scene import WINDOW_CACHE, SessionScene, make_actors, terrain_scene
    from blockloc.sim.world import session_movables

    preset = get_preset("tiny", scene_window_m=HALF_M)
    seq = SimSequence(preset, "map", 1)
    for i in range(0, len(seq), max(1, len(seq) // 12)):
        seq.frame(i)
    scene = seq.scene
    assert 2 <= len(scene._windows) <= WINDOW_CACHE
    for _, sel, *_ in scene._windows.values():
        assert len(sel) and not np.any(scene._tri_cat[sel] == scene.terrain_cat)
    loc = SessionScene(seq.world, session_movables(seq.world, "loc", False), make_actors(seq.world, "loc"), "loc")
    loc.distance(np.zeros((1, 3)))  # builds its first window
    assert loc._terrain_scene is scene._terrain_scene is terrain_scene(seq.world).scene


def test_mapping_sessions_share_one_scene_and_render_as_alone():
    """Mapping days have the same scene (base movables, no actors): one per world and process.
    A mapping drive's scan is the same whether the other drives rendered through it before."""
    from blockloc.sim import stream

    preset = get_preset("tiny", scene_window_m=HALF_M, sessions=("map1", "map2", "loc"),
                        route_length_m=(90.0, 90.0, 70.0))
    a, b = SimSequence(preset, "map1", 1), SimSequence(preset, "map2", 1)
    assert a.scene is b.scene
    assert SimSequence(preset, "loc", 1).scene is not a.scene
    b.frame(len(b) - 1)
    shared = a.frame(len(a) // 2)
    stream._MAPPING_SCENES.clear()  # a fresh scene, as a process that opened only map1
    alone = SimSequence(preset, "map1", 1)
    assert alone.scene is not a.scene
    np.testing.assert_array_equal(alone.frame(len(a) // 2).points, shared.points)


def test_shared_scenes_go_with_the_last_sequence_holding_them():
    """The shared mapping scene and terrain scene are not kept by the process once no sequence
    holds them (a serial map build forgets its drives: their scenes must go too)."""
    import gc
    import weakref

    from blockloc.sim.scene import terrain_scene

    preset = get_preset("tiny", scene_window_m=HALF_M)
    seq = SimSequence(preset, "map", 1)
    seq.frame(0)
    scene, terrain = weakref.ref(seq.scene), weakref.ref(terrain_scene(seq.world))
    assert scene() is not None and terrain() is not None
    del seq
    gc.collect()
    assert scene() is None and terrain() is None
