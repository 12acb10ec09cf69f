"""The pure parts of sim_node without processes: device mapping, cloud packing, stamp clock,
parameter builders."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sph_tissue_sim.cloud import FIELD_SPECS, POINT_DTYPE, CloudBuffer, unpack_points
from sph_tissue_sim.core.errors import ConfigError, ModelError
from sph_tissue_sim.mapping import DEFAULT_ROTATION, DeviceMapping, anchor_point, check_position
from tissue_common.rotation import quaternion_matrix
from sph_tissue_sim.core.factory import block_of
from sph_tissue_sim.params import (SIM_PARAMS, build_config, build_material, build_model, check_value,
                                   solves_in_background)
from sph_tissue_sim.timing import BACKWARDS, FIRST, JUMP, OK, REPEAT, StampClock


def defaults(**over) -> dict:
    p = {name: spec[0] for name, spec in SIM_PARAMS.items()}
    p.update(over)
    return p


# -- mapping -----------------------------------------------------------------------------------------
def test_default_rotation_maps_device_up_to_tissue_up_and_user_to_minus_y():
    R = quaternion_matrix(DEFAULT_ROTATION)
    assert R @ [0, 1, 0] == pytest.approx([0, 0, 1])      # device y (up) -> tissue z (up)
    assert R @ [1, 0, 0] == pytest.approx([1, 0, 0])      # device x (right) -> tissue x
    assert R @ [0, 0, 1] == pytest.approx([0, -1, 0])     # device z (to the user) -> tissue -y
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_quaternion_is_normalised_and_a_zero_quaternion_is_refused():
    assert quaternion_matrix([0, 0, 0, 2.0]) == pytest.approx(np.eye(3))
    half_turn_z = quaternion_matrix([0, 0, 1, 0])
    assert half_turn_z @ [1, 0, 0] == pytest.approx([-1, 0, 0])
    for bad in ([0, 0, 0, 0], [math.nan, 0, 0, 1], [1, 2, 3]):
        with pytest.raises(ValueError):
            quaternion_matrix(bad)
        with pytest.raises(ConfigError, match='quaternion'):
            DeviceMapping.build(bad, [0, 0, 0], 1.0, 1.0, np.zeros(3))


def test_device_origin_lands_on_the_anchor_and_a_press_goes_down_into_the_tissue():
    m = DeviceMapping.build(DEFAULT_ROTATION, [0.0, 0.0, 0.001], 2.0, 1.0, anchor=[0.04, 0.04, 0.05])
    assert m.to_tissue([0, 0, 0]) == pytest.approx([0.04, 0.04, 0.051])
    # 8 mm down on the device (-y) is 16 mm down in the tissue at workspace scale 2
    assert m.to_tissue([0, -0.008, 0]) == pytest.approx([0.04, 0.04, 0.051 - 0.016])
    p = np.array([0.013, -0.021, 0.007])
    assert m.to_device(m.to_tissue(p)) == pytest.approx(p)


def test_tissue_force_up_is_device_force_up_scaled_by_force_scale():
    m = DeviceMapping.build(DEFAULT_ROTATION, [0, 0, 0], 1.0, 0.5, anchor=[0, 0, 0])
    assert m.force_to_device([0.0, 0.0, 2.0]) == pytest.approx([0.0, 1.0, 0.0])
    assert m.force_to_device([0.0, -2.0, 0.0]) == pytest.approx([0.0, 0.0, 1.0])


@pytest.mark.parametrize('quaternion', [DEFAULT_ROTATION, (0.1, -0.3, 0.2, 0.9)])
def test_the_device_frame_transform_is_the_device_map_at_unit_scale(quaternion):
    """What sim_node publishes as tissue <- omni_base (tissue/device_frame, /tf_static) maps every
    device point where the simulation puts it."""
    from tissue_common.frames import Transform

    m = DeviceMapping.build(quaternion, [0.004, -0.002, 0.01], 1.0, 1.0, np.array([0.0, 0.0, 0.05]))
    tr = Transform.from_matrix('tissue', 'omni_base', m.rotation, m.origin)
    rng = np.random.default_rng(3)
    for p in rng.uniform(-0.1, 0.1, size=(20, 3)):
        assert tr.apply(p) == pytest.approx(m.to_tissue(p), abs=1e-15)


def test_mapping_refuses_bad_translation_and_scales():
    with pytest.raises(ConfigError, match='translation'):
        DeviceMapping.build(DEFAULT_ROTATION, [0, math.inf, 0], 1.0, 1.0, anchor=[0, 0, 0])
    with pytest.raises(ConfigError, match='workspace_scale'):
        DeviceMapping.build(DEFAULT_ROTATION, [0, 0, 0], 0.0, 1.0, anchor=[0, 0, 0])


def test_anchor_points_of_a_block():
    model = block_of([0.08, 0.08, 0.04], 256)              # 1 cm lattice, particles 5 mm inside
    X, s = model.positions, model.spacing
    assert anchor_point(X, s, 0.015, 'top_contact') == pytest.approx([0.04, 0.04, 0.035 + 0.015])
    assert anchor_point(X, s, 0.015, 'top_surface') == pytest.approx([0.04, 0.04, 0.04])
    assert anchor_point(X, s, 0.015, 'centre') == pytest.approx([0.04, 0.04, 0.02])
    assert anchor_point(X, s, 0.015, 'origin') == pytest.approx([0, 0, 0])
    with pytest.raises(ConfigError, match='anchor'):
        anchor_point(X, s, 0.015, 'somewhere')


def test_check_position_names_the_problem():
    assert check_position([0.01, 0.02, 0.0], 1.0) is None
    assert check_position([math.nan, 0, 0], 1.0) == 'non-finite position'
    assert check_position([0, math.inf, 0], 1.0) == 'non-finite position'
    assert 'max_device_distance' in check_position([0, 2.0, 0], 1.0)


# -- cloud ---------------------------------------------------------------------------------------------
def random_particles(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 3))
    return X + 0.01 * rng.normal(size=(n, 3)), X, rng.random(n) * 1e3, rng.integers(0, 5, n).astype(np.int8)


def test_cloud_packing_round_trips_every_field():
    n = 1000
    x, X, vm, region = random_particles(n)
    cloud = CloudBuffer(n, 'tissue')
    cloud.pack(x, X, vm, region)
    back = unpack_points(cloud.data, n)
    assert np.array_equal(back['x'], x[:, 0].astype(np.float32))
    assert np.array_equal(back['z'], x[:, 2].astype(np.float32))
    assert np.allclose(back['displacement'], np.linalg.norm(x - X, axis=1), rtol=1e-6, atol=0)
    assert np.array_equal(back['von_mises'], vm.astype(np.float32))
    assert np.array_equal(back['region'], region.astype(np.uint8))
    assert not back['held'].any()                                             # nothing held
    assert not np.frombuffer(cloud.data, np.uint8).reshape(n, 24)[:, 22:].any()  # padding stays zero


def test_cloud_held_byte_names_the_instrument_that_holds_each_particle():
    n = 10
    x, X, vm, region = random_particles(n)
    cloud = CloudBuffer(n, 'tissue')
    points = cloud.pack(x, X, vm, region, [np.array([1, 4], dtype=np.int32), np.array([], dtype=np.int32),
                                           np.array([7])])
    assert points['held'].tolist() == [0, 1, 0, 0, 1, 0, 0, 3, 0, 0]   # instrument k holds: k + 1
    assert np.array_equal(points['region'], region.astype(np.uint8))    # its neighbour byte untouched
    # a let-go particle is free at the next pack
    assert cloud.pack(x, X, vm, region, [np.array([4])])['held'].tolist() == [0, 0, 0, 0, 1, 0, 0, 0, 0, 0]


def test_cloud_marks_the_cut_faces_and_leaves_a_removed_particle_out_as_a_nan_point():
    pytest.importorskip('sensor_msgs')
    n = 6
    x, X, vm, region = random_particles(n)
    cloud = CloudBuffer(n, 'tissue')
    severed = np.array([0, 3, 0, 300, 0, 12], dtype=np.int32)
    removed = np.array([False, False, False, True, False, False])
    points = cloud.pack(x, X, vm, region, (), severed, removed)
    assert points['severed'].tolist() == [0, 3, 0, 255, 0, 12]            # clipped to the byte
    assert np.isnan([points[c][3] for c in 'xyz']).all() and points['displacement'][3] == 0.0
    keep = ~removed
    assert np.array_equal(points['x'][keep], x[keep, 0].astype(np.float32))
    assert not cloud.message().is_dense
    # the organ whole again (a reset): a dense cloud with nothing severed
    points = cloud.pack(x, X, vm, region)
    assert not points['severed'].any() and np.isfinite(points['x']).all() and cloud.message().is_dense


def test_cloud_refuses_held_indices_outside_the_cloud():
    x, X, vm, region = random_particles(3)
    with pytest.raises(ValueError, match=r'held particle indices must lie in \[0, 3\)'):
        CloudBuffer(3, 'tissue').pack(x, X, vm, region, [np.array([3])])
    with pytest.raises(ValueError, match='held particle indices'):
        CloudBuffer(3, 'tissue').pack(x, X, vm, region, [np.array([0]), np.array([-1])])


def test_cloud_repacking_overwrites_the_same_buffer_in_place():
    n = 50
    cloud = CloudBuffer(n, 'tissue')
    data = cloud.data
    cloud.pack(*random_particles(n, 1))
    x, X, vm, region = random_particles(n, 2)
    points = cloud.pack(x, X, vm, region)
    assert cloud.data is data and np.array_equal(points['y'], x[:, 1].astype(np.float32))


def test_cloud_region_codes_are_clipped_to_a_byte():
    x, X, vm, _ = random_particles(3)
    cloud = CloudBuffer(3, 'tissue')
    assert cloud.pack(x, X, vm, np.array([-1, 7, 300]))['region'].tolist() == [0, 7, 255]


def test_cloud_field_table_matches_the_point_layout():
    assert POINT_DTYPE.itemsize == 24
    for name, offset, datatype in FIELD_SPECS:
        assert POINT_DTYPE.fields[name][1] == offset
        size = POINT_DTYPE.fields[name][0].itemsize
        assert (datatype, size) in ((7, 4), (2, 1))          # FLOAT32 4 bytes, UINT8 1 byte


def test_cloud_message_header_and_layout():
    pytest.importorskip('sensor_msgs')
    cloud = CloudBuffer(7, 'tissue')
    cloud.pack(np.zeros((7, 3)), np.zeros((7, 3)), np.zeros(7), np.zeros(7, dtype=np.int8))
    msg = cloud.message()
    assert (msg.header.frame_id, msg.height, msg.width, msg.point_step) == ('tissue', 1, 7, 24)
    assert len(msg.data) == 7 * 24 and msg.row_step == 7 * 24 and not msg.is_bigendian
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'displacement', 'von_mises', 'region', 'held', 'severed']
    # later packs land in the message that is published
    x, X, vm, region = random_particles(7)
    cloud.pack(x, X, vm, region)
    assert cloud.message() is msg
    assert np.array_equal(unpack_points(msg.data, 7)['von_mises'], vm.astype(np.float32))


def test_cloud_packing_rejects_inconsistent_arrays():
    with pytest.raises(ValueError, match='do not match a cloud of 5 points'):
        CloudBuffer(5, 'tissue').pack(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros(4), np.zeros(5))


# -- stamp clock ---------------------------------------------------------------------------------------
def test_stamp_clock_rules():
    c = StampClock(nominal_dt=1e-3, max_dt=0.02)
    t = 1_000_000_000_000
    assert c.advance(t) == (1e-3, FIRST)
    assert c.advance(t + 2_500_000) == (pytest.approx(2.5e-3), OK)
    assert c.advance(t + 2_500_000) == (0.0, REPEAT)
    assert c.advance(t + 1_000_000) == (1e-3, BACKWARDS)     # the clock restarts here
    assert c.advance(t + 2_000_000) == (pytest.approx(1e-3), OK)
    assert c.advance(t + 5_000_000_000) == (0.02, JUMP)
    c.reset()
    assert c.advance(t) == (1e-3, FIRST)


# -- parameter builders ----------------------------------------------------------------------------
def test_block_model_has_the_requested_count_on_an_exact_lattice():
    model = block_of([0.08, 0.08, 0.04], 256)
    assert model.n_particles == 256 and model.spacing == pytest.approx(0.01)
    assert model.fixed.sum() == 64                           # the bottom layer


def test_liver_model_has_about_the_requested_particle_count():
    model = build_model(defaults(model='liver', n_particles=500))
    assert model.name.startswith('liver')
    assert abs(model.n_particles - 500) <= 50


@pytest.mark.parametrize('model', ['block', 'beam'])
def test_a_bad_block_or_beam_size_is_a_config_error_naming_it(model):
    with pytest.raises(ConfigError, match=f'{model} size must be 3 positive lengths'):
        build_model(defaults(model=model, **{f'{model}_size': [0.08, -0.01, 0.04]}))


def test_mesh_model_needs_an_existing_file(tmp_path):
    with pytest.raises(ConfigError, match='mesh_path'):
        build_model(defaults(model='mesh', mesh_path=''))
    with pytest.raises(ModelError, match='not found'):
        build_model(defaults(model='mesh', mesh_path=str(tmp_path / 'none.stl')))


def test_materials_by_name_and_custom():
    liver = build_material(defaults(material='liver'))
    assert liver.G == pytest.approx(1800.0) and liver.nu == pytest.approx(0.45)
    custom = build_material(defaults(material='custom', E=3000.0, nu=0.3, eta_shear=2.0,
                                     eta_bulk=-1.0, rho=1000.0))
    assert custom.E == 3000.0 and custom.eta_bulk / custom.K == pytest.approx(custom.eta_shear / custom.G)
    with pytest.raises(ConfigError, match='no material'):
        build_material(defaults(material='granite'))


def test_solver_config_cross_checks():
    assert build_config(defaults()).scheme == 'tlsph'
    with pytest.raises(ConfigError, match='k1_min'):
        build_config(defaults(k1_min=5.0, k1_max=2.0))
    with pytest.raises(ConfigError, match='max_dt'):
        build_config(defaults(nominal_dt=0.05, max_dt=0.01))


def test_the_far_field_solves_in_the_background_unless_the_timing_is_lockstep():
    """Live, a touch on new ground must not stall its frame for the organ's responses; lockstep
    replays must repeat bit for bit, which a worker thread's timing would not let them."""
    assert solves_in_background(defaults(timing_mode='live')) is True
    assert solves_in_background(defaults(timing_mode='lockstep')) is False
    assert 'background' not in SIM_PARAMS


