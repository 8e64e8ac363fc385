"""What the tracker reports per frame: :class:`Estimate` with its :class:`Diagnostics`, and why a
scan's registration was rejected (:func:`reject_reason`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

# Why a scan's registration was not accepted: ``error`` (the engine raised), ``unconverged``,
# ``fitness`` (inlier ratio below min_fitness), ``innovation`` (farther from the prediction than the
# gates), ``nonfinite``.
REJECT_REASONS = ("error", "unconverged", "fitness", "innovation", "nonfinite")


def reject_reason(res, fitness: float, inn_m: float, inn_deg: float, gates: tuple[float, float],
                  min_fitness: float, T: np.ndarray) -> str:
    """The first acceptance test a registration result fails (one of ``REJECT_REASONS``), or ""
    when it passes them all; gates are (metres, degrees)."""
    if not np.all(np.isfinite(T)):
        return "nonfinite"
    if not bool(getattr(res, "converged", True)):
        return "unconverged"
    if not fitness >= min_fitness:
        return "fitness"
    if inn_m > gates[0] or inn_deg > gates[1]:
        return "innovation"
    return ""


@dataclass
class Diagnostics:
    """Per-frame health and cost; every field is plain data for JSON."""

    # ok | rejected | imu_only | lost | recovered | uninitialized; imu_only: no scan factor (no map
    # or too few points), the IMU (LiDAR-only: the motion prior) carried the pose
    status: str = "ok"
    fitness: float = float("nan")
    innovation_m: float = float("nan")
    innovation_deg: float = float("nan")
    window_size: int = 0
    marginalized: int = 0
    switched: bool = False
    block_id: object = None
    num_points: int = 0
    weak_dims: int = 0
    imu_gap_s: float = 0.0
    prep_ms: float = 0.0  # range filter + voxel selection of the raw scan
    deskew_ms: float = 0.0
    registration_ms: float = 0.0
    smoother_ms: float = 0.0
    update_ms: float = 0.0
    map_ms: float = 0.0
    rotation_retries: int = 0  # rotated predictions registered after the prediction failed (LiDAR-only)
    rotation_retry: str = ""  # the one accepted, e.g. 'yaw+30' ('' none)
    reject_reason: str = ""  # a rejected scan: the first acceptance test it failed (REJECT_REASONS)


@dataclass(init=False)
class Estimate:
    """The tracker's answer for one frame.

    T_map_body: (4, 4) or None before the first successful initialization.
    covariance: (6, 6) Pose3 tangent (rotation rad, translation m) of T_map_body, or None; the
    tracker hands it over deferred (a callable), computed on the first read and kept.
    (LiDAR-only with per-point times the keyframe sits at the scan's mean point time; pose and
    covariance are carried to ``stamp`` with its twist.)
    velocity_map: (3,) m/s; acc_bias (3,) m/s^2 and gyro_bias (3,) rad/s in the imu frame (zeros
    in LiDAR-only mode, which estimates no biases).
    """

    index: int
    stamp: float
    T_map_body: np.ndarray | None
    velocity_map: np.ndarray
    acc_bias: np.ndarray
    gyro_bias: np.ndarray
    diagnostics: Diagnostics

    def __init__(self, index: int, stamp: float, T_map_body: np.ndarray | None,
                 covariance: np.ndarray | Callable[[], np.ndarray | None] | None, velocity_map: np.ndarray,
                 acc_bias: np.ndarray, gyro_bias: np.ndarray, diagnostics: Diagnostics) -> None:
        self.index, self.stamp, self.T_map_body = index, stamp, T_map_body
        self._covariance = covariance
        self.velocity_map, self.acc_bias, self.gyro_bias = velocity_map, acc_bias, gyro_bias
        self.diagnostics = diagnostics

    @property
    def covariance(self) -> np.ndarray | None:
        if callable(self._covariance):
            self._covariance = self._covariance()
        return self._covariance

    def as_dict(self) -> dict:
        return asdict(self.diagnostics)


def plain_id(x):
    """A JSON-friendly copy of a block / region id."""
    if x is None or isinstance(x, (int, str, float)):
        return x
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (tuple, list)):
        return [plain_id(v) for v in x]
    return str(x)
