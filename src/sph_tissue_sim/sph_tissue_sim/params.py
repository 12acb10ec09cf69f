"""Parameters of sim_node in one place (descriptors, ranges) and the builders that turn them into
core objects (model, material, solver settings, device mapping).

Each table entry: name -> (default, description, range or choices or None, read_only, rebuild).
Numeric ranges become FloatingPointRange / IntegerRange on the descriptor (rclpy enforces them at
start-up and on every set); string choices are checked at start-up and by the node's
set-parameters callback. ``rebuild`` says what a run-time change needs: ``None`` (applied at the next
step), ``'material'`` (material swapped between steps), ``'solver'`` (solver rebuilt between steps,
the tissue returns to rest), ``'mapping'`` (device map rebuilt). Read-only parameters need a restart.

The builders import no rclpy, so they are tested without ROS.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from tissue_common.force import HARD_FORCE_LIMIT
from tissue_common.params import check_choice

from .core.errors import ConfigError, ModelError
from .core.material import Material, load_material
from .core.factory import MODELS, make_model
from .core.models import TissueModel
from .core.solver import (CONTACT_INTEGRATIONS, FAR_FIELD_MODELS, INTEGRATORS, MODES, SCHEMES, SolverConfig)
from .core.tools import TOOLS
from .haptics.renderer import RENDERER_RANGES, RendererConfig
from .mapping import ANCHORS, DEFAULT_ROTATION

TIMING_MODES = ('live', 'lockstep')
HAPTIC_MODES = ('multirate', 'direct')

# name: (default, description, range/choices, read_only, rebuild)
SIM_PARAMS: dict[str, tuple[Any, str, Any, bool, str | None]] = {
    # -- model ------------------------------------------------------------------------------------
    'model': ('liver', 'tissue body: liver | block | beam | mesh (mesh_path)', MODELS, True, None),
    'mesh_path': ('', 'model mesh: surface mesh file sampled into particles', None, True, None),
    'n_particles': (3670, 'particle count (the lattice spacing is chosen to give about this many)',
                    (8, 2_000_000), True, None),
    'block_size': ([0.08, 0.08, 0.04], '[m] model block: x, y, z extent (bottom layer fixed)', None,
                   True, None),
    'beam_size': ([0.1, 0.02, 0.02], '[m] model beam: length (x), width, height (x=0 end clamped)',
                  None, True, None),
    # -- material ---------------------------------------------------------------------------------
    'material': ('liver', 'name in materials_file, or "custom" for E, nu, eta_shear, eta_bulk, rho',
                 None, False, 'material'),
    'materials_file': ('', 'material presets YAML ("" = the package config/materials.yaml)', None,
                       False, 'material'),
    'E': (5220.0, '[Pa] custom material: Young modulus', (1.0, 1e9), False, 'material'),
    'nu': (0.45, '[-] custom material: Poisson ratio', (0.0, 0.4999), False, 'material'),
    'eta_shear': (3.0, '[Pa s] custom material: shear viscosity', (0.0, 1e6), False, 'material'),
    'eta_bulk': (-1.0, '[Pa s] custom material: bulk viscosity (-1 = same retardation time as the '
                       'shear part)', (-1.0, 1e6), False, 'material'),
    'rho': (1060.0, '[kg/m^3] custom material: density', (1.0, 1e5), False, 'material'),
    # -- solver -----------------------------------------------------------------------------------
    'scheme': ('tlsph', 'paper | tlsph | mass_spring', SCHEMES, False, 'solver'),
    'mode': ('local', 'global (every particle) | local (dynamic local interaction area)', MODES,
             False, 'solver'),
    'h_ratio': (1.3, 'smoothing length h / particle spacing (support 2h)', (0.2, 4.0), False,
                'solver'),
    'k1_gain': (0.5, '[1/N] k1 = k1_gain * f_ext (paper eq. 18: 0.5); Dr = k1 h', (0.0, 100.0),
                False, 'solver'),
    'k1_min': (1.75, 'lower clamp of k1 (keeps the area non-empty without force)', (0.01, 100.0),
               False, 'solver'),
    'k1_max': (6.0, 'upper clamp of k1', (0.01, 100.0), False, 'solver'),
    'n_layers': (1, 'transmission layers N (paper eqs. 20-21)', (0, 8), False, 'solver'),
    'tool_shape': ('sphere', 'sphere (a probe tip at the stylus tip) | capsule (a shaft of tool_length '
                             'from the stylus tip along the stylus axis, rounded at both ends)',
                   tuple(TOOLS), False, 'solver'),
    'tool_radius': (0.005, '[m] radius of the sphere, or of the capsule shaft', (1e-4, 0.05), False,
                    'solver'),
    'tool_length': (0.05, '[m] capsule shaft length (tool_shape capsule)', (0.0, 0.3), False,
                    'solver'),
    'contact_stiffness': (300.0, '[N/m] penalty stiffness per contacted particle (per surface sample '
                                 'with contact_samples)', (1.0, 1e5), False, 'solver'),
    'contact_damping_ratio': (1.0, '[-] contact dashpot as a fraction of critical', (0.0, 10.0),
                              False, 'solver'),
    'cfl': (0.3, '[-] Courant number of the sub-step bounds', (0.01, 1.0), False, 'solver'),
    'max_substeps': (64, 'sub-step cap per frame (beyond it simulated time lags; reported)',
                     (1, 100000), False, 'solver'),
    'contact_disc': (0.0, 'surface-disc contact radius in spacings: 0 = particles are balls; 0.5 keeps '
                          'a pressed surface particle under a small tool (no sideways slip) but '
                          'spreads the load (local mode then needs k1_min >= 3)', (0.0, 0.5), False,
                     'solver'),
    'contact_samples': (3, 'contact with the material surface: this many samples per side of a '
                           'surface particle\'s patch (0 = the tool touches particle balls alone and '
                           'slips between them: the liver gives way near 10 mm); 3 stops the tool '
                           'slipping between particles (the tool meets the balls first; the samples '
                           'hold it out of the gaps: the force rises to the 3.3 N limit near 30 mm on '
                           'the 3670 liver) at about 4x the sub-steps '
                           'unless contact_integration is implicit', (0, 5), False, 'solver'),
    'contact_integration': ('implicit', 'contact springs and dashpots: explicit (sub-step bounded by '
                                        'the penalty) | implicit (backward along the normals: no contact '
                                        'bound; contact_samples 3 then costs 2 sub-steps, not 8)',
                            CONTACT_INTEGRATIONS, False, 'solver'),
    'integrator': ('explicit', 'explicit (symplectic Euler, sub-steps bounded by the CFL, viscous and '
                               'contact bounds) | implicit (tlsph: backward Euler on the spring, dashpots '
                               'and contacts, one solve per sub-step, stable at any sub-step: for large '
                               'frames, e.g. 16 ms visual ones)', INTEGRATORS, False, 'solver'),
    'implicit_max_dt': (0.016, '[s] implicit integrator: largest sub-step', (1e-5, 1.0), False, 'solver'),
    'implicit_tol': (0.01, 'implicit integrator: the solve stops at this velocity error relative to the '
                           'velocities', (1e-9, 0.1), False, 'solver'),
    'far_field': (1.0, 'local mode: still particles next to the solved ones follow this times the '
                       'far field model\'s response to the contact force (1, the default: the organ\'s '
                       'own response; with the half-space 0.9 suits the balls on the liver, an organ '
                       'on a fixed base being stiffer than a half-space); 0 = held still as in the '
                       'paper (stiffer than the whole organ, up to +24 %)',
                  (0.0, 2.0), False,
                  'solver'),
    'far_field_model': ('auto', 'local mode: what moves the still particles next to the solved ones: '
                                      'auto (organ for tlsph models of up to 5000 free particles, else '
                                      'half_space) | half_space (Boussinesq, far_field times it) | organ (the organ\'s own '
                                      'linear response, factored at start: 3670 liver about 5 s and 0.8 GB at '
                                      'its peak, then about 45 ms per response solved; with far_field 1 and the '
                                      'backstop samples no wider area: local within 5 % of global at 12 of 12 '
                                      'presses)', FAR_FIELD_MODELS, False, 'solver'),
    'far_field_background': (True, 'far_field_model organ: solve a touched particle\'s response on a worker '
                                   'thread instead of in the frame that first needs it (about 45 ms each on '
                                   'the 3670 liver, a few per touch on new ground); meanwhile the load is '
                                   'shared by the touched particles whose responses are ready. Not repeatable '
                                   'bit for bit, so timing_mode lockstep always waits', None, False, 'solver'),
    'parallel_min_particles': (0, 'tlsph: use numba threads (NUMBA_NUM_THREADS) when at least this '
                                  'many particles are stressed; 0 = never. Only on cores the sim '
                                  'has to itself: a busy core stalls every parallel sub-step',
                               (0, 10_000_000), False, 'solver'),
    'max_tool_speed': (1.0, '[m/s] the simulated tool (its tip, and a shaft\'s far end) follows the '
                            'device at most this fast (a pose jump of centimetres in one frame would '
                            'tear the tissue apart); a hand on the stylus stays well below 1 m/s',
                       (0.01, 10.0), False, None),
    'friction': (0.0, 'Coulomb coefficient of stick-slip friction between the tool and the touched '
                      'particles (0 = frictionless): the tool carries the tissue it presses instead of '
                      'letting it slide round it (0.3 on the liver: the pressed surface moves 0.1 mm '
                      'sideways instead of 3.3 mm at 10 mm, no dip near 18 mm; the shallow press '
                      'stiffer)', (0.0, 2.0), False, None),
    # -- force ------------------------------------------------------------------------------------
    'force_limit': (HARD_FORCE_LIMIT, f'[N] norm clamp of the force sent to the device (Omni peak '
                                      f'{HARD_FORCE_LIMIT} N, continuous 0.88 N)',
                    (0.001, HARD_FORCE_LIMIT), False, None),
    'force_scale': (1.0, 'device force = force_scale * tissue force (use workspace_scale for an '
                         'energy-consistent scaled workspace)', (0.001, 100.0), False, None),
    # -- haptic rendering (sph_tissue_sim.haptics) ------------------------------------------------
    'haptic_mode': ('multirate', 'multirate (each pose answered at once by the haptic renderer: '
                                 'velocity filter, virtual coupling, passivity control; the solver '
                                 'refreshes its contact model at its own rate) | direct (one solver '
                                 'step per pose, its reaction sent as is)', HAPTIC_MODES, True, None),
    'solver_every': (1, 'multirate, lockstep: the solver steps after every n-th pose, in order (live: '
                        'a solver thread steps as fast as it can)', (1, 1000), False, None),
    'solver_nice': (10, 'multirate live: the solver thread runs this much nicer than the thread '
                        'answering the poses (Linux thread priority; 0 = the same), so a solver '
                        'that fills a core never delays an answer', (0, 19), True, None),
    'velocity_cutoff': (RendererConfig.velocity_cutoff, '[Hz] cut-off of the position/velocity '
                        'filter of the encoder-quantised device positions (lower is smoother, '
                        'laggier)', RENDERER_RANGES['velocity_cutoff'], False, 'renderer'),
    'coupling_stiffness': (RendererConfig.coupling_stiffness, '[N/m] virtual coupling spring between '
                           'the device and the simulated tool: the stiffest the hand can feel (an '
                           'Omni renders about 700; times force_scale / workspace_scale at the '
                           'device)', RENDERER_RANGES['coupling_stiffness'], False, 'renderer'),
    'coupling_damping': (RendererConfig.coupling_damping, '[N s/m] damper on the device\'s normal '
                         'velocity in contact (passive above coupling_stiffness * period / 2)',
                         RENDERER_RANGES['coupling_damping'], False, 'renderer'),
    'proxy_damping': (RendererConfig.proxy_damping, '[N s/m] damper of the simulated tool to the '
                      'world (keeps the loop through the solver stable; the tool lags the device by '
                      'proxy_damping / coupling_stiffness)', RENDERER_RANGES['proxy_damping'], False,
                      'renderer'),
    'passivity_max_damping': (RendererConfig.passivity_max_damping, '[N s/m] the most damping the '
                              'passivity controller may add when the energy at the device port '
                              'goes negative', RENDERER_RANGES['passivity_max_damping'], False,
                              'renderer'),
    # -- device -> tissue -------------------------------------------------------------------------
    'device_frame': ('omni_base', 'frame of accepted poses (and of the force replies)', None, False,
                     None),
    'accept_empty_frame': (True, 'accept poses with an empty frame_id as device frame', None, False,
                           None),
    'tissue_frame': ('tissue', 'frame of tissue/particles and tissue/metrics', None, True, None),
    'rotation': (list(DEFAULT_ROTATION), 'device -> tissue rotation quaternion [x, y, z, w] '
                                         '(default: +90 deg about x, device y-up -> tissue z-up)',
                 None, False, 'mapping'),
    'translation': ([0.0, 0.0, 0.0], '[m] tissue-frame offset added after the anchor', None, False,
                    'mapping'),
    'anchor': ('top_contact', 'tissue point of the device origin: top_contact (tool just touching '
                              'the top surface above the model centre) | top_surface | centre | '
                              'origin', ANCHORS, False, 'mapping'),
    'workspace_scale': (1.0, 'tissue displacement per device displacement', (0.01, 100.0), False,
                        'mapping'),
    'max_device_distance': (1.0, '[m] poses farther than this from the device origin are rejected '
                                 '(an Omni workspace is ~0.16 m)', (0.001, 100.0), False, None),
    # -- timing -----------------------------------------------------------------------------------
    'timing_mode': ('live', 'live (newest pose only, never a backlog) | lockstep (every pose in '
                            'order, reliable deep queue; bit-identical replays)', TIMING_MODES, True,
                    None),
    'step_thread': (True, 'step in a worker thread fed by an inbox (live: only the newest pose is '
                          'kept; lockstep: a FIFO), so reset and parameter services never wait for '
                          'a step; false: the subscription callback steps',
                    None, True, None),
    'nominal_dt': (0.001, '[s] step of the first pose and of a pose whose stamp went backwards',
                   (1e-5, 0.1), False, None),
    'max_dt': (0.02, '[s] largest frame step; longer stamp gaps are clamped to it', (1e-4, 1.0),
               False, None),
    'lockstep_queue_limit': (100000, 'lockstep: queued poses beyond this are dropped (oldest first, '
                                     'logged)', (10, 10_000_000), True, None),
    # -- output -----------------------------------------------------------------------------------
    'particles_rate': (30.0, '[Hz] tissue/particles rate (0 = off)', (0.0, 1000.0), False, None),
    'metrics_decimation': (1, 'publish tissue/metrics every n-th step', (1, 100000), False, None),
    'reliable': (False, 'reliable QoS on omni/pose and omni/force_feedback (lockstep: always)', None,
                 True, None),
    'qos_depth': (1, 'history depth of omni/pose and omni/force_feedback (multirate live: at least '
                  '10; lockstep: at least 1000)',
                  (1, 100000), True, None),
    'warmup': (True, 'compile the numba kernels before reporting ready', None, True, None),
    'log_throttle': (1.0, '[s] at most one log line per kind of bad input in this period',
                     (0.0, 3600.0), False, None),
}


def check_value(name: str, value, table: dict = SIM_PARAMS) -> str | None:
    """Error text if ``value`` is not one of the string choices of ``name`` or a bad vector."""
    choice = check_choice(table, name, value)
    if choice:
        return choice
    default = table[name][0]
    if isinstance(default, list):
        try:
            arr = np.asarray(list(value), dtype=np.float64)
        except (TypeError, ValueError):
            return f'parameter {name} must be a list of {len(default)} numbers, got {value!r}'
        if arr.shape != (len(default),) or not np.all(np.isfinite(arr)):
            return f'parameter {name} must be {len(default)} finite numbers, got {list(value)!r}'
    return None


# -- builders (no rclpy) ----------------------------------------------------------------------------
def build_model(p: dict) -> TissueModel:
    """The tissue model selected by the parameters (:func:`~.core.factory.make_model`).

    Raises:
        ConfigError: bad size parameters.
        ModelError: the model cannot be built (mesh missing or unreadable, bad particle count).
    """
    kind, n = p['model'], int(p['n_particles'])
    if kind in ('block', 'beam'):
        return make_model(kind, size=p[f'{kind}_size'], n_particles=n)
    if kind == 'liver':
        return make_model('liver', n_particles=n)
    if kind == 'mesh':
        path = str(p['mesh_path'])
        if not path:
            raise ConfigError('model mesh needs mesh_path (a surface mesh file)')
        if not Path(path).is_file():
            raise ModelError(f'mesh file not found: {path}')
        try:
            return make_model('mesh', path=path, n_particles=n)
        except ImportError as exc:
            raise ModelError(f'model mesh is not available in this build: {exc}') from exc
    raise ConfigError(f'parameter model must be one of {", ".join(MODELS)}, got {kind!r}')


def default_materials_file() -> Path | None:
    """The installed ``share/sph_tissue_sim/config/materials.yaml`` (None: use the core default)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        path = Path(get_package_share_directory('sph_tissue_sim')) / 'config' / 'materials.yaml'
        return path if path.is_file() else None
    except Exception:  # noqa: BLE001  (no ament index: the core's source-tree default applies)
        return None


