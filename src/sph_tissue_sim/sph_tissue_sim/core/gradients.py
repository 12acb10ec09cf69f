"""Corrected reference gradients of the total-Lagrangian scheme: per pair, the vector ``g_ij`` with

    grad u (X_i) ~= sum_j (u_j - u_i) (x) g_ij,

fixed in the reference configuration (no per-step search). Both orders are a moving least-squares
fit of ``u_j - u_i`` around particle ``i`` with the kernel-gradient weight
``phi_ij = -V_j dW/dr(R0) / R0 >= 0`` over the basis ``p(D)`` of the offsets ``D = X_j - X_i``:

    M_i = sum_j phi_ij p(D_ij) p(D_ij)^T,        g_ij = phi_ij [M_i^-1 p(D_ij)]_(0..2).

- ``order=1``, ``p = D``: ``M_i`` is the Bonet-Lok shape matrix ``L_i`` and ``g_ij = V_j L_i^-1
  DWIJ0`` (the gradient is exact for linear fields, also at free surfaces).
- ``order=2``, ``p = (D, D_a D_b / h)``: also exact for quadratic fields. Inside the body the
  support is symmetric, the third moments vanish and the gradient equals the first-order one; at
  a free surface the first-order gradient is the mean over a support that lies inward, so a
  bent beam's outer fibres show too little strain and the beam is too soft in bending.

Particles whose ``M_i`` is singular or ill-conditioned fall back to the first-order correction,
and particles too sparse for that to the plain gradient ``V_j DWIJ0``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kernel import kernel_dwdr, kernel_w

#: condition number of ``M_i`` above which a particle falls back to the lower order
MAX_CONDITION = 1e4


@njit(cache=True)
def pair_weights(X, offsets, indices, h):
    """Per pair ``dW/dr(R0) / R0`` (<= 0) and the hourglass weight ``W(R0) / R0^2``."""
    nnz = indices.shape[0]
    dw = np.empty(nnz)
    w0 = np.empty(nnz)
    for i in range(X.shape[0]):
        for k in range(offsets[i], offsets[i + 1]):
            j = indices[k]
            d0 = X[i, 0] - X[j, 0]
            d1 = X[i, 1] - X[j, 1]
            d2 = X[i, 2] - X[j, 2]
            r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            dw[k] = kernel_dwdr(r, h) / r
            w0[k] = kernel_w(r, h) / (r * r)
    return dw, w0


@njit(cache=True)
def _basis(X, i, j, h, order, p):
    """``p(X_j - X_i)`` into ``p`` (3 or 9 entries)."""
    d0 = X[j, 0] - X[i, 0]
    d1 = X[j, 1] - X[i, 1]
    d2 = X[j, 2] - X[i, 2]
    p[0] = d0
    p[1] = d1
    p[2] = d2
    if order == 2:
        p[3] = d0 * d0 / h
        p[4] = d1 * d1 / h
        p[5] = d2 * d2 / h
        p[6] = d0 * d1 / h
        p[7] = d0 * d2 / h
        p[8] = d1 * d2 / h


@njit(cache=True)
def _moments(X, offsets, indices, dw, volume, h, order):
    n = 3 if order == 1 else 9
    M = np.zeros((X.shape[0], n, n))
    p = np.empty(n)
    for i in range(X.shape[0]):
        for k in range(offsets[i], offsets[i + 1]):
            _basis(X, i, indices[k], h, order, p)
            phi = -volume * dw[k]
            for a in range(n):
                for b in range(n):
                    M[i, a, b] += phi * p[a] * p[b]
    return M


@njit(cache=True)
def _gradients(X, offsets, indices, dw, volume, h, order, Q):
    """``g_k = phi_k Q_i p(D_k)`` with ``Q_i`` the first three rows of ``M_i^-1`` (N, 3, n)."""
    n = Q.shape[2]
    g = np.empty((indices.shape[0], 3))
    p = np.empty(n)
    for i in range(X.shape[0]):
        for k in range(offsets[i], offsets[i + 1]):
            _basis(X, i, indices[k], h, order, p)
            phi = -volume * dw[k]
            for a in range(3):
                t = 0.0
                for b in range(n):
                    t += Q[i, a, b] * p[b]
                g[k, a] = phi * t
    return g


@njit(cache=True)
def reverse_pairs(offsets, indices):
    """``rev[k]``: the index of pair (j, i) for pair k = (i, j) (the lists are symmetric)."""
    rev = np.full(indices.shape[0], -1, dtype=np.int64)
    for i in range(offsets.shape[0] - 1):
        for k in range(offsets[i], offsets[i + 1]):
            j = indices[k]
            for m in range(offsets[j], offsets[j + 1]):
                if indices[m] == i:
                    rev[k] = m
                    break
    return rev


def _inverse_rows(M: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """First three rows of ``M^-1`` per particle; ``fallback`` (N, 3, n) where ``M`` is singular
    or its condition number exceeds :data:`MAX_CONDITION`."""
    Q = fallback.copy()
    if len(M) == 0:
        return Q
    ok = np.abs(np.linalg.det(M)) > 0.0
    ok[ok] = np.linalg.cond(M[ok]) < MAX_CONDITION
    Q[ok] = np.linalg.inv(M[ok])[:, :3, :]
    return Q


def corrected_gradients(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float,
                        volume: float, order: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair ``g_ij`` (nnz, 3) of the given ``order`` (1 or 2), the hourglass weights
    ``W(R0) / R0^2`` (nnz,) and the number of particles that fell back to a lower order."""
    if order not in (1, 2):
        raise ValueError(f'gradient order must be 1 or 2, not {order!r}')
    dw, w0 = pair_weights(X, offsets, indices, h)
    n = len(X)
    plain = np.zeros((n, 3, 3))
    plain[:] = np.eye(3)
    M1 = _moments(X, offsets, indices, dw, volume, h, 1)
    Q = _inverse_rows(M1, plain)
    fallen = 0
    if order == 2:
        M2 = _moments(X, offsets, indices, dw, volume, h, 2)
        first = np.zeros((n, 3, 9))
        first[:, :, :3] = Q
        Q = _inverse_rows(M2, first)
        fallen = int(np.count_nonzero(np.all(Q[:, :, 3:] == 0.0, axis=(1, 2))))
    g = _gradients(X, offsets, indices, dw, volume, h, order, np.ascontiguousarray(Q))
    return g, w0, fallen
