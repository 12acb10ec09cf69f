"""Corrected reference gradients of ``tlsph`` (:mod:`sph_tissue_sim.core.gradients`) and the
second-order option (``gradient_order: 2``): exactness against polynomial fields, the forces as the
energy's gradient, and the stiffness gain that sets its sub-step bounds."""

import math

import numpy as np
import pytest
from discrete_energy import SOFT, assert_forces_are_minus_the_energy_gradient, gradients, neo_hookean_energy

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.gradients import corrected_gradients
from sph_tissue_sim.core.kernel import kernel_dwdr
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import BALL_CONTACT, Solver, SolverConfig
from sph_tissue_sim.core.tlsph import tlsph_pass


def _solver(model, order: int, material=SOFT, **config) -> Solver:
    return Solver(model, material, SolverConfig(mode='global', gradient_order=order, **config))


def test_first_order_gradients_are_the_bonet_lok_corrected_kernel_gradients():
    """g_ij = V L_i^-1 DWIJ0 with L_i = sum_j V (X_j - X_i) (x) DWIJ0, written out here in numpy."""
    s = _solver(make_block(5, 4, 3, spacing=0.005, fix='none'), 1)
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
def test_second_order_gradients_are_exact_for_quadratic_fields_at_every_particle(model):
    """u = A X + quadratic terms: the second-order gradient is exact at every particle (the block's
    corners and the liver's stepped surface included, but for the few that fall back); the
    first-order one is exact for the linear part only and misses at the surface."""
    rng = np.random.default_rng(3)
    X = model.positions
    c = X.mean(axis=0)
    Y = (X - c) / 0.01
    A, Q = rng.normal(size=(3, 3)), rng.normal(size=(3, 3, 3))
    Q = 0.5 * (Q + Q.transpose(0, 2, 1))
    u = Y @ A.T + np.einsum('abc,nb,nc->na', Q, Y, Y)
    exact = (A[None] + 2.0 * np.einsum('abc,nc->nab', Q, Y)) / 0.01
    second = _solver(model, 2)
    err2 = np.abs(gradients(second, u) - exact).max(axis=(1, 2)) / np.abs(exact).max()
    assert second.scheme.fallen <= 0.02 * len(X)          # liver 1289: 16 (thin edges)
    assert np.sort(err2)[len(X) - second.scheme.fallen - 1] < 1e-8
    err1 = np.abs(gradients(_solver(model, 1), u) - exact).max(axis=(1, 2)) / np.abs(exact).max()
    print(f"first order, largest error {err1.max():.3f}")
    assert err1.max() > 0.02
    lin = Y @ A.T
    assert np.abs(gradients(_solver(model, 1), lin) - A / 0.01).max() < 1e-8 / 0.01


def test_second_order_gradients_equal_first_order_ones_where_the_support_is_symmetric():
    """Inside the body the third moments vanish and the fit's quadratic part decouples."""
    model = make_block(9, 9, 9, spacing=0.005, fix='none')
    one, two = _solver(model, 1), _solver(model, 2)
    X = model.positions
    depth = np.minimum(X - X.min(axis=0), X.max(axis=0) - X).min(axis=1)
    inner = depth > 2.0 * one.h + 1e-9
    rows = np.repeat(np.arange(len(X)), np.diff(one.scheme.offsets))
    assert inner.sum() >= 27
    assert np.allclose(two.scheme.g[inner[rows]], one.scheme.g[inner[rows]], rtol=1e-9, atol=1e-9)
    assert not np.allclose(two.scheme.g[~inner[rows]], one.scheme.g[~inner[rows]], rtol=1e-3)


@pytest.mark.parametrize('order', [1, 2])
def test_internal_forces_are_minus_the_gradient_of_the_discrete_energy(order):
    """f_i = V P_i sum_j g_ij - sum_j V P_j g_ji is -dE/dx_i (central differences of the energy
    on a randomly distorted block, no hourglass, no viscosity)."""
    s = _solver(make_block(4, 4, 3, spacing=0.005, fix='none'), order, hourglass=0.0)
    assert_forces_are_minus_the_energy_gradient(s, lambda x: neo_hookean_energy(s, gradients(s, x)),
                                                ((0, 0), (5, 2), (17, 1), (40, 0)), seed=5)


