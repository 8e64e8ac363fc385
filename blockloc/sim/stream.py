"""Simulated sessions as ``Sequence`` objects, ray-cast on the fly (nothing written).

``open_sim_sequence("small", "loc", 1)`` -> a ``SimSequence``; frame i is a pure function of
(preset, seed, session, i): its noise comes from a generator seeded by (seed, session, i), so
random access, streaming and writing give the same scan.

Frames follow NCLT (``blockloc.datasets.nclt``): map z down, body x forward / y right / z down,
``T_body_lidar = NCLT_T_BODY_LIDAR``, IMU = body (``NCLT_T_BODY_IMU``), gravity (0, 0, +9.81).
Frame stamps are the sweep start; ``time_offsets`` lie in [0, 0.1) s.
"""

from __future__ import annotations

import functools
import logging
import threading
import weakref
from typing import Iterator

import numpy as np

from blockloc.datasets.base import ImuData, LidarFrame, SequenceInfo, frame_index
from blockloc.errors import SimError
from blockloc.geometry import Trajectory, make_T, so3_exp
from blockloc.sim.presets import Preset, get_preset
from blockloc.sim.trajectory import (D4, SimTrajectory, cover_route, crossing_route, lane_waypoints,
                                     plan_motion, relocalization_route)
from blockloc.sim.world import World, build_world, off_routes, session_movables, stable_hash

log = logging.getLogger(__name__)

#: Poses :meth:`SimSequence.mapping_poses` computes at a time (6 MB of (N, 4, 4) float64).
POSE_CHUNK = 50_000

#: Each session is another "day": (date used in NCLT file names, start epoch in s, UTC noon).
SESSION_DAYS = {"map": ("2020-06-01", 1591012800), "loc": ("2020-06-08", 1591617600),
                "loc2": ("2020-06-15", 1592222400), "loc3": ("2020-06-22", 1592827200)}


@functools.lru_cache(maxsize=4)
def cached_world(preset: Preset, seed: int) -> World:
    """``build_world`` memoised per (preset, seed) in this process and, when building it is slow
    (the city: 19 s CPU), on disk for other processes, keyed by the simulator's code. Its ground
    raster tiles are shared on disk too (:class:`blockloc.cache.DiskTiles`): each Dask worker of a
    city build otherwise rasterized the tiles its drives see, ~65 ms each, and two workers on
    two neighbouring drives rasterized 50% more tiles than one process (2 x 2000 frames: 531
    against 353)."""
    from blockloc.cache import DiskTiles, disk_memo, fingerprint

    key = fingerprint("blockloc.sim", params=(repr(preset), seed))
    world = disk_memo(f"world-{preset.name}-{seed}", key, lambda: build_world(preset, seed))
    world.material_tiles = DiskTiles(f"material-{preset.name}-{seed}", key)
    return world


@functools.lru_cache(maxsize=4)
def route_points(preset: Preset, seed: int, spacing_m: float = 0.25) -> np.ndarray:
    """(N, 2) world xy every ``spacing_m`` along the routes of all of the preset's sessions:
    where no parked object may stand (:func:`scene_movables`). Kept on disk like a drive's
    trajectory: a process that opens one drive's scene (a map-build worker) then needs neither
    every session's trajectory nor their splines."""
    from blockloc.cache import disk_memo

    return disk_memo(f"routes-{preset.name}-{seed}", drive_memo_key(preset, seed, f"routes:{spacing_m!r}"),
                     lambda: _route_points(preset, seed, spacing_m), min_build_s=DRIVE_MEMO_MIN_S)


