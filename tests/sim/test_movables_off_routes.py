"""Parked objects never stand on a route: a robot does not drive through a parked car (campus
routes passed within 1.5 m of 51 car centres, the LiDAR inside the car's mesh, until they were
taken off the routes)."""

from __future__ import annotations

import numpy as np

from blockloc.sim.world import ROUTE_CLEARANCE_M, Movables, off_routes


def _movables(xy, yaw, kind="car"):
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return Movables(np.array([kind] * len(xy)), xy, np.asarray(yaw, dtype=float), np.arange(len(xy)))


def _line(y, x0=-20.0, x1=20.0):
    x = np.arange(x0, x1, 0.25)
    return np.stack([x, np.full_like(x, y)], axis=1)


def test_a_car_is_kept_only_when_its_footprint_clears_the_route():
    # a car along x (yaw 0): half width 0.9 m across the route, so its centre may be 1.7+ m away
    cars = _movables([[0.0, 0.9 + ROUTE_CLEARANCE_M + 0.05], [0.0, 0.9 + ROUTE_CLEARANCE_M - 0.05]], [0.0, 0.0])
    kept = off_routes(cars, _line(0.0))
    assert kept.uid.tolist() == [0]
    # turned across the route (yaw 90 deg) its half length (2.2 m) faces it: 2.5 m is too close
    across = _movables([[0.0, 2.5], [0.0, 2.2 + ROUTE_CLEARANCE_M + 0.05]], [np.pi / 2, np.pi / 2])
    assert off_routes(across, _line(0.0)).uid.tolist() == [1]
    # a route that stops short of the car leaves it alone; a bin is small
    assert off_routes(_movables([[30.0, 0.0]], [0.0]), _line(0.0)).uid.tolist() == [0]
    assert off_routes(_movables([[0.0, 1.2]], [0.0], kind="bin"), _line(0.0)).uid.tolist() == [0]
    assert off_routes(_movables([[0.0, 1.0]], [0.0], kind="bin"), _line(0.0)).uid.tolist() == []


def test_a_scene_leaves_out_the_objects_on_a_route(monkeypatch):
    from blockloc.sim import stream
    from blockloc.sim.presets import PRESETS
    from blockloc.sim.world import session_movables

    world = stream.cached_world(PRESETS["small"], 1)
    base = session_movables(world, "map", True)
    car = int(np.nonzero(base.kind == "car")[0][0])
    # a route straight through that car (and nowhere near the others)
    through = base.xy[car] + np.stack([np.linspace(-3, 3, 25), np.zeros(25)], axis=1)
    monkeypatch.setattr(stream, "route_points", lambda preset, seed: through)
    got = stream.scene_movables(world, "map", True)
    assert base.uid[car] not in got.uid
    far = np.linalg.norm(base.xy - base.xy[car], axis=1) > 3.0 + 2.4 + 0.8  # out of the route's reach
    assert set(base.uid[far]) <= set(got.uid)  # everything out of reach is kept
    monkeypatch.undo()
    # the small world's own routes pass no parked object: its scenes keep every one
    assert len(stream.scene_movables(world, "map", True).uid) == len(base.uid)
