"""Trajectory files and ATE/RPE evaluation.

- trajectory files (TUM, KITTI, NCLT csv) are read and written by :mod:`blockloc.trajectory_io`.
- ``metrics``: pure numpy: ``associate``, ``umeyama_alignment``, ``absolute_pose_errors``,
  ``relative_pose_errors``.
- ``report``: ``evaluate_files``, ``evaluate_trajectories``.
- ``results``: a tracking run's metrics and results folder (``run_metrics``, ``RunWriter``).
- ``plots``: PNGs (matplotlib, Agg, imported lazily).
"""
