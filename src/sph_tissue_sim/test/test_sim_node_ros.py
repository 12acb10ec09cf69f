"""sim_node as a real process over DDS (installed executable, isolated domain, see tissue_testing.harness).

One live-mode node on a 256-particle block serves most tests of this module (started once, reset
between tests); lockstep and bad start-up parameters get their own processes.
"""

from __future__ import annotations

import math
import os
import re
import time

import numpy as np
import pytest

from sph_tissue_sim.params import SIM_PARAMS
from tissue_testing import harness
from press import tilted_shaft_press
from sim_probe import (BLOCK, N_BLOCK, START_TIMEOUT, T0_NS, SimProbe, call_reset, finite_and_bounded,
                       force_of, press_path, qos, set_parameters, sim, stamp_ns)

pytestmark = pytest.mark.ros


FORCE_LIMIT = 3.3


@pytest.fixture(scope='module')
def live_sim(ros_domain):
    """One live-mode sim_node for the module (force_limit 3.3 N, 20 Hz cloud)."""
    with sim() as proc:
        proc.wait_for_output(r'ready:', START_TIMEOUT)
        yield proc
    assert proc.returncode == 0, proc.output()


@pytest.fixture
def probe(rclpy_node, live_sim):
    p = SimProbe(rclpy_node)
    p.wait_matched(live_sim)
    res = call_reset(rclpy_node)
    assert res.success, res.message
    return p


def _unique_t0(k: int) -> int:
    return T0_NS + k * 10_000_000_000


#: [m per 1 ms pose] how far a held stylus pushes on while it waits for the tissue
HOLD_CREEP = 2e-6


def _hold_until_pushed(probe, point, t_start: int, up: float = 0.0, at_least: int = 1,
                       creep: float = HOLD_CREEP) -> np.ndarray:
    """Hold the stylus at ``point``, pushing on by ``creep`` [m] per 1 ms pose along device -y (as a
    hand holding a press does), from ``t_start`` until the force pushes it up by more than ``up``
    [N], at least ``at_least`` poses and at most 3000. Live, the renderer answers from the solver
    thread's last contact model, and on a busy machine its first step there can come after the
    press: the energy bound then gives a still stylus only what the hand put in (a few mN,
    docs/decisions/energy-bound.md), and the force grows as the hand pushes on. Returns the forces
    of the held poses."""
    forces = []
    for k in range(3000):
        at = np.asarray(point, dtype=float) - [0.0, creep * k, 0.0]
        forces.append(force_of(probe.exchange(at, t_start + k * 1_000_000)))
        if forces[-1][1] > up and k + 1 >= at_least:
            break
    return np.array(forces)


# -- pose in, wrench out ------------------------------------------------------------------------------
def test_pressing_returns_a_wrench_per_pose_with_its_stamp_pushing_back_up(probe, live_sim):
    path = press_path(60, depth=0.004)  # 1 cm above the surface point down to 4 mm below
    t0 = _unique_t0(1)
    forces = probe.run_path(path, t0)
    for k in range(len(path)):
        w = probe.forces[t0 + k * 1_000_000]
        assert w.header.frame_id == 'omni_base'
        assert stamp_ns(w.header) == t0 + k * 1_000_000
    assert finite_and_bounded(forces, FORCE_LIMIT)
    above = path[:, 1] > 0.001
    assert np.all(forces[above] == 0.0)                # no contact above the surface
    # hold the stylus 4 mm deep until the solver thread has stepped there
    f = _hold_until_pushed(probe, path[-1], t0 + len(path) * 1_000_000, up=0.02)[-1]
    assert f[1] > 0.02                                 # device +y: the tissue pushes the stylus up
    # mostly up: on this 1 cm lattice a 5 mm tool pressed 4 mm between particles meets a sideways
    # force of up to 0.45 of the normal one, depending on where it lands (core, any local-area
    # settings); live, the solver steps wherever the proxy is when it starts, so that varies
    print(f'force at 4 mm: up {f[1]:.3f} N, sideways {np.hypot(f[0], f[2]):.3f} N')
    assert f[1] > 1.5 * np.hypot(f[0], f[2])
    assert live_sim.alive()


def test_metrics_follow_the_solver_steps_with_sane_content(probe):
    """Multirate (the default): the renderer answers each pose and the solver thread steps at the
    newest proxy, so metrics come per solver step, stamped with the newest pose it simulated."""
    from tissue_msgs.msg import SimMetrics

    t0 = _unique_t0(2)
    path = press_path(40, depth=0.004)
    probe.run_path(path, t0)
    stamps = {t0 + k * 1_000_000 for k in range(len(path))}
    last_ns = t0 + (len(path) - 1) * 1_000_000
    assert probe.node.spin_until(lambda: last_ns in {stamp_ns(m.header) for m in probe.metrics}, 10.0)
    mine = [m for m in probe.metrics if stamp_ns(m.header) in stamps]
    assert 1 <= len(mine) <= len(path)
    last = mine[-1]
    assert stamp_ns(last.header) == last_ns
    assert last.header.frame_id == 'tissue'
    assert last.n_particles == N_BLOCK
    assert last.scheme == SimMetrics.SCHEME_TLSPH and last.mode == SimMetrics.MODE_LOCAL
    assert last.contact_index >= 0 and last.penetration > 0.0
    assert last.contact_force.z > 0.02                 # tissue frame: up, out of the tissue
    assert 0.0 < last.max_displacement < 0.01
    assert last.substeps >= 1 and 0.0 < last.substep_dt <= 0.001
    assert last.step_wall_time > 0.0 and last.kinetic_energy >= 0.0
    assert last.n_interaction > 0 and len(last.n_layer) == SIM_PARAMS['n_layers'][0]
    assert last.haptic_mode == SimMetrics.HAPTIC_MULTIRATE
    # the stretch is the renderer's at the newest answered pose: on a busy machine the solver may
    # not yet have handed it a model in contact (then 0), so only its sign is the node's to keep
    assert last.coupling_stretch >= 0.0 and last.model_age > 0.0 and last.added_damping >= 0.0
    assert last.energy_in >= last.energy_in_min and math.isfinite(last.solver_rate)
    sim_times = [m.sim_time for m in mine]
    assert all(b > a for a, b in zip(sim_times, sim_times[1:]))
    # the solver simulates the pose time (first pose nominal_dt, then 1 ms per pose), no more
    assert sim_times[-1] <= len(path) * 1e-3 + 1e-9


