"""Linearly implicit contact (:mod:`.core.implicit_contact`): one sub-step against a dense solve,
equal and opposite impulses, and stability with a contact stiffness an explicit step would need many
sub-steps for."""

import numpy as np
import pytest

from sph_tissue_sim.core.backward_euler import NoOperator, backward_euler_step
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core import contact_kinds
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.validation.cases import press_and_hold

LIVER = Material.from_shear(1800.0, 0.45, 3.0)
SPACING = 0.0075
#: the samples as the surface (the particles' balls too small to meet the tool first: the fixture
#: below)
SURFACE = {'contact_samples': 3}


@pytest.fixture(autouse=True)
def samples_alone(monkeypatch):
    monkeypatch.setattr(contact_kinds, 'BALL_RADIUS', 1e-3)


def _pressed(**config) -> Solver:
    """The 8 x 8 x 5 block (bottom fixed) pressed 3 mm with the samples, so that the last sub-step
    recorded its pushing samples (a capsule lies along x, its tip 2 cm back from the middle)."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    s = Solver(model, LIVER, SolverConfig(mode='global', **{**SURFACE, **config}))
    X = model.positions
    top = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, X[:, 2].max() + s.contact_reach])
    rot = None
    if s.config.tool_shape == 'capsule':
        top[0] -= 0.02
        rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])    # its z along +x
    for k in range(60):
        s.step(top - [0.0, 0.0, 0.003 * min(1.0, (k + 1) / 40)], 1e-3, rot)
    assert s.touches.count[0] >= 4
    return s


def _system(s: Solver, sets, dt: float):
    """The dense contact matrix ``sum_t Phi^T (dt^2 K_t + dt c n n^T) Phi`` (``K_t = k n n^T``, or
    ``k I`` where the friction sticks) and ``sum_t dt c Phi^T n n^T Phi`` over all particles, from
    the recorded touches."""
    t = s.touches
    sm = s.samples
    A = np.zeros((3 * s.n, 3 * s.n))
    B = np.zeros_like(A)
    for k in range(t.count[0]):
        phi = np.zeros(s.n)
        if t.kind[k] == 0:
            phi[t.idx[k]] = 1.0
            kk, cc = s.config.contact_stiffness, s.contact_damping
        else:
            j = t.idx[k]
            phi[sm.w_idx[sm.w_start[j]:sm.w_start[j + 1]]] += sm.w_val[sm.w_start[j]:sm.w_start[j + 1]]
            kk, cc = sm.stiffness, sm.damping
        g = np.kron(phi, t.normal[k])
        A += (dt * dt * kk + dt * cc) * np.outer(g, g)
        B += dt * cc * np.outer(g, g)
        if t.held[k]:
            P = np.eye(3) - np.outer(t.normal[k], t.normal[k]) - np.outer(t.axis[k], t.axis[k])
            G = np.kron(phi[:, None], P)
            A += dt * dt * kk * G @ G.T
    return A, B


@pytest.mark.parametrize('friction, shape', [(0.0, 'sphere'), (0.3, 'sphere'), (0.3, 'capsule')])
def test_one_sub_step_solves_the_linearised_backward_euler_contact_system(friction, shape):
    """``(M + sum Phi^T (dt^2 K_t + dt c n n^T) Phi) v'' = M v* + sum dt c Phi^T n n^T Phi v`` over
    the solved particles (the others' velocities held), against numpy's dense solve; with friction
    the sticking samples are held by their stiffness across the normal too (on a capsule's shaft
    not along its axis, where the friction's anchor slides with the closest point)."""
    s = _pressed(friction=friction, tool_shape=shape)
    t = s.touches
    held = t.held[:t.count[0]]
    assert held.sum() > 0 if friction else held.sum() == 0
    on_axis = np.linalg.norm(t.axis[:t.count[0]], axis=1) > 0.5
    assert on_axis.any() if shape == 'capsule' else not on_axis.any()
    sets = s.area.global_sets(-1)
    sph = sets.sph[:sets.n_sph]
    dt = 5e-4
    rng = np.random.default_rng(5)
    s.motion.v[sph] = rng.normal(scale=0.01, size=(len(sph), 3))
    s.motion.acc[sph] = rng.normal(scale=1.0, size=(len(sph), 3))
    v = s.motion.v.copy()
    v_star = v.copy()
    v_star[sph] += dt * s.motion.acc[sph]
    A, B = _system(s, sets, dt)
    rows = (3 * sph[:, None] + np.arange(3)).ravel()
    held = np.setdiff1d(np.arange(3 * s.n), rows)
    m = s.mass
    lhs = m * np.eye(len(rows)) + A[np.ix_(rows, rows)]
    rhs = m * v_star.ravel()[rows] + B[rows] @ v.ravel() - A[np.ix_(rows, held)] @ v.ravel()[held]
    expected = np.linalg.solve(lhs, rhs).reshape(-1, 3)
    s.react[:] = 0.0
    integrator = s.substep_integrator(dt)
    assert isinstance(integrator.op, NoOperator)   # the contacts alone: no dashpot pass compiled in
    backward_euler_step(integrator, s.body, s.motion, sets)
    react = s.react[0]
    np.testing.assert_allclose(s.motion.v[sph], expected, rtol=0, atol=1e-7 * np.abs(expected).max())
    # the tool takes the opposite of the impulse the solve gave the tissue beyond the explicit step
    impulse = m * (s.motion.v[sph] - v_star[sph]).sum(axis=0)
    np.testing.assert_allclose(react * dt, -impulse, rtol=1e-6, atol=1e-12)


def test_a_ten_times_stiffer_contact_keeps_the_material_sub_steps_and_holds_the_static_force():
    """Samples at 3000 N/m each (an explicit contact's bound 2 sqrt(m / k_eff) would ask for about
    3x the material's sub-steps): the sub-step stays the material's, the press stays stable, and the
    held force is the static one, which the implicit integrator (everything backward, one 1 ms
    sub-step) reaches by another path."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    base = dict(SURFACE, mode='global', contact_stiffness=3000.0, max_substeps=100000)
    s = Solver(model, LIVER, SolverConfig(**base))
    assert set(s.dt_bounds) == {'cfl', 'viscous'}
    assert s.dt_max == pytest.approx(Solver(model, LIVER, SolverConfig(mode='global')).dt_max)
    f_exp = press_and_hold(model, LIVER, SolverConfig(**base), 0.003, ramp=100, hold=200)
    f_imp = press_and_hold(model, LIVER, SolverConfig(**base, integrator='implicit'), 0.003, ramp=100, hold=200)
    print(f'sub-steps per ms {1e-3 / s.dt_max:.1f}; held force: implicit contact {f_exp[2]:.4f} N, '
          f'implicit integrator {f_imp[2]:.4f} N')
    assert f_exp[2] > 0.1
    assert f_exp[2] == pytest.approx(f_imp[2], rel=0.02)


def test_a_tool_dragged_across_the_samples_feels_coulombs_friction():
    """The samples alone meet the tool (the balls shrunk): pressed 3 mm and dragged 4 mm sideways,
    a frictionless tool is held back only by the dent's slope; with friction mu the samples slide
    once their springs reach mu |f_n|, and the tissue holds the tool back by mu times the normal
    force (the samples' normals lean a little: within 20 %)."""
    from sph_tissue_sim.validation.cases import drag

    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    X = model.positions
    xy = (float(X[:, 0].mean()) - 2e-3, float(X[:, 1].mean()))
    ratio = {}
    for mu in (0.0, 0.3):
        _, _, f = drag(model, LIVER, SolverConfig(mode='global', friction=mu, **SURFACE), 0.003, 0.004, xy,
                       press=150, hold=50)
        ratio[mu] = float(-f[-20:, 0].mean() / f[-20:, 2].mean())
    print(f'drag resistance / normal force: frictionless {ratio[0.0]:.3f}, friction 0.3 {ratio[0.3]:.3f}')
    assert abs(ratio[0.0]) < 0.1
    assert ratio[0.3] == pytest.approx(0.3, rel=0.2)
