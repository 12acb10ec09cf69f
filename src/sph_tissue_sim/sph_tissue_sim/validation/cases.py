"""Set-ups that measure the solver against :mod:`.analytic` (each returns numbers, asserts nothing).

The bar and beam models are small so that each case runs in seconds on two cores; the docstrings
say why the geometry lets the closed-form answer apply.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import SimError
from ..core.material import Material
from ..core.models import TissueModel, make_beam, make_block
from ..core.solver import Solver, SolverConfig
from ..core.tlsph import tlsph_pass, tlsph_qlv_pass
from .analytic import CANTILEVER_BETA_L, creep_strain, euler_bernoulli_f1, relaxing_creep_strain, timoshenko_f1

E_TEST = 5000.0      # Young's modulus of the test material [Pa] (liver order of magnitude)
RHO = 1060.0         # density [kg/m^3]
SPACING = 0.005      # particle spacing of the bar models [m]
BEAM_SPACING = 0.0025


def kelvin_voigt(nu: float, tau: float) -> Material:
    """Kelvin-Voigt material with Young's modulus E_TEST, Poisson ratio ``nu`` and retardation ``tau``.

    ``Material.from_shear`` with ``eta_bulk=None`` gives the volumetric dashpot the same
    retardation time as the shear one: eta_shear / G = eta_bulk / K = tau.
    """
    G = E_TEST / (2.0 * (1.0 + nu))
    return Material.from_shear(G, nu, G * tau, None, rho=RHO)


def free_bar_under_end_tractions(nx: int, ny: int, nz: int, material: Material, sigma0: float,
                                 end_clearance: float = 1.5, **config) -> tuple[Solver, np.ndarray]:
    """A free bar along x pulled by equal and opposite tractions ``sigma0`` on its two end faces.

    The total force sigma0 * A (A = ny nz spacing^2, the cross-section the particles fill) is shared
    equally by the particles of each end layer. No particle is fixed: the loads balance, so the bar
    stays in place and its lateral faces are free (uniaxial stress). Returns the solver and a mask
    of the interior particles (``end_clearance`` spacings away from both loaded ends), where the
    stress is uniform. The equal end loads are not the discrete traction of a uniform stress; the
    difference decays over about a cross-section's width (Saint-Venant), faster with first-order
    gradients than with second-order ones, which need the strain measured farther from the ends.
    """
    model = make_block(nx, ny, nz, spacing=SPACING, fix='none')
    solver = Solver(model, material, SolverConfig(mode='global', max_substeps=100000, **config))
    X = model.positions
    left = np.flatnonzero(X[:, 0] < X[:, 0].min() + 1e-9)
    right = np.flatnonzero(X[:, 0] > X[:, 0].max() - 1e-9)
    total = sigma0 * ny * nz * SPACING ** 2
    forces = np.zeros((len(left) + len(right), 3))
    forces[:len(left), 0] = -total / len(left)
    forces[len(left):, 0] = total / len(right)
    solver.set_external_forces(np.concatenate([left, right]), forces)
    clear = end_clearance * SPACING
    interior = (X[:, 0] > X[:, 0].min() + clear) & (X[:, 0] < X[:, 0].max() - clear)
    return solver, interior


def strain_slope(solver: Solver, mask: np.ndarray, axis: int) -> float:
    """Slope d u_a / d X_a of the particles in ``mask`` (least squares): the uniform strain along
    ``axis``."""
    X = solver.model.positions[mask]
    u = solver.positions[mask] - X
    return float(np.polyfit(X[:, axis], u[:, axis], 1)[0])


def advance_to(solver: Solver, t_end: float, frame: float) -> None:
    """Step ``solver`` without a tool until its simulated time is ``t_end`` [s]."""
    while solver.sim_time < t_end - 1e-12:
        solver.step(None, min(frame, t_end - solver.sim_time))


def creep(nx: int = 8, ny: int = 4, nz: int = 4, nu: float = 0.45,
          times=(0.5, 1.0, 3.0), end_clearance: float = 1.5, **config) -> list[tuple[float, float, float]]:
    """Creep of a free bar under a constant end traction against eps(t) = sigma0/E (1 - exp(-t/tau)).

    With both dashpots sharing the retardation time tau (eta_shear/G = eta_bulk/K = tau), the
    Kelvin-Voigt law is sigma = C : (eps + tau deps/dt); under uniaxial stress sigma0 (lateral
    faces free) C^-1 : sigma has axial component sigma0/E, so eps + tau deps/dt = sigma0/E. The
    formula neglects inertia; a Kelvin-Voigt bar with fundamental angular frequency
    omega = pi c_bar / L creeps at the rate 1/tau (1 + 1/(omega tau)^2 + ...), so tau is set to
    12 / omega (0.7 % rate error) and the strain is compared from t = tau/2 on, after the fast
    (elastic-wave) transients decay. Strain 1e-3 keeps the neo-Hookean spring linear to 0.1 %.

    Returns ``(t / tau, measured strain, exact strain)`` at each of ``times`` (in units of tau).
    ``config``: further :class:`SolverConfig` fields (e.g. ``integrator``); ``end_clearance`` see
    :func:`free_bar_under_end_tractions`.
    """
    omega = math.pi * math.sqrt(E_TEST / RHO) / (nx * SPACING)
    tau = 12.0 / omega
    sigma0 = 1e-3 * E_TEST
    solver, interior = free_bar_under_end_tractions(nx, ny, nz, kelvin_voigt(nu, tau), sigma0,
                                                    end_clearance, **config)
    out = []
    for t in times:
        advance_to(solver, t * tau, 5e-4)
        out.append((t, strain_slope(solver, interior, 0),
                    creep_strain(sigma0, E_TEST, tau, solver.sim_time)))
    return out


def held_stretch(material: Material, times=(0.0, 0.05, 0.5, 2.0), stretch: float = 1.02,
                 dt: float = 1e-3) -> list[tuple[float, float, float]]:
    """Relaxation under a step strain: a free block of ``material`` (a relaxing spring) put at a
    uniform stretch along x at t = 0 and held there (the positions never move; the stress passes
    run at sub-steps of ``dt``), against the relaxation function ``g(t)``: the ratio of an interior
    particle's stress P_xx to its instantaneous elastic value (a Kelvin-Voigt twin's at rest).

    Returns ``(t, measured ratio, g(t))`` at each of ``times`` [s].
    """
    model = make_block(6, 6, 6, spacing=SPACING, fix='none')
    twin = Material(material.E, material.nu, material.eta_shear, material.eta_bulk, material.rho, 'twin')
    solvers = [Solver(model, m, SolverConfig(mode='global')) for m in (material, twin)]
    for s in solvers:
        s.x[:] = s.X * [stretch, 1.0, 1.0]
    solver, kv = solvers
    sets = solver.area.global_sets(-1)
    tlsph_pass(kv.scheme.state(sets, kv.area.active, 0), kv.body, kv.motion, sets)
    X = model.positions
    centre = int(np.argmin(np.linalg.norm(X - X.mean(axis=0), axis=1)))
    elastic = kv.scheme.A[centre, 0, 0]
    scheme = solver.scheme
    out = []
    for step in range(int(round(max(times) / dt)) + 1):
        scheme.start_frame(step * dt, dt)
        tlsph_qlv_pass(scheme.state(sets, solver.area.active, 0), solver.body, solver.motion, sets)
        scheme.frame_done(True)
        t = step * dt
        if any(abs(t - want) < 0.5 * dt for want in times):
            out.append((t, float(scheme.A[centre, 0, 0] / elastic), material.relaxation(t)))
    return out


def relaxing_creep(nx: int = 8, ny: int = 4, nz: int = 4, nu: float = 0.45, prony=((0.3, 4.0), (0.2, 20.0)),
                   times=(0.5, 2.0, 8.0, 30.0, 80.0)) -> list[tuple[float, float, float]]:
    """:func:`creep` with a relaxing spring: the Kelvin-Voigt bar of :func:`creep` (its dashpot's
    retardation ``tau_v`` as there) whose spring relaxes by ``prony`` (time constants in units of
    ``tau_v``), against :func:`~.analytic.relaxing_creep_strain`. The strain creeps towards
    ``sigma0 / (g_inf E)`` with the Prony terms' slower time constants.

    Returns ``(t / tau_v, measured strain, exact strain)`` at each of ``times`` (in units of tau_v).
    """
    omega = math.pi * math.sqrt(E_TEST / RHO) / (nx * SPACING)
    tau_v = 12.0 / omega
    sigma0 = 1e-3 * E_TEST
    terms = tuple((g, k * tau_v) for g, k in prony)
    kv = kelvin_voigt(nu, tau_v)
    material = Material(kv.E, kv.nu, kv.eta_shear, kv.eta_bulk, kv.rho, 'relaxing', terms)
    solver, interior = free_bar_under_end_tractions(nx, ny, nz, material, sigma0)
    out = []
    for t in times:
        advance_to(solver, t * tau_v, 5e-4)
        out.append((t, strain_slope(solver, interior, 0),
                    relaxing_creep_strain(sigma0, E_TEST, tau_v, terms, solver.sim_time)))
    return out


def uniaxial(nx: int = 12, ny: int = 6, nz: int = 6, nu: float = 0.45, tau: float = 0.02,
             end_clearance: float = 1.5, **config) -> tuple[float, float]:
    """Static uniaxial stress on a free bar: (measured E [Pa], measured nu) from sigma0 = E eps_axial
    and eps_lateral = -nu eps_axial (Hooke's law); exact ``E_TEST`` and ``nu``.

    The viscosity (tau = 20 ms, about 1.5 fundamental periods of the 12 x 6 x 6 bar) only brings it
    to rest: after 8 tau the transient is below 1e-3 of the static strain.
    """
    sigma0 = 1e-3 * E_TEST
    solver, interior = free_bar_under_end_tractions(nx, ny, nz, kelvin_voigt(nu, tau), sigma0,
                                                    end_clearance, **config)
    advance_to(solver, 8.0 * tau, 1e-3)
    eps = strain_slope(solver, interior, 0)
    eps_lat = 0.5 * (strain_slope(solver, interior, 1) + strain_slope(solver, interior, 2))
    return sigma0 / eps, -eps_lat / eps


def crossings(t: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Times where ``z`` changes sign (linear interpolation), excluding the start at z = 0."""
    k = np.flatnonzero(z[:-1] * z[1:] < 0.0)
    return t[k] - z[k] * (t[k + 1] - t[k]) / (z[k + 1] - z[k])


def cantilever_frequency(n_across: int, slenderness: float, n_wide: int | None = None,
                         nu: float = 0.3, **config) -> tuple[float, float, float]:
    """First bending frequency (in z) of a clamped beam ``n_across`` particles tall and ``n_wide``
    wide (default square): (measured, Euler-Bernoulli, Timoshenko) [Hz].

    The beam is clamped by two fixed particle layers, set swinging in its first mode shape with a
    tip amplitude of 1 % of L from its straight shape; the period is twice the time from the
    release to the tip displacement's first zero crossing (half a period: measuring to the next
    crossing too cost the run again and moved the 10-tall beam's f1 by under 0.07 %, -6.27 % from
    Euler-Bernoulli either way explicit, -6.1 / -6.16 % from Timoshenko implicit). No tool, so the
    sub-steps follow the material's CFL bound only. ``config``: further :class:`SolverConfig` fields (e.g.
    ``integrator``).
    """
    length = slenderness * n_across * BEAM_SPACING
    model = make_beam(length, (n_wide or n_across) * BEAM_SPACING, n_across * BEAM_SPACING,
                      BEAM_SPACING, fixed_layers=2)
    L, H, W = model.info['length'], model.info['height'], model.info['width']
    f_eb = euler_bernoulli_f1(L, H, E_TEST, RHO)
    # low viscosity: the mode's damping ratio tau * omega / 2 is 1e-4
    solver = Solver(model, kelvin_voigt(nu, 1e-4 / (2 * math.pi * f_eb)),
                    SolverConfig(mode='global', max_substeps=100000, **config))
    X = model.positions
    # initial velocity in the shape of the first clamped-free mode
    b, s = CANTILEVER_BETA_L / L, 0.7341
    xi = np.clip(X[:, 0], 0.0, None)
    phi = np.cosh(b * xi) - np.cos(b * xi) - s * (np.sinh(b * xi) - np.sin(b * xi))
    phi_tip = np.cosh(b * L) - np.cos(b * L) - s * (np.sinh(b * L) - np.sin(b * L))
    free = ~model.fixed
    solver.velocities[free, 2] = 0.01 * L * 2.0 * math.pi * f_eb * phi[free] / phi_tip
    tip = X[:, 0] > X[:, 0].max() - 1e-9
    t, z = [], []
    frame = 1.0 / (200.0 * f_eb)
    while len(z) < 2 or z[-2] * z[-1] >= 0.0:     # up to the first sign change
        solver.step(None, frame)
        t.append(solver.sim_time)
        z.append(float(np.mean(solver.positions[tip, 2] - X[tip, 2])))
        if solver.sim_time > 5.0 / f_eb:
            raise RuntimeError('the cantilever does not oscillate')
    tc = crossings(np.array(t), np.array(z))
    return 1.0 / (2.0 * tc[0]), f_eb, timoshenko_f1(L, H, W, E_TEST, nu, RHO)


#: [m] presses start this far off the lattice axis, so that the first particle touched is unambiguous
NUDGE = (1e-3, 5e-4)


def first_touch(model: TissueModel, reach: float, xy, nudge=(0.0, 0.0)) -> np.ndarray:
    """Where the tool tip first touches the top of the model above ``xy`` [m]: ``reach`` (the
    solver's contact distance) above the highest free particle within 1.5 spacings, moved sideways
    by ``nudge``."""
    return _touch_along(model, reach, np.array([xy[0], xy[1], 0.0]), np.array([0.0, 0.0, 1.0]), nudge)


def press_and_hold(model: TissueModel, material: Material, config: SolverConfig, depth: float,
                   xy=None, ramp: int = 300, hold: int = 100, dt: float = 1e-3) -> np.ndarray:
    """Lower the tool from first touch ``depth`` [m] into the top surface above ``xy`` (default: the
    model's centre) over ``ramp`` frames and hold it ``hold`` frames; returns the force [N] sent
    at the end (quasi-static when the hold is long against the retardation time)."""
    solver = Solver(model, material, config)
    P = model.positions
    if xy is None:
        xy = (P[:, 0].mean(), P[:, 1].mean())
    start = first_touch(model, solver.contact_reach, xy, NUDGE)
    res = None
    for k in range(ramp + hold):
        res = solver.step(start - np.array([0.0, 0.0, depth * min(1.0, (k + 1) / ramp)]), dt)
    return res.force


def press_steps(model: TissueModel, material: Material, config: SolverConfig, depths, xy=None,
                ramp: int = 300, hold: int = 100, dt: float = 1e-3) -> np.ndarray:
    """Lower the tool from first touch into the top surface above ``xy`` through each of the
    increasing ``depths`` [m] at one speed (the deepest reached after ``ramp`` frames of motion),
    holding ``hold`` frames at each; returns the forces [N] at the ends of the holds, (len(depths), 3):
    :func:`press_and_hold` at several depths in one run."""
    solver = Solver(model, material, config)
    P = model.positions
    if xy is None:
        xy = (P[:, 0].mean(), P[:, 1].mean())
    start = first_touch(model, solver.contact_reach, xy, NUDGE)
    step = max(depths) / ramp
    forces, z = [], 0.0
    for depth in depths:
        while z < depth:
            z = min(depth, z + step)
            solver.step(start - np.array([0.0, 0.0, z]), dt)
        for _ in range(hold):
            res = solver.step(start - np.array([0.0, 0.0, z]), dt)
        forces.append(res.force)
    return np.array(forces)


def drag(model: TissueModel, material: Material, config: SolverConfig, depth: float, travel: float,
         xy, direction=(1.0, 0.0), speed: float = 0.02, press: int = 250, hold: int = 100,
         dt: float = 1e-3) -> tuple[float, float, np.ndarray]:
    """Press the tool ``depth`` [m] into the top surface above ``xy`` over ``press`` frames, hold
    ``hold`` frames, then drag it ``travel`` [m] along the horizontal unit ``direction`` at
    ``speed`` [m/s].

    Returns (the largest frame-to-frame change of the force during the drag [N], the mean Fz of
    the drag [N], the drag's forces (frames + 1, 3) from the last still frame on [N]): a smooth
    force changes by the contact stiffness times the frame's travel.
    """
    solver = Solver(model, material, config)
    start = first_touch(model, solver.contact_reach, xy)
    frames = int(round(travel / (speed * dt)))
    path = [start - np.array([0.0, 0.0, depth * min(1.0, (k + 1) / press)]) for k in range(press + hold)]
    step = np.array([direction[0], direction[1], 0.0]) * travel / frames
    path += [path[-1] + step * (k + 1) for k in range(frames)]
    forces = np.array([solver.step(p, dt).force_raw.copy() for p in path])
    dragged = forces[press + hold - 1:]
    jumps = np.linalg.norm(np.diff(dragged, axis=0), axis=1)
    return float(jumps.max()), float(forces[press + hold:, 2].mean()), dragged


def press_curve(model: TissueModel, material: Material, config: SolverConfig, depth: float,
                speed: float = 0.01, xy=(0.0, 0.0), dt: float = 1e-3, renderer=None) -> dict:
    """Press the tool straight down into the top surface above ``xy`` to ``depth`` [m] at ``speed``
    [m/s], one ``dt`` frame at a time, from first touch: :func:`press_along` the vertical.

    With a :class:`~..haptics.renderer.HapticRenderer`, ``depth`` is the device's: the renderer
    answers each device sample and the solver steps at its proxy (the lockstep schedule of the
    node, one step per sample); then ``tool`` is the simulated tool's depth [m] and ``device`` the
    force sent to the device along +z [N] (``normal`` stays the solver's).
    """
    return press_along(model, material, config, (xy[0], xy[1], 0.0), (0.0, 0.0, 1.0), depth, speed,
                       dt=dt, renderer=renderer)


def press_path(depth: float, speed: float, holds=(), dt: float = 1e-3, ramp: float = 0.0) -> tuple[list, list]:
    """A press's depth [m] at each ``dt`` frame and whether the tool advanced at ``speed`` [m/s] in
    it: to ``depth``, standing ``hold`` [s] at each ``(depth, hold)`` of ``holds``; with ``ramp`` [s]
    the speed rises linearly from 0 over that time at the start and after each hold and falls as
    steeply before each stop (a hand does not step its speed: a step makes the dashpots' force jump
    and fall back); only the frames at full speed count as advancing. Each hold lies between 0 and
    ``depth`` (``ValueError`` otherwise)."""
    pauses = sorted((d, int(round(h / dt))) for d, h in holds)
    if any(not 0.0 < d < depth for d, _ in pauses):
        raise ValueError(f'press_path: every hold must lie between 0 and the depth {depth} m, got {holds}')
    # a straight press without a ramp keeps the exact schedule m * speed * dt
    scheduled = ramp <= 0.0 and not pauses
    moves = int(math.ceil(depth / (speed * dt)))
    path, advancing = [], []
    d, m, j = 0.0, 0, 0
    while (m < moves) if scheduled else (d < depth):
        m += 1
        j += 1
        if scheduled:
            full = True
            d = min(depth, m * speed * dt)
        else:
            stop = pauses[0][0] if pauses else depth
            frac = 1.0
            if ramp > 0.0:
                frac = min(1.0, j * dt / ramp, math.sqrt(2.0 * max(stop - d, 0.0) / (speed * ramp)))
            step = max(frac, dt / ramp if ramp > 0.0 else 1.0) * speed * dt
            full = frac >= 1.0 and d + step <= stop
            d = min(stop, d + step)
        wait = 0
        if pauses and d >= pauses[0][0]:
            wait, j = pauses[0][1], 0
            pauses.pop(0)
        path += [d] * (1 + wait)
        advancing += [full] + [False] * wait
    return path, advancing


def press_along(model: TissueModel, material: Material, config: SolverConfig, point, normal, depth: float,
                speed: float, holds=(), limit: float = math.inf, dt: float = 1e-3, renderer=None,
                ramp: float = 0.0) -> dict:
    """Press the tool into the surface along ``-normal`` (a unit vector, the surface's outward one)
    on the line through ``point`` [m], from first touch to ``depth`` [m] at ``speed`` [m/s], one
    ``dt`` frame at a time, pausing ``hold`` [s] at each ``(depth, hold)`` of ``holds`` (the speed
    rising over ``ramp`` [s] after each start: :func:`press_path`); stops after the first frame whose
    force along the press reaches ``limit`` [N].

    Returns per frame: ``depth`` [m] below first touch, ``normal`` (the force along ``normal``) and
    ``sideways`` (the norm of the rest) [N], ``moving`` (whether the tool advanced at ``speed``),
    ``over``: how many particle centres lie over the tool (closer than its radius to the press's
    axis and behind its centre): tissue the tool has passed under, i.e. popped through; ``slip``:
    how far the particle touched first has moved across the press [m] (a straight press should
    carry it along). ``tool`` and ``device`` as in :func:`press_curve`.

    A step that goes unstable (:class:`~..core.errors.SimError`, e.g. the crushed tissue round a
    deep tool) ends the press: the arrays then stop at the last good frame and ``unstable_at`` is
    the depth [m] of the failed one (``None`` otherwise).
    """
    solver = Solver(model, material, config)
    P = model.positions
    n = np.asarray(normal, dtype=float)
    start = _touch_along(model, solver.contact_reach, np.asarray(point, dtype=float), n)
    first = int(np.argmin(np.linalg.norm(P - start, axis=1)))
    path, advancing = press_path(depth, speed, holds, dt, ramp)
    frames = len(path)
    out = {k: np.zeros(frames) for k in ('depth', 'normal', 'sideways', 'over', 'slip', 'tool', 'device', 'moving')}
    radius = solver.tool.radius
    rot = _turn_z_to(n)
    for k in range(frames):
        d, moving = path[k], advancing[k]
        tip = start - d * n
        if renderer is not None:
            answer = renderer.answer(tip, dt)
            out['device'][k] = answer.force @ n
            tip = answer.proxy
        try:
            res = solver.step(tip, dt, rot)
        except SimError:
            out = {key: val[:k] for key, val in out.items()}
            out['unstable_at'] = d
            return out
        f = res.force_raw
        if renderer is not None:
            renderer.refresh(res.tool_segment[0] if res.tool_segment is not None else tip, f)
        at = res.tool_segment[0] if res.tool_segment is not None else tip
        out['depth'][k] = d
        out['moving'][k] = moving
        out['tool'][k] = (start - at) @ n
        out['normal'][k] = f @ n
        out['sideways'][k] = _across(f, n)
        rel = solver.positions - at
        along = rel @ n
        out['over'][k] = np.count_nonzero((_across_rows(rel, n) < radius) & (along > 0.0))
        out['slip'][k] = _across(solver.positions[first] - P[first], n)
        if out['normal'][k] >= limit:
            out = {key: val[:k + 1] for key, val in out.items()}
            break
    out['unstable_at'] = None
    return out


def _turn_z_to(n: np.ndarray) -> np.ndarray:
    """The rotation taking +z to the unit vector ``n`` about their common normal (an instrument
    held along the press: a capsule's shaft runs back along ``n``); the identity for +z."""
    c = float(n[2])
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross([0.0, 0.0, 1.0], n)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _across(v: np.ndarray, n: np.ndarray) -> float:
    """The norm of ``v``'s part normal to the unit vector ``n`` (by ``hypot``: for ``n = +z`` exactly
    the horizontal norm)."""
    return math.hypot(*(v - (v @ n) * n))


def _across_rows(rel: np.ndarray, n: np.ndarray) -> np.ndarray:
    """:func:`_across` of each row of ``rel``."""
    w = rel - (rel @ n)[:, None] * n
    return np.hypot(np.hypot(w[:, 0], w[:, 1]), w[:, 2])


def _touch_along(model: TissueModel, reach: float, point: np.ndarray, n: np.ndarray, nudge=NUDGE) -> np.ndarray:
    """Where a tool moving along ``-n`` on the line through ``point`` first touches the model:
    ``reach`` beyond the outermost free particle within 1.5 spacings of the line, moved across it
    by ``nudge`` (x, y) [m] (its part across ``n``)."""
    rel = model.positions - point
    along = rel @ n
    line = ~model.fixed & (_across_rows(rel, n) < 1.5 * model.spacing)
    side = np.array([nudge[0], nudge[1], 0.0])
    return point + (along[line].max() + reach) * n + (side - (side @ n) * n)


def upper_surface(model: TissueModel, count: int, min_up: float = 0.6, seed=None) -> tuple[np.ndarray, np.ndarray]:
    """``count`` places on the model's upper surface, ``(points (count, 3) [m], outward normals)``:
    surface particles (:func:`~..core.surface_contact.surface_normals`) whose reference normal
    points up by at least ``min_up`` (level and sloping, up to acos(min_up)), at least three
    spacings from a fixed particle, spread by farthest-point sampling from the one nearest
    ``seed`` (x, y) (default: the highest)."""
    from ..core.neighbours import find_neighbours
    from ..core.surface_contact import surface_normals

    P, s = model.positions, model.spacing
    h = SolverConfig().h_ratio * s
    offsets, indices = find_neighbours(P, 2.0 * h)
    N = surface_normals(P, offsets, indices, h, s ** 3, s)
    fixed = P[model.fixed]
    far = np.ones(len(P), dtype=bool) if len(fixed) == 0 else np.array(
        [np.min(np.linalg.norm(fixed - p, axis=1)) >= 3.0 * s for p in P])
    cand = np.flatnonzero((N[:, 2] >= min_up) & ~model.fixed & far)
    if len(cand) < count:
        raise ValueError(f'upper_surface: {len(cand)} places on the upper surface, {count} asked')
    pts = P[cand]
    first = int(np.argmax(pts[:, 2])) if seed is None else int(np.argmin(np.hypot(pts[:, 0] - seed[0], pts[:, 1] - seed[1])))
    chosen = [first]
    dist = np.linalg.norm(pts - pts[first], axis=1)
    while len(chosen) < count:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
    return pts[chosen], N[cand[chosen]]


def thickness_along(model: TissueModel, point: np.ndarray, n: np.ndarray, radius: float) -> float:
    """[m] how thick the model is under ``point`` along ``-n``: from the surface to the far face
    through the particles within ``radius`` [m] of the line (their centres lie half a spacing
    inside both faces)."""
    rel = model.positions - np.asarray(point, dtype=float)
    along = rel[_across_rows(rel, n) < radius] @ n
    if len(along) == 0:
        raise ValueError(f'thickness_along: no particle within {radius} m of the line through {point}')
    return float(along.max() - along.min() + model.spacing)


def largest_fall(curve: dict, tolerance: float = 0.02) -> tuple[float, bool]:
    """``(fall [N], holds)``: the largest fall of a press's force below its running maximum while
    the tool advances at its speed (the maximum restarts after each slowing down or hold: what the
    dashpots lose as the tool slows and a relaxing tissue loses while held is not the tool giving
    way), and whether it is within ``tolerance`` of the largest force."""
    f, moving = curve['normal'], curve['moving'].astype(bool)
    worst, run = 0.0, -math.inf
    for k in range(len(f)):
        if not moving[k]:
            run = -math.inf
            continue
        run = max(run, f[k])
        worst = max(worst, run - f[k])
    return worst, worst <= tolerance * float(np.max(f, initial=0.0))


def gives_way(depth: np.ndarray, force: np.ndarray, tolerance: float = 0.02) -> float:
    """Depth [m] where a press's force first falls below its running maximum by more than
    ``tolerance`` of its largest force (``inf`` if it never does: the force rises monotonically
    within that tolerance): where the tissue stops holding the tool."""
    fell = np.flatnonzero(np.maximum.accumulate(force) - force > tolerance * float(np.max(force, initial=0.0)))
    return float(depth[fell[0]]) if len(fell) else math.inf


# -- grasp and two instruments --------------------------------------------------------------------
def cosine_ramp(t: float, ramp: float) -> float:
    """0 -> 1 over ``ramp`` [s] along a half cosine (a hand's start and stop), 1 after."""
    return 0.5 - 0.5 * math.cos(math.pi * min(t / ramp, 1.0))


def grasp_column(nz: int = 14, fix: str = 'bottom') -> TissueModel:
    """A column 3 x 3 particles wide (``SPACING``): the default tool just touching its top grasps its
    top layer and nothing below (the layer's corners lie 11.8 mm from the tip, the grasp reaches 12)."""
    return make_block(3, 3, nz, spacing=SPACING, fix=fix)


def grasp_touch(solver: Solver) -> np.ndarray:
    """The tool's tip 0.5 mm into the contact above the top face's centre of ``solver``'s model."""
    X = solver.model.positions
    c = X.mean(axis=0)
    near = np.linalg.norm(X[:, :2] - c[:2], axis=1) < solver.model.spacing
    return np.array([c[0], c[1], X[near, 2].max() + solver.contact_reach - 0.0005])


def grasp_lift(model: TissueModel, material: Material, config: SolverConfig, rise: float,
               ramp: float = 0.6, hold: float = 0.4, dt: float = 1e-3) -> tuple[np.ndarray, int]:
    """Close the tool on the top of ``model`` above its centre, lift it ``rise`` [m] over ``ramp``
    [s] and hold ``hold`` [s]; returns (the reaction on the tool per frame [N] (n, 3), particles
    grasped)."""
    solver = Solver(model, material, config)
    tip = grasp_touch(solver)
    solver.step(tip, dt)
    held = solver.grasp()
    forces = []
    for k in range(int(round((ramp + hold) / dt))):
        forces.append(solver.step(tip + [0.0, 0.0, rise * cosine_ramp((k + 1) * dt, ramp)], dt).force_raw)
    return np.array(forces), held


def column_pull(model: TissueModel, material: Material, rise: float) -> float:
    """Linear elasticity's pull [N] of a column held by its top layer and lifted ``rise`` [m]: a bar of
    modulus E, section A (its particles' share) and length L (bottom to top layer): E A rise / L."""
    X = model.positions
    top = np.isclose(X[:, 2], X[:, 2].max())
    area = np.count_nonzero(top) * model.spacing ** 2
    return material.E * area * rise / float(X[:, 2].max() - X[:, 2].min())


def grasp_release(model: TissueModel, material: Material, config: SolverConfig, rise: float = 0.003,
                  dt: float = 1e-3) -> tuple[float, float, float]:
    """Grasp the top of ``model``, lift ``rise`` [m] over 0.3 s, hold to 0.4 s, release, take the
    tool away and let the tissue settle 0.5 s: returns (the work the tool did on the tissue [J],
    then its largest displacement [m] and kinetic energy [J])."""
    solver = Solver(model, material, config)
    tip = grasp_touch(solver)
    solver.step(tip, dt)
    solver.grasp()
    path = [tip + [0.0, 0.0, rise * cosine_ramp((k + 1) * dt, 0.3)] for k in range(500)]
    path += [path[-1] + [0.0, 0.0, 2e-5 * (k + 1)] for k in range(500)]
    work, prev = 0.0, tip
    for k, p in enumerate(path):
        if k == 400:
            solver.release()
        res = solver.step(p, dt)
        work += float(-res.force_raw @ (p - prev))
        prev = p
    for _ in range(500):
        res = solver.step(None, dt)
    return work, res.max_displacement, res.kinetic_energy


def two_hands_on_a_floating_block(config: SolverConfig, frames: int = 150,
                                  dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An 8 x 8 x 5 block with no boundary: one instrument grasps its top and pulls up, the other
    presses its bottom 20 mm beside it and drags sideways. Returns (the block's momentum [kg m/s],
    the impulse the two tools took [N s], the peak force on each tool [N] (2,)): with the tools'
    forces the only ones on the block, momentum = -impulse."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='none')
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0), config, instruments=2)
    X = model.positions
    top = grasp_touch(solver) - [0.01, 0.0, 0.0]
    bottom = np.array([top[0] + 0.02, top[1], X[:, 2].min() - solver.contact_reach])
    flip = np.diag([1.0, -1.0, -1.0])
    impulse, peak = np.zeros(3), np.zeros(2)
    for k in range(frames):
        if k == 10:
            solver.grasp(0)
        lift = 3e-5 * max(k - 10, 0)
        res = solver.step_tools([(top + [0.0, 0.0, lift], None),
                                 (bottom + [1e-5 * k, 0.0, 1e-4 * min(k, 40)], flip)], dt)
        impulse += (res.tools[0].force_raw + res.tools[1].force_raw) * dt
        peak = np.maximum(peak, [np.linalg.norm(t.force_raw) for t in res.tools])
    return solver.mass * solver.velocities.sum(axis=0), impulse, peak


