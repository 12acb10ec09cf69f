"""The organ's linear compliance as local mode's far field (tlsph up to ``ORGAN_MAX_FREE`` free particles,
:mod:`.core.compliance`)."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from sph_tissue_sim.core import compliance, response_store
from sph_tissue_sim.core.compliance import linear_stiffness, shell_and_ring
from sph_tissue_sim.core.errors import OrganFactorError
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core import solver as solver_module
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.state import Motion
from sph_tissue_sim.core.tlsph import tlsph_pass
from sph_tissue_sim.validation.cases import press_and_hold

SOFT = Material.from_shear(1800.0, 0.45, 3.0)


@pytest.fixture(autouse=True)
def empty_response_store(tmp_path, monkeypatch):
    """Each test solves its responses (and may stand in for the factor): an empty store of its own,
    and no factoring process kept from another test."""
    monkeypatch.setenv(response_store.CACHE_ENV, str(tmp_path / 'responses'))
    monkeypatch.setattr(compliance, '_last_factor', None)
    yield tmp_path / 'responses'
    if compliance._last_factor is not None:
        compliance._last_factor.close()


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
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field=1.0))
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
    # two loads (two instruments) displace by the sum of their responses, each shared by its own
    x2 = X.copy()
    pull = np.array([0.0, 0.05, 0.2])
    organ.place_loads(x2, X, idx, [(np.array([c, other], dtype=np.int32), np.array([3.0, 1.0]), load),
                                   (np.array([other], dtype=np.int32), np.array([2.0]), pull)])
    np.testing.assert_allclose(x2[idx], expected + organ.column(other)[idx] @ pull, rtol=1e-6, atol=1e-12)
    # a particle next to a solved one borrows its response instead of paying a solve
    beside = int(top[np.argmin(np.where(top == c, np.inf, np.linalg.norm(X[top] - X[c], axis=1)))])
    assert np.array_equal(organ.column(beside), organ.column(c)) and organ.n_columns == 2


def test_an_interrupt_stops_placing_between_two_response_solves_and_moves_nothing():
    """A first touch solves a response per touched particle (tens of ms each on the liver); the
    solver's interrupt (a shutdown, a reset) is seen between two of them, not after all."""
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field=1.0))
    organ = solver.organ
    X = solver.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    at = top[[0, len(top) // 2, -1]].astype(np.int32)
    idx = np.flatnonzero(~solver.fixed).astype(np.int32)
    solve = organ._solve

    def interrupted_during_the_first_solve(c, abort=None):
        u = solve(c, abort)
        solver.interrupt()
        return u

    organ._solve = interrupted_during_the_first_solve
    x = X.copy()
    assert organ.place(x, X, idx, at, np.ones(3), np.array([0.0, 0.0, -0.3])) is False
    assert organ.n_columns == 1 and np.array_equal(x, X)   # the solved response is kept
    solver.clear_interrupt()
    organ._solve = solve
    assert organ.place(x, X, idx, at, np.ones(3), np.array([0.0, 0.0, -0.3])) is True
    assert organ.n_columns == 3 and not np.array_equal(x, X)


def test_an_interrupt_ends_the_wait_for_the_factor_and_its_answer_is_kept_for_the_next_ask():
    """The factor takes seconds on the liver: a reset or a shutdown must not wait for it."""
    organ = _organ()
    c = _top(organ)
    assert not organ.factor.started
    assert organ.column(c, np.ones(1, dtype=np.int8)) is None and organ.n_columns == 0
    assert organ.factor.started   # asked, and factoring
    col = organ.column(c)
    assert col is not None and organ.n_columns == 1 and np.isfinite(col).all()


def _place_without_waiting(organ, x, X, idx, at, weights, load) -> int:
    """``organ.place`` with every sparse solve held up: it must return anyway. Returns how many
    responses were pending then."""
    done = threading.Event()

    def run():
        organ.place(x, X, idx, at, weights, load)
        done.set()

    with organ.factor._lock:   # the worker cannot ask the factoring process while the test holds this
        threading.Thread(target=run, daemon=True).start()
        assert done.wait(60.0), 'place() waited for a response'
        return organ.pending


def test_in_the_background_a_touch_never_waits_for_a_response_and_shares_the_load_among_the_ready_ones():
    """A first touch on the liver asks for a few responses of about 45 ms each; with
    ``background`` the frame goes on without them: the load is shared by the touched
    particles whose responses are ready (none: the shell stays at rest), and once the worker has
    solved them (and the shell has come in from rest) the placement is the waiting one's."""
    cfg = SolverConfig(mode='local', far_field=1.0)
    waiting = Solver(_block(), SOFT, cfg).organ
    organ = Solver(_block(), SOFT, cfg, background=True).organ
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
    organ = _organ(background=True)
    X = organ.X
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    idx, at = top.astype(np.int32), top[:1].astype(np.int32)
    solve = organ.factor.solve

    def fails_once(c, abort=None):
        organ.factor.solve = solve
        raise OrganFactorError('the organ factoring process ended (exit code -9) before it answered')

    organ.factor.solve = fails_once
    organ.place(X.copy(), X, idx, at, np.ones(1), np.zeros(3))
    assert organ.wait(60.0) and isinstance(organ.failure, OrganFactorError) and organ.n_columns == 0
    organ.place(X.copy(), X, idx, at, np.ones(1), np.zeros(3))   # asked again at the next touch
    assert organ.wait(60.0) and organ.n_columns == 1 and organ._worker.is_alive()
    assert organ.close(30.0)


def test_a_killed_factoring_process_is_a_clear_error_and_the_next_ask_starts_another(monkeypatch):
    organ = _organ()
    c, other = _top(organ), int(np.flatnonzero(~_block().fixed)[0])
    col = organ.column(c).copy()
    organ.factor._proc.kill()
    with pytest.raises(OrganFactorError, match='ended|cannot be reached'):
        organ.column(other)
    assert not organ.factor.started
    monkeypatch.setattr(compliance, '_last_factor', None)
    again = _organ()
    np.testing.assert_array_equal(again.column(c), col)   # from disk
    assert again.column(other) is not None and again.factor.started


def test_closing_a_solver_stops_its_far_fields_worker():
    """sim_node replaces its solver on a parameter change: the old worker must not stay behind
    holding the old factor."""
    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field=1.0),
                    background=True)
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
    cfg = SolverConfig(mode='local', far_field=1.0)
    first = Solver(_block(), SOFT, cfg)
    c = int(np.argmax(first.X[:, 2]))
    again = Solver(_block(), SOFT, cfg)
    assert again.organ.reused and again.organ.factor is first.organ.factor
    assert np.array_equal(again.organ.column(c), first.organ.column(c))
    stiffer = Solver(_block(), Material.from_shear(3600.0, 0.45, 3.0), cfg)
    assert not stiffer.organ.reused
    np.testing.assert_allclose(stiffer.organ.column(c), 0.5 * first.organ.column(c), rtol=1e-4,
                               atol=1e-6 * np.abs(first.organ.column(c)).max())