def _dense_max_eigenvalue(s: Solver) -> float:
    """Largest eigenvalue of M^-1 K by finite differences of the internal forces (dense)."""
    sets = s.area.global_sets(-1)
    st = s.scheme.state(None, None, 0)
    X = s.X
    n = s.n
    K = np.zeros((3 * n, 3 * n))
    for c in range(3 * n):
        s.x[:] = X
        s.x.reshape(-1)[c] += 1e-9
        s.v[:] = 0.0
        tlsph_pass(st, s.body, s.motion, sets)
        K[:, c] = -s.acc.reshape(-1) / 1e-9
    s.x[:] = X
    return float(np.linalg.eigvalsh(0.5 * (K + K.T)).max())


def test_stiffness_gain_is_the_ratio_of_the_largest_stiffness_eigenvalues():
    """The power iteration at start against a dense eigen-decomposition of both orders; the
    second order is stiffer (its surface gradients extrapolate)."""
    model = make_block(5, 4, 3, spacing=0.005, fix='none')
    one, two = _solver(model, 1), _solver(model, 2)
    exact = _dense_max_eigenvalue(two) / _dense_max_eigenvalue(one)
    gain = two.scheme.stiffness_gain(two.body, two.area.global_sets(-1))
    print(f'stiffness gain: power iteration {gain:.3f}, dense {exact:.3f}')
    assert exact > 2.0
    assert gain == pytest.approx(exact, rel=0.03)
    assert one.scheme.stiffness_gain(one.body, one.area.global_sets(-1)) == 1.0


def test_second_order_sub_step_bounds_shrink_by_the_stiffness_gain():
    """CFL by sqrt(gain), viscous by gain; the contact bounds do not change."""
    model = make_block(5, 4, 3, spacing=0.005, fix='none')
    material = Material.from_shear(1800.0, 0.45, 3.0, 3.0, rho=1060.0)
    # explicit contact, whose bounds must stay
    one, two = _solver(model, 1, material, **BALL_CONTACT), _solver(model, 2, material, **BALL_CONTACT)
    gain = two.scheme.stiffness_gain(two.body, two.area.global_sets(-1))
    assert two.dt_bounds['cfl'] == pytest.approx(one.dt_bounds['cfl'] / math.sqrt(gain), rel=1e-12)
    assert two.dt_bounds['viscous'] == pytest.approx(one.dt_bounds['viscous'] / gain, rel=1e-12)
    assert two.dt_bounds['contact'] == one.dt_bounds['contact']


def test_second_order_gradients_leave_the_state_and_the_motion_as_they_were():
    """Measuring the gain runs the force pass on scratch positions: a material change mid-run
    must not move the tissue or change its stresses."""
    s = _solver(make_block(5, 4, 3, spacing=0.005, fix='bottom'), 2)
    c = s.X.mean(axis=0)
    top = s.X[:, 2].max()
    for k in range(30):
        s.step(np.array([c[0] + 1e-3, c[1] + 5e-4, top + s.contact_reach - 1e-4 * k]), 1e-3)
    assert s.displacement().max() > 1e-4              # pressed
    x, v, F = s.positions.copy(), s.velocities.copy(), s.scheme.F.copy()
    s.set_material(Material.from_shear(2500.0, 0.45, 3.0, 3.0, rho=1060.0))
    assert np.array_equal(s.positions, x) and np.array_equal(s.velocities, v)
    assert np.array_equal(s.scheme.F, F)


@pytest.mark.parametrize('bad', [dict(gradient_order=3), dict(gradient_order=0),
                                 dict(gradient_order=2, scheme='paper')])
def test_gradient_order_must_be_1_or_2_and_needs_tlsph(bad):
    with pytest.raises(ConfigError, match='gradient_order'):
        SolverConfig(**bad).validate()


def test_corrected_gradients_reject_other_orders():
    model = make_block(3, 3, 3, spacing=0.005, fix='none')
    s = _solver(model, 1)
    with pytest.raises(ValueError, match='order'):
        corrected_gradients(s.X, s.scheme.offsets, s.scheme.indices, s.h, s.volume, 3)
