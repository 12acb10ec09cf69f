"""How omni_driver takes force commands, in-process with injected times and a fake DDS reader.

The servo tick takes the commands itself, before the watchdog decides, and dates each by its DDS
reception time: a command that has arrived is neither missed nor counted old because the executor
thread (or the GIL) was busy. That was the spurious 20 ms trip on a clean 1 kHz stream.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from tissue_testing import harness

pytestmark = pytest.mark.ros

WALL0 = 1_700_000_000_000_000_000   # [ns] system clock at monotonic 0 in these tests


class FakeReader:
    """Stands in for the DDS reader and both clocks: commands arrive at given (monotonic) times."""

    def __init__(self, node):
        self.now = 0.0
        self.pending: list[tuple[float, object]] = []
        node._now_clocks = lambda: (self.now, WALL0 + round(self.now * 1e9))
        node._take = self.take

    def arrive(self, t: float, force=(0.3, 0.0, 0.0), stamp_ns: int = 0, frame='omni_base'):
        """A command DDS receives at monotonic ``t`` (taken at a later servo tick)."""
        from geometry_msgs.msg import WrenchStamped

        msg = WrenchStamped()
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(f) for f in force)
        self.pending.append((t, msg))

    def take(self):
        ready = [p for p in self.pending if p[0] <= self.now]
        if not ready:
            return None
        self.pending.remove(ready[0])
        t, msg = ready[0]
        return msg, {'received_timestamp': WALL0 + round(t * 1e9), 'source_timestamp': 0}

    def tick(self, node, t: float) -> np.ndarray:
        self.now = t
        return node.servo()


@pytest.fixture
def make_driver(rclpy_node):
    """OmniDriver nodes in the test's context (not started: no backend thread, no servo thread)."""
    from rclpy.parameter import Parameter

    from haptic_omni_driver.driver_node import OmniDriver

    nodes = []

    def make(**params):
        # commands here answer no pose: the stale-reply window only where a test sets it
        params = {'backend': 'scripted', 'ramp_time': 0.0, 'max_force_rate': 0.0,
                  'max_command_lag': 0.0, **params}
        node = OmniDriver(context=rclpy_node.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.destroy_node()


def test_command_received_while_the_servo_tick_was_late_is_taken_before_the_watchdog_decides(
        make_driver):
    node = make_driver(watchdog_timeout=0.02)
    dds = FakeReader(node)
    for k in range(11):                         # a clean 1 kHz stream, 1 ms servo ticks
        dds.arrive(k * 0.001)
        dds.tick(node, k * 0.001)
    for k in range(11, 36):                     # the stream goes on...
        dds.arrive(k * 0.001)
    force = dds.tick(node, 0.0352)              # ...while the servo thread was held up for 25 ms
    st = node.safety.status(0.0352)
    assert force[0] == pytest.approx(0.3) and not st.watchdog_tripped
    assert st.command_age == pytest.approx(0.0002)   # its true age, from its reception
    assert node.n_commands == 36 and node.safety.trip_count == 0


def test_commands_count_from_their_reception_even_when_taken_late(make_driver):
    node = make_driver(watchdog_timeout=0.02)
    dds = FakeReader(node)
    dds.tick(node, 0.0)
    dds.arrive(0.001)
    for k in range(2, 22):                      # taken at 2 ms; the stream then stops
        dds.tick(node, k * 0.001)
    assert not node.safety.status(0.021).watchdog_tripped
    assert not np.any(dds.tick(node, 0.0215))   # 20.5 ms after its reception: zeroed
    assert node.safety.status(0.0215).watchdog_tripped


def test_stale_command_is_rejected_and_counted_in_the_state(make_driver):
    from haptic_omni_driver.backends.base import Sample

    node = make_driver(max_command_lag=0.05)
    dds = FakeReader(node)
    pose_ns = WALL0 + 10_000_000
    node.on_sample(Sample(pose_ns, np.zeros(3)))
    for stamp in (0, -5_000_000_000, pose_ns + 1_000_000, pose_ns - 60_000_000):
        dds.arrive(0.0, force=(0.5, 0, 0), stamp_ns=stamp)
    dds.arrive(0.0, force=(0.1, 0, 0), stamp_ns=pose_ns)
    force = dds.tick(node, 0.001)
    st = node.safety.status(0.001)
    assert force[0] == pytest.approx(0.1)
    assert st.rejected_commands == 4
    assert st.rejected_by_reason == {'stale': 3, 'future': 1}


def test_reply_arriving_while_its_pose_is_being_published_answers_a_known_pose(make_driver):
    """The pose stamp is noted before publishing: an instant reply is not 'from the future'."""
    from haptic_omni_driver.backends.base import Sample

    node = make_driver(max_command_lag=0.05)
    results = []

    def publish_and_reply(msg):
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        results.append(node.safety.command((0.1, 0, 0), 'omni_base', time.monotonic(),
                                           stamp_ns * 1e-9))

    node.pose_pub.publish = publish_and_reply
    node.on_sample(Sample(WALL0 + 10_000_000, np.zeros(3)))
    assert results and results[0].accepted, results


def test_lockstep_wait_takes_its_reply_without_a_servo_tick(make_driver, tmp_path):
    from omni_test_utils import make_pose_bag

    make_pose_bag(tmp_path / 'bag', n=5)
    node = make_driver(backend='replay', bag=str(tmp_path / 'bag'), replay_mode='lockstep')
    dds = FakeReader(node)
    dds.arrive(0.0, stamp_ns=123)
    assert node.wait_for_reply(123, timeout=5.0)
    assert not node.wait_for_reply(456, timeout=0.01)


def test_force_commands_are_taken_by_the_servo_not_dispatched_by_the_executor(rclpy_node,
                                                                               make_driver):
    from geometry_msgs.msg import WrenchStamped
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    node = make_driver(reliable=True, qos_depth=10)
    assert node.force_sub not in list(node.subscriptions)
    pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback',
                                      QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    harness.wait_for_matching(rclpy_node, pub)
    executor = EventsExecutor(context=rclpy_node.context)
    executor.add_node(node)
    try:
        msg = WrenchStamped()
        msg.header.frame_id = 'omni_base'
        msg.wrench.force.y = 0.25
        pub.publish(msg)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:          # the executor has every chance to take it
            executor.spin_once(timeout_sec=0.01)
        assert node.n_commands == 0
        deadline = time.monotonic() + 10.0      # the servo tick takes it (once DDS has it)
        while node.n_commands == 0 and time.monotonic() < deadline:
            node.servo()
            time.sleep(0.001)
        assert node.n_commands == 1
        assert node.safety.status(time.monotonic()).rejected_commands == 0
    finally:
        executor.shutdown()


@pytest.mark.parametrize('recv_ns, since, expected', [
    (WALL0 + 7_000_000, 0.005, 0.007),      # DDS stamp mapped onto the monotonic clock
    (WALL0 + 2_000_000, 0.005, 0.005),      # not before the previous take (clock stepped back)
    (WALL0 + 20_000_000, 0.005, 0.010),     # not after now (clock stepped forward)
    (0, 0.005, 0.010),                      # no reception stamp: now
    (WALL0 + 7_000_000, None, 0.007),       # first take
])
def test_reception_time_is_mapped_and_bounded_to_the_take_interval(recv_ns, since, expected):
    from haptic_omni_driver.driver_node import received_at

    info = {'received_timestamp': recv_ns}
    assert received_at(info, 0.010, WALL0 + 10_000_000, since) == pytest.approx(expected, abs=1e-12)


# -- CRTK: servo_cf setpoints and state_command ----------------------------------------------------
class FakeSetpoints(FakeReader):
    """servo_cf's reader: setpoints arrive at given times (force_feedback stays with FakeReader)."""

    def __init__(self, node):
        self.now = 0.0
        self.pending = []
        node._take_setpoint = self.take


def test_a_servo_cf_setpoint_passes_the_chain_without_answering_a_pose(make_driver):
    """A CRTK client stamps its setpoint with its own clock, newer than the newest pose: on
    omni/force_feedback that is a reply from the future (rejected), on servo_cf it is accepted,
    clamped to force_limit, and a NaN is still refused."""
    from haptic_omni_driver.backends.base import Sample

    node = make_driver(max_command_lag=0.05, force_limit=0.5)
    replies, setpoints = FakeReader(node), FakeSetpoints(node)
    node._now_clocks = lambda: (replies.now, WALL0 + round(replies.now * 1e9))
    pose_ns = WALL0 + 10_000_000
    node.on_sample(Sample(pose_ns, np.zeros(3)))
    replies.arrive(0.0, force=(0.3, 0, 0), stamp_ns=pose_ns + 2_000_000)
    setpoints.arrive(0.0, force=(0.0, 0.0, float('nan')), stamp_ns=pose_ns + 2_000_000)
    setpoints.arrive(0.0, force=(0.0, 0.9, 0.0), stamp_ns=pose_ns + 2_000_000)
    force = replies.tick(node, 0.001)
    st = node.safety.status(0.001)
    assert force == pytest.approx([0.0, 0.5, 0.0])               # the setpoint, clamped
    assert st.rejected_by_reason == {'future': 1, 'nan': 1} and st.force_clamped


def test_disable_on_state_command_zeroes_the_force_and_enable_ramps_it_back(make_driver):
    from crtk_msgs.msg import StringStamped

    node = make_driver(ramp_time=0.1)
    dds = FakeReader(node)
    for k in range(5):
        dds.arrive(k * 0.001)
        force = dds.tick(node, k * 0.001)
    assert force[0] == pytest.approx(0.3 * 0.04)                 # ramping up
    node._on_state_command(StringStamped(string='disable'))
    assert node.op_state.current.state == 'DISABLED'
    for k in range(5, 60):
        dds.arrive(k * 0.001)
        assert not np.any(dds.tick(node, k * 0.001)), k           # commands keep coming: zero
    node._on_state_command(StringStamped(string='pause'))         # not from DISABLED
    assert node.op_state.current.state == 'DISABLED'
    dds.now = 0.060
    node._on_state_command(StringStamped(string='enable'))
    for k in range(60, 111):
        dds.arrive(k * 0.001)
        force = dds.tick(node, k * 0.001)
    assert node.op_state.current.state == 'ENABLED'
    assert force[0] == pytest.approx(0.3 * 0.5)                   # 50 ms into a new 0.1 s ramp


def test_a_driver_can_start_disabled_and_renders_nothing_until_enabled(make_driver):
    from crtk_msgs.msg import StringStamped

    node = make_driver(start_state='DISABLED')
    dds = FakeReader(node)
    for k in range(20):
        dds.arrive(k * 0.001)
        assert not np.any(dds.tick(node, k * 0.001))
    node._on_state_command(StringStamped(string='enable'))
    dds.arrive(0.020)
    assert dds.tick(node, 0.020)[0] == pytest.approx(0.3)


def test_the_stylus_frame_is_the_pose_sent_with_measured_cp(make_driver):
    """Where tf2 is installed the driver sends omni_base -> omni_stylus beside measured_cp: the
    pose itself, at crtk_rate (here a recorder stands in for /tf)."""
    import types

    from haptic_omni_driver.backends.base import Sample

    node = make_driver(crtk_rate=500.0)
    sent = []
    node.tf = types.SimpleNamespace(available=True, send=sent.extend)
    q = np.array([0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)])
    for k in range(4):
        node.on_sample(Sample(WALL0 + k * 1_000_000, np.array([0.01 * k, 0.02, -0.03]), q))
    assert [stamp.header.stamp.nanosec for stamp in sent] == [0, 2_000_000]
    tip = sent[-1]
    assert (tip.header.frame_id, tip.child_frame_id) == ('omni_base', 'omni_stylus')
    t, r = tip.transform.translation, tip.transform.rotation
    assert (t.x, t.y, t.z) == pytest.approx((0.02, 0.02, -0.03))
    assert (r.x, r.y, r.z, r.w) == pytest.approx(tuple(q))


