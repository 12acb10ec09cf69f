"""Physics validation of the tlsph scheme against answers from continuum mechanics.

Every reference value here comes from a closed-form solution (Kelvin-Voigt creep, Hooke's law,
Timoshenko beam theory, whose constant-coefficient ODEs are solved exactly) or from a
conservation law, never from a previous run of the code.
The particle models are small so that each test runs in seconds on two cores; each docstring
states why the chosen geometry lets the closed-form answer apply.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sph_tissue_sim.core.local_area import FAR_FIELD_MAX_STRAIN, boussinesq
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import VELOCITY_LIMIT, Solver, SolverConfig
from sph_tissue_sim.validation.cases import E_TEST, creep, press_and_hold, press_steps, uniaxial


# ---------------------------------------------------------------------------------------------
_INTEGRATIONS = {'explicit': {}, 'implicit integrator': {'integrator': 'implicit'}}


@pytest.mark.parametrize('integration', list(_INTEGRATIONS))
def test_kelvin_voigt_creep_under_constant_traction_follows_sigma_over_e_times_one_minus_exp(integration):
    """Creep of a free bar under a constant end traction: eps(t) = sigma0/E (1 - exp(-t/tau)).

    Why this is the closed-form answer: with both dashpots sharing the retardation time tau
    (eta_shear/G = eta_bulk/K = tau), the Kelvin-Voigt constitutive law is
    sigma = C : (eps + tau deps/dt) with C the isotropic elastic tensor. Under uniaxial stress
    sigma0 (lateral faces free) C^-1 : sigma has axial component sigma0/E, so
    eps + tau deps/dt = sigma0/E, whose solution from rest is sigma0/E (1 - exp(-t/tau)): the creep
    modulus is E and the viscosity in the textbook formula is eta = E tau. The formula neglects
    inertia; a Kelvin-Voigt bar with fundamental angular frequency omega = pi c_bar / L
    (c_bar = sqrt(E/rho)) creeps at the rate 1/tau (1 + 1/(omega tau)^2 + ...), so tau is set to
    12 / omega (0.7 % rate error) and the strain is compared from t = tau/2 on, after the fast
    (elastic-wave) transients decay at rate omega^2 tau. Strain 1e-3 keeps the neo-Hookean spring
    linear to 0.1 %. The implicit integrator takes the 0.5 ms frames in one sub-step each (the
    explicit scheme 50, the viscous bound): backward Euler resolves the
    creep (tau = 70 ms) and damps the bar's faster waves, which only start the creep here.
    """
    errors = {t: measured / exact - 1.0 for t, measured, exact in creep(**_INTEGRATIONS[integration])}
    print('creep relative error at t/tau:', {k: f'{v:+.4f}' for k, v in errors.items()})
    assert all(abs(e) < 0.02 for e in errors.values()), errors


@pytest.mark.parametrize('integration', list(_INTEGRATIONS))
def test_uniaxial_tension_recovers_youngs_modulus_and_poisson_ratio(integration):
    """Static uniaxial stress: sigma0 = E eps_axial and eps_lateral = -nu eps_axial (Hooke's law).

    A free bar (12 x 6 x 6 particles) under equal and opposite end tractions; the viscosity
    (tau = 20 ms, about 1.5 fundamental periods) only brings it to rest: after 8 tau the transient
    is below 1e-3 of the static strain. The strain is the slope of the interior displacement field
    (uniform stress region, 1.5 spacings from the loaded ends).
    """
    nu = 0.45
    E_meas, nu_meas = uniaxial(nu=nu, **_INTEGRATIONS[integration])
    print(f'E error {E_meas / E_TEST - 1.0:+.4f}, nu measured {nu_meas:.4f} (exact {nu})')
    assert E_meas == pytest.approx(E_TEST, rel=0.05)
    assert nu_meas == pytest.approx(nu, rel=0.05)


def _angular_momentum_drift(hourglass: float) -> float:
    """Relative change of the angular momentum of a free, unloaded block deforming for 0.2 s."""
    model = make_block(6, 5, 4, spacing=0.0075, fix='none')
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0),
                    SolverConfig(mode='global', hourglass=hourglass))
    rng = np.random.default_rng(1)
    solver.velocities[:] = rng.normal(0.0, 0.02, solver.velocities.shape)
    solver.velocities[:] -= solver.velocities.mean(axis=0)

    def angular_momentum():
        r = solver.positions - solver.positions.mean(axis=0)
        return solver.mass * np.cross(r, solver.velocities).sum(axis=0)

    r0 = solver.positions - solver.positions.mean(axis=0)
    scale = solver.mass * np.sum(np.linalg.norm(r0, axis=1) * np.linalg.norm(solver.velocities, axis=1))
    L0 = angular_momentum()
    for _ in range(200):
        solver.step(None, 1e-3)
    assert solver.displacement().max() > 5e-4          # the body did deform
    drift = float(np.abs(angular_momentum() - L0).max() / scale)
    print(f'hourglass {hourglass}: angular momentum drift / scale {drift:.2e}')
    return drift


@pytest.mark.parametrize('hourglass', [0.0, 1.0])
def test_internal_forces_conserve_angular_momentum(hourglass):
    """Internal forces exert no net torque: the elastic and viscous TLSPH forces derive from an
    objective energy, and the hourglass forces are central (along the current bond).

    A free block with random initial velocities (no loads, no contact) deforms for 200 frames;
    the total angular momentum about the centre of mass must not change (linear momentum is
    checked in test_core_solver.py).
    """
    assert _angular_momentum_drift(hourglass) < 1e-12


# ---------------------------------------------------------------------------------------------
def _random_poke(solver: Solver, frames: int, seed: int, frame: float = 1e-3,
                 depth: float | None = None) -> dict:
    """Drive the tool along random straight paths in and out of the tissue, frames of ``frame`` [s].

    Waypoints are drawn in the model's bounding box grown by 2 cm (so the tool leaves the tissue,
    re-enters and presses deep into it, or through it), with ``depth`` [m] no lower than that
    below the model's top; the tool moves at 2-20 cm/s between them.
    """
    X = solver.model.positions
    lo, hi = X.min(axis=0) - 0.02, X.max(axis=0) + 0.02
    if depth is not None:
        lo[2] = X[:, 2].max() - depth
    rng = np.random.default_rng(seed)
    pos = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), hi[2]])
    target, speed = pos, 0.0
    stats = dict(max_force=0.0, max_speed=0.0, contact_frames=0, max_disp=0.0)
    for _ in range(frames):
        if np.linalg.norm(target - pos) < 1e-9:
            target = rng.uniform(lo, hi)
            speed = rng.uniform(0.02, 0.2)
        step = target - pos
        dist = float(np.linalg.norm(step))
        pos = target.copy() if dist <= speed * frame else pos + step * (speed * frame / dist)
        res = solver.step(pos, frame)
        assert np.all(np.isfinite(res.force)) and np.all(np.isfinite(res.force_raw))
        stats['max_force'] = max(stats['max_force'], float(np.linalg.norm(res.force)))
        stats['contact_frames'] += res.contact_index >= 0
        stats['max_disp'] = max(stats['max_disp'], res.max_displacement)
        stats['max_speed'] = max(stats['max_speed'], float(np.abs(solver.velocities).max()))
    assert np.all(np.isfinite(solver.positions)) and np.all(np.isfinite(solver.velocities))
    return stats


def _check_poke(solver: Solver, stats: dict, frames: int) -> None:
    print('random poking:', stats)
    assert stats['contact_frames'] > frames // 10          # the tool really was in the tissue
    assert stats['max_force'] <= solver.config.force_limit * (1.0 + 1e-12)
    assert stats['max_speed'] < VELOCITY_LIMIT
    assert stats['max_disp'] < 0.1                         # dents, no particle flung away


def test_random_poking_of_block_for_10000_frames_stays_finite_and_bounded():
    """10 s of random pokes at 1 kHz (local mode, liver material, 600-particle block): no SimError,
    finite state, speeds below the blow-up limit, force within the device limit."""
    model = make_block(10, 10, 6, spacing=0.0075, fix='bottom')
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0), SolverConfig(mode='local'))
    stats = _random_poke(solver, 10000, seed=7)
    _check_poke(solver, stats, 10000)


def test_random_poking_of_liver_for_10000_frames_stays_finite_and_bounded():
    """The same on the 1289-particle liver (attached at its posterior layers)."""
    model = make_model('liver', n_particles=1289)
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0), SolverConfig(mode='local'))
    stats = _random_poke(solver, 10000, seed=11)
    _check_poke(solver, stats, 10000)


def test_random_poking_of_liver_at_16_ms_frames_with_the_implicit_integrator_stays_bounded():
    """The implicit integrator at a visual frame rate: 1000 frames of 16 ms (one sub-step each,
    18 times the explicit CFL step, 11 times the viscous and 15 times the contact bound) of random pokes into the
    1289-particle liver, local mode, the tool down to 25 mm below its top: finite, bounded, within
    the device limit. (Driven through the organ's interior, as the tests above do at 1 ms, it
    blows up: see README's known limits.)"""
    model = make_model('liver', n_particles=1289)
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0),
                    SolverConfig(mode='local', integrator='implicit'))
    stats = _random_poke(solver, 1000, seed=11, frame=0.016, depth=0.025)
    assert solver.last_result.substeps == 1
    _check_poke(solver, stats, 1000)


