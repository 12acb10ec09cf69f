"""Solver behaviour: contact, bad input, boundary conditions, momentum, local-area bookkeeping."""

import math

import numba
import numpy as np
import pytest
from press import momentum_drift, press

from sph_tissue_sim.core.errors import ConfigError, ModelError, SimError
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import TissueModel, make_block
from sph_tissue_sim.core.solver import (BALL_CONTACT, MODES, RELAX_DISP_TOL, SCHEMES, InvalidInput, Solver,
                                        SolverConfig, StepResult, warmup)
from sph_tissue_sim.core.tlsph import TlsphPool

LIVER = Material.from_shear(1800.0, 0.45, 3.0)


def _block(fix='bottom', n=(8, 8, 5), spacing=0.0075):
    return make_block(*n, spacing=spacing, fix=fix)


def test_scheme_and_mode_order_matches_simmetrics_constants():
    assert SCHEMES == ('paper', 'tlsph', 'mass_spring')
    assert MODES == ('global', 'local')


def test_warmup_compiles_and_returns_seconds():
    assert warmup('tlsph') >= 0.0


@pytest.mark.parametrize('mode', MODES)
def test_pressing_pushes_tissue_down_and_tissue_pushes_tool_up(mode):
    solver = Solver(_block(), LIVER, SolverConfig(mode=mode))
    res = press(solver, 0.004)
    assert isinstance(res, StepResult)
    assert res.contact_index >= 0
    assert res.force[2] > 0.02                      # reaction points out of the tissue
    assert abs(res.force[2]) > 3 * np.hypot(res.force[0], res.force[1])
    assert res.max_displacement > 0.002
    assert np.all(np.isfinite(solver.positions))
    moved_down = solver.positions[res.contact_index, 2] < solver.model.positions[res.contact_index, 2]
    assert moved_down


def test_fixed_particles_never_move():
    model = _block()
    solver = Solver(model, LIVER, SolverConfig(mode='global'))
    press(solver, 0.006, frames=200)
    assert np.array_equal(solver.positions[model.fixed], model.positions[model.fixed])


def test_force_is_clamped_to_the_device_limit_and_finite():
    solver = Solver(_block(), LIVER, SolverConfig(mode='global', force_limit=0.05, contact_stiffness=300.0))
    res = press(solver, 0.008, frames=200)
    assert res.clamped
    assert np.linalg.norm(res.force) == pytest.approx(0.05, rel=1e-9)
    assert np.linalg.norm(res.force_raw) > 0.05


@pytest.mark.parametrize('bad', [np.array([np.nan, 0.0, 0.0]), np.array([0.0, np.inf, 0.0]),
                                 np.array([1e3, 0.0, 0.0]), 'not a position', np.zeros(2)])
def test_bad_tool_position_raises_invalid_input_and_leaves_state_untouched(bad):
    solver = Solver(_block(), LIVER, SolverConfig(mode='local'))
    press(solver, 0.003, frames=50)
    x, v, t = solver.positions.copy(), solver.velocities.copy(), solver.sim_time
    with pytest.raises(InvalidInput):
        solver.step(bad, 1e-3)
    assert isinstance(InvalidInput('x'), ValueError) and isinstance(InvalidInput('x'), SimError)
    assert np.array_equal(solver.positions, x) and np.array_equal(solver.velocities, v)
    assert solver.sim_time == t


@pytest.mark.parametrize('dt', [0.0, -1e-3, float('nan'), 5.0])
def test_bad_dt_raises_invalid_input(dt):
    solver = Solver(_block(), LIVER)
    with pytest.raises(InvalidInput):
        solver.step(None, dt)


@pytest.mark.parametrize('kwargs', [dict(scheme='fem'), dict(mode='half'), dict(h_ratio=-1.0),
                                    dict(k1_min=3.0, k1_max=2.0), dict(n_layers=-1), dict(cfl=0.0),
                                    dict(tool_radius=float('nan')), dict(max_substeps=0),
                                    dict(parallel_min_particles=-1), dict(parallel_min_particles=2.5)])
def test_invalid_config_raises_config_error(kwargs):
    with pytest.raises(ConfigError):
        SolverConfig(**kwargs).validate()


def test_smoothing_length_too_small_for_any_neighbour_raises_config_error():
    # support 2h = 0.8 spacing: no lattice neighbour inside
    with pytest.raises(ConfigError, match='too small'):
        Solver(_block(), LIVER, SolverConfig(h_ratio=0.4))


