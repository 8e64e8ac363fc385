"""Trajectory files and ATE/RPE evaluation.

- ``trajectory_io``: ``read_trajectory`` (TUM, KITTI, NCLT csv, sniffed), ``write_tum``, ``write_kitti``.
- ``metrics``: pure numpy: ``associate``, ``umeyama_alignment``, ``absolute_pose_errors``,
  ``relative_pose_errors``.
- ``report``: ``evaluate_files``, ``evaluate_trajectories``.
- ``results``: a tracking run's metrics and results folder (``run_metrics``, ``RunWriter``).
- ``plots``: PNGs (matplotlib, Agg, imported lazily).
"""