def _route_points(preset: Preset, seed: int, spacing_m: float) -> np.ndarray:
    out = []
    for session in preset.sessions:
        # not through the in-process cache: the trajectories (and their splines, ~80 MB a city
        # drive) go when the points are taken; a drive opened in this process has its own
        traj = session_trajectory.__wrapped__(preset, seed, session)
        t = np.arange(0.0, traj.duration, 0.1)
        x, y, _ = traj.planar(t)
        xy = np.stack([x, y], axis=1)
        s_ = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        at = np.arange(0.0, s_[-1], spacing_m)
        out.append(np.stack([np.interp(at, s_, xy[:, 0]), np.interp(at, s_, xy[:, 1])], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def scene_movables(world: World, session: str, base: bool):
    """The movables a session's scene holds: ``session_movables`` without those standing on any
    session's route (a robot does not drive through a parked car)."""
    return off_routes(session_movables(world, session, base), route_points(world.preset, world.seed))


#: id(world) -> (weakref to the world, weakref to its mapping days' SessionScene): the scene
#: lives as long as a sequence holds it (a map build's process forgets its drives after a build).
_MAPPING_SCENES: dict = {}
_MAPPING_LOCK = threading.Lock()


def mapping_scene(world: World):
    """The ``SessionScene`` of ``world``'s mapping sessions, one per world in this process while
    a sequence holds it.

    Every mapping day has the same scene: the world's base movables, no moving actors, the
    foliage as generated (``make_actors`` and the foliage change leave mapping sessions alone),
    so a process opening several mapping drives of a city (a map build's worker) holds its
    triangle arrays (~100 MB for the city) and its scene windows once. A scan depends only on
    where it is cast, never on the windows built before (``blockloc.sim.scene.WINDOW_STEP``), so
    sharing the windows does not change a scan."""
    from blockloc.sim.scene import SessionScene, make_actors

    session = next(s for s in world.preset.sessions if world.preset.is_mapping(s))
    with _MAPPING_LOCK:
        got = _MAPPING_SCENES.get(id(world))
        scene = got[1]() if got is not None and got[0]() is world else None
        if scene is None:
            for k in [k for k, (w, sc) in _MAPPING_SCENES.items() if w() is None or sc() is None]:
                del _MAPPING_SCENES[k]
            scene = SessionScene(world, scene_movables(world, session, True), make_actors(world, session),
                                 session)
            _MAPPING_SCENES[id(world)] = (weakref.ref(world), weakref.ref(scene))
        return scene


def session_day(session: str) -> tuple[str, int]:
    """(date used in NCLT file names, start epoch s) of a session; unknown names get a day of
    their own derived from the name."""
    if session in SESSION_DAYS:
        return SESSION_DAYS[session]
    k = stable_hash(session) % 300
    epoch = 1593604800 + 86400 * k
    import datetime

    return datetime.datetime.fromtimestamp(epoch, datetime.timezone.utc).strftime("%Y-%m-%d"), epoch


def _region_routes(preset: Preset, roads, seed: int) -> list[list]:
    """Mapping routes of a preset whose mapping drives each cover a strip of the graph
    (``map_regions`` strips along x, overlapping by one road line): each first drives the
    middle east-west street across its strip (so the strips join), then covers the strip."""
    nx, ny = len(roads.xs), len(roads.ys)
    n = preset.map_regions
    bounds = np.linspace(0, nx - 1, n + 1)
    j_mid = ny // 2
    routes = []
    for k in range(n):
        i0, i1 = int(np.floor(bounds[k])), min(nx - 1, int(np.ceil(bounds[k + 1])) + (k < n - 1))
        rng = np.random.default_rng(np.random.SeedSequence([seed, stable_hash(preset.name), 4, k]))
        prefix = [(i, j_mid) for i in range(i0, i1 + 1)]
        ok = lambda nd, a=i0, b=i1: a <= nd[0] <= b  # noqa: E731
        routes.append(cover_route(roads, rng, preset.route_length_m[k], prefix[-1], ok, prefix))
    return routes


#: CPU seconds from which a drive's trajectory or mapping poses are kept on disk (a city drive:
#: ~1.5 s and ~1.1 s, paid otherwise by every process opening it; a tiny one: milliseconds).
DRIVE_MEMO_MIN_S = 0.2


def drive_memo_key(preset: Preset, seed: int, session: str) -> str:
    """The disk-cache key of a session's trajectory and poses: the code of the simulator, the
    geometry helpers and the NCLT frames (the body height comes from its extrinsic), numpy's and
    scipy's versions (the splines are pickled as scipy builds them), the preset, seed, session."""
    import scipy

    from blockloc.cache import fingerprint

    return fingerprint("blockloc.sim", "blockloc.geometry", "blockloc.datasets.nclt",
                       params=(repr(preset), int(seed), session, np.__version__, scipy.__version__))


@functools.lru_cache(maxsize=16)
def session_trajectory(preset: Preset, seed: int, session: str) -> SimTrajectory:
    """The session's trajectory (:func:`build_session_trajectory`), memoised in this process and,
    when building it is slow (a city drive), on disk for other processes (each Dask worker of a
    map build opens every drive), keyed by :func:`drive_memo_key`."""
    from blockloc.cache import disk_memo

    world = cached_world(preset, seed)
    if session not in preset.sessions:
        raise SimError(f"sim session {session!r}: preset {preset.name} has {', '.join(preset.sessions)}")
    state = disk_memo(f"trajectory-{preset.name}-{session}-{seed}", drive_memo_key(preset, seed, session),
                      lambda: build_session_trajectory(preset, seed, session).state(),
                      min_build_s=DRIVE_MEMO_MIN_S)
    return SimTrajectory.from_state(state, world)


def build_session_trajectory(preset: Preset, seed: int, session: str) -> SimTrajectory:
    """The session's trajectory computed afresh: the mapping drive covers the road graph (with
    ``map_regions`` > 1, each ``map<k>`` drive covers its strip); localization drives wander
    over the edges it drove, preferring the opposite direction and the hard places, from another
    start (or, over several mapping drives, cross all of them)."""
    world = cached_world(preset, seed)
    roads = world.roads
    if session not in preset.sessions:
        raise SimError(f"sim session {session!r}: preset {preset.name} has {', '.join(preset.sessions)}")
    k = preset.sessions.index(session)
    mapping = [s for s in preset.sessions if preset.is_mapping(s)]
    if preset.map_regions > 1:
        routes = _region_routes(preset, roads, seed)
        if session in mapping:
            route = routes[mapping.index(session)]
        else:
            rng = np.random.default_rng(np.random.SeedSequence([seed, stable_hash(session), 4]))
            mapped = {(min(a, b), max(a, b)) for r in routes for a, b in zip(r[:-2], r[1:-1])}
            route = crossing_route(roads, rng, preset.route_length_m[k], mapped)
    else:
        rng = np.random.default_rng(np.random.SeedSequence([seed, stable_hash(preset.name), 4]))
        map_route = cover_route(roads, rng, preset.route_length_m[0], (0, 0))
        if k == 0:
            route = map_route
        else:
            rng = np.random.default_rng(np.random.SeedSequence([seed, stable_hash(session), 4]))
            # the mapping drive stops part-way along its last edge: only full edges count as mapped
            driven = map_route[:-1]
            start = driven[(len(driven) * k) // (len(preset.sessions) + 1)]
            route = relocalization_route(roads, rng, preset.route_length_m[k], start, driven)
    wp, smooth = lane_waypoints(roads, route, preset.route_length_m[k])
    rng = np.random.default_rng(np.random.SeedSequence([seed, stable_hash(session), 8]))
    samples = plan_motion(wp, preset, rng, smooth)
    from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR

    body_height = preset.lidar_height_m + float(NCLT_T_BODY_LIDAR[2, 3])  # lidar 0.957 m above
    return SimTrajectory(samples, world, body_height, preset.platform,
                         int(np.random.SeedSequence([seed, stable_hash(session), 10]).generate_state(1)[0]))


def true_T_body_lidar(preset: Preset, seed: int) -> np.ndarray:
    """The robot's true LiDAR mounting: NCLT's nominal extrinsic moved by the preset's
    ``extrinsic_error_m`` / ``_deg`` (one draw per robot, i.e. per seed). The written and
    streamed sessions report the nominal one, as users are given."""
    from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA11B]))
    e = rng.normal(0.0, 1.0, 6)
    dT = make_T(so3_exp(np.deg2rad(preset.extrinsic_error_deg) * e[:3]), preset.extrinsic_error_m * e[3:])
    return np.asarray(NCLT_T_BODY_LIDAR, dtype=float) @ dT