def test_empty_model_raises_model_error():
    with pytest.raises(ModelError):
        TissueModel('empty', np.zeros((0, 3)), 0.01, np.zeros(0, dtype=bool))


def test_internal_forces_conserve_linear_momentum():
    solver = Solver(_block(fix='none', n=(6, 5, 4)), LIVER, SolverConfig(mode='global'))
    rng = np.random.default_rng(0)
    drift, scale = momentum_drift(solver, rng.normal(0.0, 0.02, solver.velocities.shape), frames=200)
    assert drift < 1e-10 * scale
    assert solver.displacement().max() > 1e-4  # the body did deform


def test_local_mode_releases_particles_after_they_relax():
    solver = Solver(_block(n=(10, 10, 5)), LIVER, SolverConfig(mode='local'))
    res = press(solver, 0.004, frames=200)
    assert res.n_interaction > 0 and res.n_layer.sum() == 0     # the organ's far field: no layers
    assert res.n_active < solver.n_particles // 2      # the area, not the model
    region = solver.region
    assert set(np.unique(region)) <= {0, 1, 2, 3}
    assert (region == 1).sum() >= res.n_interaction
    for _ in range(1500):
        res = solver.step(None, 1e-3)
        if solver.n_active == 0:
            break
    assert solver.n_active == 0
    assert res.contact_index == -1 and np.all(res.force == 0.0)
    assert solver.displacement().max() < 2 * RELAX_DISP_TOL
    assert np.all(solver.region == 0)


def test_reset_restores_reference_configuration():
    solver = Solver(_block(), LIVER, SolverConfig(mode='local'))
    press(solver, 0.004, frames=100)
    solver.reset()
    assert np.array_equal(solver.positions, solver.model.positions)
    assert not solver.velocities.any() and solver.sim_time == 0.0 and not solver.region.any()


def test_von_mises_is_zero_at_rest_and_positive_under_the_tool():
    solver = Solver(_block(), LIVER, SolverConfig(mode='global'))
    solver.step(None, 1e-3)
    assert np.max(solver.von_mises()) < 1e-6
    res = press(solver, 0.004, frames=150)
    vm = solver.von_mises()
    assert vm.shape == (solver.n_particles,) and np.all(np.isfinite(vm))
    assert vm[res.contact_index] > 10.0


def test_substeps_respect_the_cfl_bound():
    solver = Solver(_block(), LIVER)
    res = solver.step(None, 1e-3)
    c = LIVER.wave_speed
    assert res.substep_dt <= solver.config.cfl * solver.smoothing_length / c + 1e-15
    assert res.substeps * res.substep_dt == pytest.approx(1e-3)


def test_a_stiff_touching_tool_keeps_the_material_sub_steps():
    # the pushing contacts are integrated backward: at 1000 N/m an explicit ball's bound
    # 0.6 sqrt(m / k) would be the smallest
    solver = Solver(_block(), LIVER, SolverConfig(contact_stiffness=1000.0, **BALL_CONTACT))
    assert solver.dt_max > 0.6 * math.sqrt(solver.mass / 1000.0)
    frame = 0.95 * solver.dt_max
    free = solver.step(None, frame)
    touching = solver.step(solver.centre, frame)
    assert touching.contact_index >= 0
    assert free.substeps == touching.substeps == 1


@pytest.mark.skipif(numba.get_num_threads() < 2, reason='needs at least two numba threads')
@pytest.mark.parametrize('mode', MODES)
def test_threaded_tlsph_step_is_bit_identical_to_the_serial_step(mode):
    """parallel_min_particles=1 runs every sub-step on numba's thread pool; each particle's sums
    keep their order, so positions and forces match the serial solver bit for bit."""
    runs = []
    for par in (0, 1):
        solver = Solver(_block(), LIVER, SolverConfig(mode=mode, parallel_min_particles=par))
        assert (solver.par_min == 1) == (par == 1)
        # threads off: a state type whose frame compiles no parallel pass
        assert isinstance(solver.scheme.state(None, None, 0), TlsphPool) == (par == 1)
        res = press(solver, 0.004, frames=120)
        runs.append((res.force.copy(), solver.positions.copy(), solver.velocities.copy()))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)
    assert np.linalg.norm(runs[0][0]) > 0.01          # the press did load the tissue
