"""sph_tissue_sim package."""

from .blas_kernels import pin as _pin_blas_kernels

_pin_blas_kernels()   # before anything loads numpy (see blas_kernels)

# the core's code generation for the portable CPU level, before any module of the package decorates
# a kernel (numba makes its CPU target then): see core/__init__.py
from . import core as _core  # noqa: E402,F401
