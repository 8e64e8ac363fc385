"""Scan-to-map registration: NDT in ``blockloc.registration.ndt`` (numba loads on first use)."""

from blockloc.registration.ndt import (
    NdtEvaluation,
    NdtRegistration,
    NdtResult,
    NdtTarget,
    align,
)
from blockloc.registration.voxels import voxel_downsample

__all__ = ["NdtEvaluation", "NdtRegistration", "NdtResult", "NdtTarget", "align",
           "voxel_downsample"]
