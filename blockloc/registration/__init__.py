"""Scan-to-map registration: NDT in ``blockloc.registration.ndt`` (numba loads on first use)."""

from blockloc.registration.ndt import (
    NdtEvaluation,
    NdtRegistration,
    NdtResult,
    NdtTarget,
    align,
)

__all__ = ["NdtEvaluation", "NdtRegistration", "NdtResult", "NdtTarget", "align"]