def test_the_device_frame_is_latched_and_maps_the_device_where_the_simulation_does(rclpy_node,
                                                                                   live_sim):
    """tissue/device_frame: the tissue <- omni_base transform (also /tf_static where tf2 exists),
    equal to the node's own device map, for a subscriber that joins at any time."""
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from sph_tissue_sim import params as sim_params
    from sph_tissue_sim.runner import make_mapping, make_solver
    from sim_probe import BLOCK
    from tissue_common.frames import from_msg

    got = []
    rclpy_node.create_subscription(TransformStamped, 'tissue/device_frame', got.append, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    assert rclpy_node.spin_until(lambda: got, 30), live_sim.output()
    tr = from_msg(got[-1])
    assert (tr.parent, tr.child) == ('tissue', 'omni_base')
    p = {name: spec[0] for name, spec in SIM_PARAMS.items()} | BLOCK
    solver = make_solver(sim_params.build_model(p), sim_params.build_material(p),
                         sim_params.build_config(p), p['nominal_dt'])
    mapping = make_mapping(p, solver)
    for point in ([0.0, 0.0, 0.0], [0.01, -0.004, 0.02], [-0.03, 0.05, 0.0]):
        assert tr.apply(point) == pytest.approx(mapping.to_tissue(point), abs=1e-12)
    # the default map: the device's up (y) is the tissue's up (z)
    assert tr.apply([0.0, 0.01, 0.0]) - tr.apply([0.0, 0.0, 0.0]) == pytest.approx([0, 0, 0.01])
    # a new map at run time: the latched transform follows it
    n = len(got)
    try:
        assert all(r.successful for r in set_parameters(rclpy_node, {'translation': [0.01, 0.0, 0.0]}))
        assert rclpy_node.spin_until(lambda: len(got) > n, 20), live_sim.output()
        moved = from_msg(got[-1])
        assert moved.apply([0.0, 0.0, 0.0]) - tr.apply([0.0, 0.0, 0.0]) == pytest.approx([0.01, 0, 0])
    finally:
        assert all(r.successful for r in set_parameters(rclpy_node, {'translation': [0.0, 0.0, 0.0]}))


def test_particle_cloud_fields_and_count_match_the_model(probe):
    from sensor_msgs.msg import PointField

    from sph_tissue_sim.cloud import unpack_points

    probe.run_path(press_path(40, depth=0.004), _unique_t0(3))
    n0 = len(probe.clouds)
    assert probe.node.spin_until(lambda: len(probe.clouds) > n0 + 1, 10.0)
    cloud = probe.clouds[-1]
    assert cloud.header.frame_id == 'tissue'
    assert (cloud.height, cloud.width) == (1, N_BLOCK)
    assert cloud.point_step == 24 and cloud.row_step == 24 * N_BLOCK and len(cloud.data) == 24 * N_BLOCK
    fields = {f.name: (f.offset, f.datatype, f.count) for f in cloud.fields}
    f32, u8 = PointField.FLOAT32, PointField.UINT8
    assert fields == {'x': (0, f32, 1), 'y': (4, f32, 1), 'z': (8, f32, 1),
                      'displacement': (12, f32, 1), 'von_mises': (16, f32, 1), 'region': (20, u8, 1),
                      'held': (21, u8, 1), 'severed': (22, u8, 1)}
    assert cloud.is_dense                                    # nothing cut away
    pts = unpack_points(cloud.data, cloud.width)
    xyz = np.stack([pts['x'], pts['y'], pts['z']], axis=1)
    assert np.all(np.isfinite(xyz))
    # the block spans 8 x 8 x 4 cm (particles 5 mm inside the faces), pressed by at most 4 mm
    assert xyz.min(axis=0) == pytest.approx([0.005, 0.005, 0.005], abs=1e-3)
    assert xyz.max(axis=0) == pytest.approx([0.075, 0.075, 0.035], abs=1e-3)
    assert pts['displacement'].max() > 1e-4
    assert set(np.unique(pts['region'])) >= {0, 1}     # still particles and an interaction area
    assert pts['von_mises'].max() > 0.0 and np.all(pts['von_mises'] >= 0.0)


def test_reset_in_contact_returns_tissue_to_rest_and_force_stays_bounded(probe, rclpy_node):
    t0 = _unique_t0(4)
    path = press_path(40, depth=0.004)
    probe.run_path(path, t0)
    last_ns = t0 + (len(path) - 1) * 1_000_000
    # the renderer answered every pose; wait until the solver has stepped the last one too
    assert probe.node.spin_until(lambda: any(stamp_ns(m.header) == last_ns for m in probe.metrics), 10.0)
    sim_time = [m.sim_time for m in probe.metrics if stamp_ns(m.header) == last_ns][-1]
    assert 0.0 < sim_time <= 40e-3 + 1e-9
    res = call_reset(rclpy_node, keep_material=False)
    assert res.success and res.n_particles == N_BLOCK
    assert res.sim_time == pytest.approx(sim_time, rel=1e-9)
    assert 'reset' in res.message
    # the stylus is still 4 mm deep: the next steps start from the undeformed tissue, and the force
    # comes back once the solver thread has stepped there (held poses until it has: its first step
    # may take longer than a few poses on a busy machine)
    t1 = t0 + 100_000_000
    forces = _hold_until_pushed(probe, path[-1], t1, at_least=20)
    assert finite_and_bounded(forces, FORCE_LIMIT)
    assert forces[-1][1] > 0.0
    assert probe.node.spin_until(lambda: any(stamp_ns(m.header) >= t1 for m in probe.metrics), 10.0)
    first = next(m for m in probe.metrics if stamp_ns(m.header) >= t1)
    # sim time restarted: the first pose after the reset steps nominal_dt, then 1 ms per pose
    assert first.sim_time == pytest.approx((stamp_ns(first.header) - t1) * 1e-9 + 1e-3, rel=1e-6)


# -- bad input ---------------------------------------------------------------------------------------
def test_bad_poses_get_zero_force_and_the_node_keeps_running(probe, live_sim):
    t0 = _unique_t0(5)
    hold = np.repeat(press_path(1, depth=0.0, start_height=-0.004), 120, axis=0)
    path = np.concatenate([press_path(30, depth=0.004), hold])
    probe.run_path(path, t0)                           # pressed in and settled
    # until the solver thread has stepped there (its first steps in contact solve the organ's
    # responses: longer than the hold on a busy machine)
    t_held = t0 + len(path) * 1_000_000
    held = _hold_until_pushed(probe, hold[0], t_held, up=0.03)
    last_valid = t_held + (len(held) - 1) * 1_000_000
    # where the hand held it last (it pushed on while it waited): going back up to hold[0] would be
    # a withdrawal, whose force the energy bound rightly lowers
    last_at = hold[0] - np.array([0.0, HOLD_CREEP * (len(held) - 1), 0.0])
    nan, inf = float('nan'), float('inf')
    bad = [((nan, 0.0, 0.0), 'omni_base'), ((0.0, inf, 0.0), 'omni_base'),
           ((0.0, -1e6, 0.0), 'omni_base'), ((0.0, -0.004, 0.0), 'tissue')]
    t1 = t0 + 1_000_000_000
    for k, (pos, frame) in enumerate(bad):
        w = probe.exchange(pos, t1 + k * 1_000_000, frame=frame)
        assert np.all(force_of(w) == 0.0)
        assert w.header.frame_id == frame
    # stamps going backwards, a repeat, and a jump of 5 s: answered, finite and bounded
    # (rejected poses do not advance the clock)
    seq = [last_valid - 10_000_000, last_valid - 20_000_000, last_valid - 20_000_000,
           last_valid + 5_000_000_000]
    forces = [force_of(probe.exchange(last_at, ns)) for ns in seq]
    assert finite_and_bounded(forces, FORCE_LIMIT)
    assert forces[1][1] > 0.02                         # still pressed: the tissue pushes back
    assert np.array_equal(forces[1], forces[2])        # a repeated stamp is answered the same
    out = live_sim.output()
    for text in ('rejected pose (non-finite position)', 'max_device_distance',
                 "rejected pose (frame 'tissue' is not 'omni_base')", 'stamp went backwards',
                 'stamp jumped'):
        assert text in out
    assert live_sim.alive()


def test_flood_of_poses_in_live_mode_drops_to_the_newest_without_backlog(probe, live_sim):
    t0 = _unique_t0(6)
    n = 3000
    period = 20_000_000                                 # max_dt: each step is a full 20 ms frame
    path = press_path(n, depth=0.004)
    for k in range(n):                                  # as fast as Python publishes
        probe.publish(path[k], t0 + k * period)
    last_ns = t0 + n * period
    w = probe.exchange(path[-1], last_ns, timeout=30.0)
    replies = [ns for ns in probe.force_order if t0 <= ns <= last_ns]
    assert replies == sorted(replies)                   # never an older pose after a newer one
    # publishing a pose costs far less than stepping a 20 ms frame (tens of sub-steps), whatever
    # the machine: poses were dropped, not worked off one by one
    assert len(replies) < n
    forces = [force_of(probe.forces[ns]) for ns in replies] + [force_of(w)]
    assert finite_and_bounded(forces, FORCE_LIMIT)
    # and the node goes on normally: holding the stylus there, the tissue pushes back (once the
    # solver thread, which the flood kept busy with 20 ms frames, has stepped there)
    hold = _hold_until_pushed(probe, path[-1], last_ns + 1_000_000, at_least=100)
    assert finite_and_bounded(hold, FORCE_LIMIT) and hold[-1][1] > 0.0
    assert live_sim.alive()


def test_ctrl_c_while_poses_stream_in_exits_0_every_time(rclpy_node):
    """Ctrl-C arrives while pose callbacks run; the node finishes its shutdown and exits 0.

    With rclpy's own signal handlers (the context shut down from another thread, a
    KeyboardInterrupt raised inside callbacks) a node spun by the EventsExecutor occasionally
    exited 1 with a RuntimeError from spin_once, seen on a loaded machine in the fault test.
    """
    import signal

    probe = SimProbe(rclpy_node)
    hold = press_path(1, depth=0.004, start_height=-0.004)[0]   # in contact: every step publishes
    for k in range(4):
        proc = sim()
        with proc:
            probe.wait_matched(proc)
            t0 = _unique_t0(20 + k)
            probe.exchange(hold, t0)
            # stream poses as fast as Python publishes; Ctrl-C lands at a different moment each run
            i, deadline = 0, time.monotonic() + 20.0
            while proc.alive() and time.monotonic() < deadline:
                i += 1
                probe.publish(hold + [0.0, 1e-5 * (i % 7), 0.0], t0 + i * 100_000)
                if i == 300 + 97 * k:
                    proc.send_signal(signal.SIGINT)
            code = proc.wait(15.0)
            out = proc.output()
        assert code == 0 and 'Traceback' not in out, (code, out[-3000:])
        assert 'totals:' in out   # the shutdown ran to the end


#: ``ros2 launch`` sends SIGTERM this long after SIGINT (its sigterm_timeout default)
LAUNCH_SIGTERM_AFTER = 5.0


def test_sigint_in_a_live_session_exits_before_launch_sends_sigterm_with_the_totals(rclpy_node):
    """A 3 s press at the device's 1 kHz, poses still coming when SIGINT arrives (launch stops
    every node at once): exit 0 within launch's grace, the shutdown's totals and step times said."""
    import signal

    # a namespace of its own: the module's live node must not answer this probe's handshake
    probe = SimProbe(rclpy_node, ns='/stop/')
    path = press_path(3000, depth=0.004)
    with sim(ros_args=['-r', '__ns:=/stop']) as proc:
        probe.wait_matched(proc)
        t0, sigint = _unique_t0(40), None
        start = time.monotonic()
        for k, point in enumerate(path):
            if not proc.alive():
                break
            probe.publish(point, t0 + k * 1_000_000)
            if k == 2500:
                sigint = time.monotonic()
                proc.send_signal(signal.SIGINT)
            if k % 10 == 0:
                rclpy_node.spin_until(lambda: False, max(0.0, start + k * 1e-3 - time.monotonic()))
        assert sigint is not None, proc.output()[-3000:]       # it was still running then
        code = proc.wait(30.0)
        elapsed = time.monotonic() - sigint
        out = proc.output()
    assert code == 0 and 'Traceback' not in out, (code, out[-3000:])
    totals = re.search(r'totals: (\d+) poses, (\d+) steps', out)
    # poses are best effort: a busy machine loses some of the 2500 sent before SIGINT
    assert totals and int(totals[1]) >= 1000 and int(totals[2]) > 0, out[-3000:]
    assert 'step wall time median' in out and 'still inside a step' not in out, out[-3000:]
    assert elapsed < LAUNCH_SIGTERM_AFTER, (f'{elapsed:.2f} s from SIGINT to exit', out[-3000:])


# -- parameters ----------------------------------------------------------------------------------------
def test_runtime_parameters_are_applied_or_refused_with_a_reason(probe, rclpy_node):
    bad = set_parameters(rclpy_node, {'force_limit': 10.0})
    assert not bad[0].successful and bad[0].reason
    bad = set_parameters(rclpy_node, {'mode': 'sideways'})
    assert not bad[0].successful and 'mode must be one of' in bad[0].reason
    bad = set_parameters(rclpy_node, {'k1_min': 50.0})             # above k1_max 6
    assert not bad[0].successful and 'k1_min' in bad[0].reason
    bad = set_parameters(rclpy_node, {'model': 'beam'})            # read-only
    assert not bad[0].successful
    bad = set_parameters(rclpy_node, {'material': 'unobtainium'})
    assert not bad[0].successful and 'unobtainium' in bad[0].reason
    # accepted: a tighter force limit, applied at the next step
    ok = set_parameters(rclpy_node, {'force_limit': 0.05})
    assert ok[0].successful
    try:
        path = press_path(40, depth=0.006)
        forces = probe.run_path(path, _unique_t0(7))
        # 6 mm deep the tissue pushes back far more than 0.05 N, once the solver has stepped there
        held = _hold_until_pushed(probe, path[-1], _unique_t0(7) + len(path) * 1_000_000, up=0.049)
        assert finite_and_bounded(list(forces) + list(held), 0.05)
        # up to the limit, not at it to the bit: live, the energy bound may hold a slowly pushing
        # hand a little below it (49.4 mN seen)
        assert np.linalg.norm(held[-1]) == pytest.approx(0.05, rel=0.02)
        # accepted: global mode (solver rebuilt between steps)
        ok = set_parameters(rclpy_node, {'mode': 'global', 'material': 'liver_soft'})
        assert ok[0].successful and ok[1].successful
        probe.run_path(press_path(20, depth=0.004), _unique_t0(8))
        assert probe.node.spin_until(lambda: probe.metrics and probe.metrics[-1].mode == 0, 10.0)
        assert probe.metrics[-1].n_interaction == N_BLOCK - 64     # every free particle
    finally:
        assert all(r.successful for r in set_parameters(
            rclpy_node, {'force_limit': FORCE_LIMIT, 'mode': 'local', 'material': 'liver'}))


@pytest.mark.parametrize('params, message', [
    ({'n_particles': 3}, r'parameter n_particles'),
    ({'scheme': 'magic'}, r'scheme must be one of'),
    ({'k1_min': 9.0, 'k1_max': 2.0}, r'k1_min .* must be <= k1_max'),
    ({'rotation': [0.0, 0.0, 0.0, 0.0]}, r'rotation quaternion'),
    ({'instruments': ['left', 'left']}, r"'left' is named twice"),
    ({'instruments': ['left', '2nd']}, r"'2nd' is not a valid namespace"),
    ({'instruments': ['left', 'right'], 'haptic_mode': 'direct'}, r'need haptic_mode multirate'),
    ({'instruments': ['left', 'right'], 'instrument_tools': ['', 'cube 0.01']}, r"'cube 0.01' is not 'sphere R'"),
    ({'instruments': ['left', 'right'], 'instrument_tools': ['', 'sphere 0.5']},
     r"instrument 1's tool: tool_radius must be in"),
    ({'instruments': ['left', 'right'], 'instrument_offsets': [0.0, 0.0]},
     r'three per instrument'),
    ({'grasp_input': 'button3'}, r"grasp_input must be one of '', button1, button2, jaw, got 'button3'"),
    ({'tool_shape': 'blade', 'scheme': 'paper'}, r'a blade cuts the reference bonds of scheme tlsph; scheme paper has none'),
    ({'tool_shape': 'needle', 'scheme': 'mass_spring'}, r'a needle pierces the tissue of scheme tlsph'),
    ({'instruments': ['left', 'right'], 'instrument_tools': ['blade 0.0005 0.02', 'blade 0.0005 0.03']},
     r'one blade per tissue'),
    ({'grasp_input': 1}, r"parameter grasp_input: .*expecting type 'STRING'"),    # a number: the choices are strings
])
def test_invalid_start_parameters_exit_with_code_2_and_say_why(ros_domain, params, message):
    with sim({**params, 'warmup': False}) as proc:
        assert proc.wait(60) == 2
        out = proc.output()
    assert re.search(r'invalid parameters: .*' + message, out), out
    assert 'Traceback' not in out


def test_missing_mesh_exits_with_code_1(ros_domain, tmp_path):
    with sim({'model': 'mesh', 'mesh_path': str(tmp_path / 'nope.stl'), 'warmup': False}) as proc:
        assert proc.wait(60) == 1
        out = proc.output()
    assert 'cannot build the tissue: mesh file not found' in out and 'Traceback' not in out


# -- lockstep ---------------------------------------------------------------------------------------------
def test_lockstep_answers_every_pose_in_order_and_replays_bit_identically(rclpy_node):
    """Two processes (stepping in the callback, then in a worker thread), each replaying the same
    pose sequence twice with a reset between: four bit-identical force sequences."""
    n = 300
    path = press_path(n, depth=0.005, start_height=0.002)
    path[:, 0] += np.linspace(0.0, 0.006, n)              # press and drag
    runs = []
    for step_thread in (False, True):
        ns = f'/lock{int(step_thread)}/'                   # the module's live node shares the domain
        with sim({'timing_mode': 'lockstep', 'step_thread': step_thread},
                 ros_args=['-r', f'__ns:={ns[:-1]}']) as proc:
            probe = SimProbe(rclpy_node, reliable=True, ns=ns)
            probe.wait_matched(proc)
            for run in range(2):
                t0 = _unique_t0(20 + 2 * step_thread + run)   # different stamps, same differences
                probe.force_order.clear()
                for k in range(n):                        # all at once: the node queues them
                    probe.publish(path[k], t0 + k * 1_000_000)
                assert rclpy_node.spin_until(lambda: len(probe.force_order) >= n, 60.0), proc.output()
                assert probe.force_order == [t0 + k * 1_000_000 for k in range(n)]
                runs.append(np.array([force_of(probe.forces[st]) for st in probe.force_order]))
                assert call_reset(rclpy_node, ns=ns).success
            assert 'timing lockstep' in proc.output()
            assert proc.stop() == 0
    a = runs[0]
    assert finite_and_bounded(a, FORCE_LIMIT)
    assert np.abs(a[:, 1]).max() > 0.05                    # the sequence did touch the tissue
    same = [r.tobytes() == a.tobytes() for r in runs[1:]]
    assert all(same), (same, [np.abs(r - a).max() for r in runs[1:]])   # bit-identical, run after run


def test_threaded_live_mode_steps_only_the_newest_pose(rclpy_node):
    """step_thread: poses that arrive while the worker steps wait in a one-pose inbox, each newer
    pose replacing (dropping) the older one, so the next step is always the newest pose.

    Slow by construction, not by the machine: 2000 particles in global mode and 20 ms (max_dt)
    between stamps make every step after the first 60 sub-steps over the whole block (hundreds of ms
    here), against a burst that Python publishes in about a millisecond. Reliable QoS with a history
    as deep as the burst delivers every pose to the node, so the inbox is the only place a pose can
    be dropped and the node's bookkeeping can be checked exactly.
    """
    n = 30
    period = 20_000_000
    path = press_path(n, depth=0.003, start_height=0.0)    # in contact throughout
    params = {'step_thread': True, 'particles_rate': 0.0, 'mode': 'global', 'n_particles': 2000,
              'reliable': True, 'qos_depth': n, 'haptic_mode': 'direct'}
    with sim(params, ros_args=['-r', '__ns:=/thr']) as proc:
        probe = SimProbe(rclpy_node, reliable=True, ns='/thr/')
        probe.wait_matched(proc)
        t0 = _unique_t0(30)
        probe.publish(path[0], t0)                         # the node is idle: stepped at once
        assert rclpy_node.spin_until(lambda: t0 in probe.forces, 60.0), proc.output()
        for k in range(1, n):                              # the rest arrive during the next step
            probe.publish(path[k], t0 + k * period)
        last_ns = t0 + (n - 1) * period
        assert rclpy_node.spin_until(lambda: last_ns in probe.forces, 120.0), proc.output()
        replies = list(probe.force_order)
        assert proc.stop() == 0
        m = re.search(r'totals: (\d+) poses, (\d+) steps, (\d+) dropped .*?, (\d+) rejected',
                      proc.output())
    assert m, proc.output()
    poses, steps, dropped, rejected = map(int, m.groups())
    # reliable and deep enough: none lost (the probe's handshake poses are rejected by the node)
    assert poses == n + probe.handshakes_sent and rejected <= probe.handshakes_sent
    assert steps + dropped + rejected == poses             # each pose stepped, dropped or rejected
    assert replies == sorted(set(replies)) and len(replies) == steps   # one reply per step, in order
    assert replies[0] == t0 and replies[-1] == last_ns     # the newest pose is always stepped...
    assert dropped > 0                                     # ...and the older ones were not
    assert finite_and_bounded([force_of(probe.forces[ns]) for ns in replies], FORCE_LIMIT)


def test_multirate_live_answers_every_pose_while_the_solver_steps_slow_frames(rclpy_node):
    """The same burst as above in multirate mode: every pose is answered, in order, by the
    renderer while the solver thread takes hundreds of milliseconds per global frame; the solver
    steps fewer times than there were poses and never drops one (it simulates their whole time)."""
    n = 30
    period = 20_000_000
    path = press_path(n, depth=0.003, start_height=0.0)
    params = {'particles_rate': 0.0, 'mode': 'global', 'n_particles': 2000, 'reliable': True,
              'qos_depth': n}
    with sim(params, ros_args=['-r', '__ns:=/mr']) as proc:
        probe = SimProbe(rclpy_node, reliable=True, ns='/mr/')
        probe.wait_matched(proc)
        t0 = _unique_t0(31)
        for k in range(n):
            probe.publish(path[k], t0 + k * period)
        last_ns = t0 + (n - 1) * period
        assert rclpy_node.spin_until(lambda: last_ns in probe.forces, 60.0), proc.output()
        replies = [ns for ns in probe.force_order if ns >= t0]
        # a frame finished (the shutdown interrupts one in progress)
        assert rclpy_node.spin_until(lambda: len(probe.metrics) > 0, 60.0), proc.output()
        assert proc.stop() == 0
        m = re.search(r'totals: (\d+) poses, (\d+) steps, (\d+) dropped .*?, (\d+) rejected',
                      proc.output())
    assert m, proc.output()
    poses, steps, dropped, rejected = map(int, m.groups())
    assert replies == [t0 + k * period for k in range(n)]  # every pose, in order
    assert dropped == 0 and 1 <= steps < n
    assert finite_and_bounded([force_of(probe.forces[ns]) for ns in replies], FORCE_LIMIT)


def test_scripted_driver_press_is_felt_through_the_default_device_mapping(rclpy_node):
    """omni_driver (scripted press of its target (0, 0, 0) along device -y) + sim_node with the
    default mapping: the tissue pushes the stylus back up (device +y) and the driver accepts every
    force reply and renders that push.

    Live timing decides which poses are stepped, so the script is one whose contact force points up
    whichever poses are stepped: a 4 mm press (deeper, a pressed particle of this coarse block can
    slide sideways under the 5 mm tool and the sideways force can exceed the press), no lateral drag
    and no sweep stroke; the only sideways motion left is the script's tremor (0.15 mm). The script
    repeats until the press has been felt: on a busy machine the sim may answer no pose at all
    during one press.
    """
    from geometry_msgs.msg import WrenchStamped
    from tissue_msgs.msg import DeviceState

    forces, states = [], []
    felt = {'replies': 0, 'rendered': False}

    def on_force(msg) -> None:
        forces.append(force_of(msg))
        felt['replies'] += forces[-1][1] > 0.1

    def on_state(msg) -> None:
        states.append(msg)
        felt['rendered'] |= msg.force_enabled and msg.commanded_force.y > 0.1

    rclpy_node.create_subscription(WrenchStamped, '/sys/omni/force_feedback', on_force,
                                   qos(False, 10000))
    rclpy_node.create_subscription(DeviceState, '/sys/omni/state', on_state, qos(True, 10000))
    ns = ['-r', '__ns:=/sys']
    script = {'backend': 'scripted', 'loop': True, 'wait_for_subscribers': 1,
              'press_depth': 0.004, 'pull_distance': 0.0, 'sweep_length': 0.0, 'sweep_depth': 0.0,
              'approach_time': 0.3, 'press_time': 0.6, 'hold_time': 0.6, 'pull_time': 0.3,
              'release_time': 0.3, 'sweep_time': 0.3, 'return_time': 0.3,
              # no ramp: the device renders each accepted reply as it is
              'ramp_time': 0.0, 'watchdog_timeout': 0.05, 'state_rate': 200.0}
    with sim({'particles_rate': 0.0}, ros_args=ns) as sim_proc:
        sim_proc.wait_for_output(r'ready:', START_TIMEOUT)
        with harness.NodeProcess('haptic_omni_driver', 'omni_driver', params=script,
                                 ros_args=ns) as drv:
            # pushed up in 20 replies and rendered by the device, however many presses that takes
            rclpy_node.spin_until(
                lambda: (felt['replies'] >= 20 and felt['rendered']) or not drv.alive(), 120)
            assert felt['replies'] >= 20 and felt['rendered'], \
                (felt, drv.output()[-3000:], sim_proc.output()[-3000:])
            assert drv.stop() == 0, drv.output()
            driver_out = drv.output()
        seen = -1
        while seen != len(forces) + len(states):               # drain what is still queued
            seen = len(forces) + len(states)
            rclpy_node.spin_until(lambda: False, 0.3)
    # best effort at 1 kHz on a loaded machine: how many replies arrive is not the point
    f = np.array(forces).reshape(-1, 3)
    assert finite_and_bounded(f, FORCE_LIMIT)
    # in clear contact the force points up, the press dominating (measured here: the sideways part
    # stays below 0.1 of it; at the first and last touch it can reach 0.4 of a few tens of mN)
    contact = f[np.linalg.norm(f, axis=1) > 0.1]
    sideways = contact[contact[:, 1] <= np.hypot(contact[:, 0], contact[:, 2])]
    assert len(contact) and len(sideways) == 0, sideways[:10]
    # every reply is in the driver's frame and answers a pose it sent; on a busy machine a reply the
    # sim sent after a long stall may answer a pose older than max_command_lag: rightly stale, and
    # the only rejection allowed (the driver logs each reason it rejects for)
    reasons = re.findall(r'rejected force command \((\w+)', driver_out)
    assert set(reasons) <= {'stale'}, driver_out



def test_a_capsule_chosen_by_parameter_follows_the_stylus_orientation_and_is_pushed_normal_to_its_shaft(
        rclpy_node):
    """tool_shape capsule through the node: the stylus orientation (device frame) tilts the shaft
    20 degrees down towards tissue +x, the device map takes the shaft onto the liver (tip in the
    air), and the force sent back, taken into the tissue frame, is normal to the shaft
    (test_core_tools checks the same press in the core)."""
    from tissue_common.rotation import matrix_quaternion, quaternion_matrix

    from sph_tissue_sim.core.factory import make_model
    from sph_tissue_sim.core.tools import Capsule
    from sph_tissue_sim.mapping import DEFAULT_ROTATION

    n, radius, length = 2000, 0.004, 0.15
    model = make_model('liver', n_particles=n)          # the node builds the same model
    # particles meet the tool one spacing from their centre (the core's BALL_RADIUS)
    tips, rot, axis = tilted_shaft_press(model.positions, Capsule(radius, length), model.spacing,
                                         math.radians(20.0), 0.004)
    r_map = quaternion_matrix(DEFAULT_ROTATION)          # device -> tissue (anchor origin: no offset)
    params = {'model': 'liver', 'n_particles': n, 'tool_shape': 'capsule', 'tool_radius': radius,
              'tool_length': length, 'anchor': 'origin', 'particles_rate': 0.0,
              'haptic_mode': 'direct'}     # the solver's tool at the device's pose (no coupling)
    with sim(params, ros_args=['-r', '__ns:=/cap']) as proc:     # apart from the module's sim
        probe = SimProbe(rclpy_node, ns='/cap/')
        probe.wait_matched(proc)
        probe.orientation = matrix_quaternion(r_map.T @ rot)
        forces = probe.run_path(tips @ r_map, _unique_t0(40))      # rows: R^T p for each tip
        # the metrics report the simulated tool in the tissue frame (what tissue_viz draws)
        assert rclpy_node.spin_until(lambda: any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                                 == _unique_t0(40) + (len(tips) - 1) * 1_000_000
                                                 for m in probe.metrics), 10.0)
        last = probe.metrics[-1]
        p, a = last.tool_position, last.tool_axis
        assert (p.x, p.y, p.z) == pytest.approx(tuple(tips[-1]), abs=1e-9)
        assert (a.x, a.y, a.z) == pytest.approx(tuple(axis), abs=1e-9)
        assert (last.tool_length, last.tool_radius) == pytest.approx((length, radius))
        assert proc.stop() == 0
    f = r_map @ forces[-1]                                   # back into the tissue frame
    print(f'capsule force through the node (tissue frame): {f} N')
    assert np.linalg.norm(f) > 0.1 and f[2] > 0.0
    assert abs(f @ axis) < 0.05 * np.linalg.norm(f)
    assert f[0] / f[2] == pytest.approx(math.tan(math.radians(20.0)), rel=0.25)


