"""The organ's linear compliance as local mode's far field (``far_field_model: organ``, :mod:`.core.compliance`)."""

import dataclasses
import threading
import time

import numpy as np
import pytest

from sph_tissue_sim.core import compliance
from sph_tissue_sim.core.compliance import linear_stiffness, shell_and_ring
from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core import solver as solver_module
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.state import Motion
from sph_tissue_sim.core.tlsph import tlsph_pass
from sph_tissue_sim.validation.cases import press_and_hold

SOFT = Material.from_shear(1800.0, 0.45, 3.0)


def _block(nx: int = 7, nz: int = 4):
    return make_block(nx, nx, nz, spacing=0.0075, fix='bottom')


def _stiffness(solver: Solver):
    st = solver.scheme.state(None, None, 0)
    return linear_stiffness(solver.X, st.offsets, st.indices, st.g, st.gsum, st.w0, st.volume, st.G, st.K,
                            st.hg_k)


def test_the_stiffness_is_the_solvers_internal_forces_linearised_at_rest():
    solver = Solver(_block(), SOFT, SolverConfig(mode='global'))
    K = _stiffness(solver)
    X, n = solver.X, solver.n_particles
    u = np.random.default_rng(3).standard_normal((n, 3))
    u[solver.fixed] = 0.0
    eps = 1e-9
    motion = Motion(X + eps * u, np.zeros_like(X), np.zeros_like(X))
    tlsph_pass(solver.scheme.state(None, None, 0), solver.body, motion, solver.area.global_sets(-1))
    free = ~solver.fixed
    f = motion.acc[free] * solver.body.mass / eps
    f_lin = -(K @ u.ravel()).reshape(n, 3)[free]
    assert np.linalg.norm(f - f_lin) <= 1e-5 * np.linalg.norm(f)


def test_rigid_motions_cost_no_force():
    """A translation and an infinitesimal rotation strain nothing: ``K`` maps them to zero (the
    elastic part sees only sym(H), the hourglass bond error ``H X' - u'`` vanishes for u = W X)."""
    solver = Solver(_block(), SOFT, SolverConfig(mode='global'))
    K = _stiffness(solver)
    X = solver.X - solver.X.mean(axis=0)
    W = np.array([[0.0, -0.3, 0.2], [0.3, 0.0, -0.1], [-0.2, 0.1, 0.0]])
    scale = abs(K).max() * np.abs(X).max()
    for u in (np.tile([1e-3, -2e-3, 5e-4], (len(X), 1)), X @ W.T):
        assert np.abs(K @ u.ravel()).max() <= 1e-9 * scale


def test_a_particles_column_is_the_organs_displacement_under_a_unit_force_on_it():
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field_model='organ', far_field=1.0))
    organ = solver.organ
    X = solver.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    c = int(top[np.argmin(np.hypot(X[top, 0] - X[:, 0].mean(), X[top, 1] - X[:, 1].mean()))])
    col = organ.column(c)
    K = _stiffness(solver)
    free = ~solver.fixed
    for axis in range(3):
        f = -(K @ col[:, :, axis].ravel()).reshape(-1, 3)   # the internal forces balance the load
        load = np.zeros_like(f)
        load[c, axis] = 1.0
        np.testing.assert_allclose(f[free] + load[free], 0.0, atol=1e-4)   # single precision
    assert np.all(col[solver.fixed] == 0.0)
    # pulled up, the top rises under the load and less so farther away (the edges of this small,
    # nearly incompressible block sink a little)
    uz = col[top, 2, 2]
    r = np.hypot(X[top, 0] - X[c, 0], X[top, 1] - X[c, 1])
    near, far = uz[(r > 0.0) & (r < 0.01)], uz[r > 0.02]
    assert uz[r == 0.0][0] > near.mean() > 0.0 > far.mean() > -0.1 * uz[r == 0.0][0]
    assert np.array_equal(organ.column(c), col) and organ.n_columns == 1   # solved once, kept
    # a load shared by two particles displaces by the weighted sum of their responses
    other = int(top[np.argmax(X[top, 0])])
    idx = np.flatnonzero(~solver.fixed).astype(np.int32)
    load = np.array([0.01, -0.02, -0.3])
    x = X.copy()
    organ.place(x, X, idx, np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]), load)
    expected = X[idx] + 0.75 * organ.column(c)[idx] @ load + 0.25 * organ.column(other)[idx] @ load
    np.testing.assert_allclose(x[idx], expected, rtol=1e-6, atol=1e-12)
    assert organ.n_columns == 2
    # a particle next to a solved one borrows its response instead of paying a solve
    beside = int(top[np.argmin(np.where(top == c, np.inf, np.linalg.norm(X[top] - X[c], axis=1)))])
    assert np.array_equal(organ.column(beside), organ.column(c)) and organ.n_columns == 2


