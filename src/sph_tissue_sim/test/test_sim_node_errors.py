"""Error paths of sim_node's step, driven in-process (a real node object, poses handed to its
callback directly, published forces captured): unstable steps, refused inputs, internal errors, and
a fuzz of random poses and stamps; in direct mode (one step per pose) and in multirate mode with
the lockstep schedule (the renderer answers, the solver steps after each pose in the same thread)."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from sim_probe import BLOCK, GRASP_AT, T0_NS, press_path, run_grasp_lift

pytestmark = pytest.mark.ros


LIMIT = 0.5


def pose(pos, ns: int, frame: str = 'omni_base'):
    """A pose as the node hands it to its runner (the stamp a message's own)."""
    from builtin_interfaces.msg import Time

    from sph_tissue_sim.runner import Pose

    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Pose(Time(sec=sec, nanosec=nanosec), int(ns), frame, tuple(float(v) for v in pos), (0.0, 0.0, 0.0, 1.0))


@contextlib.contextmanager
def make_node(**extra):
    """An in-process sim_node on its own context; published forces land in ``node.sent``."""
    import rclpy
    from rclpy.parameter import Parameter

    from sph_tissue_sim.sim_node import SimNode

    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    params = {**BLOCK, 'force_limit': LIMIT, 'particles_rate': 0.0, 'warmup': False, **extra}
    n = SimNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    n.sent = []
    n.runner.send_force = lambda stamp, frame, f, k=0: n.sent.append(
        (stamp.sec * 1_000_000_000 + stamp.nanosec, np.array(f, dtype=float)))
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def node(ros_domain):
    with make_node(haptic_mode='direct') as n:
        yield n


@pytest.fixture(params=['direct', 'multirate'])
def any_node(request, ros_domain):
    with make_node(haptic_mode=request.param, timing_mode='lockstep') as n:
        yield n


@pytest.fixture
def multirate(ros_domain):
    with make_node(haptic_mode='multirate', timing_mode='lockstep') as n:
        yield n


def press(node, n: int = 60, t0: int = T0_NS) -> int:
    for k, p in enumerate(press_path(n, depth=0.004)):
        node.runner.handle(pose(p, t0 + k * 1_000_000))
    return t0 + n * 1_000_000


def test_unstable_step_answers_zero_and_resets_the_tissue(node, monkeypatch):
    from sph_tissue_sim.core.errors import SimError

    t = press(node)
    assert node.sent[-1][1][1] > 0.0 and node.runner.solver.sim_time > 0.0

    def unstable(poses, dt):
        raise SimError('tlsph local step went unstable')

    monkeypatch.setattr(node.runner.solver, 'step_tools', unstable)
    node.runner.handle(pose((0.0, -0.004, 0.0), t))
    assert node.sent[-1][0] == t and np.all(node.sent[-1][1] == 0.0)
    assert node.runner.counts['sim_errors'] == 1
    assert node.runner.solver.sim_time == 0.0
    assert np.array_equal(node.runner.solver.positions, node.model.positions)
    monkeypatch.undo()
    node.runner.handle(pose((0.0, 0.01, 0.0), t + 1_000_000))      # the clock restarted too
    assert node.runner.solver.sim_time == pytest.approx(node.p['nominal_dt'])


def test_input_refused_by_the_core_answers_zero_and_leaves_the_state(node, monkeypatch):
    from sph_tissue_sim.core.solver import InvalidInput

    t = press(node)
    before = node.runner.solver.positions.copy()
    monkeypatch.setattr(node.runner.solver, 'step_tools', lambda poses, dt: (_ for _ in ()).throw(
        InvalidInput('tool position is more than 10 m from the tissue')))
    node.runner.handle(pose((0.0, -0.004, 0.0), t))
    assert np.all(node.sent[-1][1] == 0.0)
    assert np.array_equal(node.runner.solver.positions, before)


def test_an_unexpected_exception_answers_zero_and_the_node_goes_on(node, monkeypatch):
    t = press(node)
    step = node.runner.solver.step_tools
    monkeypatch.setattr(node.runner.solver, 'step_tools', lambda poses, dt: 1 / 0)
    node.runner.handle(pose((0.0, -0.004, 0.0), t))
    assert node.sent[-1][0] == t and np.all(node.sent[-1][1] == 0.0)
    monkeypatch.setattr(node.runner.solver, 'step_tools', step)
    node.runner.handle(pose((0.0, -0.004, 0.0), t + 1_000_000))
    assert node.sent[-1][1][1] > 0.0


def test_random_poses_and_stamps_never_give_a_bad_force(any_node):
    """Valid presses mixed with NaN/inf/huge positions, foreign frames, repeated, backwards and
    jumping stamps: one reply per pose, always finite and within force_limit (both haptic modes)."""
    node = any_node
    rng = np.random.default_rng(1)
    t = T0_NS
    n = 600
    for k in range(n):
        r = rng.random()
        p = np.array([rng.normal(0, 0.01), rng.uniform(-0.012, 0.01), rng.normal(0, 0.01)])
        frame = 'omni_base'
        if r < 0.05:
            p[rng.integers(3)] = rng.choice([np.nan, np.inf, -np.inf])
        elif r < 0.08:
            p *= 1e6
        elif r < 0.10:
            frame = rng.choice(['', 'world', 'tissue'])
        s = rng.random()
        if s < 0.05:
            t -= int(rng.integers(1, 50_000_000))             # backwards
        elif s < 0.08:
            t += int(rng.integers(1, 3_000_000_000))          # jump
        elif s > 0.12:                                        # else: repeated stamp
            t += int(rng.integers(100_000, 2_000_000))
        node.runner.handle(pose(p, t, frame))
    assert len(node.sent) == n
    forces = np.array([f for _, f in node.sent])
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= LIMIT + 1e-12)
    assert np.any(np.linalg.norm(forces, axis=1) > 0.0)        # some presses were felt
    assert node.runner.counts["rejected"] > 0