def smooth_noise(rng: np.random.Generator, t: np.ndarray, dims: int, knot_s: float = 2.0) -> np.ndarray:
    """(len(t), dims) smooth zero-mean noise of ~unit std: cubic spline through N(0,1) knots."""
    return smooth_noise_spline(rng, float(t[0]), float(t[-1]), dims, knot_s)(t)


def smooth_noise_spline(rng: np.random.Generator, t0: float, t1: float, dims: int, knot_s: float = 2.0):
    """The spline :func:`smooth_noise` evaluates over times ``t0 .. t1`` (s): a callable t (M,)
    -> (M, dims), so that a long span can be evaluated a piece at a time (the same values)."""
    from scipy.interpolate import CubicSpline

    knots = np.arange(t0 - knot_s, t1 + 2 * knot_s, knot_s)
    vals = rng.normal(0.0, 1.0, (len(knots), dims)) / 0.85
    return CubicSpline(knots, vals)


class SimSequence:
    """One simulated session (see module docstring). Implements ``blockloc.datasets.base.Sequence``."""

    def __init__(self, preset: Preset, session: str, seed: int):
        from blockloc.datasets.nclt import NCLT_GRAVITY_MAP, NCLT_T_BODY_IMU, NCLT_T_BODY_LIDAR

        if session not in preset.sessions:
            raise SimError(f"sim session {session!r}: preset {preset.name} has {', '.join(preset.sessions)}")
        self.preset = preset
        self.session = session
        self.seed = int(seed)
        self.world = cached_world(preset, self.seed)
        self.trajectory = session_trajectory(preset, self.seed, session)
        self.date, epoch = session_day(session)
        self.epoch_us = int(epoch) * 1_000_000
        self.period_s = 1.0 / preset.lidar.rate_hz
        self._n = max(0, int((self.trajectory.duration - self.period_s) / self.period_s))
        # the renderer uses the true mounting; ``info`` carries the nominal one
        self.T_body_lidar_true = true_T_body_lidar(preset, self.seed)
        self.T_flu_lidar = D4 @ self.T_body_lidar_true
        from blockloc.sim.lidar import SensorCalibration

        self.calibration = SensorCalibration.draw(preset.lidar, self.seed)
        self._az0 = float(np.random.default_rng([self.seed, stable_hash(session), 9]).uniform(0, 2 * np.pi))
        self._scene = None
        self._imu = None
        self._mapping_poses = None
        self.info = SequenceInfo(name=f"sim:{preset.name}/{session}@{self.seed}",
                                 T_body_lidar=np.array(NCLT_T_BODY_LIDAR, dtype=float),
                                 T_body_imu=np.array(NCLT_T_BODY_IMU, dtype=float),
                                 gravity_map=np.array(NCLT_GRAVITY_MAP, dtype=float),
                                 lidar_rate_hz=preset.lidar.rate_hz, imu_rate_hz=preset.imu_rate_hz)

    # --- scene --------------------------------------------------------------------------------
    @property
    def scene(self):
        """The session's ``SessionScene`` (built on first use: static world + that day's movables).
        Mapping sessions share one per world in this process (:func:`mapping_scene`)."""
        if self._scene is None:
            from blockloc.sim.scene import SessionScene, make_actors

            if self.preset.is_mapping(self.session):
                self._scene = mapping_scene(self.world)
            else:
                self._scene = SessionScene(self.world, scene_movables(self.world, self.session, False),
                                           make_actors(self.world, self.session), self.session)
        return self._scene

    def prepare(self) -> None:
        """Build now what reading frames needs (the scene), e.g. on a build worker ahead of its
        first scan task, while the drives are planned."""
        self.scene  # noqa: B018 (built on first access)

    # --- protocol -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    def _utime(self, index: int) -> int:
        return self.epoch_us + int(round(index * self.period_s * 1e6))

    def frame_stamps(self) -> np.ndarray:
        return (self.epoch_us + np.rint(np.arange(self._n) * self.period_s * 1e6).astype(np.int64)) * 1e-6

    def frame(self, index: int) -> LidarFrame:
        return self.frame_with_labels(index)[0]

    def frame_with_labels(self, index: int) -> tuple[LidarFrame, np.ndarray]:
        """The frame and a (N,) int category per point (index into ``scene.categories``)."""
        from blockloc.sim.lidar import simulate_scan

        index = frame_index(index, self._n)
        t0 = (self._utime(index) - self.epoch_us) * 1e-6
        A = self.preset.lidar.azimuth_steps
        col_off = np.arange(A) * (self.period_s / A)
        T_wl = self.trajectory.T_world_flu(t0 + col_off) @ self.T_flu_lidar
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, stable_hash(self.session), 5, index]))
        res = simulate_scan(self.scene, T_wl, col_off, self.preset.lidar, rng, t0 + 0.5 * self.period_s,
                            self._az0, self.calibration)
        frame = LidarFrame(index, self._utime(index) * 1e-6, res.points, res.intensity,
                           res.time_offsets, res.ring)
        return frame, res.category

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[LidarFrame]:
        stop = self._n if stop is None else min(stop, self._n)
        for i in range(start, stop):
            yield self.frame(i)

    def _rel_times(self, rate_hz: float) -> np.ndarray:
        return np.arange(int(np.floor(self.trajectory.duration * rate_hz)) + 1) / rate_hz

    def imu(self) -> ImuData:
        """100 Hz samples in the body frame: ideal values through the unit's scale-factor and
        axis-misalignment errors, + white noise + bias (initial + random walk + Gauss-Markov
        instability), sampled ``time_offset_s`` before their stamps, with lost samples
        (``preset.imu``; 3DM-GX3 class)."""
        if self._imu is None:
            noise = self.preset.imu
            f = self.preset.imu_rate_hz
            t = self._rel_times(f)
            acc, gyro = self.trajectory.imu_ideal(t - noise.time_offset_s)
            unit = np.random.default_rng(np.random.SeedSequence([self.seed, 0x1AB]))
            for k, v in enumerate((acc, gyro)):
                M = np.eye(3) + unit.normal(0, noise.misalignment_sigma_rad, (3, 3)) * (1 - np.eye(3))
                S = np.diag(1.0 + unit.normal(0, noise.scale_factor_sigma, 3))
                v[:] = v @ (S @ M).T
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, stable_hash(self.session), 6]))
            n = len(t)
            ba = rng.normal(0, noise.acc_bias_init_sigma, 3) + np.cumsum(
                rng.normal(0, noise.acc_bias_random_walk / np.sqrt(f), (n, 3)), axis=0)
            bg = rng.normal(0, noise.gyro_bias_init_sigma, 3) + np.cumsum(
                rng.normal(0, noise.gyro_bias_random_walk / np.sqrt(f), (n, 3)), axis=0)
            acc = acc + ba + rng.normal(0, noise.acc_noise_density * np.sqrt(f), (n, 3))
            gyro = gyro + bg + rng.normal(0, noise.gyro_noise_density * np.sqrt(f), (n, 3))
            gm_rng = np.random.default_rng(np.random.SeedSequence([self.seed, stable_hash(self.session), 12]))
            for arr, sig, b in ((acc, noise.acc_bias_instability, ba), (gyro, noise.gyro_bias_instability, bg)):
                if sig > 0:
                    gm = _gauss_markov(gm_rng, n, 1.0 / f, noise.bias_instability_tau_s, sig)
                    arr += gm
                    b += gm
            keep = np.ones(n, dtype=bool)
            if noise.drop_prob > 0 or noise.drop_burst_per_min > 0:
                keep = rng.random(n) >= noise.drop_prob
                n_burst = rng.poisson(noise.drop_burst_per_min * t[-1] / 60.0)
                for s0 in rng.integers(int(5 * f), max(int(5 * f) + 1, n - 20), n_burst):
                    keep[s0:s0 + rng.integers(3, 13)] = False
            self.imu_bias = (ba[keep], bg[keep])
            self._imu = ImuData(self.epoch_us * 1e-6 + t[keep], acc[keep], gyro[keep])
        return self._imu

    def ground_truth(self) -> Trajectory:
        """T_map_body at ``gt_rate_hz`` (100 Hz), NCLT frames."""
        t = self._rel_times(self.preset.gt_rate_hz)
        return Trajectory(self.epoch_us * 1e-6 + t, self.trajectory.T_map_body(t))

    def mapping_poses(self) -> Trajectory:
        """Mapping session: "offline SLAM" poses = ground truth with a smooth error of about
        ``slam_error_m`` (position) and ``slam_error_rad`` (attitude); other sessions: ground truth.

        Computed once per sequence (a city drive has ~400k poses at 100 Hz: seconds of work that
        a map build would otherwise repeat for every use); the arrays are read-only. Computed
        ``POSE_CHUNK`` poses at a time (every step is per pose: the same values as all at once)
        into the one (N, 4, 4) array kept: at once, a city drive's temporaries peaked at ~200 MB
        above it in each process opening the drive. When that is slow (a city drive: ~1.1 s CPU)
        they are kept on disk for other processes (:func:`drive_memo_key`)."""
        if self._mapping_poses is None:
            from blockloc.cache import disk_memo

            stamps, poses = disk_memo(
                f"mapping-poses-{self.preset.name}-{self.session}-{self.seed}",
                drive_memo_key(self.preset, self.seed, self.session), self.compute_mapping_poses,
                min_build_s=DRIVE_MEMO_MIN_S)
            gt = Trajectory(stamps, poses)
            for a in (gt.stamps, gt.poses):
                a.flags.writeable = False
            self._mapping_poses = gt
        return self._mapping_poses

    def carries_slam_error(self) -> bool:
        """Whether :meth:`mapping_poses` carry the offline-SLAM error: a mapping drive's do (its
        own random stream, seeded by the seed and the session name)."""
        return self.preset.is_mapping(self.session)

    def compute_mapping_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`mapping_poses` computed afresh: stamps (N,) float64 s, poses (N, 4, 4)."""
        t = self._rel_times(self.preset.gt_rate_hz)
        stamps = self.epoch_us * 1e-6 + t
        poses = np.empty((len(t), 4, 4))
        noise = None
        if self.carries_slam_error():
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, stable_hash(self.session), 7]))
            rel = stamps - stamps[0]
            noise = smooth_noise_spline(rng, float(rel[0]), float(rel[-1]), 6)
        for s in range(0, len(t), POSE_CHUNK):
            part = slice(s, s + POSE_CHUNK)
            P = self.trajectory.T_map_body(t[part])
            if noise is not None:
                e = noise(rel[part])
                dT = np.zeros((len(e), 4, 4))  # make_T per pose, stacked
                dT[:, :3, :3] = so3_exp(e[:, :3] * self.preset.slam_error_rad)
                dT[:, :3, 3] = e[:, 3:] * self.preset.slam_error_m
                dT[:, 3, 3] = 1.0
                P = P @ dT
            poses[part] = P
        return stamps, poses

    # --- helpers for tests and tools ------------------------------------------------------------
    def T_world_lidar(self, t_rel: np.ndarray) -> np.ndarray:
        """(N, 4, 4) lidar pose in the world frame (z up) at session-relative times."""
        return self.trajectory.T_world_flu(t_rel) @ self.T_flu_lidar


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float, sigma: float) -> np.ndarray:
    """(n, 3) first-order Gauss-Markov process (stationary std ``sigma``, correlation time tau)."""
    phi = np.exp(-dt / tau)
    w = rng.normal(0.0, sigma * np.sqrt(1 - phi * phi), (n, 3))
    w[0] = rng.normal(0.0, sigma, 3)
    return _ar1(w, phi)


def _ar1(w: np.ndarray, phi: float) -> np.ndarray:
    """y[k] = w[k] + phi * y[k - 1] along axis 0 of ``w`` (n, d), y[0] = w[0]: the bits of
    ``scipy.signal.lfilter([1.0], [1.0, -phi], w, axis=0)`` (its recursion adds the same two
    terms), without importing scipy.signal (~0.3 s of CPU in the writing process)."""
    y = np.empty_like(w)
    if len(w):
        y[0] = w[0]
    prev = y[0] if len(w) else None
    for k in range(1, len(w)):
        prev = y[k] = w[k] + phi * prev
    return y


def open_sim_sequence(preset: str, session: str, seed: int, **overrides) -> SimSequence:
    """A simulated session streamed on the fly: ``preset`` small | campus | city | tiny,
    ``session`` map | loc | loc2 (campus) | map1..map5, loc (city), ``seed`` any int.
    ``overrides``: preset fields, e.g. ``azimuth_steps=200`` for a sparse, fast sensor, or
    ``ideal=True`` for every error source off."""
    return SimSequence(get_preset(preset, **overrides), session, int(seed))