def build_material(p: dict) -> Material:
    """The material selected by the parameters (raises ConfigError)."""
    name = str(p['material'])
    if name == 'custom':
        E, nu, eta_s, eta_b, rho = (float(p[k]) for k in ('E', 'nu', 'eta_shear', 'eta_bulk', 'rho'))
        if eta_b < 0.0:
            G = E / (2.0 * (1.0 + nu))
            K = E / (3.0 * (1.0 - 2.0 * nu))
            eta_b = K * eta_s / G
        return Material(E, nu, eta_s, eta_b, rho, 'custom')
    path = p.get('materials_file') or default_materials_file()
    return load_material(path, name)


def build_config(p: dict) -> SolverConfig:
    """Validated solver settings from the parameters (raises ConfigError)."""
    cfg = SolverConfig(scheme=p['scheme'], mode=p['mode'], h_ratio=float(p['h_ratio']),
                       k1_gain=float(p['k1_gain']), k1_min=float(p['k1_min']),
                       k1_max=float(p['k1_max']), n_layers=int(p['n_layers']),
                       tool_shape=p['tool_shape'], tool_radius=float(p['tool_radius']),
                       tool_length=float(p['tool_length']),
                       contact_stiffness=float(p['contact_stiffness']),
                       contact_damping_ratio=float(p['contact_damping_ratio']),
                       force_limit=float(p['force_limit']), cfl=float(p['cfl']),
                       max_substeps=int(p['max_substeps']),
                       parallel_min_particles=int(p['parallel_min_particles']),
                       contact_disc=float(p['contact_disc']),
                       contact_samples=int(p['contact_samples']),
                       far_field=float(p['far_field']), far_field_model=p['far_field_model'],
                       far_field_background=bool(p['far_field_background']) and p['timing_mode'] != 'lockstep',
                       max_tool_speed=float(p['max_tool_speed']), friction=float(p['friction']),
                       contact_integration=p['contact_integration'],
                       integrator=p['integrator'], implicit_max_dt=float(p['implicit_max_dt']),
                       implicit_tol=float(p['implicit_tol']))
    cfg.validate()
    if not p['max_dt'] >= p['nominal_dt']:
        raise ConfigError(f'max_dt ({p["max_dt"]}) must be >= nominal_dt ({p["nominal_dt"]})')
    if not math.isfinite(p['force_limit']) or p['force_limit'] > HARD_FORCE_LIMIT:
        raise ConfigError(f'force_limit must be <= {HARD_FORCE_LIMIT} N, got {p["force_limit"]}')
    return cfg


def build_renderer(p: dict) -> RendererConfig:
    """Haptic renderer settings from the parameters (raises ConfigError). Its force limit is the
    device's in tissue units, so the renderer's passivity accounting holds what is sent."""
    try:
        return RendererConfig(velocity_cutoff=float(p['velocity_cutoff']),
                              coupling_stiffness=float(p['coupling_stiffness']),
                              coupling_damping=float(p['coupling_damping']),
                              proxy_damping=float(p['proxy_damping']),
                              passivity_max_damping=float(p['passivity_max_damping']),
                              force_limit=float(p['force_limit']) / float(p['force_scale'])).validate()
    except ValueError as exc:
        raise ConfigError(f'haptic renderer: {exc}') from exc