def test_a_blade_chosen_by_parameter_cuts_and_the_metrics_and_cloud_show_the_cut(rclpy_node):
    """tool_shape blade through the node: the edge held upright (tissue +z) is plunged into the top
    of the block and drawn along it; the metrics count the bonds it cut and the crack's area, and
    the cloud's severed byte marks the cut faces."""
    from tissue_common.rotation import matrix_quaternion, quaternion_matrix

    from sph_tissue_sim.cloud import unpack_points
    from sph_tissue_sim.mapping import DEFAULT_ROTATION

    from sph_tissue_sim.core.factory import make_model

    r_map = quaternion_matrix(DEFAULT_ROTATION)          # device -> tissue (anchor origin: no offset)
    X = make_model('block', size=BLOCK['block_size'], n_particles=N_BLOCK).positions   # the node's block
    spacing, top = 0.01, X[:, 2].max()
    y = X[:, 1].min() + 3.5 * spacing + 0.0011           # between two rows
    x0, x1 = X[:, 0].min() + 1.5 * spacing, X[:, 0].min() + 4.5 * spacing
    plunge = np.stack([np.full(150, x0), np.full(150, y), np.linspace(top + 0.002, top - 0.012, 150)], axis=1)
    drawn = np.stack([np.linspace(x0, x1, 300), np.full(300, y), np.full(300, top - 0.012)], axis=1)
    tips = np.concatenate([plunge, drawn])
    params = {'tool_shape': 'blade', 'tool_radius': 0.0005, 'tool_length': 0.02, 'material': 'custom', 'toughness': 20.0,
              'anchor': 'origin', 'particles_rate': 50.0, 'haptic_mode': 'direct'}
    with sim(params, ros_args=['-r', '__ns:=/blade']) as proc:
        probe = SimProbe(rclpy_node, ns='/blade/')
        probe.wait_matched(proc)
        probe.orientation = matrix_quaternion(r_map.T)    # the tool's +z along tissue +z
        probe.run_path(tips @ r_map, _unique_t0(41))
        assert rclpy_node.spin_until(lambda: any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                                 == _unique_t0(41) + (len(tips) - 1) * 1_000_000
                                                 for m in probe.metrics), 10.0)
        last = probe.metrics[-1]
        n_clouds = len(probe.clouds)
        assert rclpy_node.spin_until(lambda: len(probe.clouds) > n_clouds, 10.0)
        cloud = probe.clouds[-1]
        assert proc.stop() == 0
    assert last.n_bonds_cut > 10 and last.crack_area > 0.0
    points = unpack_points(cloud.data, N_BLOCK)
    severed = points['severed']
    assert np.count_nonzero(severed) >= 4
    # the cut faces are where the blade went: beside its path, not at the far end of the block
    faces = np.stack([points['x'], points['y']], axis=1)[severed > 0]
    faces = faces[np.isfinite(faces).all(axis=1)]           # a particle the cut removed is NaN
    # a bond reaches 2h = 2.6 spacings: a particle that lost one lies that near the blade's plane and path
    reach = 2.6 * spacing + 0.002
    assert len(faces) and np.all(np.abs(faces[:, 1] - y) < reach)
    assert np.all((faces[:, 0] > x0 - reach) & (faces[:, 0] < x1 + reach))


