"""A relaxing and stiffening spring (``Material.prony``, ``Material.stiffening``: quasi-linear
viscoelasticity in :mod:`.core.tlsph`): their checks, a held strain against the relaxation
function, creep against the linear viscoelastic closed form, the frame's undo and reset, the
stiffening stress against its strain energy's gradient."""

import math

import numpy as np
import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.material import Material, load_material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.tlsph import TlsphQlv, tlsph_pass, tlsph_qlv_pass
from sph_tissue_sim.validation.cases import relaxing_creep

KV = Material.from_shear(1800.0, 0.45, 3.0)
PRONY = ((0.4, 0.05), (0.2, 0.5))


def _relaxing(prony=PRONY) -> Material:
    return Material(KV.E, KV.nu, KV.eta_shear, KV.eta_bulk, KV.rho, 'relaxing', prony)


@pytest.mark.parametrize('prony, message', [
    (((0.3, 0.0),), 'tau must be > 0'),
    (((0.3, -1.0),), 'tau must be > 0'),
    (((0.0, 1.0),), 'weight g must be > 0'),
    (((0.6, 1.0), (0.4, 10.0)), 'sum below 1'),
    (((0.7, 1.0), (0.5, 10.0)), 'sum below 1'),
    (((0.3, math.nan),), 'tau must be > 0'),
    ((0.3,), 'a pair'),
])
def test_a_prony_series_that_is_not_a_relaxing_solid_is_refused(prony, message):
    with pytest.raises(ConfigError, match=message):
        _relaxing(prony)


def test_the_relaxation_function_falls_from_one_to_g_inf():
    m = _relaxing()
    assert m.g_inf == pytest.approx(0.4)
    assert m.relaxation(0.0) == pytest.approx(1.0)
    assert m.relaxation(0.05) == pytest.approx(0.4 + 0.4 * math.exp(-1.0) + 0.2 * math.exp(-0.1))
    assert m.relaxation(100.0) == pytest.approx(0.4)
    assert KV.g_inf == 1.0 and KV.relaxation(3.0) == 1.0


def test_materials_yaml_reads_a_prony_series_and_refuses_a_bad_one(tmp_path):
    path = tmp_path / 'materials.yaml'
    path.write_text('materials:\n  soft:\n    G: 1800.0\n    nu: 0.45\n    rho: 1060.0\n    eta_shear: 3.0\n'
                    '    prony: [[0.4, 0.05], [0.2, 0.5]]\n    stiffening: 4.0\n'
                    '  fluid:\n    G: 1800.0\n    nu: 0.45\n    rho: 1060.0\n    eta_shear: 3.0\n'
                    '    prony: [[0.7, 1.0], [0.3, 5.0]]\n')
    assert load_material(path, 'soft').prony == PRONY and load_material(path, 'soft').stiffening == 4.0
    with pytest.raises(ConfigError, match='sum below 1'):
        load_material(path, 'fluid')
    # sim_node's material parameters go the same way (a start-up or run-time change is refused)
    from sph_tissue_sim.params import build_material
    assert build_material({'material': 'soft', 'materials_file': str(path)}).prony == PRONY
    with pytest.raises(ConfigError, match='sum below 1'):
        build_material({'material': 'fluid', 'materials_file': str(path)})


def test_a_relaxing_spring_needs_the_explicit_tlsph_solver():
    block = make_block(4, 4, 3, spacing=0.0075, fix='bottom')
    for config in (SolverConfig(scheme='paper'), SolverConfig(scheme='mass_spring'),
                   SolverConfig(integrator='implicit')):
        with pytest.raises(ConfigError, match='prony'):
            Solver(block, _relaxing(), config)
    solver = Solver(block, KV, SolverConfig(integrator='implicit'))
    with pytest.raises(ConfigError, match='prony'):
        solver.set_material(_relaxing())
    assert solver.material is KV


def _stretched(material: Material, F: np.ndarray | None = None):
    """A global solver on a block, every particle moved to ``x = F X`` (default a 2 % stretch along
    x), its frame sets and ``F``."""
    solver = Solver(make_block(6, 6, 6, spacing=0.005, fix='none'), material, SolverConfig(mode='global'))
    F = np.diag([1.02, 1.0, 1.0]) if F is None else F
    solver.x[:] = solver.X @ F.T
    return solver, solver.area.global_sets(-1), F


