"""Lifelong maps (issue 43): detect what changed since a map was made, update only those blocks
from verified runs, keep map versions.

- :mod:`.detect`   per-voxel occupancy evidence from many scans; removed / added / dynamic voxels
- :mod:`.runs`     a tracking run's folder: poses, per-frame status, the frames it verified
- :mod:`.pipeline` a map store + a run's scans -> the per-block report (``changes.json``)
"""
