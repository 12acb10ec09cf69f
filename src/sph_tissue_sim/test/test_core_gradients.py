"""Corrected reference gradients of ``tlsph`` (:mod:`sph_tissue_sim.core.gradients`): the Bonet-Lok
formula, exactness for linear fields (and only those), and the forces as the energy's gradient."""

import numpy as np
from discrete_energy import SOFT, assert_forces_are_minus_the_energy_gradient, gradients, neo_hookean_energy

from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.kernel import kernel_dwdr
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig
import pytest


def _solver(model, material=SOFT, **config) -> Solver:
    return Solver(model, material, SolverConfig(mode='global', **config))


def test_gradients_are_the_bonet_lok_corrected_kernel_gradients():
    """g_ij = V L_i^-1 DWIJ0 with L_i = sum_j V (X_j - X_i) (x) DWIJ0, written out here in numpy."""
    s = _solver(make_block(5, 4, 3, spacing=0.005, fix='none'))
    X, sc, h, V = s.X, s.scheme, s.h, s.volume
    for i in (0, 7, 30):
        lo, hi = sc.offsets[i], sc.offsets[i + 1]
        d = X[i] - X[sc.indices[lo:hi]]
        r = np.linalg.norm(d, axis=1)
        dwij = np.array([kernel_dwdr(q, h) for q in r])[:, None] / r[:, None] * d
        L = np.einsum('ka,kb->ab', -d, dwij) * V
        assert np.allclose(sc.g[lo:hi], V * dwij @ np.linalg.inv(L).T, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize('model', [make_block(6, 5, 4, spacing=0.005, fix='none'),
                                   make_model('liver', n_particles=1289)], ids=['block', 'liver'])
def test_gradients_are_exact_for_linear_fields_and_miss_quadratic_ones_at_the_surface(model):
    """u = A X: exact at every particle (the block's corners and the liver's stepped surface
    included); with quadratic terms added the gradient misses where the support is one-sided."""
    rng = np.random.default_rng(3)
    X = model.positions
    Y = (X - X.mean(axis=0)) / 0.01
    A, Q = rng.normal(size=(3, 3)), rng.normal(size=(3, 3, 3))
    Q = 0.5 * (Q + Q.transpose(0, 2, 1))
    s = _solver(model)
    assert np.abs(gradients(s, Y @ A.T) - A / 0.01).max() < 1e-8 / 0.01
    u = Y @ A.T + np.einsum('abc,nb,nc->na', Q, Y, Y)
    exact = (A[None] + 2.0 * np.einsum('abc,nc->nab', Q, Y)) / 0.01
    err = np.abs(gradients(s, u) - exact).max(axis=(1, 2)) / np.abs(exact).max()
    assert err.max() > 0.02


def test_internal_forces_are_minus_the_gradient_of_the_discrete_energy():
    """f_i = V P_i sum_j g_ij - sum_j V P_j g_ji is -dE/dx_i (central differences of the energy
    on a randomly distorted block, no hourglass, no viscosity)."""
    s = _solver(make_block(4, 4, 3, spacing=0.005, fix='none'), hourglass=0.0)
    assert_forces_are_minus_the_energy_gradient(s, lambda x: neo_hookean_energy(s, gradients(s, x)),
                                                ((0, 0), (5, 2), (17, 1), (40, 0)), seed=5)
