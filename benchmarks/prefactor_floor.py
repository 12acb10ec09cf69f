#!/usr/bin/env python3
"""The floor of a prefactored implicit step: what one solve with a constant, factored matrix costs.

    python benchmarks/prefactor_floor.py                    # 3670, 12k and 50k livers
    python benchmarks/prefactor_floor.py --particles 3670,12000

A corotated stretching solve (the large-step design that avoids a new factorisation every step)
integrates the energy ``sum_i V mu |F_i - R_i|^2`` backward in time with the rotations ``R_i``
lagged, so its matrix, per axis,

    A = m / dt^2 I + 2 mu V sum_i G_i^T G_i,     F_i[a, :] = sum_j (x_j^a - x_i^a) g_ij  =  G_i x^a,

does not change while the particles move and is factored once; every step then pays a
back-substitution of three right-hand sides (one per axis), the passes that build them and the
rotations, and as many such iterations as the nonlinearity needs. This script builds ``A`` from
the solver's own corrected gradients ``g_ij`` (so its pattern is the two-ring one of the tlsph
stencil) on the free particles of the liver, factors it with SuperLU (scipy, the solver scipy
ships; minimum-degree ordering on A^T + A), and times the factorisation, the fill and the
back-substitution. The back-substitution alone is a lower bound on such a step's cost.

Prints a table and writes ``prefactor_floor.csv`` to ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.gradients import corrected_gradients
from sph_tissue_sim.core.kernel import SUPPORT
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.neighbours import find_neighbours


def stretching_operator(offsets: np.ndarray, indices: np.ndarray, g: np.ndarray) -> sp.csr_matrix:
    """``G`` (3n, n): row ``3 i + c`` maps one coordinate of the positions to column ``c`` of that
    coordinate's row of ``F_i`` (``g_ij[c]`` at ``j``, ``-sum_j g_ij[c]`` at ``i``)."""
    n = len(offsets) - 1
    rows_i = np.repeat(np.arange(n), np.diff(offsets))
    r = (3 * rows_i[:, None] + np.arange(3)[None, :]).ravel()
    own = np.zeros((n, 3))
    np.add.at(own, rows_i, g)
    return sp.csr_matrix((np.concatenate([g.ravel(), -own.ravel()]),
                          (np.concatenate([r, np.arange(3 * n)]),
                           np.concatenate([np.repeat(indices, 3), np.repeat(np.arange(n), 3)]))),
                         shape=(3 * n, n))


def stretching_matrix(n_particles: int, dt: float, h_ratio: float = 1.3) -> tuple[sp.csc_matrix, float]:
    """``A`` above on the free particles of the liver, and the mean number of neighbours."""
    model = make_model('liver', n_particles=n_particles)
    X = model.positions
    h = h_ratio * model.spacing   # SolverConfig.h_ratio's default
    volume = model.particle_volume
    offsets, indices = find_neighbours(X, SUPPORT * h)
    g, _ = corrected_gradients(X, offsets, indices, h, volume)
    G = stretching_operator(offsets, indices, g)
    mat = liver_default()
    mass = mat.rho * volume
    n = len(X)
    A = (sp.identity(n) * (mass / dt ** 2) + (2.0 * mat.G * volume) * (G.T @ G)).tocsc()
    free = np.flatnonzero(~model.fixed)
    return A[free][:, free].tocsc(), len(indices) / n


def measure(n_particles: int, dt: float, repeats: int) -> dict:
    A, neighbours = stretching_matrix(n_particles, dt)
    t0 = time.perf_counter()
    lu = sla.splu(A, permc_spec='MMD_AT_PLUS_A', options=dict(SymmetricMode=True))
    factor = time.perf_counter() - t0
    b = np.random.default_rng(0).standard_normal((A.shape[0], 3))
    x = lu.solve(b)
    residual = float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        lu.solve(b)
        times.append(time.perf_counter() - t0)
    fill = lu.L.nnz + lu.U.nnz
    return dict(particles=n_particles, free=A.shape[0], neighbours=round(neighbours, 1), a_nnz=A.nnz,
                factor_s=round(factor, 3), lu_nnz=fill, lu_mib=round(fill * 12 / 2 ** 20),
                solve_ms=round(1e3 * float(np.median(times)), 3), residual=f'{residual:.1e}')


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--particles', default='3670,12000,50000', help='comma-separated liver sizes')
    ap.add_argument('--dt', type=float, default=0.016, help='[s] the step the matrix is built for')
    ap.add_argument('--repeats', type=int, default=5, help='timed back-substitutions (median)')
    ap.add_argument('--out', type=Path, default=Path(__file__).resolve().parent / 'results')
    a = ap.parse_args(argv)
    rows = []
    print('| particles | free | neighbours | A nnz | factor [s] | L+U nnz | L+U [MiB] | solve, 3 rhs [ms] | residual |')
    print('|---|---|---|---|---|---|---|---|---|')
    for n in (int(p) for p in a.particles.split(',')):
        r = measure(n, a.dt, a.repeats)
        rows.append(r)
        print('| ' + ' | '.join(str(v) for v in r.values()) + ' |', flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    with open(a.out / 'prefactor_floor.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f'wrote {a.out / "prefactor_floor.csv"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
