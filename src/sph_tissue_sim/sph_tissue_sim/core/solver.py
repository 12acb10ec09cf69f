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
from dataclasses import dataclass, field, fields

import numba
import numpy as np
from tissue_common.force import clamp_norm

from .contact import contact_vector_py, deepest_contact, surface_discs
from .errors import ConfigError, ModelError, SimError
from .integrate import (SCHEME_MASS_SPRING, SCHEME_TLSPH, frame_state_ok, run_frame, substep_bounds,
                        substeps_for)
from .kernel import SUPPORT
from .local_area import (active_stats, detect_local, far_field_shell, local_prepare, local_release,
                         restore_state, save_state)
from .material import Material
from .models import TissueModel
from .neighbours import CellGrid, find_neighbours
from .paper import PaperScheme
from .tlsph import pair_gradients, reference_pairs, tlsph_von_mises
from .tools import NO_ROTATION, TOOLS, make_tool

SCHEMES = ('paper', 'tlsph', 'mass_spring')
MODES = ('global', 'local')


class InvalidInput(SimError, ValueError):
    """A step input (tool position, dt) is non-finite or absurd; the state was not changed."""


class StepInterrupted(SimError):
    """:meth:`Solver.interrupt` stopped the step; the state is as before it."""


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
        tool_shape: ``sphere`` (default: a probe tip) or ``capsule`` (a shaft of ``tool_length``
            with a rounded tip, along the tool frame's +z), see :mod:`.tools`.
        tool_radius: radius of the tool's sphere, or of the capsule's shaft [m].
        tool_length: length of the capsule's shaft [m] (unused by the sphere).
        contact_stiffness: penalty stiffness per contacted particle [N/m].
        contact_damping_ratio: contact dashpot as a fraction of critical for one particle [-].
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
        paper_momentum: momentum equation of the ``paper`` scheme: 14 (the paper's eq. 14,
            default) or 12 (eq. 12, symmetric stiffness at free surfaces); see :mod:`.paper`.
        parallel_min_particles: a ``tlsph`` sub-step runs on numba's thread pool (``prange``,
            ``NUMBA_NUM_THREADS`` threads) when at least this many particles are stressed; 0 (the
            default) never uses threads. Results are bit-identical either way. On an idle 2-core
            machine threads halve the step (3671-particle liver: global 10.1 -> 4.3 ms, local
            0.40 -> 0.23 ms), but when other processes keep the cores busy a parallel region waits
            for a descheduled thread: local p99 went from 0.5 to 4.4 ms with one busy process
            and the median to 32 ms with two. Enable it only where the simulator has cores of its
            own.
        max_tool_speed: the simulated tool follows the requested tool pose at most this fast
            [m/s]: a frame moves its tip, and the far end of a shaft, by at most about
            ``max_tool_speed * dt`` towards the request (a
            tracking glitch or a pose jump of centimetres in one frame would otherwise drive the
            tool through the tissue in one frame and tear the particle lattice apart). A hand on a
            haptic stylus moves well below 1 m/s (the bundled sessions: up to 0.18 m/s).
        far_field: local mode: the still particles next to the solved ones move by this times the
            elastic half-space (Boussinesq) response to the contact force instead of staying at
            rest (0, the default: the paper's still region). Holding them still makes the area
            stiffer than the whole organ; on the 3671-particle liver pressed 2/4/10 mm at four
            places the local force differs from global by -7 ... +24 % with 0 and -14 ... +6 %
            with 1. Off by default because the shell changes as the area moves: dragging the tool
            across a block, the largest frame-to-frame force change is 10 % of Fz with 1 against
            5 % with 0 (global: 4 %).
    """

    scheme: str = 'tlsph'
    mode: str = 'local'
    h_ratio: float = 1.3
    k1_gain: float = 0.5
    k1_min: float = 1.0
    k1_max: float = 6.0
    n_layers: int = 2
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
    paper_momentum: int = 14
    parallel_min_particles: int = 0
    far_field: float = 0.0
    max_tool_speed: float = 1.0

    def validate(self) -> 'SolverConfig':
        """Check ranges; raises :class:`ConfigError` naming the bad field. Returns self."""
        if self.scheme not in SCHEMES:
            raise ConfigError(f'scheme must be one of {SCHEMES}, got {self.scheme!r}')
        if self.mode not in MODES:
            raise ConfigError(f'mode must be one of {MODES}, got {self.mode!r}')
        if self.tool_shape not in TOOLS:
            raise ConfigError(f'tool_shape must be one of {tuple(TOOLS)}, got {self.tool_shape!r}')
        for f in fields(self):
            val = getattr(self, f.name)
            if f.name in ('scheme', 'mode', 'tool_shape'):
                continue
            if not isinstance(val, (int, float)) or isinstance(val, bool) or not math.isfinite(val):
                raise ConfigError(f'{f.name} must be a finite number, got {val!r}')
        positive = ('h_ratio', 'k1_min', 'k1_max', 'tool_radius', 'contact_stiffness', 'force_limit',
                    'cfl', 'relax_disp_tol', 'relax_vel_tol', 'velocity_limit', 'max_tool_distance',
                    'spring_radius', 'contact_particle_radius', 'max_tool_speed')
        for name in positive:
            if getattr(self, name) <= 0.0:
                raise ConfigError(f'{name} must be > 0, got {getattr(self, name)}')
        for name in ('k1_gain', 'contact_damping_ratio', 'hourglass', 'tool_length'):
            if getattr(self, name) < 0.0:
                raise ConfigError(f'{name} must be >= 0, got {getattr(self, name)}')
        if not 0.2 <= self.h_ratio <= 4.0:
            raise ConfigError(f'h_ratio must be in [0.2, 4] particle spacings, got {self.h_ratio}')
        if self.k1_min > self.k1_max:
            raise ConfigError(f'k1_min ({self.k1_min}) must be <= k1_max ({self.k1_max})')
        if int(self.n_layers) != self.n_layers or not 0 <= self.n_layers <= 8:
            raise ConfigError(f'n_layers must be an integer in [0, 8], got {self.n_layers}')
        if int(self.max_substeps) != self.max_substeps or not 1 <= self.max_substeps <= 100000:
            raise ConfigError(f'max_substeps must be an integer in [1, 100000], got {self.max_substeps}')
        if self.cfl > 1.0:
            raise ConfigError(f'cfl must be <= 1, got {self.cfl}')
        if not 0.0 <= self.contact_disc <= 0.5:
            raise ConfigError(f'contact_disc must be in [0, 0.5] spacings, got {self.contact_disc}')
        if not 0.0 <= self.far_field <= 2.0:
            raise ConfigError(f'far_field must be in [0, 2], got {self.far_field}')
        if self.paper_momentum not in (12, 14):
            raise ConfigError(f'paper_momentum must be 12 or 14 (paper eq. 12 or 14), got {self.paper_momentum}')
        if int(self.parallel_min_particles) != self.parallel_min_particles or self.parallel_min_particles < 0:
            raise ConfigError(f'parallel_min_particles must be an integer >= 0, got {self.parallel_min_particles}')
        self.parallel_min_particles = int(self.parallel_min_particles)
        self.paper_momentum = int(self.paper_momentum)
        self.n_layers = int(self.n_layers)
        self.max_substeps = int(self.max_substeps)
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
        self.config = (config or SolverConfig()).validate()
        self.model = model
        self.n = model.n_particles
        self.h = self.config.h_ratio * model.spacing
        self.volume = model.particle_volume
        self.X = np.ascontiguousarray(model.positions, dtype=np.float64)
        self.fixed = np.ascontiguousarray(model.fixed, dtype=np.bool_)
        self.free_idx = np.flatnonzero(~self.fixed).astype(np.int32)
        self.all_idx = np.arange(self.n, dtype=np.int32)
        self.centre = self.X.mean(axis=0)
        cfg = self.config
        self.tool = make_tool(cfg.tool_shape, cfg.tool_radius, cfg.tool_length)
        self.contact_reach = self.tool.radius + cfg.contact_particle_radius * model.spacing
        self.extent = float(np.linalg.norm(self.X.max(axis=0) - self.X.min(axis=0)))
        self._setup_neighbours()
        self._alloc()
        pm = self.config.parallel_min_particles
        self.par_min = pm if pm > 0 and numba.get_num_threads() > 1 else self.n + 1
        self.material = material
        self.set_material(material)
        if self.config.scheme == 'paper':
            self._paper = PaperScheme(self)
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _setup_neighbours(self) -> None:
        support = SUPPORT * self.h
        self.grid = CellGrid(self.X, support)
        self.offsets, self.indices = find_neighbours(self.X, support)
        counts = np.diff(self.offsets)
        if counts.max() == 0:
            raise ConfigError(f'smoothing length h = {self.h:.3g} m is too small: no particle has a '
                              f'neighbour within 2h (spacing {self.model.spacing:.3g} m)')
        self.dw, self.w0, self.Linv = reference_pairs(self.X, self.offsets, self.indices, self.h,
                                                      self.volume)
        self.gv = pair_gradients(self.X, self.offsets, self.indices, self.dw, self.volume)
        self.contact_surf = surface_discs(self.X, self.offsets, self.indices, self.h, self.volume,
                                          self.model.spacing, self.config.contact_disc)
        self.contact_disc = self.contact_surf[-1]
        self.disc_max = float(self.contact_disc.max()) if self.n else 0.0
        # mass-spring: springs to reference neighbours within spring_radius spacings
        s = self.model.spacing
        self.s_offsets, self.s_indices = find_neighbours(self.X, self.config.spring_radius * s * 1.0001)
        rows = np.repeat(np.arange(self.n), np.diff(self.s_offsets))
        self.s_rest = np.linalg.norm(self.X[self.s_indices] - self.X[rows], axis=1)

    def _alloc(self) -> None:
        n = self.n
        self.x = self.X.copy()
        self.v = np.zeros((n, 3))
        self.acc = np.zeros((n, 3))
        self.F = np.zeros((n, 3, 3))
        self.F[:] = np.eye(3)
        self.Fd = np.zeros((n, 3, 3))
        self.A = np.zeros((n, 3, 3))
        self.H = np.zeros((n, 3, 3))
        self.region_arr = np.zeros(n, dtype=np.int8)
        self.in_active = np.zeros(n, dtype=np.int8)
        self.in_area = np.zeros(n, dtype=np.int8)
        self.stamp = np.zeros(n, dtype=np.int64)
        self.stamp_val = 0
        self.active_list = np.zeros(n, dtype=np.int32)
        self.sph_list = np.zeros(n, dtype=np.int32)
        self.layer_list = np.zeros(n, dtype=np.int32)
        self.layer_w = np.zeros(n)
        self.stress_list = np.zeros(n, dtype=np.int32)
        self.cand_list = np.zeros(2 * n, dtype=np.int32)
        self.tmp = np.zeros(n, dtype=np.int32)
        self.buf_x = np.zeros((n, 3))
        self.buf_v = np.zeros((n, 3))
        self.touch_idx = np.zeros(256, dtype=np.int32)
        self.touch_w = np.zeros(256)
        self.n_touch = 0
        self.area_centre = np.zeros(3)
        self.react = np.zeros(3)
        self.fbuf = np.zeros(3)
        self.layer_counts = np.zeros(max(self.config.n_layers, 1), dtype=np.int64)
        self.n_stress_last = 0
        self.ext_idx = np.zeros(0, dtype=np.int32)
        self.ext_force = np.zeros((0, 3))
        # far-field shell (local mode, far_field > 0): allocated on first use
        self.ff_list = np.zeros(0, dtype=np.int32)
        self.n_ff = 0
        self.ff_mark = np.zeros(0, dtype=np.int8)
        self.ff_buf = np.zeros((0, 3))
        self.ff_load = np.zeros(3)
        self.abort = np.zeros(1, dtype=np.int8)   # set by interrupt() from another thread

    def interrupt(self) -> None:
        """Make the step running in another thread stop before its next sub-step (it then raises
        :class:`StepInterrupted` with the state restored), and every later step until
        :meth:`clear_interrupt`. Safe to call from any thread: the frame loops run without the GIL.
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
        self.ext_idx = idx
        self.ext_force = f

    def set_material(self, material: Material) -> None:
        """Change the material (takes effect at the next step; sub-step bounds are recomputed)."""
        if not isinstance(material, Material):
            raise ConfigError(f'material must be a Material, got {type(material).__name__}')
        self.material = material
        cfg = self.config
        self.mass = material.rho * self.volume
        self.inv_mass = 1.0 / self.mass
        self.contact_damping = cfg.contact_damping_ratio * 2.0 * math.sqrt(cfg.contact_stiffness * self.mass)
        s = self.model.spacing
        # mass-spring stiffness calibrated on a cubic lattice (face + edge springs, k_d = k_f / 2):
        # E = 1.8 k_f / s; other lengths scale as (s / L0)^2
        self.s_k = material.E * s / 1.8 * (s / np.maximum(self.s_rest, 1e-12)) ** 2
        vol2 = self.volume ** 2
        self.hg_k = cfg.hourglass * material.E * vol2
        # the hourglass dashpot uses the viscous analogue of E (9 eta_b eta_s / (3 eta_b + eta_s)),
        # so hourglass bonds creep with the material's own retardation time (eta_longitudinal
        # would give them (K + 4G/3)/E times that and slow the creep of non-linear fields)
        eta_s, eta_b = material.eta_shear, material.eta_bulk
        eta_e = 9.0 * eta_b * eta_s / (3.0 * eta_b + eta_s) if eta_b + eta_s > 0.0 else 0.0
        self.hg_c = cfg.hourglass * eta_e * vol2
        c = material.wave_speed
        if cfg.scheme == 'mass_spring':
            kmax = float(np.max(np.add.reduceat(self.s_k, self.s_offsets[:-1]))) if len(self.s_k) else 0.0
            c = max(c, math.sqrt(max(kmax, 1e-30) / self.mass) * s)
        self.dt_bounds = substep_bounds(self.h, c, material.rho, material.eta_longitudinal,
                                        self.mass, cfg.contact_stiffness, cfg.cfl)
        if cfg.contact_damping_ratio > 0.0:
            # explicit dashpot: dt < 2 m / c; keep a factor 2 margin
            self.dt_bounds['contact_damping'] = self.mass / self.contact_damping
        self.dt_max = min(self.dt_bounds.values())
        # without a tool no contact spring or dashpot acts, so only the material bounds apply
        self.dt_max_free = min(v for k, v in self.dt_bounds.items() if not k.startswith('contact'))

    def reset(self) -> None:
        """Back to the reference configuration at rest, sim time 0, no active area."""
        self.x[:] = self.X
        self.v[:] = 0.0
        self.acc[:] = 0.0
        self.F[:] = np.eye(3)
        self.Fd[:] = 0.0
        self.A[:] = 0.0
        self.H[:] = 0.0
        self.region_arr[:] = 0
        self.in_active[:] = 0
        self.in_area[:] = 0
        self.n_active = 0
        self.n_ff = 0
        self.sim_time = 0.0
        self.f_prev = 0.0
        self.tool_prev: np.ndarray | None = None     # the tip position [m] of the previous frame
        self.seg_prev: np.ndarray | None = None      # and the tool's segment (2, 3)
        self.last_result: StepResult | None = None
        self.n_stress_last = 0
        if self.config.mode == 'global':
            self.region_arr[self.free_idx] = 1
        if hasattr(self, '_paper'):
            self._paper.reset()

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
        return self.region_arr

    @property
    def n_particles(self) -> int:
        return self.n

    @property
    def smoothing_length(self) -> float:
        return self.h

    def displacement(self) -> np.ndarray:
        """(N,) displacement norms |x - X| [m]."""
        return np.linalg.norm(self.x - self.X, axis=1)

    def von_mises(self) -> np.ndarray:
        """(N,) von Mises stress [Pa] of the last computed stress state (0 where none was computed)."""
        out = np.zeros(self.n)
        m = self.material
        if self.config.scheme == 'tlsph':
            if self.config.mode == 'global':
                idx, n = self.all_idx, self.n
            else:
                idx, n = self.stress_list, self.n_stress_last
            tlsph_von_mises(self.F, self.Fd, m.G, m.K, m.eta_shear, m.eta_bulk, idx, n, out)
        elif self.config.scheme == 'paper' and hasattr(self, '_paper'):
            out[:] = self._paper.von_mises()
        else:
            # mass-spring: a strain measure from the neighbour displacement field times E
            d = self.x - self.X
            rows = np.repeat(np.arange(self.n), np.diff(self.s_offsets))
            strain = np.abs(np.linalg.norm(self.x[self.s_indices] - self.x[rows], axis=1) / self.s_rest - 1.0)
            out[:] = m.E * np.maximum.reduceat(strain, self.s_offsets[:-1]) if len(strain) else 0.0
            del d
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
        n_sub, sub_dt, capped = substeps_for(dt, self.dt_max if tool_on else self.dt_max_free,
                                             cfg.max_substeps)
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
        reach = self.contact_reach
        if cfg.mode == 'global':
            res = self._global_step(seg0, seg1, tool_on, reach, n_sub, sub_dt, dt)
        else:
            res = self._local_step(seg0, seg1, tool_on, reach, n_sub, sub_dt, dt)
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

    def _scheme_arrays(self):
        if self.config.scheme == 'mass_spring':
            return SCHEME_MASS_SPRING, self.s_offsets, self.s_indices, self.s_k, self.s_rest
        return SCHEME_TLSPH, self.offsets, self.indices, self.dw, self.w0

    def _run(self, lists, seg0, seg1, tool_on, reach, contact, n_sub, sub_dt, dt):
        """One frame on the index sets ``lists``; returns ``(overlap, ok)``.

        ``ok`` is False when the frame left a non-finite or too fast particle or a non-finite
        reaction (checked outside the fast-math kernels, see :func:`~.integrate.frame_state_ok`).
        """
        (stress, n_stress, sph, n_sph, layer, layer_w, n_lp, cand, n_cand) = lists
        if self.config.scheme == 'paper':
            overlap, ok = self._paper.run(lists, seg0, seg1, tool_on, reach, contact, n_sub, sub_dt, dt)
        else:
            m = self.material
            sid, off, idx, dw, w0 = self._scheme_arrays()
            overlap = run_frame(
                sid, self.X, self.x, self.v, self.acc, self.fixed, self.inv_mass, self.volume,
                off, idx, dw, w0, self.Linv, self.F, self.Fd, self.A, self.H, self.gv,
                m.G, m.K, m.eta_shear, m.eta_bulk, self.hg_k, self.hg_c, m.retardation_time,
                stress, n_stress, sph, n_sph, layer, layer_w, n_lp, cand, n_cand, contact,
                seg0, seg1, tool_on, reach, self.config.contact_stiffness, self.contact_damping,
                n_sub, sub_dt, dt, self.react, self.fbuf,
                self.ext_idx, self.ext_force, len(self.ext_idx), self.contact_surf,
                self.touch_idx, self.touch_w, self.n_touch, self.par_min, self.abort)
            ok = True
        ok = ok and frame_state_ok(self.x, self.v, sph, n_sph, layer, n_lp, self.config.velocity_limit,
                                   self.react)
        return overlap, ok and self.abort[0] == 0

    def _frame_error(self, mode: str) -> SimError:
        """The error of a frame that did not finish (its state was restored by the caller)."""
        if self.abort[0] != 0:
            return StepInterrupted(f'{self.config.scheme} {mode} step interrupted; state restored')
        return SimError(f'{self.config.scheme} {mode} step went unstable (non-finite or speed > '
                        f'{self.config.velocity_limit} m/s); state restored')

    def _global_step(self, seg0, seg1, tool_on, reach, n_sub, sub_dt, dt) -> dict:
        contact = self._sticky_contact(seg1, reach) if tool_on else -1
        if tool_on and contact < 0:
            contact = deepest_contact(self.x, self.all_idx, self.n, seg1, reach, self.contact_surf)
        self.buf_x[:] = self.x
        self.buf_v[:] = self.v
        lists = (self.all_idx, self.n, self.free_idx, len(self.free_idx), self.layer_list, self.layer_w, 0,
                 self.all_idx, self.n)
        overlap, ok = self._run(lists, seg0, seg1, tool_on, reach, contact, n_sub, sub_dt, dt)
        if not ok:
            self.x[:] = self.buf_x
            self.v[:] = self.buf_v
            self.react[:] = 0.0
            raise self._frame_error('global')
        md, ke = active_stats(self.x, self.X, self.v, self.free_idx, len(self.free_idx), self.mass)
        self.n_stress_last = self.n
        return dict(contact_index=int(contact), penetration=float(max(overlap, 0.0)),
                    n_interaction=len(self.free_idx), n_layer=np.zeros(self.config.n_layers, dtype=np.int64),
                    n_relaxing=0, max_displacement=float(md), kinetic_energy=float(ke), k1=0.0,
                    n_active=len(self.free_idx))

    def _local_step(self, seg0, seg1, tool_on, reach, n_sub, sub_dt, dt) -> dict:
        cfg = self.config
        g = self.grid
        margin = cfg.relax_disp_tol
        self.n_touch = 0
        if tool_on:
            deepest, self.n_touch = detect_local(
                self.X, self.x, self.active_list, self.n_active, g.origin, g.cell, g.dims,
                g.cell_start, g.cell_particles, seg1, reach, margin, self.tmp, self.contact_surf,
                self.touch_idx, self.touch_w, self.area_centre)
            contact = self._sticky_contact(seg1, reach)
            if contact < 0:
                contact = deepest
        if tool_on:
            # candidates: every particle the tool can reach anywhere on its way through the frame
            # (scalar maths: numpy's per-call overhead on 4 points is a few per cent of a local step)
            ends = seg0.tolist() + seg1.tolist()
            c = [0.25 * (ends[0][a] + ends[1][a]) + 0.25 * (ends[2][a] + ends[3][a]) for a in range(3)]
            cand_centre = np.array(c)
            cand_radius = (max(math.dist(e, c) for e in ends) + reach + self.disc_max + margin)
        else:
            contact = -1
            cand_centre = self.centre
            cand_radius = -1.0
        k1 = min(max(cfg.k1_gain * self.f_prev, cfg.k1_min), cfg.k1_max)
        Dr = k1 * self.h
        if cfg.scheme == 'paper':
            # the paper's area: around the contact particle (sec. 4.2), Dr from that point
            if contact >= 0:
                self.area_centre[:] = self.X[contact]
        elif self.n_touch > 0:
            # around the overlap-weighted centroid of the touched particles (moves continuously
            # when the deepest particle changes), with Dr measured from the edge of the touched
            # patch (surface discs included) so a load spread over several particles is inside
            ti = self.touch_idx[:self.n_touch]
            d = self.X[ti] - self.area_centre
            Dr += float((np.sqrt((d * d).sum(axis=1)) + self.contact_disc[ti]).max())
        self.stamp_val += 1
        (self.n_active, n_sph, n_lp, n_stress, n_cand, n_inter, n_relax) = local_prepare(
            self.X, self.x, self.fixed, self.offsets, self.indices,
            g.origin, g.cell, g.dims, g.cell_start, g.cell_particles,
            self.in_active, self.active_list, self.n_active, self.region_arr, self.in_area,
            self.stamp, self.stamp_val, contact, self.area_centre, Dr, 0.5 * self.h, cfg.n_layers,
            cand_centre, cand_radius, self.sph_list, self.layer_list, self.layer_w, self.stress_list,
            self.cand_list, self.tmp, self.layer_counts)
        if cfg.far_field > 0.0 or self.n_ff:
            # the load on the tissue is the reaction on the tool reversed (previous frame's, as k1)
            np.multiply(self.react, -cfg.far_field, out=self.ff_load)
            if len(self.ff_list) != self.n:
                self.ff_list = np.zeros(self.n, dtype=np.int32)
                self.ff_mark = np.zeros(self.n, dtype=np.int8)
                self.ff_buf = np.zeros((self.n, 3))
            self.n_ff = far_field_shell(
                self.X, self.x, self.fixed, self.stress_list, n_stress, self.sph_list, n_sph,
                self.layer_list, n_lp, self.ff_mark, self.ff_list, self.n_ff, self.area_centre,
                self.ff_load, self.material.G, self.material.nu, self.buf_x, self.ff_buf)
        save_state(self.x, self.v, self.sph_list, n_sph, self.layer_list, n_lp, self.buf_x, self.buf_v)
        lists = (self.stress_list, n_stress, self.sph_list, n_sph, self.layer_list, self.layer_w, n_lp,
                 self.cand_list, n_cand)
        overlap, ok = self._run(lists, seg0, seg1, tool_on, reach, contact, n_sub, sub_dt, dt)
        if not ok:
            restore_state(self.x, self.v, self.sph_list, n_sph, self.layer_list, n_lp, self.buf_x, self.buf_v)
            self.react[:] = 0.0
            raise self._frame_error('local')
        self.n_stress_last = n_stress
        n_active_frame = self.n_active
        md, ke = active_stats(self.x, self.X, self.v, self.active_list, self.n_active, self.mass)
        self.n_active = local_release(self.X, self.x, self.v, self.in_active, self.active_list, self.n_active,
                                      self.region_arr, self.in_area, cfg.relax_disp_tol, cfg.relax_vel_tol)
        return dict(contact_index=int(contact), penetration=float(max(overlap, 0.0)),
                    n_interaction=int(n_inter), n_layer=self.layer_counts[:cfg.n_layers].copy(),
                    n_relaxing=int(n_relax), max_displacement=float(md), kinetic_energy=float(ke),
                    k1=float(k1), n_active=int(n_active_frame))


def warmup(scheme: str | None = None) -> float:
    """Compile every numba kernel on a tiny block (numba caches to disk); returns seconds taken."""
    from .models import make_block

    t0 = time.perf_counter()
    schemes = SCHEMES if scheme is None else (scheme,)
    model = make_block(4, 4, 4, spacing=0.005)
    mat = Material.from_shear(1800.0, 0.45, 3.0)
    for sch in schemes:
        for mode in MODES:
            try:
                solver = Solver(model, mat, SolverConfig(scheme=sch, mode=mode))
            except ConfigError:
                continue
            top = model.positions[:, 2].max()
            for k in range(3):
                try:
                    solver.step(np.array([0.01, 0.01, top + 0.005 - 0.001 * k]), 1e-3)
                except ConfigError:
                    break
            solver.von_mises()
    return time.perf_counter() - t0