def test_multirate_answers_from_the_renderer_and_steps_the_solver_after_each_pose(multirate):
    node = multirate
    t = press(node)
    assert node.runner.counts['steps'] == 60 and len(node.sent) == 60
    assert node.sent[-1][1][1] > 0.0                          # pushed back up (device y)
    status = node.runner.haptic.status()
    assert status.model_age == pytest.approx(1e-3) and status.stretch > 0.0
    node.runner.handle(pose((0.0, -0.004, 0.0), t - 1_000_000))     # a repeated stamp: the same answer
    assert np.array_equal(node.sent[-1][1], node.sent[-2][1]) and node.runner.counts['steps'] == 60


def test_multirate_unstable_solver_step_resets_the_tissue_and_the_renderer(multirate, monkeypatch):
    from sph_tissue_sim.core.errors import SimError

    node = multirate
    t = press(node)
    felt = node.sent[-1][1]
    assert felt[1] > 0.0

    def unstable(poses, dt):
        raise SimError('tlsph local step went unstable')

    monkeypatch.setattr(node.runner.solver, 'step_tools', unstable)
    node.runner.handle(pose((0.0, -0.004, 0.0), t))
    # the pose was answered from the contact model before the solver failed
    assert np.all(np.isfinite(node.sent[-1][1])) and np.linalg.norm(node.sent[-1][1]) <= LIMIT
    assert node.runner.counts['sim_errors'] == 1 and node.runner.solver.sim_time == 0.0
    assert node.runner.haptic.renderer.model.magnitude == 0.0        # the contact is forgotten
    monkeypatch.undo()
    node.runner.handle(pose((0.0, -0.004, 0.0), t + 1_000_000))
    assert np.all(node.sent[-1][1] == 0.0)                    # no model yet: nothing is pushed


def test_multirate_rejected_pose_is_answered_zero_and_charged_as_zero(multirate):
    node = multirate
    t = press(node)
    node.runner.handle(pose((np.nan, 0.0, 0.0), t))
    assert np.all(node.sent[-1][1] == 0.0) and node.runner.counts['rejected'] == 1
    assert np.all(node.runner.haptic.renderer.observer._f == 0.0)   # E_in charges what the device held


@pytest.fixture
def live_multirate(ros_domain):
    with make_node(haptic_mode='multirate', timing_mode='live') as n:
        n.start()
        try:
            yield n
        finally:
            n.shutdown()


def test_multirate_live_solver_thread_runs_nicer_than_the_answering_thread(live_multirate):
    import os
    import threading

    node = live_multirate
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    solver = os.getpriority(os.PRIO_PROCESS, node.runner._solver_thread.native_id)
    assert solver == min(mine + node.p['solver_nice'], 19) and node.p['solver_nice'] == 10


def test_multirate_live_pose_history_carries_poses_over_a_stall(live_multirate):
    from sph_tissue_sim.runner import MULTIRATE_MIN_DEPTH

    assert live_multirate.io_qos.depth >= MULTIRATE_MIN_DEPTH >= 10