def test_every_solver_parameter_is_its_solver_config_field_with_the_same_default_doc_and_limits():
    """One source: the node's solver parameters are written from SolverConfig's fields, the
    node's defaults build exactly the core's default config, and a run-time change goes through
    SolverConfig.validate like a start-up value (limits included)."""
    import dataclasses

    from sph_tissue_sim.core.solver import SolverConfig
    from sph_tissue_sim.params import NEXT_STEP_SETTINGS, solver_params

    for f in dataclasses.fields(SolverConfig):
        if f.metadata['node']:
            assert SIM_PARAMS[f.name][:3] == (f.default, f.metadata['doc'], f.metadata['limits']), f.name
        else:
            assert f.name not in SIM_PARAMS, f.name
    assert build_config(defaults()) == SolverConfig()
    assert set(NEXT_STEP_SETTINGS) == {'friction', 'grasp_limit', 'max_tool_speed', 'force_limit'}
    for name, spec in solver_params().items():
        limits = spec[2]
        if isinstance(limits, tuple) and not isinstance(limits[0], str):
            with pytest.raises(ConfigError, match=name):
                build_config(defaults(**{name: limits[1] * 2 + 1}))


def test_one_blas_thread_leaves_every_blas_library_with_one_thread():
    from threadpoolctl import threadpool_info, threadpool_limits
    from sph_tissue_sim.sim_node import one_blas_thread

    with threadpool_limits(limits=None):   # put back what the process had after the test
        one_blas_thread()
        blas = [i for i in threadpool_info() if i['user_api'] == 'blas']
        assert blas and all(i['num_threads'] == 1 for i in blas)


