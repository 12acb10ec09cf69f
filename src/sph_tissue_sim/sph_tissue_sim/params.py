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

from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
from tissue_common.instruments import check_instruments
from tissue_common.params import check_choice, choices_text

from .core.errors import ConfigError, ModelError
from .core.material import Material, load_material
from .core.factory import MODELS, make_model
from .core.models import TissueModel
from .core.solver import SolverConfig
from .haptics.renderer import RENDERER_RANGES, RendererConfig
from .mapping import ANCHORS, DEFAULT_ROTATION

TIMING_MODES = ('live', 'lockstep')
HAPTIC_MODES = ('multirate', 'direct')
#: what closes an instrument's jaw: nothing, a stylus button (omni/state), the CRTK jaw
GRASP_INPUTS = ('', 'button1', 'button2', 'jaw')
#: [rad] the most a jaw/measured_js angle reads closed: the driver sends 0 for a closed jaw, and a
#: CRTK client's jaw that closes on tissue may stop a few degrees short of it
JAW_CLOSED_MAX = 0.1


def solver_params() -> dict[str, tuple[Any, str, Any, bool, str | None]]:
    """The :class:`SolverConfig` fields sim_node declares, as table entries written from the fields'
    own default, doc, limits and rebuild (:func:`~.core.solver.setting`): one source."""
    return {f.name: (f.default, f.metadata['doc'], f.metadata['limits'], False, f.metadata['rebuild'])
            for f in fields(SolverConfig) if f.metadata['node']}


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
    'toughness': (200.0, '[J/m^2] custom material: fracture toughness G_c, the work a blade pays per unit '
                         'area of the crack it opens (a named material has its own in materials_file)',
                  (1.0, 1e5), False, 'material'),
    # -- solver: every SolverConfig field sim_node declares, from its metadata ----------------------
    **solver_params(),
    # -- force ------------------------------------------------------------------------------------
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
    'coupling_damping': (RendererConfig.coupling_damping, '[N s/m] damper on the device\'s velocity '
                         'along the coupling spring in contact (passive above coupling_stiffness * period / 2)',
                         RENDERER_RANGES['coupling_damping'], False, 'renderer'),
    'proxy_damping': (RendererConfig.proxy_damping, '[N s/m] damper of the simulated tool to the '
                      'world (keeps the loop through the solver stable; the tool lags the device by '
                      'proxy_damping / coupling_stiffness)', RENDERER_RANGES['proxy_damping'], False,
                      'renderer'),
    'passivity_max_damping': (RendererConfig.passivity_max_damping, '[N s/m] the most damping the '
                              'passivity controller may add when the energy at the device port '
                              'goes negative', RENDERER_RANGES['passivity_max_damping'], False,
                              'renderer'),
    'energy_bound_stiffness': (RendererConfig.energy_bound_stiffness, '[N/m] live timing: the force '
                               'never gives back more than a spring this stiff would from the energy '
                               'the hand put in (a late solver is felt softer, not '
                               'active; stiffer tissue is felt this stiff)',
                               RENDERER_RANGES['energy_bound_stiffness'], False, 'renderer'),
    # -- instruments ------------------------------------------------------------------------------
    'instruments': ([''], 'the instruments on the tissue, each name a namespace of its own omni/pose, '
                          'omni/force_feedback, grasp input (grasp_input) and tissue/metrics ([""]: '
                          'one, no namespace); several need haptic_mode multirate',
                    None, True, None),
    'grasp_input': ('button1', 'what closes the instrument\'s jaw on the tissue in reach: button1 | button2 '
                        '(that stylus button, omni/state DeviceState) | jaw (the CRTK omni/jaw/measured_js: '
                        f'closed at most {JAW_CLOSED_MAX:g} rad) | \'\' off (the jaw never closes); lockstep: from the first pose stamped after the change',
                    GRASP_INPUTS, True, None),
    'instrument_offsets': ([0.0, 0.0, 0.0], '[m] tissue-frame offset of each instrument\'s device '
                                            'origin, added to translation: three numbers per instrument '
                                            'in the order of instruments (missing ones: 0)', None, True,
                           None),
    'instrument_tools': ([''], 'each instrument\'s tool, in the order of instruments: \'sphere R\', '
                               '\'capsule R L\', \'blade R L\' or \'needle R L\' (radius, shaft or edge length [m], in '
                               'tool_radius\'s and tool_length\'s ranges), \'\' or missing: tool_shape, '
                               'tool_radius and tool_length', None, True,
                         None),
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


#: the solver settings a run-time change applies at the next step, without a new solver
NEXT_STEP_SETTINGS = tuple(name for name, spec in solver_params().items() if spec[4] is None)


def check_value(name: str, value, table: dict = SIM_PARAMS) -> str | None:
    """Error text if ``value`` is not one of the string choices of ``name`` or a bad vector."""
    choice = check_choice(table, name, value)
    if choice:
        return choice
    default = table[name][0]
    if name == 'instruments':
        return check_instruments(value)
    if name == 'instrument_tools':
        try:
            for text in value:
                parse_tool(text)
        except ConfigError as exc:
            return f'parameter {name}: {exc}'
        except TypeError:
            return f'parameter {name} must be a list of tool descriptions, got {value!r}'
        return None
    if name == 'instrument_offsets':
        try:
            arr = np.asarray(list(value), dtype=np.float64)
        except (TypeError, ValueError):
            return f'parameter {name} must be a list of numbers, got {value!r}'
        if arr.ndim != 1 or len(arr) % 3 or not np.all(np.isfinite(arr)):
            return f'parameter {name} must be finite numbers, three per instrument, got {list(value)!r}'
        return None
    if isinstance(default, list):
        try:
            arr = np.asarray(list(value), dtype=np.float64)
        except (TypeError, ValueError):
            return f'parameter {name} must be a list of {len(default)} numbers, got {value!r}'
        if arr.shape != (len(default),) or not np.all(np.isfinite(arr)):
            return f'parameter {name} must be {len(default)} finite numbers, got {list(value)!r}'
    return None