def test_a_needle_chosen_by_parameter_punctures_and_the_metrics_and_cloud_show_its_track(rclpy_node):
    """tool_shape needle through the node: held upright and pushed 25 mm down into the top of the
    block, its state goes touching, then inserted with a depth below the entry point; the cloud's
    held byte marks the particles along its shaft."""
    from tissue_common.rotation import matrix_quaternion, quaternion_matrix

    from sph_tissue_sim.cloud import unpack_points
    from sph_tissue_sim.core.factory import make_model
    from sph_tissue_sim.mapping import DEFAULT_ROTATION
    from tissue_msgs.msg import SimMetrics

    r_map = quaternion_matrix(DEFAULT_ROTATION)          # device -> tissue (anchor origin: no offset)
    X = make_model('block', size=BLOCK['block_size'], n_particles=N_BLOCK).positions   # the node's block
    top = X[:, 2].max()
    xy = X[:, :2].mean(axis=0) + 0.002
    tips = np.stack([np.full(500, xy[0]), np.full(500, xy[1]),
                     np.concatenate([np.linspace(top + 0.003, top - 0.025, 400), np.full(100, top - 0.025)])],
                    axis=1)
    params = {'tool_shape': 'needle', 'tool_radius': 0.0005, 'tool_length': 0.06, 'material': 'custom',
              'toughness': 50.0, 'anchor': 'origin', 'particles_rate': 50.0, 'haptic_mode': 'direct'}
    with sim(params, ros_args=['-r', '__ns:=/needle']) as proc:
        probe = SimProbe(rclpy_node, ns='/needle/')
        probe.wait_matched(proc)
        probe.orientation = matrix_quaternion(r_map.T)    # the tool's +z along tissue +z
        probe.run_path(tips @ r_map, _unique_t0(43))
        assert rclpy_node.spin_until(lambda: any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                                 == _unique_t0(43) + (len(tips) - 1) * 1_000_000
                                                 for m in probe.metrics), 10.0)
        states = [m.needle_state for m in probe.metrics]
        last = probe.metrics[-1]
        n_clouds = len(probe.clouds)
        assert rclpy_node.spin_until(lambda: len(probe.clouds) > n_clouds, 10.0)
        cloud = probe.clouds[-1]
        assert proc.stop() == 0
    touching, inserted = SimMetrics.NEEDLE_TOUCHING, SimMetrics.NEEDLE_INSERTED
    assert touching in states and states.index(touching) < states.index(inserted)
    assert last.needle_state == inserted and 0.005 < last.needle_depth < 0.028
    assert last.contact_force.z > 0.0                     # the tissue resists along the shaft
    points = unpack_points(cloud.data, N_BLOCK)
    track = np.stack([points['x'], points['y'], points['z']], axis=1)[points['held'] == 1]
    assert len(track) >= 2
    # held along the shaft: near its axis, below the top and above the tip
    assert np.all(np.linalg.norm(track[:, :2] - xy, axis=1) < 0.016)
    assert np.all(track[:, 2] > top - 0.025 - 1e-3)


