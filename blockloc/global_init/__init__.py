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
store map sources, on-disk pyramid cache), ``refine`` (NDT), ``verify`` (verification and the
decision over candidates), ``no_hint`` (the place stages and the regions' fallback), ``relocalize``
(the pipeline), ``params`` (the ``global_init`` config section and the localizer's parameters).
"""

__all__ = ["GlobalLocalizer", "InitCandidate", "InitParams", "InitResult", "localize", "localize_points",
           "pose_error"]


def __getattr__(name):
    # Lazy: ``blockloc.config`` imports ``global_init.params``, which must not load the pipeline.
    if name in __all__:
        from blockloc.global_init import relocalize

        return getattr(relocalize, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
