"""Global initialization: coarse-to-fine branch-and-bound over (x, y, yaw), NDT refinement, verification.

Public API (see ``relocalize``):

- ``localize(scan_points_lidar, *, T_body_lidar, map_store, gravity_body | roll_pitch, gravity_map,
  hint_xy=None, hint_yaw=None, window_m=40, yaw_window_deg=360, params=None) -> InitResult``
- ``localize_points(map_points, scan_points_body, ...) -> InitResult`` (arrays, no store)
- ``GlobalLocalizer.for_store(store, gravity_map, params)`` / ``.for_points(...)``, then
  ``.localize(points_body, gravity_body, hint_xy, hint_yaw, window_m, yaw_window_deg)``: keeps the
  per-entry pyramids in memory between calls (tracking start and recovery).

Modules: ``projection`` (levelling, local ground, height band, rasters), ``pyramid`` (admissible
sliding-window max pyramid), ``bnb`` + ``_kernels`` (numba branch and bound), ``maps`` (array and
store map sources, on-disk pyramid cache), ``refine`` (NDT), ``relocalize`` (the pipeline),
``command`` (``blockloc init``).
"""

from blockloc.global_init.relocalize import (GlobalLocalizer, InitCandidate, InitParams, InitResult, localize,
                                             localize_points, pose_error)

__all__ = ["GlobalLocalizer", "InitCandidate", "InitParams", "InitResult", "localize", "localize_points",
           "pose_error"]
