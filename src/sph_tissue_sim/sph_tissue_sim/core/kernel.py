"""Cubic spline SPH kernel (paper eq. 9) and its gradient (eq. 10 with the typo fixed).

All functions are module-level ``@njit(cache=True)`` so they inline into the scheme loops.
Naming follows PySPH: ``RIJ = |x_i - x_j|``, ``XIJ = x_i - x_j``, ``WIJ = W(RIJ, h)`` and
``DWIJ = grad_i W(x_i - x_j, h)``.

    W(R, h) = 3 / (2 pi h^3) * { 2/3 - R^2 + R^3 / 2     0 <= R < 1
                               { (2 - R)^3 / 6            1 <= R < 2
                               { 0                        R >= 2,        R = RIJ / h

    dW/dr   = 1 / (pi h^4)   * { -3 R + 2.25 R^2          0 <= R < 1     (paper: 1.25, a typo)
                               { -0.75 (2 - R)^2          1 <= R < 2

    DWIJ    = dW/dr(RIJ) * XIJ / RIJ

The support radius is ``2 h``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SUPPORT = 2.0
"""Support radius in units of h."""


@njit(cache=True, fastmath=True)
def kernel_w(rij: float, h: float) -> float:
    """WIJ: cubic spline value for a pair distance ``rij`` [m] and smoothing length ``h`` [m]."""
    q = rij / h
    sigma = 3.0 / (2.0 * math.pi * h * h * h)
    if q < 1.0:
        return sigma * (2.0 / 3.0 - q * q + 0.5 * q * q * q)
    if q < 2.0:
        t = 2.0 - q
        return sigma * t * t * t / 6.0
    return 0.0


@njit(cache=True, fastmath=True)
def kernel_dwdr(rij: float, h: float) -> float:
    """dW/dr at ``rij``: ``1/(pi h^4) * (-3R + 2.25R^2 | -0.75(2-R)^2)`` (<= 0 inside the support)."""
    q = rij / h
    fac = 1.0 / (math.pi * h * h * h * h)
    if q < 1.0:
        return fac * (-3.0 * q + 2.25 * q * q)
    if q < 2.0:
        t = 2.0 - q
        return -0.75 * fac * t * t
    return 0.0


@njit(cache=True, fastmath=True)
def kernel_dwij(xij0: float, xij1: float, xij2: float, h: float, out: np.ndarray) -> None:
    """DWIJ = dW/dr(RIJ) * XIJ / RIJ written into ``out`` (3,); zero at RIJ = 0."""
    rij = math.sqrt(xij0 * xij0 + xij1 * xij1 + xij2 * xij2)
    if rij < 1e-300:
        out[0] = 0.0
        out[1] = 0.0
        out[2] = 0.0
        return
    f = kernel_dwdr(rij, h) / rij
    out[0] = f * xij0
    out[1] = f * xij1
    out[2] = f * xij2


ZERO3X3 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
"""A 3x3 matrix as a row-major 9-tuple: a pair-sum accumulator that stays in registers."""


@njit(cache=True, fastmath=True, inline='always')
def add_outer(m, d0, d1, d2, g0, g1, g2):
    """``m + d (x) g`` for a row-major 9-tuple ``m``: one pair's term of ``sum_j d_j (x) DWIJ``."""
    return (m[0] + d0 * g0, m[1] + d0 * g1, m[2] + d0 * g2,
            m[3] + d1 * g0, m[4] + d1 * g1, m[5] + d1 * g2,
            m[6] + d2 * g0, m[7] + d2 * g1, m[8] + d2 * g2)


@njit(cache=True, fastmath=True, inline='always')
def strain_rate(f, h):
    """``dE/dt = sym(F^T dF/dt)`` (the Green-Lagrange strain rate) as ``(r00, r11, r22, r01, r02,
    r12)`` from ``F`` and ``dF/dt`` as row-major 9-tuples (scalars: no temporaries per particle)."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = f
    h00, h01, h02, h10, h11, h12, h20, h21, h22 = h
    return (h00 * f00 + h10 * f10 + h20 * f20,
            h01 * f01 + h11 * f11 + h21 * f21,
            h02 * f02 + h12 * f12 + h22 * f22,
            0.5 * (h00 * f01 + h10 * f11 + h20 * f21 + f00 * h01 + f10 * h11 + f20 * h21),
            0.5 * (h00 * f02 + h10 * f12 + h20 * f22 + f00 * h02 + f10 * h12 + f20 * h22),
            0.5 * (h01 * f02 + h11 * f12 + h21 * f22 + f01 * h02 + f11 * h12 + f21 * h22))


@njit(cache=True)
def kernel_w_array(r: np.ndarray, h: float) -> np.ndarray:
    """:func:`kernel_w` over an array of distances (the first moments of the surface normals)."""
    out = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        out[i] = kernel_w(r[i], h)
    return out