def test_an_interrupt_stops_placing_between_two_response_solves_and_moves_nothing():
    """A first touch solves a response per touched particle (tens of ms each on the liver); the
    solver's interrupt (a shutdown, a reset) is seen between two of them, not after all."""
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field_model='organ', far_field=1.0))
    organ = solver.organ
    X = solver.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    at = top[[0, len(top) // 2, -1]].astype(np.int32)
    idx = np.flatnonzero(~solver.fixed).astype(np.int32)
    lu = organ.lu

    class InterruptedDuringTheFirstSolve:
        def solve(self, rhs):
            solver.interrupt()
            return lu.solve(rhs)

    organ.lu = InterruptedDuringTheFirstSolve()
    x = X.copy()
    assert organ.place(x, X, idx, at, np.ones(3), np.array([0.0, 0.0, -0.3])) is False
    assert organ.n_columns == 1 and np.array_equal(x, X)   # the solved response is kept
    solver.clear_interrupt()
    organ.lu = lu
    assert organ.place(x, X, idx, at, np.ones(3), np.array([0.0, 0.0, -0.3])) is True
    assert organ.n_columns == 3 and not np.array_equal(x, X)


def _place_without_waiting(organ, x, X, idx, at, weights, load) -> int:
    """``organ.place`` with every sparse solve held up: it must return anyway. Returns how many
    responses were pending then."""
    done = threading.Event()

    def run():
        organ.place(x, X, idx, at, weights, load)
        done.set()

    with compliance._solve_lock:   # the worker cannot solve while the test holds this
        threading.Thread(target=run, daemon=True).start()
        assert done.wait(60.0), 'place() waited for a response'
        return organ.pending


def test_in_the_background_a_touch_never_waits_for_a_response_and_shares_the_load_among_the_ready_ones():
    """A first touch on the liver asks for a few responses of about 45 ms each; with
    ``far_field_background`` the frame goes on without them: the load is shared by the touched
    particles whose responses are ready (none: the shell stays at rest), and once the worker has
    solved them (and the shell has come in from rest) the placement is the waiting one's."""
    cfg = SolverConfig(mode='local', far_field_model='organ', far_field=1.0)
    waiting = Solver(_block(), SOFT, cfg).organ
    organ = Solver(_block(), SOFT, dataclasses.replace(cfg, far_field_background=True)).organ
    assert organ.background and not waiting.background
    X = organ.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    c, other, third = (int(top[k]) for k in (0, len(top) // 2, -1))
    idx = np.flatnonzero(~_block().fixed).astype(np.int32)
    load = np.array([0.01, -0.02, -0.3])
    x = X + 1e-3
    assert _place_without_waiting(organ, x, X, idx, np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]),
                                  load) == 2
    np.testing.assert_array_equal(x[idx], X[idx])   # nothing ready: at rest
    assert organ.wait(60.0) and organ.n_columns == 2 and organ.pending == 0
    # ready, the shell comes in from rest over READY_RAMP (a late response must not step the force)
    organ.place(x, X, idx, np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]), load)
    np.testing.assert_array_equal(x[idx], X[idx])
    time.sleep(2.0 * compliance.READY_RAMP)   # (a sleep may end a hair early on the monotonic clock)
    organ.place(x, X, idx, np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]), load)
    expected = X.copy()
    waiting.place(expected, X, idx, np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]), load)
    np.testing.assert_allclose(x[idx], expected[idx], rtol=1e-12, atol=1e-15)
    assert np.abs(x[idx] - X[idx]).max() > 1e-6
    # a third touched particle, not solved yet: the ready one carries the whole load meanwhile
    assert _place_without_waiting(organ, x, X, idx, np.array([c, third], dtype=np.int32), np.array([1.0, 1.0]),
                                  load) == 1
    waiting.place(expected, X, idx, np.array([c], dtype=np.int32), np.array([1.0]), load)
    np.testing.assert_allclose(x[idx], expected[idx], rtol=1e-12, atol=1e-15)
    assert organ.wait(60.0) and organ.n_columns == 3