def test_the_threads_parameter_reaches_the_solver_config():
    assert build_config(defaults()).parallel_min_particles == 0
    assert build_config(defaults(parallel_min_particles=2000)).parallel_min_particles == 2000


def test_the_contact_parameters_reach_the_solver_config_and_bad_ones_are_refused():
    assert build_config(defaults(contact_samples=0)).contact_samples == 0
    assert (build_config(defaults()).friction, build_config(defaults(friction=0.3)).friction) == (0.0, 0.3)
    with pytest.raises(ConfigError, match='friction'):
        build_config(defaults(friction=-0.1))
    assert 'must be one of' in check_value('tool_shape', 'cone')



def test_the_integrator_reaches_the_solver_config_and_bad_values_are_refused():
    cfg = build_config(defaults(integrator='implicit', implicit_max_dt=0.004))
    assert (cfg.integrator, cfg.implicit_max_dt) == ('implicit', 0.004)
    assert build_config(defaults()).integrator == 'explicit'
    for bad, match in ((dict(integrator='verlet'), 'integrator'),
                       (dict(integrator='implicit', scheme='paper'), 'integrator implicit needs scheme tlsph'),
                       (dict(implicit_max_dt=0.0), 'implicit_max_dt')):
        with pytest.raises(ConfigError, match=match):
            build_config(defaults(**bad))


