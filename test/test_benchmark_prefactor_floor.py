"""benchmarks/prefactor_floor.py builds the stretching solve's matrix from the solver's own gradients
and factors it: its operator reproduces the deformation gradient of an affine motion, the matrix is
symmetric positive definite, and a small run writes its table and CSV (times are not asserted)."""

from __future__ import annotations

import csv
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as sla

from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.gradients import corrected_gradients
from sph_tissue_sim.core.kernel import SUPPORT
from sph_tissue_sim.core.neighbours import find_neighbours

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / 'benchmarks' / 'prefactor_floor.py'


def _load():
    spec = importlib.util.spec_from_file_location('prefactor_floor', SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_stretching_operator_gives_the_deformation_gradient_of_an_affine_motion():
    pf = _load()
    model = make_model('liver', n_particles=289)
    X = model.positions
    h = 1.3 * model.spacing
    offsets, indices = find_neighbours(X, SUPPORT * h)
    g, _ = corrected_gradients(X, offsets, indices, h, model.particle_volume)
    G = pf.stretching_operator(offsets, indices, g)
    F = np.array([[1.1, 0.2, -0.05], [0.03, 0.9, 0.1], [-0.2, 0.0, 1.05]])
    x = X @ F.T + np.array([0.01, -0.02, 0.03])
    for a in range(3):
        rows = (G @ x[:, a]).reshape(-1, 3)            # row a of F_i at every particle
        np.testing.assert_allclose(rows, np.broadcast_to(F[a], rows.shape), atol=1e-9)


def test_the_matrix_is_symmetric_positive_definite_and_its_factor_solves_it():
    pf = _load()
    A, neighbours = pf.stretching_matrix(289, 0.016)
    assert abs(A - A.T).max() <= 1e-9 * abs(A).max()
    assert neighbours > 20
    lam = sla.eigsh(A, k=1, which='SA', return_eigenvectors=False)[0]
    assert lam > 0.0
    r = pf.measure(289, 0.016, repeats=1)
    assert float(r['residual']) < 1e-10 and r['lu_nnz'] >= r['a_nnz'] // 2


def test_a_small_run_prints_its_table_and_writes_the_csv(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), '--particles', '289,743', '--repeats', '1',
                           '--out', str(tmp_path)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert '| particles | free |' in proc.stdout
    with open(tmp_path / 'prefactor_floor.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r['particles']) for r in rows] == [289, 743]
    assert all(float(r['solve_ms']) > 0.0 and int(r['free']) < int(r['particles']) for r in rows)