def _kv_stress(F: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``V P`` of the Kelvin-Voigt twin at rest at ``x = F X`` (its spring's)."""
    kv, sets, _ = _stretched(KV, F)
    tlsph_pass(kv.scheme.state(sets, kv.area.active, 0), kv.body, kv.motion, sets)
    return kv.scheme.A.copy()


def _pass(solver: Solver, sets, t: float = 0.0, dt: float = 1e-3):
    """One stress and force pass of a stiffening or relaxing solver as a frame's first sub-step at
    sim time ``t``; returns the scheme (its ``A`` then holds ``V P``)."""
    scheme = solver.scheme
    scheme.start_frame(t, dt)
    state = scheme.state(sets, solver.area.active, 0)
    assert isinstance(state, TlsphQlv)
    tlsph_qlv_pass(state, solver.body, solver.motion, sets)
    scheme.frame_done(True)
    return scheme


def test_a_held_stretch_relaxes_as_the_relaxation_function_in_every_particle():
    """The strain applied at t = 0 and held (the positions never move): every particle's stress
    ``P = A / V`` is its instantaneous elastic stress times g(t), to rounding, at every sub-step
    length (the update is exact for a held strain)."""
    m = _relaxing()
    for dt in (2e-4, 1e-3, 0.01):
        solver, sets, F = _stretched(m)
        elastic = _kv_stress(F)        # V P_e: at rest the Kelvin-Voigt stress is the spring's
        for step in range(int(round(1.0 / dt)) + 1):
            scheme = _pass(solver, sets, step * dt, dt)
            if step in (0, int(round(0.05 / dt)), int(round(1.0 / dt))):
                g = m.relaxation(step * dt)
                np.testing.assert_allclose(scheme.A, g * elastic, rtol=1e-9, atol=1e-12 * np.abs(elastic).max())


def test_a_free_bar_creeps_as_linear_viscoelasticity_says():
    """Constant end tractions on a free bar of the relaxing material: the interior strain follows
    the closed form of the Kelvin-Voigt dashpot in parallel with the relaxing spring within 2 %,
    from the dashpot's fast creep to the Prony terms' slow one."""
    rows = relaxing_creep(prony=((0.3, 2.0), (0.2, 8.0)), times=(0.5, 2.0, 8.0))
    for t, measured, exact in rows:
        print(f't = {t:g} tau_v: strain {measured:.6g}, closed form {exact:.6g} ({measured / exact - 1:+.2%})')
        assert measured == pytest.approx(exact, rel=0.02)
    # it crept beyond the instantaneous strain (1e-3), towards sigma0 / (g_inf E) = 2e-3
    assert rows[-1][1] > 1.2e-3


def test_an_undone_frame_puts_the_internal_variables_back():
    m = _relaxing()
    solver, sets, _ = _stretched(m)
    scheme = solver.scheme
    scheme.start_frame(0.0, 1e-3)
    state = scheme.state(sets, solver.area.active, 0)
    tlsph_qlv_pass(state, solver.body, solver.motion, sets)
    scheme.frame_done(True)
    before = [a.copy() for a in (state.Se, state.Q, state.t_up)]
    solver.x[:] *= 1.01
    scheme.start_frame(1e-3, 1e-3)
    state = scheme.state(sets, solver.area.active, 0)
    tlsph_qlv_pass(state, solver.body, solver.motion, sets)
    assert not np.array_equal(state.Q, before[1])
    scheme.frame_done(False)
    for a, b in zip((state.Se, state.Q, state.t_up), before):
        assert np.array_equal(a, b)


def _press_and_hold(solver: Solver, depth: float = 0.004, ramp: int = 100, hold: int = 400):
    """Fz [N] when the tool reaches ``depth`` below first touch (lowered over ``ramp`` 1 ms
    frames at the top centre) and after ``hold`` frames there."""
    X = solver.X
    start = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, X[:, 2].max() + solver.contact_reach])
    forces = []
    for k in range(ramp + hold):
        forces.append(solver.step(start - [0.0, 0.0, depth * min(1.0, (k + 1) / ramp)], 1e-3).force[2])
    return forces[ramp - 1], forces[-1]


@pytest.mark.parametrize('mode', ['global', 'local'])
def test_a_press_relaxes_while_held_and_reset_forgets_the_history(mode):
    """Pressed 4 mm and held for 0.4 s, the force falls towards g_inf of it (Kelvin-Voigt's
    holds); after a reset the same press gives the same forces bit for bit. (No far field: the
    organ's lends a response solved before the reset to a neighbour, by design.)"""
    block = make_block(8, 8, 5, spacing=0.0075, fix='bottom')
    held = {}
    for name, material in (('kv', KV), ('relaxing', _relaxing())):
        solver = Solver(block, material, SolverConfig(mode=mode, far_field=0.0))
        held[name] = _press_and_hold(solver)
        if name == 'relaxing':
            solver.reset()
            assert _press_and_hold(solver) == held[name]
    print(held)
    assert held['kv'][1] > 0.95 * held['kv'][0]
    assert held['relaxing'][1] < 0.8 * held['relaxing'][0]


# ------------------------------------------------------------------------------ a stiffening spring
def _stiffening(b: float, prony=()) -> Material:
    return Material(KV.E, KV.nu, KV.eta_shear, KV.eta_bulk, KV.rho, 'stiffening', prony, b)


@pytest.mark.parametrize('b', [-0.1, 51.0, math.nan, math.inf])
def test_a_softening_or_absurd_stiffening_exponent_is_refused(b):
    with pytest.raises(ConfigError, match='stiffening must be in'):
        _stiffening(b)