def test_measured_cp_keeps_its_rate_and_measured_cv_its_sense_across_a_replay_loop(make_driver):
    """Three passes of a 1 m/s ramp, the stamps going back at each start (a looping replay):
    every pass publishes every other sample at the default 500 Hz, and the velocity never carries
    the jump back (it starts afresh)."""
    import types

    from haptic_omni_driver.backends.base import Sample

    node = make_driver()
    cps, cvs = [], []
    node.cp_pub = types.SimpleNamespace(publish=cps.append)
    node.cv_pub = types.SimpleNamespace(publish=lambda m: cvs.append(m.twist.linear.x))
    per_pass = []
    for _ in range(3):
        n0 = len(cps)
        for k in range(1000):
            node.on_sample(Sample(WALL0 + k * 1_000_000, np.array([k * 1e-3, 0.0, 0.0])))
        per_pass.append(len(cps) - n0)
    assert per_pass == [500, 500, 500]
    assert max(cvs) <= 1.0 + 1e-9 and min(cvs) >= 0.0
    assert cvs[-1] == pytest.approx(1.0, abs=1e-6)


# -- CRTK: the jaw (a stylus button, and jaw/servo_jp) ---------------------------------------------
def _record_jaw_and_poses(node) -> list:
    """('jaw', stamp, angle) and ('pose', stamp) in the order the driver publishes them."""
    import types

    out = []
    node.jaw_pub = types.SimpleNamespace(publish=lambda m: out.append(
        ('jaw', m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, list(m.position))))
    node.pose_pub = types.SimpleNamespace(publish=lambda m: out.append(
        ('pose', m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)))
    return out