def test_check_value_catches_bad_choices_and_vectors():
    assert check_value('mode', 'local') is None
    assert 'must be one of' in check_value('mode', 'diagonal')
    assert 'timing_mode' in check_value('timing_mode', 'fast')
    assert check_value('translation', [0.0, 0.1, 0.0]) is None
    assert '3 finite numbers' in check_value('translation', [0.0, 0.1])
    assert '4 finite numbers' in check_value('rotation', [0.0, math.nan, 0.0, 1.0])


# -- shipped files ---------------------------------------------------------------------------------
PKG_DIR = __import__('pathlib').Path(__file__).resolve().parents[1]


def test_config_files_name_only_declared_parameters_with_valid_values():
    import yaml

    base = yaml.safe_load((PKG_DIR / 'config' / 'sim_node.yaml').read_text())['sim_node']['ros__parameters']
    assert set(base) == set(SIM_PARAMS)                     # every parameter documented there
    for name, value in base.items():
        default = SIM_PARAMS[name][0]
        assert type(value) is type(default), name            # a ROS params file is typed
        assert value == default, name                         # the file is the defaults, not a copy that drifts
        assert check_value(name, value) is None
    paper = yaml.safe_load((PKG_DIR / 'config' / 'sim_node_paper.yaml').read_text())
    paper = paper['sim_node']['ros__parameters']
    assert set(paper) <= set(SIM_PARAMS)
    merged = {**base, **paper}
    assert merged['scheme'] == 'paper' and merged['n_particles'] == 3670
    assert build_material(merged).nu == 0.0                  # the paper's eq. 3 material
    build_config(merged)