def test_a_failed_background_solve_is_kept_and_the_worker_goes_on():
    organ = Solver(_block(), SOFT, SolverConfig(mode='local', far_field_model='organ', far_field=1.0,
                                                far_field_background=True)).organ
    X = organ.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    idx, at = top.astype(np.int32), top[:1].astype(np.int32)
    lu = organ.lu

    class FailsOnce:
        def solve(self, rhs):
            organ.lu = lu
            raise MemoryError('no room for the right-hand sides')

    organ.lu = FailsOnce()
    organ.place(X.copy(), X, idx, at, np.ones(1), np.zeros(3))
    assert organ.wait(60.0) and isinstance(organ.failure, MemoryError) and organ.n_columns == 0
    organ.place(X.copy(), X, idx, at, np.ones(1), np.zeros(3))   # asked again at the next touch
    assert organ.wait(60.0) and organ.n_columns == 1 and organ._worker.is_alive()
    assert organ.close(30.0)


def test_closing_a_solver_stops_its_far_fields_worker():
    """sim_node replaces its solver on a parameter change: the old worker must not stay behind
    holding the old factor."""
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field_model='organ', far_field=1.0,
                                                 far_field_background=True))
    X = solver.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    solver.organ.place(X.copy(), X, top.astype(np.int32), top[:1].astype(np.int32), np.ones(1), np.zeros(3))
    worker = solver.organ._worker
    assert worker.is_alive()
    solver.close()
    worker.join(30.0)
    assert not worker.is_alive()


def test_a_solver_rebuilt_on_the_same_organ_reuses_its_factor_and_another_material_does_not():
    """A rebuild (a parameter change in sim_node, each press of the validation) would pay the
    factorisation again (5 s on the liver); the same stiffness reuses the last factor and solves
    bit-identical responses."""
    cfg = SolverConfig(mode='local', far_field_model='organ', far_field=1.0)
    first = Solver(_block(), SOFT, cfg)
    c = int(np.argmax(first.X[:, 2]))
    again = Solver(_block(), SOFT, cfg)
    assert again.organ.reused and again.organ.lu is first.organ.lu
    assert np.array_equal(again.organ.column(c), first.organ.column(c))
    stiffer = Solver(_block(), Material.from_shear(3600.0, 0.45, 3.0), cfg)
    assert not stiffer.organ.reused
    np.testing.assert_allclose(stiffer.organ.column(c), 0.5 * first.organ.column(c), rtol=1e-4,
                               atol=1e-6 * np.abs(first.organ.column(c)).max())