def test_a_cut_before_the_first_solve_reaches_neither_the_factor_nor_a_later_solver_on_the_intact_organ(
        monkeypatch):
    """The factoring process gets the organ at the first response not on disk; a blade's cut before
    it (the scheme's gradients and hourglass weights changed in place) must not reach the factor
    kept under the intact organ's key (and its disk store), which a later solver on the intact
    organ reuses."""
    monkeypatch.setenv(response_store.CACHE_ENV, '')   # every response from the factor
    cfg = SolverConfig(mode='local', far_field=1.0)
    first = Solver(_block(), SOFT, cfg)
    c = int(np.argmax(first.X[:, 2]))
    reference = first.organ.column(c).copy()
    compliance._last_factor.close()
    compliance._last_factor = None
    cutting = Solver(_block(), SOFT, cfg)   # its factor not started yet
    bonds = cutting.scheme.bonds(cutting.fixed)
    bonds.cut(np.arange(bonds.offsets[c], bonds.offsets[c + 1])[::2])
    assert bonds.n_cut > 0
    intact = Solver(_block(), SOFT, cfg)
    assert intact.organ.reused and intact.organ.factor is cutting.organ.factor
    assert np.array_equal(intact.organ.column(c), reference)
    assert np.array_equal(cutting.organ.column(c), reference)   # the intact organ's, as its key says


def test_the_far_field_moves_the_shell_and_the_shells_neighbours_and_nothing_solved():
    solver = Solver(_block(12, 5), SOFT, SolverConfig(mode='local', far_field=1.0))
    X = solver.X
    tip = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean(), X[:, 2].max() + solver.contact_reach - 0.003])
    for _ in range(5):
        solver.step(tip, 1e-3)
    area = solver.area
    seg = tip[None].repeat(2, 0)
    sets = area.prepare(solver.body, [(seg, seg, solver.contact.cand_reach, -1, 1.75 * solver.h)], 2e-4, False)[0]
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
        cfg = SolverConfig(mode=mode, far_field=1.0)
        f[mode] = press_and_hold(block, SOFT, cfg, 0.004, ramp=300, hold=200)[2]
    print(f)
    assert f['global'] > 0.05
    assert abs(f['local'] / f['global'] - 1.0) <= 0.05