@pytest.mark.parametrize('haptic_mode, step_thread', [(None, None), ('direct', None), ('direct', False)])
def test_shipped_config_starts_the_liver_model(ros_domain, haptic_mode, step_thread):
    share = harness.INSTALL / 'sph_tissue_sim' / 'share' / 'sph_tissue_sim' / 'config'
    extra = {} if step_thread is None else {'step_thread': step_thread}
    if haptic_mode is not None:
        extra['haptic_mode'] = haptic_mode
    with harness.NodeProcess('sph_tissue_sim', 'sim_node', params_file=share / 'sim_node.yaml',
                             params={'n_particles': 500, 'particles_rate': 0.0,
                                     'qos_depth': 5, **extra}) as proc:
        m = proc.wait_for_output(r'ready: model (\S+) \((\d+) particles', START_TIMEOUT)
        out = proc.output()
        assert proc.stop() == 0
    assert re.search(r'numba warm-up \(compile or cache load\) and first step: [0-9.]+ s', out)
    assert 'scheme tlsph, mode local, contact 3x3 samples per surface particle (backstop), far field organ' in out
    # the shipped far field is the organ's own on a liver this small, factored when first needed
    assert re.search(r'far field organ x1 \([0-9]+ responses on disk, factored when first needed\), '
                     r'material liver', out)
    assert 'timing live' in out
    if haptic_mode is None:
        # the shipped multirate answers in microseconds: at least 10 poses carry over a stall
        assert 'pose history depth' not in out and 'pose QoS best effort depth 10' in out
    elif step_thread is None:
        # direct steps in a thread fed by a newest-pose inbox: the transport queue may be deeper
        # without a backlog
        assert 'pose history depth' not in out and 'pose QoS best effort depth 5' in out
    else:
        # stepping in the callback, a deeper pose history would be a backlog: forced to 1
        assert 'pose history depth 5 -> 1' in out and 'pose QoS best effort depth 1' in out
    assert m.group(1) in ('liver', 'block')        # block: a core without the liver generator
    if m.group(1) == 'block':
        assert 'model liver is not available' in out
    assert abs(int(m.group(2)) - 500) <= 50


