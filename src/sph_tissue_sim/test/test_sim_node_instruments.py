"""sim_node with two instruments on one tissue, as a real process over DDS: each namespace its own
poses, forces, metrics and grasp input (a stylus button or the CRTK jaw)."""

from __future__ import annotations

import re

import pytest

from sim_probe import START_TIMEOUT, T0_NS, SimProbe, force_of, press_path, qos, sim

pytestmark = pytest.mark.ros

TWO = {'instruments': ['left', 'right'], 'instrument_offsets': [-0.015, 0.0, 0.0, 0.015, 0.0, 0.0]}


def _device_frames(node, ns: str) -> dict:
    """Each instrument's latched tissue/device_frame, by instrument name (once both came)."""
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    got = {}
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    subs = [node.create_subscription(TransformStamped, f'{ns}{name}/tissue/device_frame',
                                     lambda msg, name=name: got.__setitem__(name, msg), latched)
            for name in ('left', 'right')]
    assert node.spin_until(lambda: len(got) == 2, 20.0)
    for sub in subs:
        node.destroy_subscription(sub)
    return got


def _jaw(node, ns: str, grasp_input: str):
    """A publisher of the instrument's grasp input, and the message that closes its jaw (a button
    down on omni/state, or the CRTK jaw at 0 rad)."""
    if grasp_input == 'jaw':
        from sensor_msgs.msg import JointState

        return node.create_publisher(JointState, ns + 'omni/jaw/measured_js', qos(True, 10)), \
            JointState(name=['jaw'], position=[0.0])
    from tissue_msgs.msg import DeviceState

    return node.create_publisher(DeviceState, ns + 'omni/state', qos(True, 10)), DeviceState(**{grasp_input: True})


@pytest.mark.parametrize('grasp_input', ['button1', 'jaw'])
def test_two_instruments_are_each_answered_on_their_own_topics_and_one_grasps_and_lifts(rclpy_node, grasp_input):
    ns = '/hands/'
    with sim({**TWO, 'timing_mode': 'lockstep', 'grasp_input': grasp_input},
             ros_args=['-r', f'__ns:={ns[:-1]}']) as proc:
        left, right = SimProbe(rclpy_node, reliable=True, ns=ns + 'left/'), SimProbe(rclpy_node, reliable=True,
                                                                                    ns=ns + 'right/')
        proc.wait_for_output(r'ready:', START_TIMEOUT)
        jaw, closed = _jaw(rclpy_node, ns + 'left/', grasp_input)
        from tissue_testing import harness
        for endpoint in (left.pose_pub, left.force_sub, left.metrics_sub, right.pose_pub, right.force_sub,
                         right.metrics_sub, jaw):
            harness.wait_for_matching(rclpy_node, endpoint)
        assert 'instruments left (device origin' in proc.output()
        # each device's frame, in its namespace, where its offset puts it
        frames = _device_frames(rclpy_node, ns)
        assert [frames[n].child_frame_id for n in ('left', 'right')] == ['left/omni_base', 'right/omni_base']
        at = [frames[n].transform.translation for n in ('left', 'right')]
        assert (at[1].x - at[0].x, at[1].y - at[0].y, at[1].z - at[0].z) == pytest.approx((0.03, 0.0, 0.0), abs=1e-9)
        # lockstep rounds: the left's poses wait for the right's
        path = press_path(80, depth=0.002)
        for k, p in enumerate(path):
            left.publish(p, T0_NS + k * 1_000_000)
        assert not rclpy_node.spin_until(lambda: left.force_order, 1.0)
        for k, p in enumerate(path):
            right.publish(p, T0_NS + k * 1_000_000)
        n = len(path)
        assert rclpy_node.spin_until(lambda: len(left.force_order) >= n and len(right.force_order) >= n, 60.0), \
            proc.output()
        assert left.force_order == right.force_order == [T0_NS + k * 1_000_000 for k in range(n)]
        pressed = [force_of(probe.forces[left.force_order[-1]]) for probe in (left, right)]
        assert pressed[0][1] > 0.02 and pressed[1][1] > 0.02
        # the left closes its jaw and lifts: it feels the pull, the right keeps pressing
        jaw.publish(closed)
        # the grasp applies at the first solver step after the jaw's message: each round of
        # the lift waits for its answers, so the message is read before the lift ends
        t0 = T0_NS + n * 1_000_000
        lift = [path[-1] + [0.0, 1e-4 * (j + 1), 0.0] for j in range(50)]          # up 5 mm (device +y)
        for j, p in enumerate(lift):
            stamp = t0 + j * 1_000_000
            left.publish(p, stamp)
            right.publish(path[-1], stamp)
            assert rclpy_node.spin_until(lambda: stamp in left.forces and stamp in right.forces, 20.0), \
                proc.output()
        last = t0 + (len(lift) - 1) * 1_000_000
        assert re.search(r'instrument left grasped \d+ particles', proc.output()), proc.output()
        assert force_of(left.forces[last])[1] < -0.01           # pulled down towards the tissue
        assert force_of(right.forces[last])[1] > 0.02
        assert rclpy_node.spin_until(lambda: any(m.n_grasped > 0 for m in left.metrics), 10.0)
        assert all(m.n_grasped == 0 for m in right.metrics)
        assert proc.stop() == 0
    assert 'Traceback' not in proc.output()
