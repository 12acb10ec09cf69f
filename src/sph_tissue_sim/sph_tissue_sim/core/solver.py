"""One solver for every scheme and mode: ``Solver(model, material, config).step(tool_pos, dt, tool_rot)``.

Schemes (index order = ``SimMetrics.SCHEME_*``): ``paper`` (updated-Lagrangian SPH, eqs. 11-16),
``tlsph`` (total-Lagrangian SPH, the default) and ``mass_spring`` (the paper's Table 1 baseline).
Modes (``SimMetrics.MODE_*``): ``global`` (every free particle) and ``local`` (the paper's dynamic
local interaction area, see :mod:`.local_area`).

A frame of ``dt`` seconds is split into sub-steps bounded by the CFL, viscous and (when a tool is
given) contact limits;
the tool (a shape from :mod:`.tools`, posed by its tip position and orientation) moves linearly
from its previous to its new pose across the sub-steps, and the force
returned is the mean reaction of the tissue on the tool over the frame, clamped to ``force_limit``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba
import numpy as np
from tissue_common.force import clamp_norm

from . import frame
from .contact import contact_vector_py, deepest_contact, surface_discs
from .surface_contact import (SURFACE_OFFSET, nearest_sample_gap, no_samples, sample_stiffness_factor,
                              surface_samples)
from .errors import ConfigError, ModelError, SimError
from .implicit_contact import contact_terms, make_touches
from .backward_euler import BackwardSolve
from .compliance import OrganCompliance
from .integrate import SymplecticEuler, frame_state_ok, substep_bounds, substeps_for
from .kernel import SUPPORT
from .local_area import LocalArea, active_stats
from .material import Material
from .models import TissueModel
from .neighbours import CellGrid, find_neighbours
from .paper import PaperScheme
from .protocols import STATUS_OK
from .springs import MassSpringScheme
from .stability import DASHPOT_RATE_EVERY, DashpotRate
from .state import Body, Loads, Motion, Samples, Sets, ToolPath, Topology, no_touches
from .tlsph import TlsphScheme
from .tools import NO_ROTATION, TOOLS, make_tool

SCHEMES = ('paper', 'tlsph', 'mass_spring')
#: conjugate-gradient iterations of one implicit contact solve at most
CONTACT_MAX_ITER = 200
#: the implicit integrator's solve (stiffer: its condition number grows with (dt / CFL step)^2)
IMPLICIT_MAX_ITER = 2000
MODES = ('global', 'local')
CONTACT_INTEGRATIONS = ('explicit', 'implicit')
#: backstop samples that push the tool grow the local area's radius by this many h (with the
#: half-space far field)
SAMPLE_AREA_GROWTH = 1.5
FAR_FIELD_MODELS = ('auto', 'half_space', 'organ')
#: the organ's far field lends a particle's response to the particles within this many spacings
#: (a response costs a back-substitution, about 45 ms on the 3670 liver)
ORGAN_SHARE = 1.01
#: the organ's far field factors the whole model: beyond this many free particles its start-up
#: and its responses cost too much (the 12k liver, 11149 free: 66 s, 4.6 GB, 0.3 s per response)
ORGAN_MAX_FREE = 5000
INTEGRATORS = ('explicit', 'implicit')
#: the contact of the defaults before 2026-11-27: the tool against the particles' balls alone,
#: explicitly integrated, with the half-space far field (SolverConfig(**BALL_CONTACT))
BALL_CONTACT = {'contact_samples': 0, 'contact_integration': 'explicit', 'far_field_model': 'half_space',
                'far_field': 0.9}
#: relative residual of the implicit contact's solve (cheap: it spans the particles under the tool)
CONTACT_TOL = 1e-8


class InvalidInput(SimError, ValueError):
    """A step input (tool position, dt) is non-finite or absurd; the state was not changed."""


class StepInterrupted(SimError):
    """:meth:`Solver.interrupt` stopped the step; the state is as before it."""


#: (lowest, highest, kind) of every numeric :class:`SolverConfig` field; kind ``open``: lowest
#: excluded, ``int``: an integer, ``closed``: both included
CONFIG_RANGES = {
    'h_ratio': (0.2, 4.0, 'closed'), 'k1_gain': (0.0, math.inf, 'closed'),
    'k1_min': (0.0, math.inf, 'open'), 'k1_max': (0.0, math.inf, 'open'),
    'n_layers': (0, 8, 'int'), 'tool_radius': (0.0, math.inf, 'open'),
    'tool_length': (0.0, math.inf, 'closed'), 'contact_stiffness': (0.0, math.inf, 'open'),
    'contact_damping_ratio': (0.0, math.inf, 'closed'), 'force_limit': (0.0, math.inf, 'open'),
    'cfl': (0.0, 1.0, 'open'), 'max_substeps': (1, 100000, 'int'),
    'relax_disp_tol': (0.0, math.inf, 'open'), 'relax_vel_tol': (0.0, math.inf, 'open'),
    'hourglass': (0.0, math.inf, 'closed'), 'velocity_limit': (0.0, math.inf, 'open'),
    'max_tool_distance': (0.0, math.inf, 'open'), 'spring_radius': (0.0, math.inf, 'open'),
    'contact_particle_radius': (0.0, math.inf, 'open'), 'contact_disc': (0.0, 0.5, 'closed'),
    'parallel_min_particles': (0, math.inf, 'int'),
    'far_field': (0.0, 2.0, 'closed'), 'far_field_tau': (0.0, 1.0, 'closed'),
    'max_tool_speed': (0.0, math.inf, 'open'),
    'contact_samples': (0, 5, 'int'),
    'implicit_max_dt': (0.0, 1.0, 'open'), 'implicit_tol': (0.0, 1.0, 'open'),
    'friction': (0.0, 2.0, 'closed'),
}


@dataclass
class SolverConfig:
    """Solver settings (SI units).

    Attributes:
        scheme: ``tlsph`` (default), ``paper`` or ``mass_spring``.
        mode: ``global`` or ``local``.
        h_ratio: smoothing length h / particle spacing (support 2h).
        k1_gain: k1 = k1_gain * f_ext [1/N] (paper eq. 18: 0.5).
        k1_min, k1_max: clamp of k1 (Dr = k1 h); k1_min keeps the area non-empty without force.
        n_layers: transmission layers N (paper eqs. 20-21), 0..8.
            The defaults (k1_min 1.75, one layer, with ``far_field`` 0.9) were chosen on the
            3671-particle liver pressed 2 / 4 / 10 mm at four places (local within 5 % of global
            at 12 of 12, worst -3.9 %; at four other places 11 of 12, worst +11 % at a 2 mm press
            that meets 0.012 N) at 1.3x the cost of k1_min 1 with two layers and the still region
            (up to +33 % there); see ``benchmarks/README.md``.
        tool_shape: ``sphere`` (default: a probe tip) or ``capsule`` (a shaft of ``tool_length``
            with a rounded tip, along the tool frame's +z), see :mod:`.tools`.
        tool_radius: radius of the tool's sphere, or of the capsule's shaft [m].
        tool_length: length of the capsule's shaft [m] (unused by the sphere).
        contact_stiffness: penalty stiffness per contacted particle, or per contacted surface sample
            with ``contact_samples`` [N/m].
        contact_damping_ratio: contact dashpot as a fraction of critical for one particle (or for
            a sample's share of its particle's mass) [-].
        force_limit: clamp of the force norm sent to the device [N] (Omni peak 3.3 N).
        cfl: Courant number C of the sub-step bounds.
        max_substeps: cap per frame (if reached, simulated time lags the wall clock; reported).
        relax_disp_tol: a particle outside the area is released when its displacement is below this [m]
        relax_vel_tol: ... and its speed below this [m/s].
        hourglass: Ganzenmueller hourglass coefficient alpha [-] (tlsph).
        velocity_limit: a speed above this [m/s] is treated as a blow-up (state restored, SimError).
        max_tool_distance: tool positions farther than this from the model centre are rejected [m].
        spring_radius: mass-spring neighbour radius in particle spacings.
        contact_particle_radius: contact radius of a particle in spacings; the tool touches a particle
            when their centres are closer than tool_radius + this * spacing. 0.5 is the geometric
            surface; larger values spread the tool load over more particles so that a tool smaller
            than the spacing cannot slip between surface particles (default 1.0).
        contact_disc: radius of a surface particle's contact disc in spacings (0..0.5). 0 (default)
            treats particles as balls of contact_particle_radius; 0.5 makes a surface particle a flat
            patch normal to the current surface (rounded by contact_particle_radius), so pressing
            anywhere above it pushes it straight in instead of sideways off the tool (on the
            3671-particle liver at 10 mm: 0.85 mm instead of 8.9 mm sideways slip), but it spreads
            the load, and the local area then needs k1_min >= 3 to stay within 10 % of global.
        parallel_min_particles: a ``tlsph`` sub-step runs on numba's thread pool (``prange``,
            ``NUMBA_NUM_THREADS`` threads) when at least this many particles are stressed; 0 (the
            default) never uses threads. Results are bit-identical either way. On an idle 2-core
            machine threads halve the step (3671-particle liver: global 10.1 -> 4.3 ms, local
            0.40 -> 0.23 ms), but when other processes keep the cores busy a parallel region waits
            for a descheduled thread: local p99 went from 0.5 to 4.4 ms with one busy process
            and the median to 32 ms with two. Enable it only where the simulator has cores of its
            own.
        contact_samples: 0: the tool touches particles alone (balls of
            ``contact_particle_radius``). 1..5 (3, the default): it touches ``contact_samples**2`` samples per surface
            particle on the material's surface, half a spacing outside the particle centres, which
            move with the particles around them and spread the force back to them by kernel
            weights (:mod:`.surface_contact`): the tool cannot slip between particles. On the
            3671-particle liver (3, pressed straight down at the top of the dome) the force rises
            monotonically to 3.7 N at 31 mm (particles: 0.39 N at 10 mm, then falling to nothing),
            the pressed surface slips 1.3-1.4 mm instead of 6.2 mm at 10 mm, and local mode is
            within 5 % of global at 10 of 12 presses (as balls 12 of 12). But the surface,
            interpolated over a kernel width, makes the tool a blunter indenter (Hertz block: +36 %
            at 2.5 mm spacing); on coarse models (the 743 liver, tool radius 0.43 spacings) the
            tool sinks through the surface layer by 6 mm; and the samples are 9 times stiffer per
            area: the explicit step needs about 4x the sub-steps (local step 2.8 ms instead of
            0.64 ms on this liver); with ``contact_integration`` implicit it keeps the material's
            (0.78 ms).
        contact_integration: ``implicit`` (default) or ``explicit``: the pushing contacts backward
            along their normals (:mod:`.implicit_contact`), no contact sub-step bound; explicit,
            the samples' stiffness bounds the sub-step (about 4x as many on the liver).
        integrator: ``explicit`` (default: symplectic Euler, sub-steps bounded by the CFL,
            viscous and contact bounds) or ``implicit`` (``tlsph`` only): linearly implicit backward
            Euler on everything, the elastic spring, the dashpots and the pushing contacts (one
            conjugate-gradient solve per sub-step, :mod:`.backward_euler`), stable at any
            sub-step; a frame then takes sub-steps of at most ``implicit_max_dt``. Backward Euler
            damps what it cannot resolve (motions faster than about ``1 / dt``), so it suits
            quasi-static presses and large visual frames, not a vibration at the frame rate.
            ``contact_integration`` is then implicit whatever it says.
        implicit_max_dt: the implicit integrator's largest sub-step [s].
        implicit_tol: its solve stops at this velocity error relative to the velocities (those of
            the sub-step's start or of the solution, the larger; 0.01: the 1289-particle liver
            pressed 8 mm and palpated at 16 ms frames within 6e-6 N of a 1e-6 solve, 29
            conjugate-gradient iterations per sub-step against 41 at 1e-3 and 82 at 1e-6).
        max_tool_speed: the simulated tool follows the requested tool pose at most this fast
            [m/s]: a frame moves its tip, and the far end of a shaft, by at most about
            ``max_tool_speed * dt`` towards the request (a
            tracking glitch or a pose jump of centimetres in one frame would otherwise drive the
            tool through the tissue in one frame and tear the particle lattice apart). A hand on a
            haptic stylus moves well below 1 m/s (the bundled sessions: up to 0.18 m/s).
        far_field: local mode: the still particles next to the solved ones move by this times the
            far field model's response to the contact force instead of staying at rest (0: the
            paper's still region). The default, 1, is the organ's own response
            (``far_field_model``). With the half-space (Boussinesq) response and the balls alone,
            0.9 suited the liver better, because an organ
            bonded to a fixed base is stiffer than a half-space (the thin lobe: -5.1 % with 1,
            -3.9 % with 0.9; 0.85 ... 0.925 meet every local-global and drag target, 0.95
            misses the drag's by 0.04 %). Holding them still makes the area stiffer than the
            whole organ: on the 3671-particle liver pressed 2/4/10 mm at four places, with k1_min 1
            and two layers, the local force is within 5 % of global at 7 of 12 presses with 1
            (-13.7 ... +6.2 %, the worst at 2 mm on the thinnest lobe, where the half-space is too
            soft), at 2 of 12 with 0 (-6.7 ... +23.7 %), at the same cost per frame; with the
            default area (see ``n_layers``) at 11 of 12 with 1 and 12 of 12 with 0.9. Dragging over
            a coarse block (7.5 mm spacing), the tool's passage between particles changed the force
            by 8 % of Fz with 1 (global 4 %).
        far_field_tau: time constant [s] of the low pass on the far field's load (0: the previous
            frame's force as it is). The shell follows the force and the force the shell; on a
            fine model, where the area (``k1 h``) is small, that loop rang and grew: the 30k liver
            pressed 11-16 mm with surface samples changed its force by up to 1 N from one frame to
            the next with 0, by 14 mN with 3 ms (global 3.6 mN).
        far_field_model: local mode: what moves the still particles next to the solved ones.
            ``auto`` (default): ``organ`` for a ``tlsph`` model of at most ``ORGAN_MAX_FREE``
            free particles (the bundled liver), else ``half_space``.
            ``half_space``: the Boussinesq response (``far_field``'s docs).
            ``organ``: the organ's own linear response to the contact force, shared by the
            touched particles (:mod:`.compliance`: the material's stiffness at rest, factored
            once in single precision when the solver is made or its material changes; a
            particle's response is solved the first time it carries the tool, unless one within
            ``ORGAN_SHARE`` spacings has one), placed on the stress shell and on the shell's
            neighbours; then ``far_field`` 1 is the organ itself, and the backstop samples need
            no wider area. On the 3670 liver with the backstop samples, no area growth and
            ``far_field`` 1: local within 5 % of global at 12 of 12 presses (-3.3 ... +3.2 %;
            the half-space with the growth: -3.5 ... +3.8 %, without it 10 of 12) at 1.3-1.4x
            the balls' step instead of 2.3-2.5x. The price: a start-up factorisation (3670
            liver: about 5 s idle, 41 M factor entries, about 0.8 GB at its peak; it grows
            faster than the particle count: the 12k liver 66 s, 4.6 GB and 0.3 s per response,
            so models with more than ``ORGAN_MAX_FREE`` free particles are refused) and about
            45 ms for each response solved.
        far_field_background: solve the organ's responses on a worker thread of the lowest
            priority (:mod:`.compliance`) instead of in the frame that first needs them: a touch
            on new ground then never stalls its frame (3670 liver pressed at 20 mm/s at four
            places, 1 ms frames paced at 1 kHz, idle: longest frame 1.0-1.6 ms instead of
            53-54 ms); until a response is ready the load is shared by the touched particles
            whose responses are (none: the shell at rest, stiffer, and the first ready response
            comes in over 50 ms): idle, Fz within 4-13 mN of waiting; beside a busy process the
            responses came too late for a 10 mm press and Fz was up to 0.37 N (50 %) higher.
            Not repeatable bit for bit (it depends on the thread's timing), so False by default;
            sim_node turns it on unless its timing is lockstep.
        friction: Coulomb coefficient of stick-slip friction between the tool and the particles'
            balls (0, the default: frictionless; the samples stay frictionless), see
            :mod:`.contact`: a touched particle is carried with the tool until the tangential
            force reaches ``friction`` times the normal one. On the 3670 liver with the default
            contact, pressed straight down at the dome, 0.3 moves the first-touched particle
            0.08 / 0.10 mm sideways by 10 mm (local / global; frictionless 3.3 mm) and the force
            rises to the 3.3 N limit without the dip near 18 mm (peak 3.95 N at 29 mm); but it
            stiffens the shallow press (0.37 against 0.27 N at 5 mm) and local mode is within 5 %
            of global at 11 of 12 presses (+5.6 % at 4 mm at the centre); see
            ``benchmarks/README.md``.
    """

    scheme: str = 'tlsph'
    mode: str = 'local'
    h_ratio: float = 1.3
    k1_gain: float = 0.5
    k1_min: float = 1.75
    k1_max: float = 6.0
    n_layers: int = 1
    tool_shape: str = 'sphere'
    tool_radius: float = 0.005
    tool_length: float = 0.0
    contact_stiffness: float = 300.0
    contact_damping_ratio: float = 1.0
    force_limit: float = 3.3
    cfl: float = 0.3
    max_substeps: int = 64
    relax_disp_tol: float = 2e-4
    relax_vel_tol: float = 2e-3
    hourglass: float = 1.0
    velocity_limit: float = 50.0
    max_tool_distance: float = 10.0
    spring_radius: float = 1.5
    contact_particle_radius: float = 1.0
    contact_disc: float = 0.0
    parallel_min_particles: int = 0
    far_field: float = 1.0
    far_field_tau: float = 0.003
    far_field_model: str = 'auto'
    far_field_background: bool = False
    max_tool_speed: float = 1.0
    contact_samples: int = 3
    contact_integration: str = 'implicit'
    integrator: str = 'explicit'
    implicit_max_dt: float = 0.016
    implicit_tol: float = 0.01
    friction: float = 0.0

    def validate(self) -> 'SolverConfig':
        """Check ranges (:data:`CONFIG_RANGES`); raises :class:`ConfigError` naming the bad field.
        Returns self, with the integer fields as ``int``."""
        for name, choices in (('scheme', SCHEMES), ('mode', MODES), ('tool_shape', tuple(TOOLS)),
                              ('contact_integration', CONTACT_INTEGRATIONS),
                              ('far_field_model', FAR_FIELD_MODELS), ('integrator', INTEGRATORS)):
            if getattr(self, name) not in choices:
                raise ConfigError(f'{name} must be one of {choices}, got {getattr(self, name)!r}')
        for name, (lo, hi, kind) in CONFIG_RANGES.items():
            val = getattr(self, name)
            if not isinstance(val, (int, float)) or isinstance(val, bool) or not math.isfinite(val):
                raise ConfigError(f'{name} must be a finite number, got {val!r}')
            if kind == 'int' and int(val) != val:
                raise ConfigError(f'{name} must be an integer, got {val}')
            if val < lo or (kind == 'open' and val == lo) or val > hi:
                sign = '>' if kind == 'open' else '>='
                span = (f'{sign} {lo:g}' if hi == math.inf else
                        f'in {"(" if kind == "open" else "["}{lo:g}, {hi:g}]')
                raise ConfigError(f'{name} must be {span}, got {val}')
            if kind == 'int':
                setattr(self, name, int(val))
        if self.k1_min > self.k1_max:
            raise ConfigError(f'k1_min ({self.k1_min}) must be <= k1_max ({self.k1_max})')
        if self.contact_samples > 0 and self.contact_disc > 0.0:
            raise ConfigError('contact_disc must be 0 with contact_samples > 0 (the samples are the surface)')
        if self.far_field_model == 'organ' and self.scheme != 'tlsph':
            raise ConfigError(f'far_field_model organ needs scheme tlsph, got {self.scheme!r}')
        if not isinstance(self.far_field_background, (bool, np.bool_)):
            raise ConfigError(f'far_field_background must be true or false, got {self.far_field_background!r}')
        if self.integrator == 'implicit' and self.scheme != 'tlsph':
            raise ConfigError(f'integrator implicit needs scheme tlsph, got {self.scheme!r}')
        return self

    @property
    def scheme_index(self) -> int:
        return SCHEMES.index(self.scheme)

    @property
    def mode_index(self) -> int:
        return MODES.index(self.mode)


@dataclass
class StepResult:
    """Outcome of one :meth:`Solver.step` (tissue frame, SI units)."""

    force: np.ndarray                 # (3,) [N] reaction of the tissue on the tool, clamped
    force_raw: np.ndarray             # (3,) [N] before clamping
    clamped: bool
    contact_index: int                # -1 without contact
    penetration: float                # [m] overlap of the deepest contacted particle
    substeps: int
    substep_dt: float                 # [s]
    n_interaction: int
    n_layer: np.ndarray               # (n_layers,) int
    n_relaxing: int
    max_displacement: float           # [m]
    kinetic_energy: float             # [J]
    wall_time: float                  # [s]
    substeps_capped: bool = False     # the frame needed more than max_substeps (time lagged)
    tool_lag: float = 0.0             # [m] requested minus simulated tool position (max_tool_speed)
    tool_segment: np.ndarray | None = None   # (2, 3) [m] the tool's segment after the step (None: no tool)
    k1: float = 0.0                   # interaction radius factor used (local mode)
    n_active: int = 0                 # particles integrated this frame


class Solver:
    """Viscoelastic tissue simulator for one :class:`TissueModel`.

    Args:
        model: reference configuration (positions, spacing, fixed mask).
        material: Kelvin-Voigt material.
        config: solver settings (validated here).

    Raises:
        ModelError: empty model.
        ConfigError: bad settings, or a smoothing length too small for any particle to have
            a neighbour.
    """

    def __init__(self, model: TissueModel, material: Material, config: SolverConfig | None = None) -> None:
        if model is None or len(model.positions) == 0:
            raise ModelError('the model has no particles')
        if not isinstance(material, Material):
            raise ConfigError(f'material must be a Material, got {type(material).__name__}')
        self.config = cfg = (config or SolverConfig()).validate()
        self.model = model
        self.n = model.n_particles
        self.h = cfg.h_ratio * model.spacing
        self.volume = model.particle_volume
        self.X = np.ascontiguousarray(model.positions, dtype=np.float64)
        self.fixed = np.ascontiguousarray(model.fixed, dtype=np.bool_)
        self.free_idx = np.flatnonzero(~self.fixed).astype(np.int32)
        self.all_idx = np.arange(self.n, dtype=np.int32)
        self.centre = self.X.mean(axis=0)
        self.tool = make_tool(cfg.tool_shape, cfg.tool_radius, cfg.tool_length)
        self.extent = float(np.linalg.norm(self.X.max(axis=0) - self.X.min(axis=0)))
        support = SUPPORT * self.h
        self.grid = CellGrid(self.X, support)
        self.offsets, self.indices = find_neighbours(self.X, support)
        if np.diff(self.offsets).max() == 0:
            raise ConfigError(f'smoothing length h = {self.h:.3g} m is too small: no particle has a '
                              f'neighbour within 2h (spacing {model.spacing:.3g} m)')
        self.contact_surf = surface_discs(self.X, self.offsets, self.indices, self.h, self.volume,
                                          model.spacing, cfg.contact_disc)
        self._contact_geometry(model.spacing)
        self.x = self.X.copy()
        self.v = np.zeros((self.n, 3))
        self.acc = np.zeros((self.n, 3))
        self.motion = Motion(self.x, self.v, self.acc)
        self.react = np.zeros(3)
        self.abort = np.zeros(1, dtype=np.int8)   # set by interrupt() from another thread
        self.loads = Loads(np.zeros(0, dtype=np.int32), np.zeros((0, 3)), 0)
        pm = cfg.parallel_min_particles
        self.par_min = pm if pm > 0 and numba.get_num_threads() > 1 else self.n + 1
        self.scheme = self._make_scheme()
        # backward Euler for everything or for the pushing contacts alone (one solve), or None
        stiffness = cfg.integrator == 'implicit'
        contacts = stiffness or cfg.contact_integration == 'implicit'
        self.backward = (BackwardSolve(self.scheme if stiffness else None, self.n,
                                       cfg.implicit_tol if stiffness else CONTACT_TOL,
                                       IMPLICIT_MAX_ITER if stiffness else CONTACT_MAX_ITER, stiffness)
                         if contacts else None)
        n_samples = len(self.sample_arrays[4]) if self.sample_arrays is not None else 0
        self.touches = make_touches(self.n + n_samples) if contacts else no_touches()
        #: friction's anchors (contact.stick_slip)
        self.anchor = np.zeros((self.n, 3))
        self.stuck = np.zeros(self.n, dtype=np.bool_)
        self._touch_vn = np.zeros(len(self.touches.idx))
        self.area = LocalArea(self.X, self.fixed, Topology(self.offsets, self.indices), self.grid.bundle,
                              self.h, cfg.n_layers, self.contact_surf)
        self.set_material(material)
        self.reset()

    def _contact_geometry(self, spacing: float) -> None:
        """Where the tool touches: the reach of the particles' balls, of touch detection and of
        the local area's candidates, and the surface samples (``contact_samples`` > 0)."""
        cfg = self.config
        per = cfg.contact_samples
        if per == 0:
            self.contact_reach = self.tool.radius + cfg.contact_particle_radius * spacing
            self.ball_reach = self.detect_reach = self.cand_reach = self.samples_reach = self.contact_reach
            self.sample_arrays, self.sample_margin, self.sample_factor = None, 0.0, 1.0
            return
        # the tool meets samples on the material's surface, half a spacing outside the particle
        # centres, and the particles' own balls: of the tool's size behind the samples, or of
        # contact_particle_radius in front of them (the samples then a backstop)
        surface_reach = self.tool.radius + SURFACE_OFFSET * spacing
        self.ball_reach = self.tool.radius + cfg.contact_particle_radius * spacing
        self.contact_reach = max(surface_reach, self.ball_reach)
        *self.sample_arrays, reach, support = surface_samples(self.X, self.offsets, self.indices, self.h,
                                                              self.volume, spacing, per)
        # a sample reads particles within `support` of it: farther than this from its owner, the
        # material around it is torn apart
        self.sample_margin = reach + support + spacing
        self.sample_factor = sample_stiffness_factor(*self.sample_arrays[1:4])
        # touch detection (the local area's centre) sees a particle where its samples may touch,
        # and local mode solves every particle a touching sample reads
        self.detect_reach = max(self.tool.radius + reach, self.ball_reach)
        self.cand_reach = self.samples_reach = max(self.tool.radius + reach + support, self.ball_reach)
        # a sample lies within `reach` of its owner, inside the owner's ball: until a sample
        # pushes the tool (Solver.samples_push), the balls' candidates and area suffice
        self.cand_reach = self.ball_reach

    def _make_scheme(self):
        cfg = self.config
        if cfg.scheme == 'paper':
            return PaperScheme(self.X, self.x, self.fixed, self.offsets, self.indices, self.h)
        if cfg.scheme == 'mass_spring':
            return MassSpringScheme(self.X, self.model.spacing, cfg.spring_radius)
        return TlsphScheme(self.X, self.offsets, self.indices, self.h, self.volume, cfg.hourglass,
                           self.par_min,
                           explicit_dashpots=cfg.integrator == 'explicit')

    def interrupt(self) -> None:
        """Make the step running in another thread stop before its next sub-step or organ response
        solve (it then raises :class:`StepInterrupted` with the state restored), and every later
        step until :meth:`clear_interrupt`. Safe to call from any thread: the frame loop runs
        without the GIL.
        """
        self.abort[0] = 1

    def clear_interrupt(self) -> None:
        """Let steps run again after :meth:`interrupt`."""
        self.abort[0] = 0

    def set_external_forces(self, indices, forces) -> None:
        """Constant external loads [N] on particles (e.g. a traction on a face); replaces previous ones.

        Applied every sub-step to free particles of the fully solved set (all free particles in
        global mode; in local mode only to particles that are active). ``indices=[]`` clears them.
        """
        idx = np.ascontiguousarray(indices, dtype=np.int32).reshape(-1)
        f = np.ascontiguousarray(forces, dtype=np.float64).reshape(-1, 3)
        if len(f) == 1 and len(idx) > 1:
            f = np.repeat(f, len(idx), axis=0)
        if len(idx) != len(f):
            raise ConfigError(f'{len(idx)} indices but {len(f)} forces')
        if len(idx) and (idx.min() < 0 or idx.max() >= self.n):
            raise ConfigError('external force index out of range')
        if not np.all(np.isfinite(f)):
            raise ConfigError('external forces must be finite')
        self.loads = Loads(idx, f, len(idx))

    def close(self, timeout: float = 0.0) -> bool:
        """Stop the far field's worker thread, if any, waiting up to ``timeout`` [s] for it to
        finish the response it is solving; False if it has not (see
        :meth:`~.compliance.OrganCompliance.close`)."""
        if getattr(self, 'organ', None) is None:
            return True
        return self.organ.close(timeout)

    def set_material(self, material: Material) -> None:
        """Change the material (takes effect at the next step; sub-step bounds are recomputed)."""
        if not isinstance(material, Material):
            raise ConfigError(f'material must be a Material, got {type(material).__name__}')
        self.material = material
        cfg = self.config
        self.mass = material.rho * self.volume
        self.inv_mass = 1.0 / self.mass
        self.body = Body(self.X, self.fixed, self.mass, self.inv_mass)
        self.contact_damping = cfg.contact_damping_ratio * 2.0 * math.sqrt(cfg.contact_stiffness * self.mass)
        per = cfg.contact_samples
        if per > 0:
            # a sample carries 1/per**2 of its particle's mass: the same damping ratio per sample
            self.samples = Samples(*self.sample_arrays[:5], self.tool.radius, cfg.contact_stiffness,
                                   self.contact_damping / per, self.sample_margin, *self.sample_arrays[5:])
        else:
            self.samples = no_samples(self.n)
        self.scheme.set_material(material, self.mass)
        #: the organ's compliance for local mode's far field (None: the half-space's)
        self.close()
        self.organ = None
        #: how long its factorisation took [s]
        self.organ_factor_s = 0.0
        n_free = int(np.count_nonzero(~self.fixed))
        organ = cfg.far_field_model == 'organ' or (cfg.far_field_model == 'auto' and cfg.scheme == 'tlsph'
                                                    and n_free <= ORGAN_MAX_FREE)
        if organ and cfg.mode == 'local' and cfg.far_field > 0.0:
            if n_free > ORGAN_MAX_FREE:
                raise ConfigError(
                    f'far_field_model organ factors the whole model\'s stiffness; {n_free} free particles '
                    f'are more than {ORGAN_MAX_FREE} (3276 free: 5 s, 0.8 GB, 45 ms per response; 11149: '
                    f'66 s, 4.6 GB, 0.3 s per response): use far_field_model half_space')
            t0 = time.perf_counter()
            self.organ = OrganCompliance(self.X, self.fixed, self.scheme.state(None, None, 0),
                                         ORGAN_SHARE * self.model.spacing, self.abort,
                                         background=cfg.far_field_background)
            self.organ_factor_s = time.perf_counter() - t0
        if self.backward is not None:
            self.backward.set_material(material)
        c = self.scheme.wave_speed(material, self.mass)
        self.dt_bounds = substep_bounds(self.h, c, material.rho, material.eta_longitudinal, self.mass,
                                        cfg.contact_stiffness * self.sample_factor, cfg.cfl)
        if cfg.contact_damping_ratio > 0.0:
            # explicit dashpot: dt < 2 m / c; keep a factor 2 margin (implicit contact: none)
            self.dt_bounds['contact_damping'] = self.mass / (self.samples.damping * self.sample_factor
                                                             if per > 0 else self.contact_damping)
        if self.touches.on:
            # the pushing contacts are integrated backward along their normals
            self.dt_bounds.pop('contact', None)
            self.dt_bounds.pop('contact_damping', None)
        if cfg.integrator == 'implicit':
            # stable at any sub-step: only the accuracy the caller asks for bounds it
            self.dt_bounds = {'implicit': cfg.implicit_max_dt}
        dashpots = self.scheme.dashpots_only() if isinstance(self.scheme, TlsphScheme) else None
        #: follows the explicit dashpots' rate as the tissue deforms (None: no explicit dashpots)
        self.dashpot_rate = DashpotRate(dashpots, self.n, DASHPOT_RATE_EVERY) if dashpots is not None else None
        self.dt_max = min(self.dt_bounds.values())
        # without a tool no contact spring or dashpot acts, so only the material bounds apply
        self.dt_max_free = min(v for k, v in self.dt_bounds.items() if not k.startswith('contact'))

    def reset(self) -> None:
        """Back to the reference configuration at rest, sim time 0, no active area."""
        self.x[:] = self.X
        self.v[:] = 0.0
        self.acc[:] = 0.0
        self.area.reset(self.config.mode == 'global')
        self.scheme.reset()
        if self.dashpot_rate is not None:
            self.dashpot_rate.reset()
        self.sim_time = 0.0
        self.f_prev = 0.0
        self.stuck[:] = False
        #: backstop samples: one has pushed the tool, and the tool has touched the tissue ever since
        #: (the local area is the samples')
        self.samples_push = False
        self.tool_prev: np.ndarray | None = None     # the tip position [m] of the previous frame
        self.seg_prev: np.ndarray | None = None      # and the tool's segment (2, 3)
        self.last_result: StepResult | None = None
        self._last_sets: Sets | None = None           # the sets of the last finished frame

    # ------------------------------------------------------------------ state
    @property
    def positions(self) -> np.ndarray:
        """(N, 3) current positions [m] (the live array: read, do not modify)."""
        return self.x

    @property
    def velocities(self) -> np.ndarray:
        """(N, 3) current velocities [m/s] (the live array)."""
        return self.v

    @property
    def region(self) -> np.ndarray:
        """(N,) int8: 0 still, 1 interaction (full solve), 1 + i transmission layer i."""
        return self.area.region

    @property
    def n_active(self) -> int:
        """Particles moving outside the reference state (local mode; 0 in global mode)."""
        return self.area.n_active

    @property
    def n_stress_last(self) -> int:
        """Particles that got a stress state in the last finished frame."""
        return self._last_sets.n_stress if self._last_sets is not None else 0

    @property
    def pair_visits_last(self) -> int:
        """Neighbour pairs one sub-step of the last finished frame gathered over: the reference
        neighbours of its stressed particles (stress pass) and of its solved ones (force pass)."""
        s = self._last_sets
        if s is None:
            return 0
        deg = np.diff(self.offsets)
        return int(deg[s.stress[:s.n_stress]].sum() + deg[s.sph[:s.n_sph]].sum())

    @property
    def n_particles(self) -> int:
        return self.n

    @property
    def far_field_in_use(self) -> str:
        """Local mode's far field as built: ``organ``, ``half_space`` or ``none`` (global mode,
        or ``far_field`` 0); ``far_field_model: auto`` resolves to one of the first two."""
        if self.config.mode != 'local' or self.config.far_field <= 0.0:
            return 'none'
        return 'organ' if self.organ is not None else 'half_space'

    @property
    def smoothing_length(self) -> float:
        return self.h

    def displacement(self) -> np.ndarray:
        """(N,) displacement norms |x - X| [m]."""
        return np.linalg.norm(self.x - self.X, axis=1)

    def von_mises(self) -> np.ndarray:
        """(N,) von Mises stress [Pa] of the last computed stress state (0 where none was computed;
        the mass-spring scheme gives E times the largest spring strain)."""
        out = np.zeros(self.n)
        if self._last_sets is not None:
            self.scheme.von_mises(self.x, self._last_sets, out)
        return out

    # ------------------------------------------------------------------ stepping
    def _check_inputs(self, tool_pos, dt) -> np.ndarray | None:
        try:
            dt = float(dt)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(f'dt must be a number, got {dt!r}') from exc
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise InvalidInput(f'dt must be in (0, 1] s, got {dt}')
        if tool_pos is None:
            return None
        try:
            tool = np.asarray(tool_pos, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(f'tool position must be 3 numbers, got {tool_pos!r}') from exc
        # scalar checks: numpy's per-call overhead on a 3-vector matters at 1 kHz
        t0, t1, t2 = tool.tolist()
        if not (math.isfinite(t0) and math.isfinite(t1) and math.isfinite(t2)):
            raise InvalidInput(f'tool position is not finite: {tool}')
        c0, c1, c2 = self.centre.tolist()
        if math.sqrt((t0 - c0) ** 2 + (t1 - c1) ** 2 + (t2 - c2) ** 2) > self.config.max_tool_distance:
            raise InvalidInput(f'tool position {tool} is more than {self.config.max_tool_distance} m '
                               f'from the tissue')
        return tool.copy()

    @staticmethod
    def _check_rotation(tool_rot) -> np.ndarray:
        """The tool's orientation as a 3x3 rotation matrix (identity for None)."""
        if tool_rot is None:
            return NO_ROTATION
        try:
            rot = np.asarray(tool_rot, dtype=np.float64).reshape(3, 3)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(f'tool rotation must be a 3x3 matrix, got {tool_rot!r}') from exc
        if not np.all(np.isfinite(rot)):
            raise InvalidInput(f'tool rotation is not finite: {rot.tolist()}')
        # a stretched or skewed matrix would deform the tool: only a rotation (to rounding)
        if not (np.abs(rot.T @ rot - NO_ROTATION).max() < 1e-6 and np.linalg.det(rot) > 0.0):
            raise InvalidInput(f'tool rotation is not a rotation matrix: {rot.tolist()}')
        return rot

    def _limit_sweep(self, seg: np.ndarray, max_travel: float) -> float:
        """Move the far end of a shaft (``seg[1]``, in place) at most ``max_travel`` [m] from where
        it was, keeping the shaft's length: a fast twist of a long tool would otherwise sweep its
        far end through the tissue in one frame. Returns the distance left to the request [m]."""
        prev = self.seg_prev[1]
        far, lag = self._limit_travel(prev, seg[1], max_travel)
        if lag > 0.0:
            length = math.dist(seg[1].tolist(), seg[0].tolist())
            d = far - seg[0]
            n = math.sqrt(float(d @ d))
            if n > 0.0:
                seg[1] = seg[0] + d * (length / n)
        return lag

    def step(self, tool_pos, dt: float, tool_rot=None) -> StepResult:
        """Advance the tissue by ``dt`` seconds with the tool's tip at ``tool_pos`` (tissue frame, m)
        and its orientation ``tool_rot`` (3x3 rotation matrix, tissue frame; None: identity).

        ``tool_pos=None`` means no tool. Raises :class:`InvalidInput` (state untouched) for
        non-finite/absurd inputs and :class:`SimError` (state restored) if the step went unstable.
        """
        t0 = time.perf_counter()
        tool = self._check_inputs(tool_pos, dt)
        dt = float(dt)
        cfg = self.config
        tool_on = tool is not None
        dt_max = self.dt_max if tool_on else self.dt_max_free
        if self.dashpot_rate is not None:
            dt_max = min(dt_max, self.dashpot_rate.bound())
        n_sub, sub_dt, capped = substeps_for(dt, dt_max, cfg.max_substeps)
        tool_lag = 0.0
        if tool_on:
            rot = self._check_rotation(tool_rot)
            if self.tool_prev is not None:
                tool, tool_lag = self._limit_travel(self.tool_prev, tool, cfg.max_tool_speed * dt)
            seg1 = self.tool.segment(tool, rot)
            if self.seg_prev is not None and self.tool.oriented:
                tool_lag = max(tool_lag, self._limit_sweep(seg1, cfg.max_tool_speed * dt))
            seg0 = self.seg_prev if self.seg_prev is not None else seg1
        else:
            seg0 = seg1 = np.stack([self.centre, self.centre])
        if not tool_on:
            self.stuck[:] = False      # a new touch starts a new anchor
        path = ToolPath(seg0, seg1, tool_on, self.ball_reach, cfg.contact_stiffness,
                        self.contact_damping, self.contact_surf, self.samples, self.touches,
                        cfg.friction, self.anchor, self.stuck)
        if cfg.mode == 'global':
            res = self._global_step(path, n_sub, sub_dt, dt)
        else:
            res = self._local_step(path, n_sub, sub_dt, dt)
        if self.dashpot_rate is not None:
            # explicit contacts add their dashpots on the touched particles (the samples' own,
            # spread over their particles, are left out)
            contact = ((path.seg1, path.reach, path.surf, self.contact_damping * self.inv_mass)
                       if tool_on and not self.touches.on and cfg.contact_damping_ratio > 0.0 else None)
            self.dashpot_rate.update(self.body, self.x, self._last_sets, sub_dt, contact)
        force_raw = self.react.copy()
        force, clamped = clamp_norm(force_raw, cfg.force_limit)
        f0, f1, f2 = force.tolist()
        self.f_prev = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        self.tool_prev = tool if tool_on else None
        self.seg_prev = seg1 if tool_on else None
        self.sim_time += n_sub * sub_dt
        result = StepResult(force=force, force_raw=force_raw, clamped=clamped, substeps=n_sub,
                            substep_dt=sub_dt, wall_time=time.perf_counter() - t0,
                            substeps_capped=capped, tool_lag=tool_lag,
                            tool_segment=seg1 if tool_on else None, **res)
        self.last_result = result
        return result

    @staticmethod
    def _limit_travel(prev: np.ndarray, target: np.ndarray, max_travel: float) -> tuple[np.ndarray, float]:
        """``target`` moved back towards ``prev`` so that the travel is at most ``max_travel`` [m];
        returns (position, distance left to the target [m])."""
        p0, p1, p2 = prev.tolist()
        d0, d1, d2 = (target - prev).tolist()
        dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if dist <= max_travel:
            return target, 0.0
        f = max_travel / dist
        return np.array([p0 + f * d0, p1 + f * d1, p2 + f * d2]), dist - max_travel

    def _sticky_contact(self, seg: np.ndarray, reach: float) -> int:
        """Keep the previous contact particle while the tool still touches it.

        The interaction area is centred on the contact particle; letting it hop between equally
        deep neighbours every frame would re-centre the area and release kinematically moved layer
        particles into full SPH far from equilibrium.
        """
        prev = self.last_result.contact_index if self.last_result is not None else -1
        if prev >= 0:
            u = contact_vector_py(prev, self.x, seg, self.contact_surf)
            if u[0] * u[0] + u[1] * u[1] + u[2] * u[2] < reach * reach:
                return prev
        return -1

    def substep_integrator(self, sub_dt: float):
        """The integrator of a sub-step of ``sub_dt`` [s]: symplectic Euler, or backward Euler for
        the implicit dashpots and contacts (:mod:`.backward_euler`)."""
        if self.backward is None:
            return SymplecticEuler(sub_dt)
        return self.backward.integrator(sub_dt, contact_terms(
            self.touches, self.samples, self.config.contact_stiffness, self.contact_damping, self.react,
            self._touch_vn))

    def _frame(self, sets: Sets, path: ToolPath, n_sub: int, sub_dt: float, dt: float, mode: str) -> float:
        """One frame on ``sets`` (:func:`~.frame.run`); returns the last overlap [m].

        On a blow-up (non-finite or too fast, checked outside the fast-math kernels with
        :func:`~.integrate.frame_state_ok`), a torn body or an interrupt the moved particles go
        back to their state before the frame and :class:`SimError` is raised.
        """
        self.area.save(self.x, self.v, sets)
        status, overlap = frame.run(self.scheme, self.substep_integrator(sub_dt), self.body, self.motion, sets,
                                    path, self.loads, n_sub, dt, self.react, self.abort,
                                    self.area.active, self.area.n_active)
        ok = (status == STATUS_OK and self.abort[0] == 0
              and frame_state_ok(self.x, self.v, sets.sph, sets.n_sph, sets.layer, sets.n_layer,
                                 self.config.velocity_limit, self.react))
        self.scheme.frame_done(ok)
        if not ok:
            self.area.restore(self.x, self.v, sets)
            self.react[:] = 0.0
            self.stuck[:] = False      # the anchors belong to the discarded frame
            if self.abort[0] != 0:
                raise StepInterrupted(f'{self.config.scheme} {mode} step interrupted; state restored')
            raise SimError(f'{self.config.scheme} {mode} step went unstable (non-finite, torn apart or '
                           f'speed > {self.config.velocity_limit} m/s); state restored')
        self._last_sets = sets
        return overlap

    def _global_step(self, path: ToolPath, n_sub: int, sub_dt: float, dt: float) -> dict:
        contact = -1
        if path.on:
            contact = self._sticky_contact(path.seg1, self.detect_reach)
            if contact < 0:
                contact = deepest_contact(self.x, self.all_idx, self.n, path.seg1, self.detect_reach,
                                          self.contact_surf)
        sets = self.area.global_sets(contact)
        overlap = self._frame(sets, path, n_sub, sub_dt, dt, 'global')
        md, ke = active_stats(self.x, self.X, self.v, sets.sph, sets.n_sph, self.mass)
        return dict(contact_index=int(contact), penetration=float(max(overlap, 0.0)),
                    n_interaction=sets.n_sph, n_layer=np.zeros(self.config.n_layers, dtype=np.int64),
                    n_relaxing=0, max_displacement=float(md), kinetic_energy=float(ke), k1=0.0,
                    n_active=sets.n_sph)

    def _local_step(self, path: ToolPath, n_sub: int, sub_dt: float, dt: float) -> dict:
        cfg = self.config
        area = self.area
        margin = cfg.relax_disp_tol
        area.n_touch = 0
        contact = -1
        if path.on:
            deepest = area.detect(self.x, path.seg1, self.detect_reach, margin)
            contact = self._sticky_contact(path.seg1, self.detect_reach)
            if contact < 0:
                contact = deepest
        k1 = min(max(cfg.k1_gain * self.f_prev, cfg.k1_min), cfg.k1_max)
        Dr, reach = k1 * self.h, self.cand_reach
        if self.samples_push:
            # the samples spread their load over their support: solve every particle a touching
            # sample reads, and with the half-space far field a larger area (sized for the balls,
            # its shell is too near that load: local mode 12 % too soft or 7 % too stiff at a
            # 10 mm press); the organ's far field knows the organ's shape there
            reach = self.samples_reach
            if self.organ is None:
                Dr += SAMPLE_AREA_GROWTH * self.h
        sets, n_inter, n_relax = area.prepare(self.body, path.seg0 if path.on else None, path.seg1,
                                              reach, margin, contact, Dr, cfg.scheme == 'paper')
        area.far_field(self.body, self.x, sets, self.react, cfg.far_field, self.material.G, self.material.nu,
                       -math.expm1(-dt / cfg.far_field_tau) if cfg.far_field_tau > 0.0 else 1.0, self.organ)
        overlap = self._frame(sets, path, n_sub, sub_dt, dt, 'local')
        push = path.on and nearest_sample_gap(self.x, self.v, sets.cand, sets.n_cand, path.seg1,
                                              self.samples, 0.0) < 0.0
        # and while the tool still touches: shrinking the area as the samples slide past a
        # deep tool (the tissue giving way) made the 30k liver's step blow up at 28.5 mm
        self.samples_push = push or (self.samples_push and overlap > 0.0)
        n_active_frame = area.n_active
        md, ke = area.stats(self.x, self.v, self.mass)
        area.release(self.x, self.v, cfg.relax_disp_tol, cfg.relax_vel_tol)
        return dict(contact_index=int(contact), penetration=float(max(overlap, 0.0)),
                    n_interaction=int(n_inter), n_layer=area.layer_counts[:cfg.n_layers].copy(),
                    n_relaxing=int(n_relax), max_displacement=float(md), kinetic_energy=float(ke),
                    k1=float(k1), n_active=int(n_active_frame))


def warmup(scheme: str | None = None, contact_integration: str = 'explicit',
           integrator: str = 'explicit') -> float:
    """Compile every numba kernel on a tiny block (numba caches to disk); returns seconds taken.
    ``contact_integration`` and ``integrator`` pick the integrator's specialisation of the frame
    loop."""
    from .models import make_block

    t0 = time.perf_counter()
    schemes = SCHEMES if scheme is None else (scheme,)
    model = make_block(4, 4, 4, spacing=0.005)
    mat = Material.from_shear(1800.0, 0.45, 3.0)
    for sch in schemes:
        for mode in MODES:
            try:
                integ = integrator if sch == 'tlsph' else 'explicit'
                solver = Solver(model, mat, SolverConfig(scheme=sch, mode=mode,
                                                         contact_integration=contact_integration,
                                                         integrator=integ))
            except ConfigError:
                continue
            top = model.positions[:, 2].max()
            for k in range(3):
                try:
                    solver.step(np.array([0.01, 0.01, top + 0.005 - 0.001 * k]), 1e-3)
                except ConfigError:
                    break
            solver.von_mises()
    if 'tlsph' in schemes:
        # the backstop samples' nearness test runs outside the frame kernel
        solver = Solver(model, mat, SolverConfig(contact_samples=1,
                                                 contact_integration=contact_integration))
        solver.step(np.array([0.01, 0.01, model.positions[:, 2].max() + 0.005]), 1e-3)
    return time.perf_counter() - t0