def _jaw_changes(out: list) -> list[tuple[int, float]]:
    """(stamp, angle) of each change of the published jaw angle; each must come before its pose."""
    changes, last = [], None
    for i, event in enumerate(out):
        if event[0] == 'jaw' and event[2] != last:
            last = event[2]
            changes.append((event[1], event[2][0]))
            assert ('pose', event[1]) in out[i + 1:], f'the jaw change at {event[1]} came after its pose'
    return changes


@pytest.mark.parametrize('jaw_button', [1, 2])
def test_jaw_measured_js_follows_its_button_and_a_servo_jp_command_until_the_button_next_changes(
        make_driver, jaw_button):
    """Each change is stamped with the sample it came with and sent before that pose (a lockstep
    replay grasps at the same pose every time): open, a command (from the next sample on), closed by
    the button (which wins over a command taken at the same sample), a command while it is held,
    open again when it is released; the other button does nothing."""
    from sensor_msgs.msg import JointState

    from haptic_omni_driver.backends.base import Sample

    node = make_driver(jaw_button=jaw_button, jaw_open_angle=0.8, crtk_rate=2000.0)
    # beside measured_cp (omni/measured_cp), as a dVRK arm's jaw is beside the arm
    assert (node.jaw_pub.topic_name, node.jaw_sub.topic_name) == ('/omni/jaw/measured_js', '/omni/jaw/servo_jp')
    out = _record_jaw_and_poses(node)

    def buttons(down: bool, other: bool = False) -> tuple[bool, bool]:
        return (down, other) if jaw_button == 1 else (other, down)

    for k in range(30):
        if k == 5:
            node._on_jaw_command(JointState(name=['jaw'], position=[0.3]))
        if k == 12:
            node._on_jaw_command(JointState(position=[0.6]))     # before the press there: the press wins
        if k == 15:
            node._on_jaw_command(JointState(position=[0.5]))     # while held: the newest wins
        down = 12 <= k < 20
        node.on_sample(Sample(WALL0 + k * 1_000_000, np.zeros(3), buttons=buttons(down, other=k >= 25)))
    assert _jaw_changes(out) == [(WALL0, 0.8), (WALL0 + 5 * 1_000_000, 0.3), (WALL0 + 12 * 1_000_000, 0.0),
                                 (WALL0 + 15 * 1_000_000, 0.5), (WALL0 + 20 * 1_000_000, 0.8)]
    # and at crtk_rate (here every 0.5 ms: every sample) with each sample's stamp
    assert {e[1] for e in out if e[0] == 'jaw'} == {WALL0 + k * 1_000_000 for k in range(30)}