# ---------------------------------------------------------------------------------------------
_BLOCK = make_block(10, 10, 6, spacing=0.0075, fix='bottom')
_SOFT = Material.from_shear(1800.0, 0.45, 3.0)


def _press_and_hold(mode: str, depth: float, **config) -> np.ndarray:
    """Lower the tool 4 mm into the top of a bottom-fixed block over 0.4 s, hold 0.3 s; force [N]."""
    return press_and_hold(_BLOCK, _SOFT, SolverConfig(mode=mode, **config), depth, ramp=400, hold=300)


@pytest.mark.parametrize('k1_min,far_field,n_layers,integrator', [
    (1.0, 0.0, 2, 'explicit'), (3.0, 0.0, 2, 'explicit'), (1.0, 1.0, 2, 'explicit'),
    (1.75, 0.9, 1, 'explicit'), (1.75, 0.9, 1, 'implicit')])
def test_local_area_contact_force_matches_global_at_same_indentation(k1_min, far_field, n_layers, integrator):
    """Quasi-static press: the local-area model gives the global model's force within 10 %.

    The block is pressed 4 mm by the tool over 0.4 s and held 0.3 s (the retardation time is
    1.7 ms, so the hold is quasi-static). ``k1_min`` bounds the interaction radius Dr = k1 h from
    below; the paper's k1 = f/2 (f in N) gives k1 < 1 at these forces. ``far_field`` 0 is the
    paper's still region beyond the layers, 1 the half-space response; the last case is the
    default (k1_min 1.75, far field 0.9: the organ's, so no layer), also with the implicit
    integrator in both modes.
    """
    f_global = _press_and_hold('global', 0.004, k1_min=k1_min, integrator=integrator)
    f_local = _press_and_hold('local', 0.004, k1_min=k1_min, far_field=far_field, n_layers=n_layers,
                              integrator=integrator)
    err = f_local[2] / f_global[2] - 1.0
    print(f'k1_min {k1_min}, far_field {far_field}, {n_layers} layers: global {f_global[2]:.4f} N, '
          f'local {f_local[2]:.4f} N, error {err:+.4f}')
    assert f_global[2] > 0.1
    assert abs(err) < 0.10


