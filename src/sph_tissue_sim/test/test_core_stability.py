"""The dashpots' rate at the current deformation (:mod:`.core.stability`): the tracked rate against
the dense damping matrix's eigenvalues, and a creep whose dashpots outgrow the reference bounds."""

import numpy as np
import pytest

from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.state import Motion
from sph_tissue_sim.core.stability import DASHPOT_LIMIT, DASHPOT_RATE_EVERY, DashpotRate
from sph_tissue_sim.core.tlsph import tlsph_pass

LIVER = Material.from_shear(1800.0, 0.45, 3.0)


def _tracked(s: Solver, every: int) -> Solver:
    """``s`` with its dashpots' rate followed every ``every`` frames (0: the reference bounds alone)."""
    s.dashpot_rate = DashpotRate(s.scheme.dashpots_only(), s.n, every) if every else None
    return s


def _largest_dashpot_rate(s: Solver, x: np.ndarray) -> float:
    """max |eig(M^-1 C)| of the dashpots at positions ``x``, ``C`` assembled column by column."""
    state = s.scheme.dashpots_only()
    sets = s.area.global_sets(-1)
    sph = sets.sph[:sets.n_sph]
    n = len(sph)
    C = np.zeros((3 * n, 3 * n))
    v = np.zeros((s.n, 3))
    acc = np.zeros((s.n, 3))
    for k in range(3 * n):
        v[:] = 0.0
        v[sph[k // 3], k % 3] = 1.0
        tlsph_pass(state, s.body, Motion(x, v, acc), sets)
        C[:, k] = -acc[sph].ravel()
    return float(np.abs(np.linalg.eigvals(C)).max())


def test_the_tracked_rate_converges_to_the_dashpots_largest_eigenvalue_at_rest_and_deformed():
    model = make_block(5, 5, 4, spacing=0.005, fix='bottom')
    s = _tracked(Solver(model, LIVER, SolverConfig(mode='global')), 1)
    sets = s.area.global_sets(-1)
    deformed = s.X @ np.diag([1.4, 1.2, 0.8]).T
    rates = []
    for x in (s.X.copy(), deformed):
        exact = _largest_dashpot_rate(s, x)
        for _ in range(30):
            s.dashpot_rate.update(s.body, x, sets, 1e-4)
        # power iteration approaches it from below; 30 warm iterations are within 1 %
        assert 0.99 * exact <= s.dashpot_rate.rate <= exact * (1 + 1e-9)
        rates.append(exact)
    # stretched dashpots are faster: F S(sym(F^T dF)) grows with the stretch
    assert rates[1] > 1.3 * rates[0]


def _creep(every: int, cfl: float = 0.3, frames: int = 800) -> tuple[np.ndarray, np.ndarray]:
    """A 6 x 5 x 5 block (its -x face fixed), ten times the liver's viscosity, pulled at its +x
    face (0.2 N per particle) in frames of two reference sub-steps; returns its length over the
    rest length and the sub-steps, per frame."""
    model = make_block(6, 5, 5, spacing=0.005, fix='left')
    material = LIVER.with_viscosity_scale(10.0)
    dt = 2.0 * Solver(model, material, SolverConfig(mode='global')).dt_max
    s = _tracked(Solver(model, material, SolverConfig(mode='global', cfl=cfl)), every)
    X = model.positions
    face = np.flatnonzero(X[:, 0] >= X[:, 0].max() - 1e-9)
    s.set_external_forces(face, [0.2, 0.0, 0.0])
    length = X[:, 0].max() - X[:, 0].min()
    stretch, substeps = np.zeros(frames), np.zeros(frames, dtype=int)
    for k in range(frames):
        r = s.step(None, dt)
        stretch[k] = (s.x[face, 0].mean() - X[:, 0].min()) / length
        substeps[k] = r.substeps
    return stretch, substeps


def test_a_block_creeping_to_1_7_times_its_length_stays_on_the_small_step_path():
    """The block's dashpots speed up with its stretch until the reference bounds' sub-step has
    ``c dt`` past 2: without the rate bound the creep rings (9 % of the length off the path of
    sub-steps four times smaller, a frame's change 2.4x the path's); with it the sub-steps go from
    2 to 4 and the creep stays within 0.1 % of that path."""
    fine, fine_sub = _creep(0, cfl=0.075)
    tracked, sub = _creep(DASHPOT_RATE_EVERY)
    bare, bare_sub = _creep(0)
    assert fine[-1] == pytest.approx(1.757, abs=0.01)
    assert np.abs(tracked - fine).max() < 2e-3
    assert sub[0] == bare_sub.max() == 2 and sub.max() > 2 and fine_sub.min() > sub.max()
    assert np.abs(bare - fine).max() > 0.03
    assert np.abs(np.diff(bare)).max() > 1.5 * np.abs(np.diff(fine)).max()


def test_a_shallow_press_takes_the_same_substeps_and_forces_with_the_rate_followed_or_off():
    """A shallow press, whose dashpots stay near their rate at rest, takes the same sub-steps and
    forces with the reference bounds alone and with the rate followed every frame; the implicit
    integrator has no explicit dashpots whose rate to follow."""
    model = make_block(5, 5, 4, spacing=0.005, fix='bottom')
    off = _tracked(Solver(model, LIVER, SolverConfig(mode='global')), 0)
    on = _tracked(Solver(model, LIVER, SolverConfig(mode='global')), 1)
    assert off.dashpot_rate is None
    top = model.positions[:, 2].max()
    for k in range(60):
        tip = np.array([0.011, 0.012, top + on.contact_reach - 0.0001 * k])
        a, b = off.step(tip, 1e-3), on.step(tip, 1e-3)
        assert a.substeps == b.substeps
        assert np.array_equal(a.force_raw, b.force_raw)
        assert on.dashpot_rate.rate * b.substep_dt <= DASHPOT_LIMIT
    assert on.dashpot_rate.rate > 0.0
    assert Solver(model, LIVER, SolverConfig()).dashpot_rate.every == DASHPOT_RATE_EVERY
    assert Solver(model, LIVER, SolverConfig(integrator='implicit')).dashpot_rate is None
