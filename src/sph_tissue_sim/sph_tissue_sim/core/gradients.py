"""Corrected reference gradients of the total-Lagrangian scheme: per pair, the vector ``g_ij`` with

    grad u (X_i) ~= sum_j (u_j - u_i) (x) g_ij,

fixed in the reference configuration (no per-step search): the Bonet-Lok correction, a moving
least-squares fit of ``u_j - u_i`` around particle ``i`` with the kernel-gradient weight
``phi_ij = -V_j dW/dr(R0) / R0 >= 0`` over the offsets ``D = X_j - X_i``:

    L_i = sum_j phi_ij D_ij D_ij^T,        g_ij = phi_ij L_i^-1 D_ij = V_j L_i^-1 DWIJ0,

exact for linear fields, also at free surfaces. Particles whose ``L_i`` is singular or
ill-conditioned keep the plain gradient ``V_j DWIJ0``. (Second-order gradients, exact for
quadratic fields, lost: docs/decisions/retired-gradient_order.md.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kernel import kernel_dwdr, kernel_w

#: condition number of ``L_i`` above which a particle keeps the plain gradient
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
def _offset(X, i, j, p):
    """``X_j - X_i`` into ``p``."""
    p[0] = X[j, 0] - X[i, 0]
    p[1] = X[j, 1] - X[i, 1]
    p[2] = X[j, 2] - X[i, 2]


@njit(cache=True)
def _moments(X, offsets, indices, dw, volume):
    n = 3
    M = np.zeros((X.shape[0], n, n))
    p = np.empty(n)
    for i in range(X.shape[0]):
        for k in range(offsets[i], offsets[i + 1]):
            _offset(X, i, indices[k], p)
            phi = -volume * dw[k]
            for a in range(n):
                for b in range(n):
                    M[i, a, b] += phi * p[a] * p[b]
    return M


@njit(cache=True)
def _gradients(X, offsets, indices, dw, volume, Q):
    """``g_k = phi_k Q_i D_k`` with ``Q_i = L_i^-1`` (N, 3, 3)."""
    n = Q.shape[2]
    g = np.empty((indices.shape[0], 3))
    p = np.empty(n)
    for i in range(X.shape[0]):
        for k in range(offsets[i], offsets[i + 1]):
            _offset(X, i, indices[k], p)
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


def _inverse(M: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``M^-1`` per particle; ``fallback`` (N, 3, 3) where ``M`` is singular or its condition
    number exceeds :data:`MAX_CONDITION`."""
    Q = fallback.copy()
    if len(M) == 0:
        return Q
    ok = np.abs(np.linalg.det(M)) > 0.0
    ok[ok] = np.linalg.cond(M[ok]) < MAX_CONDITION
    Q[ok] = np.linalg.inv(M[ok])
    return Q


def corrected_gradients(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float,
                        volume: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pair ``g_ij`` (nnz, 3) and the hourglass weights ``W(R0) / R0^2`` (nnz,)."""
    dw, w0 = pair_weights(X, offsets, indices, h)
    plain = np.zeros((len(X), 3, 3))
    plain[:] = np.eye(3)
    Q = _inverse(_moments(X, offsets, indices, dw, volume), plain)
    g = _gradients(X, offsets, indices, dw, volume, np.ascontiguousarray(Q))
    return g, w0