def _press_liver(model, mode: str, xy: tuple, **config) -> np.ndarray:
    """Lower the tool through 2, 4 and 10 mm into the liver's top surface above ``xy`` at 33 mm/s,
    holding 0.1 s at each; returns the force norms [N] at the three depths."""
    forces = press_steps(model, _SOFT, SolverConfig(mode=mode, **config), _LIVER_DEPTHS, xy=xy, ramp=300, hold=100)
    return np.linalg.norm(forces, axis=1)


def test_boussinesq_far_field_matches_the_half_space_solution():
    """Point load P on a half-space (Timoshenko & Goodier sec. 138): on the surface
    u_z = P (1 - nu) / (2 pi G r) and u_r = -P (1 - 2 nu) / (4 pi G r); on the load axis at depth z
    u_z = P (3 - 2 nu) / (4 pi G z). The load here points along -x, so 'down' is -x."""
    G, nu, P = 1800.0, 0.45, 0.01
    load = np.array([-P, 0.0, 0.0])
    r = np.array([0.02, 0.05])
    d = np.array([[0.0, r[0], 0.0], [0.0, 0.0, r[1]], [-0.03, 0.0, 0.0]])
    u = np.zeros((3, 3))
    boussinesq(d, load, G, nu, u)
    uz_surface = P * (1 - nu) / (2 * math.pi * G * r)
    ur_surface = -P * (1 - 2 * nu) / (4 * math.pi * G * r)
    np.testing.assert_allclose(-u[:2, 0], uz_surface, rtol=1e-12)        # pushed in, along -x
    np.testing.assert_allclose([u[0, 1], u[1, 2]], ur_surface, rtol=1e-12)  # drawn towards the load
    np.testing.assert_allclose(-u[2, 0], P * (3 - 2 * nu) / (4 * math.pi * G * 0.03), rtol=1e-12)
    assert u[0, 2] == 0.0 and u[2, 1] == 0.0 and u[2, 2] == 0.0
    # near the load point the singular solution is capped; no load, no displacement
    near = np.array([[0.0, 1e-4, 0.0], [1e-4, 0.0, 0.0]])
    un = np.zeros((2, 3))
    boussinesq(near, np.array([-3.3, 0.0, 0.0]), G, nu, un)
    assert np.all(np.linalg.norm(un, axis=1) <= FAR_FIELD_MAX_STRAIN * 1e-4 * (1 + 1e-12))
    boussinesq(d, np.zeros(3), G, nu, u)
    assert not u.any()