def parse_tool(text: str) -> dict | None:
    """One ``instrument_tools`` entry: ``'sphere R'`` or ``'capsule R L'``, ``'blade R L'``, ``'needle R L'``
    [m] as SolverConfig's tool
    fields, ``''``: None (the shared tool). Ranges are the solver's to check."""
    words = str(text).split()
    if not words:
        return None
    shapes = {'sphere': 1, 'capsule': 2, 'blade': 2, 'needle': 2}
    if words[0] not in shapes or len(words) != 1 + shapes[words[0]]:
        raise ConfigError(f"{text!r} is not 'sphere R', 'capsule R L', 'blade R L' or 'needle R L' (radius and "
                          f"length in m)")
    try:
        size = [float(w) for w in words[1:]]
    except ValueError:
        raise ConfigError(f'{text!r}: {words[1:]} are not numbers') from None
    tool = {'tool_shape': words[0], 'tool_radius': size[0]}
    if len(size) > 1:
        tool['tool_length'] = size[1]
    return tool


def instrument_tools(p: dict) -> list[dict | None]:
    """Each instrument's tool (:func:`parse_tool`; missing entries: the shared tool)."""
    given = list(p['instrument_tools'])
    return [parse_tool(given[k]) if k < len(given) else None for k in range(len(p['instruments']))]


def instrument_translations(p: dict) -> list[list[float]]:
    """Each instrument's ``translation`` (the shared one plus its ``instrument_offsets``)."""
    offsets = list(p['instrument_offsets'])
    out = []
    for k in range(len(p['instruments'])):
        extra = offsets[3 * k:3 * k + 3] or [0.0, 0.0, 0.0]
        out.append([float(a) + float(b) for a, b in zip(p['translation'], extra)])
    return out


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
        E, nu, eta_s, eta_b, rho, g_c = (float(p[k]) for k in ('E', 'nu', 'eta_shear', 'eta_bulk', 'rho', 'toughness'))
        if eta_b < 0.0:
            G = E / (2.0 * (1.0 + nu))
            K = E / (3.0 * (1.0 - 2.0 * nu))
            eta_b = K * eta_s / G
        return Material(E, nu, eta_s, eta_b, rho, 'custom', toughness=g_c)
    path = p.get('materials_file') or default_materials_file()
    return load_material(path, name)


def build_config(p: dict) -> SolverConfig:
    """Validated solver settings from the parameters (raises ConfigError)."""
    cfg = SolverConfig(**{name: p[name] for name in solver_params()})
    cfg.validate()
    if not p['max_dt'] >= p['nominal_dt']:
        raise ConfigError(f'max_dt ({p["max_dt"]}) must be >= nominal_dt ({p["nominal_dt"]})')
    if len(p['instruments']) > 1 and p['haptic_mode'] != 'multirate':
        raise ConfigError(f'{len(p["instruments"])} instruments need haptic_mode multirate, got '
                          f'{p["haptic_mode"]}')
    return cfg


def solves_in_background(p: dict) -> bool:
    """The organ's far field solves its responses on a worker thread unless the timing is lockstep:
    live, a touch on new ground must not stall its frame; lockstep replays repeat bit for bit."""
    return p['timing_mode'] != 'lockstep'


def build_renderer(p: dict) -> RendererConfig:
    """Haptic renderer settings from the parameters (raises ConfigError). Its force limit is the
    device's in tissue units, so the renderer's passivity accounting holds what is sent."""
    try:
        return RendererConfig(velocity_cutoff=float(p['velocity_cutoff']),
                              coupling_stiffness=float(p['coupling_stiffness']),
                              coupling_damping=float(p['coupling_damping']),
                              proxy_damping=float(p['proxy_damping']),
                              passivity_max_damping=float(p['passivity_max_damping']),
                              energy_bound_stiffness=float(p['energy_bound_stiffness']),
                              force_limit=float(p['force_limit']) / float(p['force_scale'])).validate()
    except ValueError as exc:
        raise ConfigError(f'haptic renderer: {exc}') from exc


# -- the README's parameter table ------------------------------------------------------------------
_ON_CHANGE = {'solver': 'new solver', 'material': 'material', 'mapping': 'map', 'renderer': 'renderer reset',
              None: 'next step'}


def _limits_text(limits) -> str:
    if limits is None:
        return ''
    if isinstance(limits[0], str):
        return choices_text(limits)
    return f'{limits[0]:g} … {limits[1]:g}'


def parameter_table(table: dict = SIM_PARAMS) -> str:
    """The package README's parameter table, written from ``table`` (``python -m
    sph_tissue_sim.params`` prints it; a test keeps the README equal to it)."""
    rows = ['| parameter | default | range | what it is | a change |', '|---|---|---|---|---|']
    for name, (default, text, limits, read_only, rebuild) in table.items():
        shown = ('true' if default else 'false') if isinstance(default, bool) else (
            repr(default) if default == '' else f'{default:g}' if isinstance(default, float) else default)
        doc = text.replace('|', '\\|')
        change = 'read-only' if read_only else _ON_CHANGE[rebuild]
        rows.append(f'| `{name}` | {shown} | {_limits_text(limits)} | {doc} | {change} |')
    return '\n'.join(rows) + '\n'


if __name__ == '__main__':
    print(parameter_table(), end='')