def test_the_organs_far_field_is_built_for_tlsph_in_local_mode_up_to_organ_max_free(monkeypatch):
    default = Solver(_block(5, 3), SOFT, SolverConfig(mode='local'))
    assert default.organ is not None and default.far_field_in_use == 'organ'
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', scheme='mass_spring')).far_field_in_use == 'half_space'
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', scheme='paper')).far_field_in_use == 'half_space'
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='global')).far_field_in_use == 'none'
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local', far_field=0.0)).far_field_in_use == 'none'
    # an organ too large to factor (the 30k and 100k livers) takes the half-space's
    monkeypatch.setattr(solver_module, 'ORGAN_MAX_FREE', 10)
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='local')).far_field_in_use == 'half_space'


def test_the_far_field_object_is_the_organs_the_half_spaces_or_none_and_follows_the_material(monkeypatch):
    from sph_tissue_sim.core.far_field import HalfSpace, Organ, make_far_field

    assert make_far_field(False, 1.0, SOFT, None) is None
    assert make_far_field(True, 0.0, SOFT, None) is None
    organ = Solver(_block(5, 3), SOFT, SolverConfig(mode='local'))
    assert isinstance(organ.far, Organ) and organ.far.compliance is organ.organ
    monkeypatch.setattr(solver_module, 'ORGAN_MAX_FREE', 10)
    half = Solver(_block(5, 3), SOFT, SolverConfig(mode='local'))
    assert isinstance(half.far, HalfSpace) and (half.far.G, half.far.nu) == (SOFT.G, SOFT.nu)
    stiff = Material.from_shear(3 * SOFT.G, 0.4, 3.0)
    half.set_material(stiff)
    assert (half.far.G, half.far.nu) == (stiff.G, stiff.nu)
    assert Solver(_block(5, 3), SOFT, SolverConfig(mode='global')).far is None


def _organ(background: bool = False, material: Material = SOFT):
    return Solver(_block(), material, SolverConfig(mode='local', far_field=1.0),
                  background=background).organ


def _top(organ) -> int:
    return int(np.argmax(organ.X[:, 2]))


def test_a_response_solved_once_is_read_back_from_disk_bit_identical_without_a_factor(monkeypatch):
    """A restart of sim_node on the same organ feels where it was touched before at once: the
    response is on disk, and nothing is factored for it."""
    first = _organ()
    c = _top(first)
    solved = first.column(c).copy()
    assert first.factor.factor_seconds > 0.0 and first.factor.factor_nnz > 0
    monkeypatch.setattr(compliance, '_last_factor', None)   # a new process: no factor in memory
    again = _organ(background=True)
    assert not again.factor.started and len(again.disk) == 1
    assert np.array_equal(again.column(c), solved)
    assert not again.factor.started and again.disk.hits == 1
    # another material is another stiffness: its own folder, solved afresh
    stiffer = _organ(material=Material.from_shear(3600.0, 0.45, 3.0))
    assert stiffer.disk.folder != first.disk.folder and len(stiffer.disk) == 0


#: sim_node's factor and solve before they moved to a process of their own, in a process that
#: pins the BLAS kernels as a node does (this one may have loaded them first)
IN_PROCESS = """
import sys
import sph_tissue_sim
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from sph_tissue_sim.sim_node import one_blas_thread
one_blas_thread()
k = sp.load_npz(sys.argv[1])
rhs = np.load(sys.argv[2])
np.save(sys.argv[3], sla.splu(k.astype(np.float32).tocsc(), permc_spec='MMD_AT_PLUS_A').solve(rhs))
"""


def test_the_factoring_process_solves_what_sim_node_solved_in_process_bit_for_bit(tmp_path):
    import scipy.sparse as sp

    solver = Solver(_block(), SOFT, SolverConfig(mode='local', far_field=1.0))
    organ = solver.organ
    c = _top(organ)
    free = organ.free_dofs
    sp.save_npz(tmp_path / 'k.npz', _stiffness(solver)[free][:, free])
    rhs = np.zeros((3 * organ.n, 3), dtype=np.float32)
    rhs[3 * c:3 * c + 3] = np.eye(3)
    np.save(tmp_path / 'rhs.npy', rhs[free])
    subprocess.run([sys.executable, '-c', IN_PROCESS, str(tmp_path / 'k.npz'), str(tmp_path / 'rhs.npy'),
                    str(tmp_path / 'u.npy')], check=True, timeout=120)
    u = np.zeros_like(rhs)
    u[free] = np.load(tmp_path / 'u.npy')
    assert np.array_equal(organ.column(c), u.reshape(organ.n, 3, 3))