def two_tools_on_a_block(model: TissueModel, material: Material, config: SolverConfig, apart: float,
                         grasp: bool, frames: int = 220, dt: float = 1e-3) -> np.ndarray:
    """Two tools ``apart`` [m] along x on the top of the block ``model``: the first presses 4 mm
    (or, ``grasp``, grasps and lifts 3 mm), the second presses 4 mm, over 150 ms, then both hold.
    Returns their last forces [N] (2, 3)."""
    solver = Solver(model, material, config, instruments=2)
    X = model.positions
    c, top = X.mean(axis=0), X[:, 2].max() + solver.contact_reach
    a = np.array([c[0] - apart / 2, c[1], top - (0.0005 if grasp else 0.0)])
    b = np.array([c[0] + apart / 2, c[1], top])
    for k in range(frames):
        u = min(1.0, k / 150)
        if grasp and k == 1:
            solver.grasp(0)
        move = [0.0, 0.0, 0.003 * u] if grasp else [0.0, 0.0, -0.004 * u]
        res = solver.step_tools([(a + move, None), (b - [0.0, 0.0, 0.004 * u], None)], dt)
    return np.array([t.force_raw for t in res.tools])


def two_hands_on_the_liver(model: TissueModel, material: Material, config: SolverConfig, grasp_xy, press_xy,
                           lift: float = 0.01, depth: float = 0.01, ramp: float = 0.6, hold: float = 0.3,
                           dt: float = 1e-3) -> tuple[Solver, np.ndarray]:
    """One instrument grasps the top of ``model`` at ``grasp_xy`` [m] and lifts it ``lift`` [m] while
    the other presses ``depth`` [m] at ``press_xy``, both over ``ramp`` [s], then both hold
    ``hold`` [s]. Returns (the solver, left as it ends; the reaction on each tool per frame [N]
    (n, 2, 3))."""
    solver = Solver(model, material, config, instruments=2)
    a = first_touch(model, solver.contact_reach, grasp_xy) - [0.0, 0.0, 0.0005]
    b = first_touch(model, solver.contact_reach, press_xy)
    solver.step_tools([(a, None), (b, None)], dt)
    solver.grasp(0)
    forces = []
    for k in range(int(round((ramp + hold) / dt))):
        u = cosine_ramp((k + 1) * dt, ramp)
        res = solver.step_tools([(a + [0.0, 0.0, lift * u], None), (b - [0.0, 0.0, depth * u], None)], dt)
        forces.append([t.force_raw for t in res.tools])
    return solver, np.array(forces)