_LIVER_PLACES = [(0.0, 0.0), (0.03, 0.0), (-0.04, 0.01), (0.0, -0.03)]
_LIVER_DEPTHS = (0.002, 0.004, 0.010)


@pytest.mark.slow
def test_local_area_force_on_the_liver_matches_global():
    """The 3671-particle liver pressed through 2, 4 and 10 mm (held 0.1 s at each) at four places,
    local against global.

    With the paper's still region (far_field 0, k1_min 3, two layers) the area is stiffer than the
    whole organ, the more so the deeper: up to +12.7 % here. The defaults (the organ's own far
    field, ``far_field`` 1, k1_min 1.75, no layers under it) are within 5 % at every depth (here
    -4.5 ... +1.3 %; ``validate.py``, separate presses with the liver's material: -3.93 ... +0.46 %). Global
    runs use numba threads when there are two (bit-identical to serial, only faster).
    """
    model = make_model('liver', n_particles=3670)
    worst_still, worst_ff = 0.0, 0.0
    for xy in _LIVER_PLACES:
        f_global = _press_liver(model, 'global', xy, parallel_min_particles=1)
        err_still = _press_liver(model, 'local', xy, k1_min=3.0, far_field=0.0, n_layers=2) / f_global - 1.0
        err_ff = _press_liver(model, 'local', xy) / f_global - 1.0
        for k, depth in enumerate(_LIVER_DEPTHS):
            print(f'liver at {xy} m, {depth * 1e3:.0f} mm: global {f_global[k]:.4f} N, local k1_min 3 '
                  f'far_field 0 {err_still[k]:+.3f}, default {err_ff[k]:+.3f}')
        assert f_global.min() > 0.02
        worst_still = max(worst_still, err_still.max())
        worst_ff = max(worst_ff, np.abs(err_ff).max())
    assert worst_still > 0.05          # the still region alone is too stiff ...
    assert worst_ff < 0.05             # ... the far field brings the area to the organ