def test_an_unreadable_or_foreign_response_file_is_solved_again_and_replaced():
    first = _organ()
    c = _top(first)
    solved = first.column(c).copy()
    path = first.disk.folder / f'{c}.npy'
    for bad in (b'not a response', None):
        if bad is None:   # a well-formed array of the wrong shape
            np.save(path, np.zeros((3, 3), dtype=np.float32))
        else:
            path.write_bytes(bad)
        organ = _organ()
        assert np.array_equal(organ.column(c), solved) and organ.disk.errors == 1 and organ.disk.hits == 0
        assert np.array_equal(np.load(path), solved)   # rewritten whole


def test_a_store_that_cannot_be_written_costs_a_solve_and_nothing_else(monkeypatch, tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('')
    monkeypatch.setenv(response_store.CACHE_ENV, str(blocker))   # a folder cannot be made under a file
    monkeypatch.setattr(compliance, '_last_factor', None)
    organ = _organ()
    c = _top(organ)
    assert np.isfinite(organ.column(c)).all() and len(organ.disk) == 0
    monkeypatch.setenv(response_store.CACHE_ENV, '')
    assert _organ().disk.folder is None


def test_in_the_background_an_organ_never_touched_starts_its_factor_before_its_first_touch():
    """A live sim_node on an organ with nothing on disk: the factor (seconds on the liver) starts
    with the node, not at the first touch; with responses on disk it waits for a miss."""
    organ = _organ(background=True)
    deadline = time.monotonic() + 30.0
    while not organ.factor.started and time.monotonic() < deadline:
        time.sleep(0.01)
    assert organ.factor.started and organ.n_columns == 0
    c = _top(organ)
    assert np.isfinite(organ.column(c)).all() and organ.factor.factor_seconds > 0.0


#: a process that starts an organ's factoring process, prints the child's pid and waits to be killed
PARENT = """
import time
import numpy as np
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig
organ = Solver(make_block(7, 7, 4, spacing=0.0075, fix='bottom'), Material.from_shear(1800.0, 0.45, 3.0),
               SolverConfig(mode='local', far_field=1.0)).organ
organ.factor.start_soon()
while not organ.factor.started:
    time.sleep(0.01)
print(organ.factor._proc.pid, flush=True)
time.sleep(600)
"""


def test_the_factoring_process_ends_when_its_parent_is_killed():
    parent = subprocess.Popen([sys.executable, '-c', PARENT], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        parent.kill()
        parent.wait(30)
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
        pytest.fail(f'the factoring process {child} outlived its killed parent')
    finally:
        parent.kill()


def _ignores_sigint(pid: int) -> bool:
    with open(f'/proc/{pid}/status') as f:
        mask = next(int(line.split()[1], 16) for line in f if line.startswith('SigIgn:'))
    return bool(mask & (1 << (signal.SIGINT - 1)))


def test_a_ctrl_c_to_the_process_group_leaves_the_factoring_process_to_its_parent():
    """A terminal's Ctrl-C reaches every process of the group: the child must not die with a
    traceback mid-factor; its parent ends it (at exit, or when the parent is gone)."""
    organ = _organ()
    c = _top(organ)
    organ.factor.start_soon()
    deadline = time.monotonic() + 30.0
    while not organ.factor.started and time.monotonic() < deadline:
        time.sleep(0.01)
    pid = organ.factor._proc.pid
    while not _ignores_sigint(pid) and time.monotonic() < deadline:   # past its imports
        time.sleep(0.01)
    os.kill(pid, signal.SIGINT)
    assert np.isfinite(organ.column(c)).all()


def test_closing_ends_the_workers_wait_for_a_busy_factoring_process():
    """A node stopped while its organ is being factored (seconds on the liver) must not wait for
    the factor: its worker leaves the wait, and the process exits normally."""
    organ = _organ(background=True)
    X = organ.X
    deadline = time.monotonic() + 30.0
    while not organ.factor.started and time.monotonic() < deadline:
        time.sleep(0.01)
    pid = organ.factor._proc.pid
    os.kill(pid, signal.SIGSTOP)   # a factor that takes its time
    try:
        top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
        organ.place(X.copy(), X, top.astype(np.int32), top[:1].astype(np.int32), np.ones(1), np.zeros(3))
        while organ.pending == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        t0 = time.monotonic()
        assert organ.close(10.0)
        assert time.monotonic() - t0 < 5.0
    finally:
        os.kill(pid, signal.SIGCONT)
