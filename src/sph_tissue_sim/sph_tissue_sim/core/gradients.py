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
def _moments(X, offsets, indices, dw, alive, volume, rows):
    """``L_i`` (len(rows), 3, 3) of the particles ``rows`` over their ``alive`` pairs."""
    n = 3
    M = np.zeros((rows.shape[0], n, n))
    p = np.empty(n)
    for t in range(rows.shape[0]):
        i = rows[t]
        for k in range(offsets[i], offsets[i + 1]):
            if not alive[k]:
                continue
            _offset(X, i, indices[k], p)
            phi = -volume * dw[k]
            for a in range(n):
                for b in range(n):
                    M[t, a, b] += phi * p[a] * p[b]
    return M


@njit(cache=True)
def _gradients(X, offsets, indices, dw, alive, volume, rows, Q, g):
    """``g_k = phi_k Q_t D_k`` into ``g`` for the pairs of the particles ``rows`` (``Q_t =
    L_i^-1``, (len(rows), 3, 3)); zero for a pair that is not ``alive``."""
    n = Q.shape[2]
    p = np.empty(n)
    for t in range(rows.shape[0]):
        i = rows[t]
        for k in range(offsets[i], offsets[i + 1]):
            if not alive[k]:
                g[k, 0] = 0.0
                g[k, 1] = 0.0
                g[k, 2] = 0.0
                continue
            _offset(X, i, indices[k], p)
            phi = -volume * dw[k]
            for a in range(3):
                t_ = 0.0
                for b in range(n):
                    t_ += Q[t, a, b] * p[b]
                g[k, a] = phi * t_


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


def _inverse(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M^-1, ok)`` per particle: the identity (the plain gradient) where ``M`` is singular or its
    condition number exceeds :data:`MAX_CONDITION` (``ok`` False there)."""
    Q = np.zeros_like(M)
    Q[:] = np.eye(3)
    if len(M) == 0:
        return Q, np.zeros(0, dtype=bool)
    ok = np.abs(np.linalg.det(M)) > 0.0
    ok[ok] = np.linalg.cond(M[ok]) < MAX_CONDITION
    Q[ok] = np.linalg.inv(M[ok])
    return Q, ok


def fit_gradients(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, dw: np.ndarray,
                  alive: np.ndarray, volume: float, rows: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Fit ``g`` (nnz, 3) of the particles ``rows`` over their ``alive`` pairs (``dw`` of
    :func:`pair_weights`); returns per row whether its ``L_i`` was invertible (else the plain gradient)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    Q, ok = _inverse(_moments(X, offsets, indices, dw, alive, volume, rows))
    _gradients(X, offsets, indices, dw, alive, volume, rows, np.ascontiguousarray(Q), g)
    return ok


def corrected_gradients(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float,
                        volume: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pair ``g_ij`` (nnz, 3) and the hourglass weights ``W(R0) / R0^2`` (nnz,)."""
    dw, w0 = pair_weights(X, offsets, indices, h)
    g = np.empty((len(indices), 3))
    fit_gradients(X, offsets, indices, dw, np.ones(len(indices), dtype=np.bool_), volume,
                  np.arange(len(X)), g)
    return g, w0