# ---------------------------------------------------------------------------------------------
def test_the_upper_surface_places_point_up_lie_on_the_top_and_spread_apart():
    """On a bottom-fixed block the upper surface is the top face and its upper edges: every place
    is a top-layer particle (or an upper edge's, whose normal leans at most to 45 degrees), its
    normal points up by at least ``min_up``, and farthest-point sampling spreads them at least a
    third of the face's width apart."""
    from sph_tissue_sim.validation.cases import upper_surface

    model = make_block(12, 12, 6, spacing=0.005, fix='bottom')
    points, normals = upper_surface(model, 4, seed=(0.0275, 0.0275))
    top = model.positions[:, 2].max()
    assert np.allclose(points[:, 2], top)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.all(normals[:, 2] >= 0.6)
    gaps = [np.linalg.norm(a - b) for k, a in enumerate(points) for b in points[k + 1:]]
    assert min(gaps) >= 0.055 / 3.0
    with pytest.raises(ValueError, match='places on the upper surface'):
        upper_surface(model, 10_000)


def test_the_thickness_under_a_place_is_the_block_height_down_and_its_width_across():
    """A 12 x 12 x 6 block of 5 mm spacing is 30 mm thick from its top face down and 60 mm wide
    across (the particle centres lie half a spacing inside each face); along a slanted line the
    particles within the radius of it count."""
    from sph_tissue_sim.validation.cases import thickness_along

    model = make_block(12, 12, 6, spacing=0.005, fix='bottom')
    X = model.positions
    top = X[np.argmax(X[:, 2] - 1e-3 * np.abs(X[:, 0] - X[:, 0].mean()))]
    assert thickness_along(model, top, np.array([0.0, 0.0, 1.0]), 0.004) == pytest.approx(0.030, abs=1e-12)
    side = X[np.argmax(X[:, 0])]
    assert thickness_along(model, side, np.array([1.0, 0.0, 0.0]), 0.004) == pytest.approx(0.060, abs=1e-12)
    tilted = np.array([0.6, 0.0, 0.8])
    assert 0.030 < thickness_along(model, top, tilted, 0.004) < 0.060


def test_a_fall_while_the_tool_advances_is_a_give_way_and_a_fall_while_it_is_held_is_not():
    """``largest_fall`` scores only advancing frames, its running maximum restarting after a hold:
    a relaxing hold (force down 30 %) then a rise again passes; a 5 % fall while advancing fails."""
    from sph_tissue_sim.validation.cases import largest_fall

    rise = np.linspace(0.0, 1.0, 50)
    held = 1.0 - 0.3 * (1.0 - np.exp(-np.arange(20) / 5.0))
    moving = np.r_[np.ones(50), np.zeros(20), np.ones(50)]
    curve = {'normal': np.r_[rise, held, held[-1] + rise], 'moving': moving}
    fall, rises = largest_fall(curve)
    assert rises and fall == 0.0
    f = curve['normal']
    f[100] -= 0.05 * f.max()
    fall, rises = largest_fall(curve)
    assert not rises and fall == pytest.approx(f[70:100].max() - f[100])


