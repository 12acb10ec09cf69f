"""sph_tissue_sim package."""

from .blas_kernels import pin as _pin_blas_kernels

_pin_blas_kernels()   # before anything loads numpy (see blas_kernels)
