"""Backward-Euler dashpots (``viscosity: implicit``, :mod:`.core.backward_euler`): the solve
against a dense one, the damping matrix's symmetry, and stability beyond the explicit viscous bound."""

import numpy as np
import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.backward_euler import _apply, backward_euler_step
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import BALL_CONTACT, Solver, SolverConfig
from sph_tissue_sim.validation.cases import press_and_hold

LIVER = Material.from_shear(1800.0, 0.45, 3.0)


def _deformed_block(material: Material = LIVER, tol: float = 1e-3) -> Solver:
    """A 4 x 4 x 3 block (bottom fixed) with the implicit dashpots, pressed and released so that
    its particles are displaced and moving."""
    model = make_block(4, 4, 3, spacing=0.005, fix='bottom')
    s = Solver(model, material, SolverConfig(mode='global', viscosity='implicit', viscous_tol=tol))
    top = model.positions[:, 2].max()
    for k in range(40):
        s.step(np.array([0.007, 0.008, top + s.contact_reach - 0.002 * min(1.0, k / 20)]), 1e-3)
    return s


def _damping_matrix(s: Solver, sets, integ) -> np.ndarray:
    """``C`` (3n, 3n) over the solved particles, column by column (``C e_k = -f_visc(e_k)``)."""
    sph = sets.sph[:sets.n_sph]
    n = len(sph)
    C = np.zeros((3 * n, 3 * n))
    vel = np.zeros((s.n, 3))
    zero = np.zeros((s.n, 3))
    out = np.zeros((s.n, 3))
    for k in range(3 * n):
        vel[:] = 0.0
        vel[sph[k // 3], k % 3] = 1.0
        _apply(integ.op, s.motion.x, vel, sets, 1.0, zero, out)
        C[:, k] = out[sph].ravel()
    return C


def test_the_dashpots_damping_matrix_is_symmetric_and_dissipative():
    """``f_visc = -dD/dv`` of a quadratic dissipation, so ``C`` is symmetric positive
    semi-definite: the conjugate-gradient solve applies, and the dashpots only take energy."""
    s = _deformed_block()
    sets = s.area.global_sets(-1)
    C = _damping_matrix(s, sets, s.backward.integrator(1e-4))
    scale = np.abs(C).max()
    assert scale > 0.0
    np.testing.assert_allclose(C, C.T, atol=1e-9 * scale)
    assert np.linalg.eigvalsh(0.5 * (C + C.T)).min() > -1e-9 * scale


def test_one_sub_step_solves_the_backward_euler_system_of_a_dense_solver():
    """``(I + dt/m C) v' = v + dt a`` and ``x += dt v'`` for the solved particles, against numpy's
    dense solve (conjugate gradients to 1e-10), with the viscosity x50."""
    s = _deformed_block(LIVER.with_viscosity_scale(50.0), tol=1e-10)
    sets = s.area.global_sets(-1)
    sph = sets.sph[:sets.n_sph]
    n = len(sph)
    dt = 2e-4
    integ = s.backward.integrator(dt)
    C = _damping_matrix(s, sets, integ)
    rng = np.random.default_rng(3)
    s.motion.v[sph] = rng.normal(scale=0.01, size=(n, 3))
    s.motion.acc[sph] = rng.normal(scale=1.0, size=(n, 3))
    v_star = (s.motion.v[sph] + dt * s.motion.acc[sph]).ravel()
    x0 = s.motion.x[sph].copy()
    expected = np.linalg.solve(np.eye(3 * n) + dt * s.inv_mass * C, v_star).reshape(n, 3)
    backward_euler_step(integ, s.body, s.motion, sets)
    np.testing.assert_allclose(s.motion.v[sph], expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_allclose(s.motion.x[sph], x0 + dt * s.motion.v[sph], rtol=0, atol=1e-15)


def test_ten_times_the_viscosity_needs_no_viscous_sub_steps_and_holds_the_same_force():
    """With the viscosity x10 the explicit sub-step shrinks tenfold (the viscous bound); the
    implicit dashpots leave the CFL, contact and hourglass-dashpot bounds, stay stable, and after
    a hold (quasi-static: the dashpots carry nothing) press with the explicit scheme's force."""
    model = make_block(6, 6, 4, spacing=0.005, fix='bottom')
    thick = LIVER.with_viscosity_scale(10.0)
    # explicit contact: its bounds stay
    exp = Solver(model, thick, SolverConfig(mode='global', **BALL_CONTACT))
    imp = Solver(model, thick, SolverConfig(mode='global', viscosity='implicit', **BALL_CONTACT))
    assert 'viscous' not in imp.dt_bounds and 'viscous' in exp.dt_bounds
    assert set(imp.dt_bounds) == {'cfl', 'contact', 'contact_damping', 'hourglass_damping'}
    assert imp.dt_max > 3.0 * exp.dt_max
    config = dict(BALL_CONTACT, mode='global', max_substeps=100000)
    f_exp = press_and_hold(model, thick, SolverConfig(**config), 0.003, ramp=100, hold=900)
    f_imp = press_and_hold(model, thick, SolverConfig(viscosity='implicit', **config), 0.003, ramp=100, hold=900)
    print(f'sub-steps per ms: explicit {1e-3 / exp.dt_max:.1f}, implicit {1e-3 / imp.dt_max:.1f}; '
          f'held force: explicit {f_exp[2]:.4f} N, implicit {f_imp[2]:.4f} N')
    assert f_exp[2] > 0.05
    assert f_imp[2] == pytest.approx(f_exp[2], rel=0.02)


def test_backward_euler_needs_the_tlsph_scheme():
    with pytest.raises(ConfigError, match='viscosity'):
        SolverConfig(scheme='paper', viscosity='implicit').validate()
    with pytest.raises(ConfigError, match='viscosity'):
        SolverConfig(viscosity='semi').validate()