def test_driver_lockstep_bag_replay_gives_bit_identical_forces_run_after_run(rclpy_node, tmp_path):
    """The regression use: omni_driver replays a bag in lockstep (each pose waits for its force),
    sim_node in lockstep; two separate runs (fresh processes) give the same force bytes."""
    from geometry_msgs.msg import WrenchStamped
    from haptic_omni_driver.bag_types import POSE_TYPE, typestore
    from haptic_omni_driver.bag_writer import write_bag

    n = 200
    ts = typestore().types
    Time, Header = ts['builtin_interfaces/msg/Time'], ts['std_msgs/msg/Header']
    Pose, Point, Quat = (ts['geometry_msgs/msg/Pose'], ts['geometry_msgs/msg/Point'],
                         ts['geometry_msgs/msg/Quaternion'])
    path = press_path(n, depth=0.005, start_height=0.003)
    path[:, 0] += np.linspace(0.0, 0.005, n)
    records = []
    for k, p in enumerate(path):
        stamp = T0_NS + k * 1_000_000
        msg = ts['geometry_msgs/msg/PoseStamped'](
            Header(Time(*divmod(stamp, 1_000_000_000)), 'omni_base'),
            Pose(Point(*map(float, p)), Quat(0.0, 0.0, 0.0, 1.0)))
        records.append(('/omni/pose', POSE_TYPE, stamp, msg))
    write_bag(tmp_path / 'press', records)

    runs = []
    for run in range(2):
        ns = f'/rep{run}'
        got = []
        sub = rclpy_node.create_subscription(WrenchStamped, f'{ns}/omni/force_feedback',
                                             lambda m, got=got: got.append(m), qos(True, 10000))
        with sim({'timing_mode': 'lockstep', 'particles_rate': 0.0},
                 ros_args=['-r', f'__ns:={ns}']) as sim_proc:
            sim_proc.wait_for_output(r'ready:', START_TIMEOUT)
            harness.wait_for_matching(rclpy_node, sub)
            with harness.NodeProcess('haptic_omni_driver', 'omni_driver', ros_args=['-r', f'__ns:={ns}'],
                                     params={'backend': 'replay', 'bag': str(tmp_path / 'press'),
                                             'replay_mode': 'lockstep', 'exit_on_end': True,
                                             'lockstep_timeout': 30.0}) as drv:
                assert rclpy_node.spin_until(lambda: not drv.alive(), 120), drv.output()
                assert drv.wait(5) == 0, drv.output()
                assert re.search(rf'replay finished: {n} poses .*{n} replies, 0 timeouts',
                                 drv.output()), drv.output()
            rclpy_node.spin_until(lambda: len(got) >= n, 30.0)
        assert [stamp_ns(m.header) for m in got] == [T0_NS + k * 1_000_000 for k in range(n)]
        runs.append(np.array([force_of(m) for m in got]))
    assert finite_and_bounded(runs[0], FORCE_LIMIT) and runs[0][:, 1].max() > 0.05
    assert runs[0].tobytes() == runs[1].tobytes()


