"""Moved to :mod:`blockloc.global_init.scan_prep` (a scan's preparation for global localization).

Kept only so ``blockloc/session.py`` and ``blockloc/commands/init.py`` (another branch's scope
while the application layer is built) keep importing; delete once they import the new path: this
re-export is the one arrow from ``tracking`` up to ``global_init``.
"""

from blockloc.global_init.scan_prep import (  # noqa: F401
    IMU_HALF_WINDOW_S,
    InitScan,
    deskew_rotation,
    gravity_from_imu,
    gravity_from_scan_points,
    prepare_for_init,
)