def test_the_far_field_moves_the_shell_and_the_shells_neighbours_and_nothing_solved():
    solver = Solver(_block(12, 5), SOFT, SolverConfig(mode='local', far_field_model='organ', far_field=1.0))
    X = solver.X
    tip = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean(), X[:, 2].max() + solver.contact_reach - 0.003])
    for _ in range(5):
        solver.step(tip, 1e-3)
    area = solver.area
    sets = area.prepare(solver.body, tip[None].repeat(2, 0), tip[None].repeat(2, 0), solver.cand_reach, 2e-4,
                        -1, 1.75 * solver.h, False)[0]
    solved = set(sets.sph[:sets.n_sph].tolist()) | set(sets.layer[:sets.n_layer].tolist())
    shell = {j for j in sets.stress[:sets.n_stress].tolist() if j not in solved and not solver.fixed[j]}
    topo = area.topo
    ring = {int(k) for j in shell for k in topo.indices[topo.offsets[j]:topo.offsets[j + 1]]}
    expected = (shell | ring) - solved - set(np.flatnonzero(solver.fixed).tolist())
    mark = np.zeros(len(X), dtype=np.int8)
    ff_list = np.zeros(len(X), dtype=np.int32)
    x = solver.positions.copy()
    m = shell_and_ring(solver.body, topo, sets, mark, ff_list, 0, x)
    assert set(ff_list[:m].tolist()) == expected and m == len(expected)
    assert len(shell) > 0 and len(expected) > len(shell)
    assert not mark.any()
    # a frame later with nothing solved, the listed particles go back to rest
    empty = sets._replace(n_sph=0, n_layer=0, n_stress=0)
    x[ff_list[:m]] += 1e-3
    assert shell_and_ring(solver.body, topo, empty, mark, ff_list, m, x) == 0
    np.testing.assert_array_equal(x[ff_list[:m]], X[ff_list[:m]])


def test_local_mode_with_the_organs_far_field_gives_the_global_force():
    """A 4 mm press on a bottom-fixed block, held quasi-statically: with the organ's own response
    (``far_field`` 1, no tuning) local mode is within 5 % of the whole block."""
    block = _block(9, 5)
    f = {}
    for mode in ('global', 'local'):
        cfg = SolverConfig(mode=mode, far_field_model='organ', far_field=1.0)
        f[mode] = press_and_hold(block, SOFT, cfg, 0.004, ramp=300, hold=200)[2]
    print(f)
    assert f['global'] > 0.05
    assert abs(f['local'] / f['global'] - 1.0) <= 0.05


def test_a_model_too_large_to_factor_is_refused_with_a_clear_error(monkeypatch):
    monkeypatch.setattr(solver_module, 'ORGAN_MAX_FREE', 40)
    with pytest.raises(ConfigError, match='free particles are more than 40.*use far_field_model half_space'):
        Solver(_block(5, 3), SOFT, SolverConfig(mode='local', far_field_model='organ'))
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='global', far_field_model='organ')).organ is None


def test_the_organ_far_field_needs_tlsph_and_is_built_only_for_local_mode():
    with pytest.raises(ConfigError, match='far_field_model'):
        SolverConfig(far_field_model='whole').validate()
    with pytest.raises(ConfigError, match='needs scheme tlsph'):
        SolverConfig(scheme='paper', far_field_model='organ').validate()
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='global', far_field_model='organ')).organ is None
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', far_field=0.0, far_field_model='organ')).organ is None
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', far_field_model='half_space')).organ is None


def test_the_default_far_field_is_the_organs_for_tlsph_and_the_half_space_otherwise(monkeypatch):
    assert SolverConfig().far_field_model == 'auto'
    default = Solver(_block(5, 3), SOFT, SolverConfig(mode='local'))
    assert default.organ is not None and default.far_field_in_use == 'organ' and default.organ_factor_s > 0.0
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', scheme='mass_spring')).far_field_in_use == 'half_space'
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='global')).far_field_in_use == 'none'
    # beyond the size guard auto falls back to the half-space instead of refusing the model
    monkeypatch.setattr(solver_module, 'ORGAN_MAX_FREE', 10)
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local')).far_field_in_use == 'half_space'
    with pytest.raises(ConfigError, match='half_space'):
        Solver(_block(5, 3), SOFT, SolverConfig(mode='local', far_field_model='organ'))