def test_a_press_path_ramps_its_speed_up_at_the_start_and_after_each_hold():
    """``press_path`` with a 10 ms ramp at 10 mm/s: the advance per 1 ms frame grows 1/10 of full
    speed per frame, falls as steeply into the hold (no frame's speed changes by more than 2/10
    of full speed), the hold's frames stand at its depth, the ramp starts again after it, and the
    path ends exactly at the depth; only full-speed frames count as advancing; without a ramp every
    frame advances at full speed."""
    from sph_tissue_sim.validation.cases import press_path

    path, moving = press_path(0.003, 0.01, holds=[(0.001, 0.005)], ramp=0.01)
    step = np.diff(np.r_[0.0, path])
    assert step[:10] == pytest.approx(1e-5 * np.arange(1, 11) / 10)
    at = path.index(0.001)
    assert not any(moving[:9]) and moving[9] and not any(moving[at - 5:at + 6]) and path[at:at + 6] == [0.001] * 6
    assert step[at + 6:at + 9] == pytest.approx(1e-5 * np.arange(1, 4) / 10)
    assert path[-1] == 0.003 and all(np.diff(path) >= 0.0)
    assert np.max(np.abs(np.diff(step))) <= 0.2 * 1e-5 + 1e-12
    assert step[at - 1] < 0.3e-5 and step[-1] < 0.3e-5
    flat, moving = press_path(0.003, 0.01)
    assert len(flat) == 300 and all(moving) and np.diff(np.r_[0.0, flat]) == pytest.approx(1e-5)
    held, moving = press_path(0.003, 0.007, holds=[(0.001, 0.002)])
    step = np.diff(np.r_[0.0, held])
    assert np.all(step <= 7e-6 + 1e-15) and held.count(0.001) == 3 and held[-1] == 0.003
    assert not moving[held.index(0.001)]                    # the step that reaches the hold is short
    with pytest.raises(ValueError, match='between 0 and the depth'):
        press_path(0.01, 0.01, holds=[(0.02, 0.1)], ramp=0.05)


def test_a_press_along_a_tilted_normal_starts_on_its_line_and_turns_the_instrument_along_it():
    """A press along a normal tilted 40 degrees from +z: the rotation takes +z to the normal (a
    capsule's shaft runs back along it), and the first touch lies a contact reach beyond the
    outermost particle near the line, nudged across the line only."""
    from sph_tissue_sim.validation.cases import NUDGE, _touch_along, _turn_z_to

    n = np.array([math.sin(0.7), 0.0, math.cos(0.7)])
    R = _turn_z_to(n)
    assert R[:, 2] == pytest.approx(n) and R.T @ R == pytest.approx(np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.array_equal(_turn_z_to(np.array([0.0, 0.0, 1.0])), np.eye(3))
    model = make_block(8, 8, 5, spacing=0.005, fix='bottom')
    point = np.array([0.0175, 0.0175, 0.01])
    start = _touch_along(model, 0.008, point, n)
    rel = model.positions - point
    along = rel @ n
    near = ~model.fixed & (np.linalg.norm(rel - along[:, None] * n, axis=1) < 1.5 * model.spacing)
    offset = start - point
    assert offset @ n == pytest.approx(along[near].max() + 0.008)
    across = offset - (offset @ n) * n
    assert np.linalg.norm(across) == pytest.approx(np.linalg.norm(np.array([*NUDGE, 0.0]) - NUDGE[0] * n[0] * n))


def test_a_press_along_a_normal_holds_where_asked_and_stops_at_the_force_limit():
    """``press_along`` on a block's top at 20 mm/s with a 30 ms hold at 1 mm: the tool arrives at
    exactly 1 mm and stands there the hold's frames (none of them scored as advancing), the force along the press rises, and the press ends
    at the first frame whose force reaches the limit."""
    from sph_tissue_sim.validation.cases import press_along

    model = make_block(8, 8, 5, spacing=0.005, fix='bottom')
    mat = Material.from_shear(1800.0, 0.45, 3.0)
    top = (0.0175, 0.0175, 0.0)
    c = press_along(model, mat, SolverConfig(mode='global'), top, (0.0, 0.0, 1.0), 0.003, 0.02, holds=[(0.001, 0.03)])
    still = c['depth'] == 0.001
    assert still.sum() == 1 + 30 and not c['moving'][still].any()      # the arrival, then the hold
    assert c['depth'][-1] == 0.003 and c['moving'].sum() >= len(c['depth']) - 31 - 2
    assert c['normal'][-1] > c['normal'][still][-1] > 0.0 and c['over'].max() == 0
    limit = 0.5 * c['normal'][-1]
    cut = press_along(model, mat, SolverConfig(mode='global'), top, (0.0, 0.0, 1.0), 0.003, 0.02,
                      holds=[(0.001, 0.03)], limit=limit)
    assert cut['normal'][-1] >= limit > cut['normal'][-2]
    assert np.array_equal(cut['normal'], c['normal'][:len(cut['normal'])])