@pytest.mark.slow
def test_lockstep_first_start_on_a_cold_numba_cache_matches_later_starts(rclpy_node, tmp_path):
    """First start after a core change: the kernels are compiled in the node's process (in a fresh
    cache here) and return the same forces as a later start's, which loads them from the cache
    (both for the portable CPU level: docs/decisions/portable-codegen-order.md)."""
    n = 150
    path = press_path(n, depth=0.005, start_height=0.002)
    path[:, 0] += np.linspace(0.0, 0.004, n)
    env = harness.ros_env(int(os.environ['ROS_DOMAIN_ID']))
    env['NUMBA_CACHE_DIR'] = str(tmp_path / 'numba_cache')
    runs, outputs = [], []
    for start in range(2):
        ns = f'/cold{start}/'
        with sim({'timing_mode': 'lockstep', 'particles_rate': 0.0},
                 ros_args=['-r', f'__ns:={ns[:-1]}'], env=env) as proc:
            probe = SimProbe(rclpy_node, reliable=True, ns=ns)
            probe.wait_matched(proc)
            for k in range(n):
                probe.publish(path[k], T0_NS + k * 1_000_000)
            assert rclpy_node.spin_until(lambda: len(probe.force_order) >= n, 60.0), proc.output()
            runs.append(np.array([force_of(probe.forces[st]) for st in probe.force_order]))
            assert proc.stop() == 0
            outputs.append(proc.output())
    assert '(0 kernels compiled' not in outputs[0], outputs[0]
    assert '(0 kernels compiled' in outputs[1], outputs[1]
    assert runs[0].tobytes() == runs[1].tobytes()