def test_launch_file_imports_without_the_launch_packages():
    import importlib.util

    spec = importlib.util.spec_from_file_location('sim_launch', PKG_DIR / 'launch' / 'sim.launch.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert callable(mod.generate_launch_description)
    try:  # (a bare 'import launch' can find some folder named launch as a namespace package)
        from launch import LaunchDescription  # noqa: F401
        from launch_ros.actions import Node  # noqa: F401
    except ImportError:
        return
    assert mod.generate_launch_description() is not None


def test_bringup_launch_sets_only_parameters_its_nodes_declare():
    """The bring-up's arguments reach parameters each node really has (a typo would be ignored by
    ROS at launch, silently), an empty argument leaves the YAML's value, and lockstep needs a
    replay; the launch packages are absent here, so this checks the mapping the file builds its
    nodes from, and that the file imports."""
    import importlib.util

    from haptic_omni_driver.params import DRIVER_PARAMS
    from tissue_viz.viz_node import PARAMETERS as VIZ_PARAMS

    spec = importlib.util.spec_from_file_location('bringup', PKG_DIR / 'launch' / 'bringup.launch.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert callable(mod.generate_launch_description)
    declared = {'omni_driver': DRIVER_PARAMS, 'sim_node': SIM_PARAMS, 'viz_node': VIZ_PARAMS}
    every = mod.node_overrides({'backend': 'replay', 'bag': '/b', 'model': 'block', 'tool': 'capsule',
                                'timing': 'lockstep', 'report_dir': '/r', 'exit_at_end': 'true'})
    assert every == {'omni_driver': {'backend': 'replay', 'bag': '/b', 'replay_mode': 'lockstep',
                                     'exit_on_end': True},
                     'sim_node': {'model': 'block', 'tool_shape': 'capsule', 'timing_mode': 'lockstep'},
                     'viz_node': {'report_dir': '/r'}}
    for node, params in every.items():
        assert set(params) <= set(declared[node]), (node, set(params) - set(declared[node]))
        for name, value in params.items():
            choices = declared[node][name][2]
            assert not isinstance(choices, tuple) or not isinstance(choices[0], str) or \
                value in choices, (node, name, value)
    defaults = mod.node_overrides({name: spec[0] for name, spec in mod.ARGUMENTS.items()})
    assert defaults == {'omni_driver': {}, 'sim_node': {'timing_mode': 'live'}, 'viz_node': {}}
    with pytest.raises(ValueError, match='needs backend:=replay'):
        mod.node_overrides({'backend': 'scripted', 'timing': 'lockstep'})
    # exit_at_end: the launch ends with the driver, which exits at the end of its replay; false
    # (the default) or empty leaves exit_on_end to the driver's YAML
    assert mod.ARGUMENTS['exit_at_end'][0] == 'false' and not mod.exit_at_end({})
    assert mod.exit_at_end({'exit_at_end': 'True'}) and not mod.exit_at_end({'exit_at_end': ''})
    for value, driver in (('true', {'exit_on_end': True}), ('false', {}), ('', {})):
        assert mod.node_overrides({'backend': 'replay', 'exit_at_end': value})['omni_driver'] == \
            {'backend': 'replay', **driver}, value
    with pytest.raises(ValueError, match='exit_at_end must be true or false'):
        mod.node_overrides({'exit_at_end': 'yes please'})


def test_shutdown_interrupts_the_step_and_reports_a_thread_that_outlives_its_wait(monkeypatch):
    """Ctrl-C interrupts the solver's step; a stepping thread still busy after ``SHUTDOWN_JOIN``
    (a native solve that never looks at the interrupt) makes ``shutdown`` return False, so that
    ``main`` leaves without finalising the interpreter under it (that exited 120)."""
    import threading
    from types import SimpleNamespace

    from sph_tissue_sim import runner
    monkeypatch.setattr(runner, 'SHUTDOWN_JOIN', 0.05)
    release = threading.Event()
    busy = threading.Thread(target=lambda: release.wait(30.0), daemon=True)
    busy.start()
    interrupts = []
    loop = SimpleNamespace(
        _stop=threading.Event(), _cv=threading.Condition(), _wake=threading.Event(), _worker=None, _retired=[],
        _solver_thread=busy, solver=SimpleNamespace(interrupt=lambda: interrupts.append(1), close=lambda t: True))
    assert runner.Runner.shutdown(loop) is False
    assert interrupts and loop._stop.is_set() and loop._wake.is_set()
    release.set()
    busy.join(5.0)
    assert runner.Runner.shutdown(loop) is True
    # the far field's worker still inside a sparse solve counts the same
    waits = []
    loop.solver.close = lambda timeout: waits.append(timeout) or False
    assert runner.Runner.shutdown(loop) is False and waits == [0.05]
