"""One solver for every scheme and mode: ``Solver(model, material, config).step(tool_pos, dt, tool_rot)``,
or with several instruments on one tissue ``Solver(..., instruments=2).step_tools([(pos, rot), None], dt)``.

Schemes (index order = ``SimMetrics.SCHEME_*``): ``paper`` (updated-Lagrangian SPH, eqs. 11-16),
``tlsph`` (total-Lagrangian SPH, the default) and ``mass_spring`` (the paper's Table 1 baseline).
Modes (``SimMetrics.MODE_*``): ``global`` (every free particle) and ``local`` (the paper's dynamic
local interaction area, see :mod:`.local_area`).

A frame of ``dt`` seconds is split into sub-steps bounded by the CFL, viscous and (when a tool is
given) contact limits;
each tool (a shape from :mod:`.tools`, posed by its tip position and orientation) moves linearly
from its previous to its new pose across the sub-steps, and the force
returned for it is the mean reaction of the tissue on it over the frame, clamped to ``force_limit``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields, replace

import numba
import numpy as np
from tissue_common.force import HARD_FORCE_LIMIT, clamp_norm

from . import frame
from .contact import contact_vector_py, deepest_contact
from .contact_kinds import BallContact, BladeContact, NeedleContact, make_contact
from .cutting import Cutter
from .needle import INSERTED, Puncture, no_shaft
from .surface_contact import nearest_sample_gap, no_samples
from .errors import ConfigError, ModelError, SimError
from .far_field import make_far_field
from .gradients import reverse_pairs
from .grasp import GRASP_REGION, grasp_region, no_grip, trail_after
from .implicit_contact import contact_terms, make_touches
from .instrument import Instrument, ToolResult
from .backward_euler import BackwardSolve
from .compliance import OrganCompliance, organ_place
from .integrate import frame_state_ok, substep_bounds, substeps_for
from .kernel import SUPPORT
from .local_area import LocalArea, active_stats
from .material import Material
from .models import TissueModel
from .neighbours import CellGrid, find_neighbours
from .paper import PaperScheme
from .protocols import STATUS_OK
from .springs import MassSpringScheme
from .stability import DASHPOT_RATE_EVERY, DashpotRate
from .state import TOUCH_BOND, Body, Grip, Loads, Motion, Sets, ToolPath, Topology
from .tlsph import TlsphScheme
from .tools import NO_ROTATION, TOOLS, make_tool

SCHEMES = ('paper', 'tlsph', 'mass_spring')
#: conjugate-gradient iterations of one implicit contact solve at most
CONTACT_MAX_ITER = 200
#: the implicit integrator's solve (stiffer: its condition number grows with (dt / CFL step)^2)
IMPLICIT_MAX_ITER = 2000
MODES = ('global', 'local')
#: the organ's far field lends a particle's response to the particles within this many spacings
#: (a response costs a back-substitution, about 45 ms on the 3670 liver)
ORGAN_SHARE = 1.01
#: the organ's far field factors the whole model: beyond this many free particles its start-up
#: and its responses cost too much (the 12k liver, 11149 free: 66 s, 4.6 GB, 0.3 s per response)
ORGAN_MAX_FREE = 5000
INTEGRATORS = ('explicit', 'implicit')
#: the tool against the particles' balls alone (SolverConfig(**BALL_CONTACT)): the paper's contact,
#: for comparisons with the surface samples
BALL_CONTACT = {'contact_samples': 0}
#: relative residual of the implicit contact's solve (cheap: it spans the particles under the tool)
CONTACT_TOL = 1e-8
#: the implicit integrator's solve stops at this velocity error relative to the velocities: holds a
#: press's force to 1e-5 N; a free vibration swings 1 % slower than at 1e-3 (test_core_beams)
IMPLICIT_TOL = 0.01
#: [m], [m/s] a particle outside the local area is released below this displacement and speed
RELAX_DISP_TOL, RELAX_VEL_TOL = 2e-4, 2e-3
#: [m/s] a faster particle is a blow-up (state restored, SimError)
VELOCITY_LIMIT = 50.0
#: [m] tool positions farther than this from the model centre are refused
MAX_TOOL_DISTANCE = 10.0
#: [m] where a particle a cut removed is kept, from its reference place: beyond any tool's reach
REMOVED_OFFSET = np.array([0.0, 0.0, -10.0 * MAX_TOOL_DISTANCE])
#: instruments on one tissue at most
MAX_INSTRUMENTS = 8
#: [s] low pass on the far field's load: with the samples as the surface the 30k liver's shell and
#: force rang (1 N per frame) without it; the default contact stays smooth either way
FAR_FIELD_TAU = 0.003


class InvalidInput(SimError, ValueError):
    """A step input (tool position, dt) is non-finite or absurd; the state was not changed."""


class StepInterrupted(SimError):
    """:meth:`Solver.interrupt` stopped the step; the state is as before it."""


def setting(default, doc: str, limits=None, node: bool = True, rebuild: str | None = 'solver'):
    """A :class:`SolverConfig` field with its one source of truth: ``doc`` (one line, unit first in
    brackets), ``limits`` (``(low, high)`` both included for a number, a tuple of strings for a
    choice, None for a flag), ``node`` (sim_node declares it as a parameter) and ``rebuild`` (what a
    run-time change needs: ``'solver'`` a new solver, None the next step)."""
    return field(default=default, metadata={'doc': doc, 'limits': limits, 'node': node, 'rebuild': rebuild})


@dataclass
class SolverConfig:
    """Solver settings (SI units); each field's doc, limits and role are in its metadata
    (:func:`setting`). Why each default is what it is: ``docs/decisions/``."""

    # -- scheme and area --------------------------------------------------------------------------
    scheme: str = setting('tlsph', 'tlsph (total-Lagrangian SPH) | paper (updated-Lagrangian, eqs. 11-16, '
                          'for comparison: 1.9-2.4x tlsph\'s cost per particle-sub-step, unstable in long '
                          'holds) | mass_spring (the paper\'s Table 1 baseline: 0.27x tlsph\'s global step)',
                          SCHEMES)
    mode: str = setting('local', 'local (the dynamic local interaction area) | global (every free particle: '
                        '4.8x the local step on the 3671 liver, for reference runs)', MODES)
    h_ratio: float = setting(1.3, '[-] smoothing length h / particle spacing (support 2h)', (0.2, 4.0))
    k1_gain: float = setting(0.5, '[1/N] k1 = k1_gain * f_ext (paper eq. 18); the area radius Dr = k1 h',
                             (0.0, 100.0))
    k1_min: float = setting(1.75, '[-] lower clamp of k1: keeps the area non-empty without force', (0.01, 100.0))
    k1_max: float = setting(6.0, '[-] upper clamp of k1', (0.01, 100.0))
    n_layers: int = setting(1, 'transmission layers N (paper eqs. 20-21); none under the organ\'s far field, '
                            'which places that band itself', (0, 8))
    hourglass: float = setting(1.0, '[-] tlsph: Ganzenmueller hourglass coefficient alpha', (0.0, 100.0),
                               node=False)
    # -- tool and contact -------------------------------------------------------------------------
    tool_shape: str = setting('sphere', 'sphere (a probe tip) | capsule (a shaft of tool_length along '
                              'the tool\'s +z, rounded: an instrument; 1.17x the sphere\'s step at a 6 mm '
                              'press) | blade (an edge of tool_length along +z that cuts: tlsph only) | needle '
                              '(a shaft that pierces past its puncture force: tlsph only)', tuple(TOOLS))
    tool_radius: float = setting(0.005, '[m] radius of the sphere, or of the capsule\'s shaft', (1e-4, 0.05))
    tool_length: float = setting(0.05, '[m] length of the capsule\'s or needle\'s shaft or of the blade\'s edge '
                                 '(unused by the sphere)', (0.0, 0.3))
    contact_stiffness: float = setting(300.0, '[N/m] penalty stiffness per touched particle or surface '
                                       'sample', (1.0, 1e5))
    contact_damping_ratio: float = setting(1.0, '[-] contact dashpot as a fraction of critical for one '
                                           'particle', (0.0, 10.0))
    contact_samples: int = setting(3, 'samples per side of a surface particle behind the balls, which hold '
                                   'the tool out of the gaps between particles (0: the balls alone, the '
                                   'tool slips between them, the paper\'s; 3 costs 0.9-1.15x the balls\' step)',
                                   (0, 5))
    friction: float = setting(0.0, '[-] Coulomb coefficient of stick-slip friction between the tool and '
                              'the tissue, balls and surface samples (0: frictionless; 0.3 holds the touched '
                              'particle to 0.1 mm at a 10 mm press but stiffens the shallow press by a third)',
                              (0.0, 2.0), rebuild=None)
    grasp_limit: float = setting(0.5, '[N] a grasped particle pulled harder than this lets go: the grasp '
                                 'slips one particle at a time instead of tearing the tissue', (0.001, 10.0),
                                 rebuild=None)
    max_tool_speed: float = setting(1.0, '[m/s] the simulated tool follows the request at most this fast '
                                    '(a hand stays below 1 m/s; 1000: no limit)', (0.01, 1000.0), rebuild=None)
    force_limit: float = setting(HARD_FORCE_LIMIT, '[N] norm clamp of the force sent to the device (Omni '
                                 'peak 3.3 N, continuous 0.88 N)', (0.001, HARD_FORCE_LIMIT), rebuild=None)
    # -- integration ------------------------------------------------------------------------------
    integrator: str = setting('explicit', 'explicit (symplectic Euler within the CFL and viscous bounds, '
                              'the pushing contacts backward) | implicit (tlsph: backward Euler on everything, '
                              'for large visual frames: a 16 ms frame costs 0.84-1.35x sixteen explicit ones)',
                              INTEGRATORS)
    cfl: float = setting(0.3, '[-] Courant number of the sub-step bounds', (0.01, 1.0))
    max_substeps: int = setting(64, 'sub-steps per frame at most (beyond it simulated time lags; reported)',
                                (1, 100000))
    implicit_max_dt: float = setting(0.016, '[s] the implicit integrator\'s largest sub-step', (1e-5, 1.0))
    parallel_min_particles: int = setting(0, 'tlsph: numba\'s threads from this many stressed particles (0: '
                                          'never; 2 idle threads: the local 3671 step 1.2x faster, but a '
                                          'busy core stalls each sub-step)',
                                          (0, 10_000_000))
    # -- far field --------------------------------------------------------------------------------
    far_field: float = setting(1.0, '[-] local mode: the still particles next to the solved ones follow this '
                               'times the far field\'s response to the contact force (the organ\'s own for '
                               f'tlsph up to {ORGAN_MAX_FREE} free particles, factored once and cached on disk, '
                               'else an elastic half-space\'s; 0: held still as in the paper, whose area was '
                               'then up to 24 % stiffer than global)',
                               (0.0, 2.0))

    def validate(self) -> 'SolverConfig':
        """Check every field against its limits; raises :class:`ConfigError` naming the bad field.
        Returns self, with the integer fields as ``int``."""
        for f in fields(self):
            val, limits = getattr(self, f.name), f.metadata['limits']
            if isinstance(f.default, str):
                if val not in limits:
                    raise ConfigError(f'{f.name} must be one of {limits}, got {val!r}')
            else:
                if not isinstance(val, (int, float)) or isinstance(val, bool) or not math.isfinite(val):
                    raise ConfigError(f'{f.name} must be a finite number, got {val!r}')
                if isinstance(f.default, int) and int(val) != val:
                    raise ConfigError(f'{f.name} must be an integer, got {val}')
                lo, hi = limits
                if not lo <= val <= hi:
                    raise ConfigError(f'{f.name} must be in [{lo:g}, {hi:g}], got {val}')
                if isinstance(f.default, int):
                    setattr(self, f.name, int(val))
        if self.k1_min > self.k1_max:
            raise ConfigError(f'k1_min ({self.k1_min}) must be <= k1_max ({self.k1_max})')
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
    """Outcome of one :meth:`Solver.step` (tissue frame, SI units); ``force``, ``contact_index`` and
    the other tool fields are the first instrument's (:attr:`tools` has each one's)."""

    tools: tuple                      # a ToolResult per instrument
    substeps: int
    substep_dt: float                 # [s]
    n_interaction: int
    n_layer: np.ndarray               # (n_layers,) int
    n_relaxing: int
    max_displacement: float           # [m]
    kinetic_energy: float             # [J]
    wall_time: float                  # [s]
    substeps_capped: bool = False     # the frame needed more than max_substeps (time lagged)
    k1: float = 0.0                   # interaction radius factor used (local mode; the first instrument's)
    n_active: int = 0                 # particles integrated this frame

    @property
    def force(self) -> np.ndarray:
        return self.tools[0].force

    @property
    def force_raw(self) -> np.ndarray:
        return self.tools[0].force_raw

    @property
    def clamped(self) -> bool:
        return self.tools[0].clamped

    @property
    def contact_index(self) -> int:
        return self.tools[0].contact_index

    @property
    def penetration(self) -> float:
        return self.tools[0].penetration

    @property
    def tool_lag(self) -> float:
        return self.tools[0].tool_lag

    @property
    def tool_segment(self) -> np.ndarray | None:
        return self.tools[0].tool_segment


def tool_shapes(cfg: SolverConfig, instruments: int, tools) -> list[SolverConfig]:
    """Each instrument's tool: ``cfg`` with ``tools[k]`` (a dict of ``tool_shape``, ``tool_radius``,
    ``tool_length``; None: the config's own) over it, checked against the config's limits."""
    if tools is None:
        tools = [None] * instruments
    if isinstance(tools, (str, dict)) or len(tools) != instruments:
        raise ConfigError(f'tools must give one entry per instrument ({instruments}), got {tools!r}')
    out = []
    for k, over in enumerate(tools):
        over = dict(over or {})
        unknown = set(over) - {'tool_shape', 'tool_radius', 'tool_length'}
        if unknown:
            raise ConfigError(f'instrument {k}\'s tool: {sorted(unknown)} is not tool_shape, tool_radius or tool_length')
        try:
            out.append(replace(cfg, **over).validate())
        except ConfigError as exc:
            raise ConfigError(f'instrument {k}\'s tool: {exc}') from exc
    return out


def contact_key(shape: SolverConfig) -> tuple[float, str]:
    """Which tools share a contact kind: those of one radius that meet the same things (a blade
    its bonds, a needle the balls, the others the surface samples, built once per radius)."""
    family = shape.tool_shape if shape.tool_shape in ('blade', 'needle') else 'surface'
    return shape.tool_radius, family


def organ_far_field(cfg: SolverConfig, X: np.ndarray, fixed: np.ndarray, scheme, spacing: float,
                    abort: np.ndarray, background: bool) -> OrganCompliance | None:
    """Local mode's far field from the organ's own linear response (tlsph, up to
    :data:`ORGAN_MAX_FREE` free particles), or None (the half-space's: larger organs and the other
    schemes; or no far field: global mode, ``far_field`` 0)."""
    n_free = int(np.count_nonzero(~fixed))
    if not (cfg.scheme == 'tlsph' and n_free <= ORGAN_MAX_FREE and cfg.mode == 'local'
            and cfg.far_field > 0.0):
        return None
    return OrganCompliance(X, fixed, scheme.state(None, None, 0), ORGAN_SHARE * spacing, abort,
                           background=background)


def check_material(cfg: SolverConfig, material: Material) -> None:
    """Raise :class:`ConfigError` if ``cfg``'s solver cannot model ``material``: a relaxing or
    stiffening spring needs the tlsph scheme's explicit integrator (the others treat it as
    Kelvin-Voigt)."""
    if material.beyond_kelvin_voigt and (cfg.scheme != 'tlsph' or cfg.integrator != 'explicit'):
        raise ConfigError(f'material {material.name}: a relaxing (prony) or stiffening spring needs scheme '
                          f'tlsph with integrator explicit, got {cfg.scheme} with {cfg.integrator}')


def frame_bounds(cfg: SolverConfig, h: float, wave_speed: float, material: Material) -> dict:
    """[s] the largest stable sub-step of each bound (:func:`~.integrate.substep_bounds`), by name.
    The contacts that push are integrated backward (:mod:`.implicit_contact`) and bound nothing; the
    implicit integrator has one bound, the accuracy the caller asks for."""
    if cfg.integrator == 'implicit':
        return {'implicit': cfg.implicit_max_dt}
    return substep_bounds(h, wave_speed, material.rho, material.eta_longitudinal, cfg.cfl)


class Solver:
    """Viscoelastic tissue simulator for one :class:`TissueModel`.

    Args:
        model: reference configuration (positions, spacing, fixed mask).
        material: Kelvin-Voigt material.
        config: solver settings (validated here).
        background: the organ's far field solves its responses on a worker thread, so a touch
            never waits for one (not repeatable bit for bit: sim_node's live timing).
        instruments: how many tools touch the tissue at once (each of the config's shape; more
            than one needs ``mode: global``).

    Raises:
        ModelError: empty model.
        ConfigError: bad settings, or a smoothing length too small for any particle to have
            a neighbour.
    """

    def __init__(self, model: TissueModel, material: Material, config: SolverConfig | None = None,
                 background: bool = False, instruments: int = 1, tools=None) -> None:
        if model is None or len(model.positions) == 0:
            raise ModelError('the model has no particles')
        if not isinstance(material, Material):
            raise ConfigError(f'material must be a Material, got {type(material).__name__}')
        self.config = cfg = (config or SolverConfig()).validate()
        if isinstance(instruments, bool) or not isinstance(instruments, int) or not 1 <= instruments <= MAX_INSTRUMENTS:
            raise ConfigError(f'instruments must be an integer in [1, {MAX_INSTRUMENTS}], got {instruments!r}')
        self.background = background
        self.model = model
        self.n = model.n_particles
        self.h = cfg.h_ratio * model.spacing
        self.volume = model.particle_volume
        self.X = np.ascontiguousarray(model.positions, dtype=np.float64)
        self.fixed = np.array(model.fixed, dtype=np.bool_)      # a cut adds the particles it removes
        self._fixed_at_rest = self.fixed.copy()
        self.free_idx = np.flatnonzero(~self.fixed).astype(np.int32)
        self.all_idx = np.arange(self.n, dtype=np.int32)
        self.centre = self.X.mean(axis=0)
        shapes = tool_shapes(cfg, instruments, tools)
        self.extent = float(np.linalg.norm(self.X.max(axis=0) - self.X.min(axis=0)))
        support = SUPPORT * self.h
        self.grid = CellGrid(self.X, support)
        self.offsets, self.indices = find_neighbours(self.X, support)
        if np.diff(self.offsets).max() == 0:
            raise ConfigError(f'smoothing length h = {self.h:.3g} m is too small: no particle has a '
                              f'neighbour within 2h (spacing {model.spacing:.3g} m)')
        kinds: dict[tuple, BallContact] = {}      # the surface samples are built once per radius
        for shape in shapes:
            key = contact_key(shape)
            if key in kinds:
                continue
            if shape.tool_shape == 'needle':    # it enters the tissue: the balls alone, no surface
                kinds[key] = NeedleContact(shape.tool_radius, model.spacing)
            elif shape.tool_shape == 'blade':    # a crack face has no surface samples: a blade meets the balls and the bonds
                kinds[key] = BladeContact(shape.tool_radius, model.spacing, self.X, self.offsets, self.indices,
                                          reverse_pairs(self.offsets, self.indices))
            else:
                kinds[key] = make_contact(cfg.contact_samples, shape.tool_radius, model.spacing, self.X,
                                          self.offsets, self.indices, self.h, self.volume)
        if cfg.scheme != 'tlsph' and any(key[1] == 'blade' for key in kinds):
            raise ConfigError(f'a blade cuts the reference bonds of scheme tlsph; scheme {cfg.scheme} has none')
        if sum(shape.tool_shape == 'blade' for shape in shapes) > 1:
            # the bonds' samples are aimed at one edge each frame (cutting.aim_bonds)
            raise ConfigError('one blade per tissue: the bonds\' contact samples follow one edge')
        if cfg.scheme != 'tlsph' and any(shape.tool_shape == 'needle' for shape in shapes):
            raise ConfigError(f'a needle pierces the tissue of scheme tlsph (its bonds, its stress); scheme '
                              f'{cfg.scheme} has none')
        self.x = self.X.copy()
        self.v = np.zeros((self.n, 3))
        self.acc = np.zeros((self.n, 3))
        self.motion = Motion(self.x, self.v, self.acc)
        self.react = np.zeros((instruments, 3))      # the reaction on each tool [N]
        self._overlap = np.zeros(instruments)          # and each tool's overlap in the last sub-step [m]
        self.abort = np.zeros(1, dtype=np.int8)   # set by interrupt() from another thread
        self.loads = Loads(np.zeros(0, dtype=np.int32), np.zeros((0, 3)), 0)
        pm = cfg.parallel_min_particles
        self.par_min = pm if pm > 0 and numba.get_num_threads() > 1 else self.n + 1
        self.scheme = self._make_scheme()
        # backward Euler for everything or for the pushing contacts alone (one solve)
        stiffness = cfg.integrator == 'implicit'
        self.backward = BackwardSolve(self.scheme if stiffness else None, self.n,
                                      IMPLICIT_TOL if stiffness else CONTACT_TOL,
                                      IMPLICIT_MAX_ITER if stiffness else CONTACT_MAX_ITER)
        # every instrument's pushing contacts, for one backward solve
        # (a particle both touched and held is recorded twice)
        n_samples = max(kind.n_samples for kind in kinds.values())   # the same samples whatever the radius
        self.touches = make_touches(instruments * (2 * self.n + n_samples))
        self.instruments = [Instrument(self.n + n_samples, make_tool(c.tool_shape, c.tool_radius, c.tool_length),
                                       kinds[contact_key(c)]) for c in shapes]
        #: the first instrument's tool and contact kind (the only ones of one instrument)
        self.tool, self.contact = self.instruments[0].tool, self.instruments[0].kind
        self._no_grip = no_grip()
        self._touch_vn = np.zeros(len(self.touches.idx))
        self._touch_vt = np.zeros((len(self.touches.idx), 3))
        self.area = LocalArea(self.X, self.fixed, Topology(self.offsets, self.indices), self.grid.bundle,
                              self.h, cfg.n_layers, instruments)
        #: each blade's crack (instrument index -> :class:`~.cutting.Cutter`)
        self.cutters = {k: Cutter(self.scheme.bonds(self.fixed), hand.kind)
                        for k, hand in enumerate(self.instruments) if hand.tool.cuts}
        #: each needle's phase (instrument index -> :class:`~.needle.Puncture`)
        self.needles = {k: Puncture(self.n, 2.0 * hand.tool.radius, hand.kind, cfg.contact_stiffness,
                                    model.spacing)
                        for k, hand in enumerate(self.instruments) if hand.tool.pierces}
        self._no_shaft = no_shaft()
        self.set_material(material)
        self.reset()

    def _make_scheme(self):
        cfg = self.config
        if cfg.scheme == 'paper':
            return PaperScheme(self.X, self.x, self.fixed, self.offsets, self.indices, self.h)
        if cfg.scheme == 'mass_spring':
            return MassSpringScheme(self.X, self.model.spacing)
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
        if getattr(self, 'far', None) is None:
            return True
        return self.far.close(timeout)

    def set_material(self, material: Material) -> None:
        """Change the material (takes effect at the next step): its constants, the organ's far field
        and the sub-step bounds follow."""
        if not isinstance(material, Material):
            raise ConfigError(f'material must be a Material, got {type(material).__name__}')
        cfg = self.config
        check_material(cfg, material)
        self.material = material
        self.mass = material.rho * self.volume
        self.inv_mass = 1.0 / self.mass
        self.body = Body(self.X, self.fixed, self.mass, self.inv_mass)
        self.contact_damping = cfg.contact_damping_ratio * 2.0 * math.sqrt(cfg.contact_stiffness * self.mass)
        for hand in self.instruments:
            hand.samples = hand.kind.samples(self.n, hand.tool.radius, cfg.contact_stiffness, self.contact_damping)
        #: the implicit contact's view of the surface samples (their places are every sampled
        #: instrument's) and of a blade's bond samples
        no = no_samples(self.n)
        self.samples = next((hand.samples for hand in self.instruments
                             if hand.kind.n_samples and not isinstance(hand.kind, BladeContact)), no)
        self.bond_samples = next((hand.samples for hand in self.instruments
                                  if isinstance(hand.kind, BladeContact)), no)
        self.scheme.set_material(material, self.mass)
        self.close()
        #: the organ's compliance for local mode's far field (None: the half-space's, or none)
        self.organ = organ_far_field(cfg, self.X, self.fixed, self.scheme, self.model.spacing, self.abort,
                                     self.background)
        #: local mode's far field (:mod:`.far_field`; None in global mode or with ``far_field`` 0)
        self.far = make_far_field(cfg.mode == 'local', cfg.far_field, material, self.organ)
        # the organ's far field places the band the transmission layers would move, at the organ's
        # response to every instrument's load: no layers then (docs/decisions/local-area-far-field.md)
        self.area.n_layers = 0 if self.organ is not None else cfg.n_layers
        self.backward.set_material(material)
        self.dt_bounds = frame_bounds(cfg, self.h, self.scheme.wave_speed(material, self.mass), material)
        dashpots = self.scheme.dashpots_only() if isinstance(self.scheme, TlsphScheme) else None
        #: follows the explicit dashpots' rate as the tissue deforms (None: no explicit dashpots)
        self.dashpot_rate = DashpotRate(dashpots, self.n, DASHPOT_RATE_EVERY) if dashpots is not None else None
        self.dt_max = min(self.dt_bounds.values())

    def reset(self) -> None:
        """Back to the reference configuration at rest, sim time 0, no active area, the organ whole."""
        self.fixed[:] = self._fixed_at_rest   # the particles a cut removed are back
        self.x[:] = self.X
        self.v[:] = 0.0
        self.acc[:] = 0.0
        self.area.reset(self.config.mode == 'global')
        self.scheme.reset()
        if self.dashpot_rate is not None:
            self.dashpot_rate.reset()
        self.sim_time = 0.0
        self.f_prev = [0.0] * len(self.instruments)   # each tool's last force [N]: its area's size
        for hand in self.instruments:
            hand.reset()
        for cutter in self.cutters.values():
            cutter.reset()
            cutter.kind.reset()
        for needle in self.needles.values():
            needle.reset()
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
    def n_instruments(self) -> int:
        return len(self.instruments)

    @property
    def tool_prev(self) -> np.ndarray | None:
        """The first instrument's tip [m] after the last frame (None: lifted)."""
        return self.instruments[0].tip

    @property
    def seg_prev(self) -> np.ndarray | None:
        """The first instrument's segment (2, 3) [m] after the last frame (None: lifted)."""
        return self.instruments[0].segment

    @property
    def samples_push(self) -> bool:
        """Local mode: a backstop sample has pushed the tool since it touched (the area is the samples')."""
        return self.instruments[0].samples_push

    @property
    def far_field_in_use(self) -> str:
        """Local mode's far field as built: ``organ``, ``half_space`` or ``none`` (global mode,
        or ``far_field`` 0): :func:`organ_far_field` decides between the first two."""
        return self.far.name if self.far is not None else 'none'

    @property
    def contact_reach(self) -> float:
        """[m] from the first instrument's tool axis to a particle centre at the first touch (its
        contact kind's)."""
        return self.contact.contact_reach

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
    def _check_dt(self, dt) -> float:
        try:
            dt = float(dt)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(f'dt must be a number, got {dt!r}') from exc
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise InvalidInput(f'dt must be in (0, 1] s, got {dt}')
        return dt

    def _check_position(self, tool_pos) -> np.ndarray:
        try:
            tool = np.asarray(tool_pos, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(f'tool position must be 3 numbers, got {tool_pos!r}') from exc
        # scalar checks: numpy's per-call overhead on a 3-vector matters at 1 kHz
        t0, t1, t2 = tool.tolist()
        if not (math.isfinite(t0) and math.isfinite(t1) and math.isfinite(t2)):
            raise InvalidInput(f'tool position is not finite: {tool}')
        c0, c1, c2 = self.centre.tolist()
        if math.sqrt((t0 - c0) ** 2 + (t1 - c1) ** 2 + (t2 - c2) ** 2) > MAX_TOOL_DISTANCE:
            raise InvalidInput(f'tool position {tool} is more than {MAX_TOOL_DISTANCE} m '
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

    def _check_poses(self, poses) -> list:
        """Each instrument's (tip, rotation), or None where it is lifted; raises InvalidInput."""
        try:
            poses = list(poses)
        except TypeError as exc:
            raise InvalidInput(f'poses must be a sequence of (position, rotation) or None, got {poses!r}') from exc
        if len(poses) != len(self.instruments):
            raise InvalidInput(f'{len(poses)} poses for {len(self.instruments)} instruments')
        checked = []
        for pose in poses:
            if pose is None:
                checked.append(None)
                continue
            try:
                pos, rot = pose
            except (TypeError, ValueError) as exc:
                raise InvalidInput(f'a pose is (position, rotation) or None, got {pose!r}') from exc
            if pos is None:
                checked.append(None)
                continue
            tip = self._check_position(pos)
            checked.append((tip, self._check_rotation(rot)))
        return checked

    def _limit_sweep(self, prev: np.ndarray, seg: np.ndarray, max_travel: float) -> float:
        """Move the far end of a shaft (``seg[1]``, in place) at most ``max_travel`` [m] from where
        it was (``prev[1]``), keeping the shaft's length: a fast twist of a long tool would
        otherwise sweep its far end through the tissue in one frame. Returns the distance left to
        the request [m]."""
        far, lag = self._limit_travel(prev[1], seg[1], max_travel)
        if lag > 0.0:
            length = math.dist(seg[1].tolist(), seg[0].tolist())
            d = far - seg[0]
            n = math.sqrt(float(d @ d))
            if n > 0.0:
                seg[1] = seg[0] + d * (length / n)
        return lag

    def _hand(self, k: int) -> Instrument:
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < len(self.instruments):
            raise InvalidInput(f'instrument {k!r} is not one of the {len(self.instruments)} instruments')
        return self.instruments[int(k)]

    def grasp_reach(self, k: int = 0) -> float:
        """[m] instrument ``k``, closing, holds the free particles whose centres lie this close to its
        segment (:mod:`.grasp`)."""
        return GRASP_REGION * self._hand(k).kind.contact_reach

    def grasp(self, k: int = 0) -> int:
        """Close instrument ``k`` on the tissue: it holds the free particles within
        :meth:`grasp_reach` of its tool (replacing what it held) until :meth:`release`, until it is
        lifted, or each until pulled harder than ``grasp_limit``. Returns how many it holds: 0 for
        a lifted instrument or a grasp on nothing."""
        hand = self._hand(k)
        if hand.segment is None:
            hand.let_go()
            return 0
        idx = grasp_region(self.x, self.fixed, hand.segment, GRASP_REGION * hand.kind.contact_reach)
        hand.hold(idx, (self.x[idx] - hand.tip) @ hand.rotation)   # rows of R^T (x - tip)
        return len(idx)

    def release(self, k: int = 0) -> int:
        """Open instrument ``k``: it lets go of everything; returns how many particles it held (0:
        a release without a grasp)."""
        return self._hand(k).let_go()

    def _grip(self, hand: Instrument, rot: np.ndarray, trail: np.ndarray) -> Grip:
        """What ``hand`` holds across this frame, its anchors turned from the last frame's
        orientation to ``rot`` and trailing the tip by ``hand.grip_trail`` at its start and ``trail``
        at its end."""
        prev = hand.rotation if hand.rotation is not None else rot
        return Grip(hand.grip_idx, len(hand.grip_idx), hand.grip_local @ prev.T + hand.grip_trail,
                    hand.grip_local @ rot.T + trail, hand.grip_held, self.config.grasp_limit)

    def step(self, tool_pos, dt: float, tool_rot=None) -> StepResult:
        """Advance the tissue by ``dt`` seconds with the tool's tip at ``tool_pos`` (tissue frame, m)
        and its orientation ``tool_rot`` (3x3 rotation matrix, tissue frame; None: identity).

        ``tool_pos=None`` means no tool. Raises :class:`InvalidInput` (state untouched) for
        non-finite/absurd inputs and :class:`SimError` (state restored) if the step went unstable.
        A solver of several instruments steps with :meth:`step_tools`.
        """
        if len(self.instruments) != 1:
            raise InvalidInput(f'this solver has {len(self.instruments)} instruments: step_tools() poses them all')
        return self.step_tools((None if tool_pos is None else (tool_pos, tool_rot),), dt)

    def step_tools(self, poses, dt: float) -> StepResult:
        """Advance the tissue by ``dt`` seconds with every instrument at its pose: ``poses`` holds,
        per instrument, ``(tip position, rotation)`` (tissue frame; rotation None: identity) or
        None (lifted). One frame for all: each tool's reaction is in ``StepResult.tools``.
        Errors as :meth:`step`."""
        t0 = time.perf_counter()
        dt = self._check_dt(dt)
        poses = self._check_poses(poses)
        cfg = self.config
        dt_max = self.dt_max
        if self.dashpot_rate is not None:
            dt_max = min(dt_max, self.dashpot_rate.bound())
        growth = self.scheme.stiffness_growth()
        if growth > 1.0:      # a stiffening spring's waves are faster: the CFL bound at its stiffness
            m = self.material
            dt_max = min(dt_max, cfg.cfl * self.h / math.sqrt((m.K + 4.0 * m.G * growth / 3.0) / m.rho))
        n_sub, sub_dt, capped = substeps_for(dt, dt_max, cfg.max_substeps)
        paths, tips, rots, lags, trails = [], [], [], [], []
        for k, (hand, pose) in enumerate(zip(self.instruments, poses)):
            lag = 0.0
            grip = self._no_grip
            rot = None
            trail = None
            if pose is not None:
                tip, rot = pose
                if hand.tip is not None:
                    tip, lag = self._limit_travel(hand.tip, tip, cfg.max_tool_speed * dt)
                seg1 = hand.tool.segment(tip, rot)
                if hand.segment is not None and hand.tool.oriented:
                    sweep = self._limit_sweep(hand.segment, seg1, cfg.max_tool_speed * dt)
                    if sweep > 0.0:
                        rot = _turned_to(rot, seg1)     # what it holds turns as far as the shaft did
                    lag = max(lag, sweep)
                seg0 = hand.segment if hand.segment is not None else seg1
                if len(hand.grip_idx):
                    trail = trail_after(hand.grip_trail, seg0[0], seg1[0], dt)
                    grip = self._grip(hand, rot, trail)
            else:
                tip = None
                seg0 = seg1 = np.stack([self.centre, self.centre])
                hand.stuck[:] = False      # a new touch starts a new anchor
                hand.let_go()              # and a lifted instrument holds nothing
            tips.append(tip)
            rots.append(rot)
            lags.append(lag)
            trails.append(trail)
            needle = self.needles.get(k)
            shaft = (needle.shaft(self.material.toughness, self.material.needle_hold) if needle is not None
                     else self._no_shaft)
            paths.append(ToolPath(seg0, seg1, pose is not None, hand.kind.ball_reach, cfg.contact_stiffness,
                                  self.contact_damping, hand.samples, self.touches,
                                  cfg.friction, hand.anchor, hand.stuck, k, grip, shaft))
        paths = tuple(paths)
        held = [hand.grip_held.copy() if len(hand.grip_idx) else None for hand in self.instruments]
        try:
            if cfg.mode == 'global':
                contacts, res = self._global_step(paths, n_sub, sub_dt, dt)
            else:
                contacts, res = self._local_step(paths, n_sub, sub_dt, dt)
        except SimError:
            for hand, flags in zip(self.instruments, held):
                if flags is not None:
                    hand.grip_held[:] = flags  # the slips belong to the discarded frame
            raise
        if self.dashpot_rate is not None:
            self.dashpot_rate.update(self.body, self.x, self._last_sets, sub_dt)
        if self.cutters:
            self._cut(paths, contacts)
        for k, needle in self.needles.items():
            was = needle.state
            touching = paths[k].on and (contacts[k] >= 0 or self._overlap[k] > 0.0)
            sets = self._last_sets
            needle.update(paths[k].seg1 if paths[k].on else None, self.react[k], touching, self.material.toughness,
                          self.x, sets.cand[:sets.n_cand])
            if (was == INSERTED) != (needle.state == INSERTED):
                self.instruments[k].stuck[:] = False    # its anchors were the other contact's
        tools = []
        for k, hand in enumerate(self.instruments):
            force_raw = self.react[k].copy()
            force, clamped = clamp_norm(force_raw, cfg.force_limit)
            on = paths[k].on
            tools.append(ToolResult(force, force_raw, clamped, int(contacts[k]),
                                    float(max(self._overlap[k], 0.0)), lags[k], paths[k].seg1 if on else None,
                                    hand.holding, self.cutters[k].cut if k in self.cutters else 0))
            hand.tip = tips[k]
            hand.segment = paths[k].seg1 if on else None
            hand.rotation = rots[k]
            hand.contact = int(contacts[k])
            if trails[k] is not None:
                hand.grip_trail = trails[k]
        for k, tool in enumerate(tools):
            f0, f1, f2 = tool.force.tolist()
            self.f_prev[k] = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        self.sim_time += n_sub * sub_dt
        result = StepResult(tools=tuple(tools), substeps=n_sub, substep_dt=sub_dt,
                            wall_time=time.perf_counter() - t0, substeps_capped=capped, **res)
        self.last_result = result
        return result

    def _cut(self, paths: tuple, contacts: list) -> None:
        """Each blade breaks the bonds its frame paid for (:mod:`.cutting`); the particles the cut
        tore off leave the simulation."""
        sets = self._last_sets
        for k, cutter in self.cutters.items():
            path = paths[k]
            touching = path.on and (contacts[k] >= 0 or self._overlap[k] > 0.0)
            pairs = cutter.frame(self.x, self.v, path.seg0, path.seg1, self.react[k], touching, sets.cand,
                                 sets.n_cand, self.instruments[k].samples, self.material.toughness)
            if len(pairs):
                cut, gone = cutter.bonds.cut(pairs)
                for blade in {id(c.kind): c.kind for c in self.cutters.values()}.values():
                    blade.drop(cut)
                if len(gone):
                    self._remove(gone)

    def _remove(self, idx: np.ndarray) -> None:
        """Particles ``idx`` (bondless now) leave: held still far from every tool (a tool is refused
        beyond :data:`MAX_TOOL_DISTANCE`) until :meth:`reset`."""
        self.fixed[idx] = True
        self.x[idx] = self.X[idx] + REMOVED_OFFSET
        self.v[idx] = 0.0
        self.acc[idx] = 0.0
        self.area.drop(idx)

    @property
    def removed(self) -> np.ndarray | None:
        """(N,) bool: the particles a cut removed (None: no blade, nothing can be)."""
        cutter = next(iter(self.cutters.values()), None)
        return cutter.bonds.removed if cutter is not None else None

    @property
    def severed(self) -> np.ndarray | None:
        """(N,) the reference bonds each particle lost to a cut (None: no blade)."""
        cutter = next(iter(self.cutters.values()), None)
        return cutter.bonds.severed if cutter is not None else None

    def crack_area(self, k: int = 0) -> float:
        """[m^2] the crack instrument ``k`` opened: its bonds cut times a bond's crack area (0: not a
        blade)."""
        cutter = self.cutters.get(k)
        return cutter.cut * cutter.bonds.area if cutter is not None else 0.0

    def cut_length(self, k: int = 0) -> float:
        """[m] how far instrument ``k``'s edge has cut: its travel across itself from the first bond it
        broke to the last (0: not a blade)."""
        cutter = self.cutters.get(k)
        return cutter.length if cutter is not None else 0.0

    def held_particles(self, k: int = 0) -> np.ndarray:
        """The particles instrument ``k`` holds (int32): those it grasped and that have not slipped,
        and those its inserted needle's shaft holds (the needle's track)."""
        hand = self._hand(k)
        held = hand.grip_idx[hand.grip_held]
        needle = self.needles.get(int(k))
        if needle is not None and needle.state == INSERTED:
            held = np.union1d(held, needle.holding()).astype(np.int32)
        return held

    def needle_state(self, k: int = 0) -> int:
        """Instrument ``k``'s needle: :data:`~.needle.OUTSIDE`, ``TOUCHING`` or ``INSERTED`` (0 for
        a tool that is not a needle)."""
        needle = self.needles.get(k)
        return needle.state if needle is not None else 0

    def needle_depth(self, k: int = 0) -> float:
        """[m] how far instrument ``k``'s needle tip is below its entry point (0: not inserted, or
        not a needle)."""
        needle = self.needles.get(k)
        return needle.depth if needle is not None else 0.0

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

    def _sticky_contact(self, hand: Instrument, seg: np.ndarray, reach: float) -> int:
        """Keep ``hand``'s previous contact particle while its tool still touches it.

        The interaction area is centred on the contact particle; letting it hop between equally
        deep neighbours every frame would re-centre the area and release kinematically moved layer
        particles into full SPH far from equilibrium.
        """
        prev = hand.contact
        if prev >= 0:
            u = contact_vector_py(prev, self.x, seg)
            if u[0] * u[0] + u[1] * u[1] + u[2] * u[2] < reach * reach:
                return prev
        return -1

    def _pressed_bond_ends(self, k: int) -> np.ndarray:
        """The particles at either end of the bonds instrument ``k``'s edge pressed in the last
        sub-step (sorted, unique): its load's place while it touches no particle."""
        t = self.touches
        c = int(t.count[0])
        s = t.idx[:c][(t.kind[:c] == TOUCH_BOND) & (t.tool[:c] == k)]
        w_idx = self.instruments[k].kind.w_idx
        return np.unique(np.concatenate([w_idx[2 * s], w_idx[2 * s + 1]]))

    def substep_integrator(self, sub_dt: float):
        """The integrator of a sub-step of ``sub_dt`` [s]: symplectic Euler with the pushing contacts
        (and with ``integrator: implicit`` everything) backward in time (:mod:`.backward_euler`)."""
        return self.backward.integrator(sub_dt, contact_terms(
            self.touches, self.samples, self.bond_samples, self.config.contact_stiffness, self.contact_damping, self.react,
            self._touch_vn, self._touch_vt))

    def _frame(self, sets: Sets, paths: tuple, n_sub: int, sub_dt: float, dt: float, mode: str) -> None:
        """One frame on ``sets`` (:func:`~.frame.run`); each tool's last overlap [m] in ``_overlap``.

        On a blow-up (non-finite or too fast, checked outside the fast-math kernels with
        :func:`~.integrate.frame_state_ok`), a torn body or an interrupt the moved particles go
        back to their state before the frame and :class:`SimError` is raised.
        """
        self.area.save(self.x, self.v, sets)
        for k, cutter in self.cutters.items():
            if paths[k].on:
                cutter.aim(self.x, paths[k].seg1, sets.cand, sets.n_cand)
        self.scheme.start_frame(self.sim_time, sub_dt)
        status = frame.run(self.scheme, self.substep_integrator(sub_dt), self.body, self.motion, sets,
                           paths, self.loads, n_sub, dt, self.react, self._overlap, self.abort,
                           self.area.active, self.area.n_active)
        ok = (status == STATUS_OK and self.abort[0] == 0
              and frame_state_ok(self.x, self.v, sets.sph, sets.n_sph, sets.layer, sets.n_layer,
                                 VELOCITY_LIMIT, self.react.reshape(-1)))
        self.scheme.frame_done(ok)
        if not ok:
            self.area.restore(self.x, self.v, sets)
            self.react[:] = 0.0
            for hand in self.instruments:
                hand.stuck[:] = False      # the anchors belong to the discarded frame
            if self.abort[0] != 0:
                raise StepInterrupted(f'{self.config.scheme} {mode} step interrupted; state restored')
            raise SimError(f'{self.config.scheme} {mode} step went unstable (non-finite, torn apart or '
                           f'speed > {VELOCITY_LIMIT} m/s); state restored')
        self._last_sets = sets

    def _global_step(self, paths: tuple, n_sub: int, sub_dt: float, dt: float) -> tuple[list, dict]:
        contacts = []
        for hand, path in zip(self.instruments, paths):
            contact = -1
            if path.on:
                contact = self._sticky_contact(hand, path.seg1, hand.kind.detect_reach)
                if contact < 0:
                    contact = deepest_contact(self.x, self.all_idx, self.n, path.seg1, hand.kind.detect_reach)
            contacts.append(contact)
        sets = self.area.global_sets(contacts)
        self._frame(sets, paths, n_sub, sub_dt, dt, 'global')
        md, ke = active_stats(self.x, self.X, self.v, sets.sph, sets.n_sph, self.mass)
        return contacts, dict(n_interaction=sets.n_sph, n_layer=np.zeros(self.config.n_layers, dtype=np.int64),
                              n_relaxing=0, max_displacement=float(md), kinetic_energy=float(ke), k1=0.0,
                              n_active=sets.n_sph)

    def _local_step(self, paths: tuple, n_sub: int, sub_dt: float, dt: float) -> tuple[list, dict]:
        """One local frame: the union of the instruments' areas (each centred on what its tool
        touches, or holds), solved at once."""
        cfg = self.config
        area = self.area
        margin = RELAX_DISP_TOL
        contacts, tools, k1s = [], [], []
        for k, (hand, path) in enumerate(zip(self.instruments, paths)):
            contact = -1
            area.skip(k)
            if path.on:
                deepest = area.detect(self.x, path.seg1, hand.kind.detect_reach, margin, k)
                contact = self._sticky_contact(hand, path.seg1, hand.kind.detect_reach)
                if contact < 0:
                    contact = deepest
            centre = contact
            if contact < 0 and path.grip.n:
                held = path.grip.idx[path.grip.held]
                if len(held):
                    centre = area.hold(held, k)   # the area's centre; nothing touches (contact stays -1)
            if centre < 0 and k in self.needles and path.on:
                held = self.needles[k].holding()  # a dent, or a shaft between the particles
                if len(held):
                    centre = area.hold(held, k)
            if centre < 0 and k in self.cutters and path.on:
                pressed = self._pressed_bond_ends(k)
                if len(pressed):
                    area.hold(pressed, k)         # where the far field loads the organ; still no area
            k1 = min(max(cfg.k1_gain * self.f_prev[k], cfg.k1_min), cfg.k1_max)
            reach, Dr = hand.kind.area(hand.samples_push, self.organ is not None, k1 * self.h, self.h)
            if path.grip.n:
                # what it holds is solved: it sits within the grasp's reach plus its spring's stretch
                reach = max(reach, GRASP_REGION * hand.kind.contact_reach + cfg.grasp_limit / cfg.contact_stiffness
                            + self.model.spacing)
            contacts.append(contact)
            k1s.append(k1)
            tools.append((path.seg0 if path.on else None, path.seg1, reach, centre, Dr))
        sets, n_inter, n_relax = area.prepare(self.body, tools, margin, cfg.scheme == 'paper')
        area.far_field(self.body, self.x, sets, self.react, cfg.far_field, -math.expm1(-dt / FAR_FIELD_TAU),
                       self.far)
        self._frame(sets, paths, n_sub, sub_dt, dt, 'local')
        for k, (hand, path) in enumerate(zip(self.instruments, paths)):
            push = path.on and nearest_sample_gap(self.x, self.v, sets.cand, sets.n_cand, path.seg1,
                                                  hand.samples, 0.0) < 0.0
            # and while the tool still touches: shrinking the area as the samples slide past a
            # deep tool (the tissue giving way) made the 30k liver's step blow up at 28.5 mm
            hand.samples_push = push or (hand.samples_push and self._overlap[k] > 0.0)
        n_active_frame = area.n_active
        md, ke = area.stats(self.x, self.v, self.mass)
        area.release(self.x, self.v, RELAX_DISP_TOL, RELAX_VEL_TOL)
        return contacts, dict(n_interaction=int(n_inter), n_layer=area.layer_counts[:cfg.n_layers].copy(),
                              n_relaxing=int(n_relax), max_displacement=float(md), kinetic_energy=float(ke),
                              k1=float(k1s[0]), n_active=int(n_active_frame))


def _turned_to(rot: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """``rot`` turned by the least rotation that takes its +z (the shaft's request) onto the axis
    of ``seg`` (the shaft as its sweep limit left it)."""
    a = rot[:, 2]
    b = seg[1] - seg[0]
    n = float(np.linalg.norm(b))
    if n == 0.0:
        return rot
    b = b / n
    v = np.cross(a, b)
    c = float(a @ b)
    if c <= -1.0 + 1e-12:       # turned right round: any half turn about a normal will do
        return rot @ np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return (np.eye(3) + vx + vx @ vx / (1.0 + c)) @ rot


def warmup(scheme: str | None = None, integrator: str = 'explicit', instruments: int = 1) -> float:
    """Compile every numba kernel on a tiny block (numba caches to disk); returns seconds taken.
    ``integrator`` picks the integrator's specialisation of the frame loop; ``instruments`` > 1 also
    compiles several tools' kernels (their layers, their far-field loads), which one tool never runs."""
    from .models import make_block

    t0 = time.perf_counter()
    schemes = SCHEMES if scheme is None else (scheme,)
    model = make_block(4, 4, 4, spacing=0.005)
    mat = Material.from_shear(1800.0, 0.45, 3.0)
    for sch in schemes:
        for mode in MODES:
            try:
                integ = integrator if sch == 'tlsph' else 'explicit'
                solver = Solver(model, mat, SolverConfig(scheme=sch, mode=mode, integrator=integ))
            except ConfigError:
                continue
            top = model.positions[:, 2].max()
            # held in contact until the dashpots' rate is measured (every DASHPOT_RATE_EVERY frames):
            # its kernels too, else the live loop loads them at its first touch
            for k in range(DASHPOT_RATE_EVERY + 1):
                try:
                    solver.step(np.array([0.01, 0.01, top + 0.005 - 0.001 * min(k, 2)]), 1e-3)
                except ConfigError:
                    break
            solver.von_mises()
            if mode == 'local' and sch == 'tlsph':
                # the organ's far field places its shell with organ_place, its loads one broadcast
                # (C or A, read-only) or several concatenated (C or F): the tiny block has no shell,
                # so each layout is loaded here (loaded at a live first touch, it held the solver
                # thread for 30-300 ms while the press went on without a contact model)
                x, idx = np.zeros((2, 3)), np.zeros(2, dtype=np.int32)
                for loads in (np.broadcast_to(np.zeros(3), (1, 3)), np.broadcast_to(np.zeros(3), (2, 3)),
                              np.zeros((2, 3)), np.zeros((2, 3), order='F')):
                    organ_place(x, x.copy(), idx, idx.copy(), np.ones(2), idx.copy(),
                                np.zeros((1, 2, 3, 3), dtype=np.float32), loads)
            if instruments > 1 and sch == 'tlsph':
                # sim_node steps these in its live loop: compiled there, the first steps took seconds
                solver = Solver(model, mat, SolverConfig(scheme=sch, mode=mode, integrator=integ), instruments=2)
                for k in range(3):
                    solver.step_tools([(np.array([0.004, 0.01, top + 0.005 - 0.001 * k]), None),
                                       (np.array([0.011, 0.01, top + 0.005 - 0.001 * k]), None)], 1e-3)
    if 'tlsph' in schemes:
        # the backstop samples' nearness test runs outside the frame kernel
        solver = Solver(model, mat, SolverConfig(contact_samples=1))
        solver.step(np.array([0.01, 0.01, model.positions[:, 2].max() + 0.005]), 1e-3)
        # a blade's kernels (its bonds' samples, the cut, the refit) run once it cuts: a soft tissue
        # here, so that it does within a few frames
        for mode in MODES:
            solver = Solver(model, replace(mat, toughness=1.0), SolverConfig(
                mode=mode, integrator=integrator, tool_shape='blade', tool_radius=0.0005, tool_length=0.01))
            top = model.positions[:, 2].max()
            for k in range(6):
                solver.step(np.array([0.0075, 0.0085, top + 0.001 - 0.002 * k]), 1e-3, NO_ROTATION)
            # a needle's: its dent, then, punctured at once in a tissue this weak, its shaft and tip
            solver = Solver(model, replace(mat, toughness=0.01), SolverConfig(
                mode=mode, integrator=integrator, tool_shape='needle', tool_radius=0.0005, tool_length=0.01))
            for k in range(8):
                solver.step(np.array([0.0075, 0.0085, top + 0.003 - 0.001 * k]), 1e-3, NO_ROTATION)
            if solver.needle_state() != INSERTED:
                raise SimError('warmup: the needle did not enter the tiny block')
    return time.perf_counter() - t0
