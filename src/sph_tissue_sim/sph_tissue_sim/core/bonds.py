"""Reference bonds that break: how a cut changes the total-Lagrangian scheme.

A TLSPH particle feels its reference neighbours through the pair gradients ``g_ij``
(:mod:`.gradients`). Cutting a bond removes the pair (i, j) for good: ``g_ij``, ``g_ji`` and the
pair's hourglass weight become zero, and both particles' gradients are fitted again over the bonds
they keep,

    L_i = sum_{j alive} phi_ij D_ij D_ij^T,    g_ij = phi_ij L_i^-1 D_ij (alive), 0 (cut),

so ``F`` stays exact for linear fields on each side of the crack (a crack face is a free surface,
which the fit already handles) and nothing in the force kernels changes: a cut pair adds nothing.
A particle whose remaining bonds no longer span three dimensions (``L_i`` singular or
ill-conditioned, :data:`~.gradients.MAX_CONDITION`) loses the rest of its bonds too and leaves the
simulation (:attr:`Bonds.removed`), as does one left with no bond; the fit is redone around it.

Every bond stands for the same crack area ``a_b`` (:func:`bond_area`): a plane through the bulk
crosses one bond per ``a_b`` of its area, so cutting every bond across a plane of area ``A`` frees
``A / a_b`` bonds and costs ``G_c A``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .gradients import fit_gradients


@njit(cache=True)
def sync_rows(rows, offsets, rev, g, gr, gsum):
    """``gr[rev[k]] = g[k]`` and ``gsum[i] = sum_k g[k]`` (in the pairs' order, whatever the CPU)
    for the pairs k of the particles ``rows``."""
    for t in range(rows.shape[0]):
        i = rows[t]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            gr[rev[k], 0] = g[k, 0]
            gr[rev[k], 1] = g[k, 1]
            gr[rev[k], 2] = g[k, 2]
            s0 += g[k, 0]
            s1 += g[k, 1]
            s2 += g[k, 2]
        gsum[i, 0] = s0
        gsum[i, 1] = s1
        gsum[i, 2] = s2


def bond_area(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, volume: float) -> float:
    """[m^2] the crack area one bond stands for: ``2 V / sum_j |R_ij . n|`` over the particles with
    full neighbourhoods (the most neighbours), averaged over the three axes ``n``.

    A plane of normal ``n`` cuts the bond (i, j) when it passes between them: per unit area, the
    bonds of the particles in a slab of thickness ``|R_ij . n|``, ``(1 / V) sum_j |R_ij . n| / 2``
    (each bond counted from both ends)."""
    counts = np.diff(offsets)
    full = np.flatnonzero(counts >= counts.max())
    rows = np.repeat(full, counts[full])
    cols = np.concatenate([indices[offsets[i]:offsets[i + 1]] for i in full])
    R = np.abs(X[cols] - X[rows])                       # (pairs, 3): |R . n| for n = x, y, z
    per_particle = R.sum(axis=0) / len(full)            # (3,) sum_j |R_ij . n| on average
    return float(np.mean(2.0 * volume / per_particle))


class Bonds:
    """Which reference bonds of a :class:`~.tlsph.TlsphScheme` are intact, and the scheme's pair
    arrays kept consistent with them (:meth:`cut`, :meth:`reset`).

    Args:
        X: (N, 3) reference positions [m]; offsets, indices: reference neighbours (CSR, symmetric).
        dw: per pair ``dW/dr(R0) / R0`` (:func:`~.gradients.pair_weights`); rev: the reverse pairs.
        volume: particle volume [m^3]; fixed: (N,) held particles (never removed).
        g, gr, gsum, w0: the scheme's pair gradients, their reverse pairs, their sums and the
            hourglass weights, changed in place.
    """

    def __init__(self, X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, dw: np.ndarray,
                 rev: np.ndarray, volume: float, fixed: np.ndarray, g: np.ndarray, gr: np.ndarray,
                 gsum: np.ndarray, w0: np.ndarray) -> None:
        self.X, self.offsets, self.indices, self.dw, self.rev = X, offsets, indices, dw, rev
        self.volume, self.fixed = volume, fixed
        self.g, self.gr, self.gsum, self.w0 = g, gr, gsum, w0
        self.owner = np.repeat(np.arange(len(X), dtype=np.int64), np.diff(offsets))
        self.area = bond_area(X, offsets, indices, volume)
        self.alive = np.ones(len(indices), dtype=np.bool_)
        self.severed = np.zeros(len(X), dtype=np.int32)     # bonds each particle lost
        self.removed = np.zeros(len(X), dtype=np.bool_)
        self.n_cut = 0                                      # bonds cut (each pair once)
        self._intact: tuple | None = None                   # the arrays before the first cut

    def cut(self, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cut the bonds ``pairs`` (pair indices into the CSR; either direction, repeats and cut
        ones ignored) and fit the gradients again; returns ``(cut, removed)``: every pair cut (both
        directions, with those of the particles the cut tore off) and the particles removed
        (:attr:`removed`)."""
        pairs = np.unique(np.asarray(pairs, dtype=np.int64))
        pairs = pairs[self.alive[pairs]]
        if not len(pairs):
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if self._intact is None:
            self._intact = (self.g.copy(), self.gr.copy(), self.gsum.copy(), self.w0.copy())
            # particles fitted with the plain gradient from the start are not torn off by a cut
            self._fitted = fit_gradients(self.X, self.offsets, self.indices, self.dw, self.alive,
                                         self.volume, np.arange(len(self.X)), np.empty_like(self.g))
        removed, cut = [], []
        while len(pairs):
            both = np.unique(np.concatenate([pairs, self.rev[pairs]]))
            pairs = both[both < self.rev[both]]
            cut.append(both)
            self.alive[both] = False
            self.w0[both] = 0.0
            self.n_cut += len(pairs)
            ends = self.owner[both]
            np.add.at(self.severed, ends, 1)
            rows = np.unique(ends)
            ok = fit_gradients(self.X, self.offsets, self.indices, self.dw, self.alive, self.volume,
                               rows, self.g)
            self._sync(rows)
            # a particle whose bonds no longer span 3-D (or none left) leaves: its last bonds go too
            left = np.array([np.count_nonzero(self.alive[self.offsets[i]:self.offsets[i + 1]]) for i in rows])
            torn = (~ok & self._fitted[rows]) | (left == 0)
            gone = rows[torn & ~self.removed[rows] & ~self.fixed[rows]]
            self.removed[gone] = True
            removed.append(gone)
            pairs = np.concatenate([np.arange(self.offsets[i], self.offsets[i + 1]) for i in gone]) \
                if len(gone) else np.zeros(0, dtype=np.int64)
            pairs = pairs[self.alive[pairs]]
        return np.concatenate(cut), np.concatenate(removed)

    def _sync(self, rows: np.ndarray) -> None:
        """The reverse-pair gradients and the sums of ``rows`` after their ``g`` changed."""
        sync_rows(np.ascontiguousarray(rows, dtype=np.int64), self.offsets, self.rev, self.g, self.gr, self.gsum)

    def reset(self) -> None:
        """Every bond intact again (the scheme's arrays as built)."""
        if self._intact is not None:
            for mine, intact in zip((self.g, self.gr, self.gsum, self.w0), self._intact):
                mine[:] = intact
            self._intact = None
        self.alive[:] = True
        self.severed[:] = 0
        self.removed[:] = False
        self.n_cut = 0