def test_multirate_live_cloud_is_packed_and_published_by_the_solver_thread(live_multirate):
    import threading
    import time

    node = live_multirate
    published = threading.Event()
    threads = []

    class Recorder:
        def publish(self, msg):
            threads.append((threading.current_thread().name, msg.width))
            published.set()

    node.cloud_pub = Recorder()
    node.runner.cloud_tick()                      # what the cloud timer calls on the executor thread
    deadline = time.monotonic() + 30.0
    while not published.wait(0.1) and time.monotonic() < deadline:
        pass
    assert threads == [('sim_solver', node.runner.solver.n_particles)]


def test_lockstep_clouds_carry_the_simulation_clock_from_the_start(any_node):
    """Before the first pose a lockstep cloud has stamp zero (no simulated time yet), never the
    wall clock, so that the replay's older stamps do not run backwards; then the last pose's."""
    node = any_node
    stamps = []

    class Recorder:
        def publish(self, msg):
            stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)

    node.cloud_pub = Recorder()
    node.runner.send_cloud_once()
    last = press(node) - 1_000_000             # the last pose's stamp
    node.runner.send_cloud_once()
    assert stamps == [0, last]


def test_a_cloud_that_fails_to_publish_is_logged_and_the_next_one_goes_out(multirate):
    node = multirate
    press(node)
    sent = []

    class Flaky:
        def publish(self, msg):
            if not sent:
                sent.append(None)
                raise RuntimeError('transport gone')
            sent.append(msg.width)

    node.cloud_pub = Flaky()
    node.runner.send_cloud_once()                 # raises inside: logged, never out of the node
    node.runner.send_cloud_once()
    assert sent == [None, node.runner.solver.n_particles]
    assert node.runner._log_throttle.counts['cloud'] == 1



@pytest.mark.parametrize('chosen, topics', [
    ({}, ['/left/omni/state', '/right/omni/state']),        # by default the stylus's button 1
    ({'grasp_input': 'button2'}, ['/left/omni/state', '/right/omni/state']),
    ({'grasp_input': ''}, []),
    ({'grasp_input': 'jaw'}, ['/left/omni/jaw/measured_js', '/right/omni/jaw/measured_js']),
])
def test_each_instrument_grasps_from_the_input_grasp_input_names(ros_domain, chosen, topics):
    with make_node(**chosen, instruments=['left', 'right'], mode='global') as n:
        assert [s.topic_name for s in n.grasp_subs] == topics


def closed_message(grasp_input: str, stamp_ns: int):
    """What the driver sends when the jaw closes: DeviceState with that button down, or the CRTK jaw
    at 0 rad."""
    if grasp_input == 'jaw':
        from sensor_msgs.msg import JointState

        msg = JointState(name=['jaw'], position=[0.0])
    else:
        from tissue_msgs.msg import DeviceState

        msg = DeviceState(**{grasp_input: True})
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def test_a_lockstep_grasp_from_the_button_or_the_jaw_applies_at_the_same_pose_whichever_arrives_first(
        ros_domain):
    """The node's own subscription takes the message: the jaw (a JointState) grasps at the very pose
    the button does, the forces bit for bit the same, whether it arrives before or after its pose."""
    ms = 1_000_000
    runs = {}
    for grasp_input in ('button1', 'jaw'):
        for close_first in (True, False):
            with make_node(timing_mode='lockstep', step_thread=False, grasp_input=grasp_input) as n:
                grasp = n.grasp_subs[0].callback
                run_grasp_lift(lambda k, p: n.runner.on_pose(pose(p, T0_NS + k * ms)),
                               lambda: grasp(closed_message(grasp_input, T0_NS + GRASP_AT * ms)), close_first)
                runs[grasp_input, close_first] = np.array([f for _, f in n.sent])
                assert n.runner.solver.instruments[0].holding > 0, (grasp_input, close_first)
    first = runs['button1', True]
    assert all(run.tobytes() == first.tobytes() for run in runs.values())
    assert first[-1][1] < -0.02                       # the lift pulls


def test_a_jaw_message_that_is_not_one_finite_angle_is_ignored_with_a_warning(ros_domain):
    from sensor_msgs.msg import JointState

    with make_node(timing_mode='lockstep', step_thread=False, grasp_input='jaw') as n:
        logs = []
        n.runner.log = lambda level, text: logs.append((level, text))
        jaw, ch = n.grasp_subs[0].callback, n.runner.channels[0]
        for bad in ([float('nan')], [0.0, 0.0], []):
            jaw(JointState(position=bad))
        assert ch.grasps == [] and not ch.closed
        assert logs and logs[0][0] == 'warn', logs
        assert '/omni/jaw/measured_js: not one finite jaw angle ([nan]): ignored' in logs[0][1]
        jaw(JointState(position=[1.0]))                # open: nothing changes
        jaw(JointState(position=[0.1]))                # at most 0.1 rad reads closed
        assert ch.grasps == [(0, True)]