def _energy(F: np.ndarray, m: Material) -> float:
    """The spring's strain energy density [J/m^3] (the module docstring of core/material.py)."""
    J = np.linalg.det(F)
    I1 = float(np.sum(F * F))
    lam = m.K - 2.0 * m.G / 3.0
    psi = 0.5 * m.G * (I1 - 3.0) - m.G * math.log(J) + 0.5 * lam * math.log(J) ** 2
    x = J ** (-2.0 / 3.0) * I1 - 3.0
    b = m.stiffening
    return psi + (m.G / (2.0 * b) * (math.exp(b * x) - 1.0 - b * x) if b > 0.0 else 0.0)


@pytest.mark.parametrize('F', [np.diag([1.25, 0.92, 0.9]),
                               np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.05, 0.0, 0.97]])])
def test_the_stiffening_spring_is_the_gradient_of_its_strain_energy(F):
    """At a homogeneous deformation (a stretch, a shear) every particle's stress ``P = A / V`` is
    d psi / d F of the strain energy, by central differences (the stress at rest: none)."""
    m = _stiffening(8.0)
    solver, sets, _ = _stretched(m, F)
    scheme = _pass(solver, sets)
    P = scheme.A / solver.volume
    dPsi = np.zeros((3, 3))
    eps = 1e-6
    for p in range(3):
        for q in range(3):
            d = np.zeros((3, 3))
            d[p, q] = eps
            dPsi[p, q] = (_energy(F + d, m) - _energy(F - d, m)) / (2.0 * eps)
    np.testing.assert_allclose(P, np.broadcast_to(dPsi, P.shape), rtol=2e-6, atol=1e-6 * np.abs(dPsi).max())
    assert scheme.stiffness_growth() > 1.5
    assert np.abs(P[0]).max() > 1.2 * np.abs(_kv_stress(F)[0] / solver.volume).max()


def test_the_stiffening_term_leaves_the_small_strain_moduli_alone():
    """At 0.1 % stretch the stiffening term is of third order: with b = 20 the stress within 2e-4
    of the neo-Hookean spring's (b (I1b - 3) is about 5e-5 there)."""
    F = np.diag([1.001, 0.9995, 0.9995])
    solver, sets, _ = _stretched(_stiffening(20.0), F)
    stiff, soft = _pass(solver, sets).A, _kv_stress(F)
    np.testing.assert_allclose(stiff, soft, rtol=0, atol=2e-4 * np.abs(soft).max())
    assert not np.array_equal(stiff, soft)


@pytest.mark.parametrize('mode', ['global', 'local'])
def test_a_stiffening_liver_block_pushes_back_harder_deep_and_takes_smaller_sub_steps(mode):
    block = make_block(8, 8, 5, spacing=0.0075, fix='bottom')
    out = {}
    for name, material in (('kv', KV), ('stiff', _stiffening(10.0, PRONY))):
        solver = Solver(block, material, SolverConfig(mode=mode, far_field=0.0))
        X = solver.X
        start = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, X[:, 2].max() + solver.contact_reach])
        res = [solver.step(start - [0.0, 0.0, 0.012 * min(1.0, (k + 1) / 200)], 1e-3) for k in range(200)]
        out[name] = (res[20].force_raw[2], res[-1].force_raw[2], max(r.substeps for r in res),
                     solver.scheme.stiffness_growth())
    print(out)
    # shallow, the instantaneous spring is the same; deep it stiffens (and relaxes a little)
    assert out['stiff'][0] == pytest.approx(out['kv'][0], rel=0.05)
    assert out['stiff'][1] > 1.3 * out['kv'][1]
    assert out['stiff'][3] > 1.5 and out['stiff'][2] > out['kv'][2]


def test_a_crushed_particle_stiffens_no_more_than_the_cap():
    """Far beyond the cap (b (I1b - 3) > ln 50) the spring is neo-Hookean at STIFFENING_CAP G more:
    the stress that law gives, and the CFL bound sees the cap (an uncapped exponential needed 64+
    sub-steps and blew up a 3000 N/m press into the stiffened liver at 22 mm)."""
    from sph_tissue_sim.core.tlsph import STIFFENING_CAP

    m = _stiffening(10.0)
    F = np.diag([0.55, 1.45, 1.3])
    solver, sets, _ = _stretched(m, F)
    scheme = _pass(solver, sets)
    J, I1 = np.linalg.det(F), float(np.sum(F * F))
    assert m.stiffening * (J ** (-2.0 / 3.0) * I1 - 3.0) > math.log(STIFFENING_CAP)
    Finv_T = np.linalg.inv(F).T
    lam = m.K - 2.0 * m.G / 3.0
    expected = (m.G * (F - Finv_T) + lam * math.log(J) * Finv_T
                + m.G * (STIFFENING_CAP - 1.0) * J ** (-2.0 / 3.0) * (F - I1 / 3.0 * Finv_T))
    np.testing.assert_allclose(scheme.A / solver.volume, np.broadcast_to(expected, scheme.A.shape),
                               rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    assert scheme.stiffness_growth() == STIFFENING_CAP
