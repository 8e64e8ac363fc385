"""Scan-to-map registration. NDT: ``blockloc.registration.ndt`` (numba kernels load on first use)."""

from blockloc.registration.ndt import NdtRegistration, NdtResult, NdtTarget, align

__all__ = ["NdtRegistration", "NdtResult", "NdtTarget", "align"]
