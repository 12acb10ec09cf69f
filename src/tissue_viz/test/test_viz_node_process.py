"""viz_node as a real process over DDS: diagnostics levels follow the metrics rate, reports, markers."""

from __future__ import annotations

import json
import math
import re
import signal
import time

import numpy as np
import pytest
from PIL import Image

from tissue_testing import harness
from tissue_viz.report import ANIMATION, PLOTS, SNAPSHOTS

pytestmark = pytest.mark.ros

# Small, fast targets. The probe publishes at 200 Hz; an OK rate only needs 80 Hz of them in a
# window (100 Hz * (1 - 0.2)), so a probe held back on a busy machine still reaches it.
FAST = {
    'window': 1.0, 'diagnostics_rate': 5.0, 'stale_timeout': 1.0, 'summary_period': 1.0,
    'metrics_min_rate': 100.0, 'metrics_max_rate': 250.0, 'rate_tolerance': 0.2,
    'particles_required': False, 'pose_required': False, 'force_required': False,
    'report_on_shutdown': False,
}
SUMMARY_INFO = re.compile(r'\[INFO\].*haptic \d+ Hz \| step p50')


def _metrics(stamp_ns: int, step: float = 1e-4, fz: float = 0.5, disp: float = 0.004):
    from tissue_msgs.msg import SimMetrics

    msg = SimMetrics()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = 'tissue'
    msg.step_wall_time = step
    msg.n_particles, msg.n_interaction, msg.n_layer, msg.n_relaxing = 3670, 100, [40, 20], 5
    msg.contact_force.z = fz
    msg.max_displacement = disp
    msg.scheme, msg.mode = msg.SCHEME_TLSPH, msg.MODE_LOCAL
    return msg


class Probe:
    """Publishes metrics at a chosen rate while collecting /diagnostics."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from tissue_msgs.msg import SimMetrics

        self.node = node
        self.pub = node.create_publisher(
            SimMetrics, 'tissue/metrics', QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.arrays = []
        self.diag_sub = node.create_subscription(DiagnosticArray, '/diagnostics',
                                                 self.arrays.append, 10)
        self.sent = 0
        self.stamp_ns = 1_000_000_000
        self.send_times = []

    def status(self, name_part: str):
        """Newest status whose name contains ``name_part`` (None before any arrived)."""
        for array in reversed(self.arrays):
            for s in array.status:
                if name_part in s.name:
                    return s
        return None

    def value(self, name_part: str, key: str):
        """``key``'s value in the newest status named by ``name_part`` (None before any arrived)."""
        s = self.status(name_part)
        return None if s is None else {kv.key: kv.value for kv in s.values}.get(key)

    def run(self, rate: float, until, timeout: float, make=None) -> bool:
        """Publish at ``rate`` Hz (0: publish nothing) until ``until()`` or ``timeout``."""
        period = 1.0 / rate if rate > 0 else None
        next_pub = time.monotonic()
        deadline = next_pub + timeout
        executor = self.node.executor_for_test
        while time.monotonic() < deadline:
            if until():
                return True
            now = time.monotonic()
            if period is not None and now >= next_pub:
                self.stamp_ns += int(period * 1e9)
                self.pub.publish(make(self) if make else _metrics(self.stamp_ns))
                self.sent += 1
                self.send_times.append(now)
                next_pub += period
                if now - next_pub > 0.1:  # fell far behind (loaded machine): do not burst
                    next_pub = now
            executor.spin_once(timeout_sec=0.001)
        return until()


def _level(status) -> int:
    return status.level[0] if isinstance(status.level, (bytes, bytearray)) else int(status.level)


def test_diagnostics_follow_the_metrics_rate_ok_then_warn_then_no_data(rclpy_node):
    with harness.NodeProcess('tissue_viz', 'viz_node', params=FAST) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        harness.wait_for_matching(rclpy_node, probe.pub)
        harness.wait_for_matching(rclpy_node, probe.diag_sub)

        # Nothing published yet: the required metrics topic says "no data" (ERROR).
        assert probe.run(0, lambda: probe.status('tissue/metrics rate') is not None, 15)
        first = probe.status('tissue/metrics rate')
        assert _level(first) == 2 and first.message == 'no data'
        assert _level(probe.status('omni/pose rate')) == 0   # not required here

        # 200 Hz inside [100, 250]: OK.
        def metrics_ok():
            s = probe.status('tissue/metrics rate')
            return s is not None and _level(s) == 0
        assert probe.run(200.0, metrics_ok, 20), probe.status('tissue/metrics rate')
        rate = float(probe.value('tissue/metrics rate', 'rate [Hz]'))
        assert 100 * 0.8 <= rate <= 250 * 1.2
        assert 'p99' in probe.status('step time').message and _level(probe.status('step time')) == 0
        # All OK now: the one-line summary turns from a warning into an info line.
        assert probe.run(200.0, lambda: SUMMARY_INFO.search(viz.output()), 15), viz.output()

        # 40 Hz is below 100 Hz * (1 - 0.2): WARN "rate too low".
        def metrics_warn():
            s = probe.status('tissue/metrics rate')
            return _level(s) == 1
        assert probe.run(40.0, metrics_warn, 20), probe.status('tissue/metrics rate')
        assert 'too low' in probe.status('tissue/metrics rate').message

        # Stopped for longer than stale_timeout: ERROR "no data for ...".
        def metrics_stopped():
            s = probe.status('tissue/metrics rate')
            return _level(s) == 2
        assert probe.run(0, metrics_stopped, 20), probe.status('tissue/metrics rate')
        assert probe.status('tissue/metrics rate').message.startswith('no data for')
        viz.wait_for_output(r'\[WARN\].*haptic \d+ Hz \| step p50', timeout=10)
        assert viz.alive() and 'Traceback' not in viz.output(), viz.output()


def test_nan_and_backwards_metrics_are_counted_and_the_node_keeps_running(rclpy_node):
    def bad(probe):
        # Every 5th message is NaN; every 7th goes back in time.
        k = probe.sent
        stamp = probe.stamp_ns - (500_000_000 if k % 7 == 3 else 0)
        return _metrics(stamp, step=math.nan if k % 5 == 0 else 1e-4)

    with harness.NodeProcess('tissue_viz', 'viz_node', params=FAST) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        harness.wait_for_matching(rclpy_node, probe.pub)
        harness.wait_for_matching(rclpy_node, probe.diag_sub)

        def input_warn():
            s = probe.status('input')
            return s is not None and _level(s) == 1 and 'NaN' in s.message and 'backwards' in s.message
        assert probe.run(200.0, input_warn, 20, make=bad), probe.status('input')
        # The finite messages still give step statistics.
        assert _level(probe.status('step time')) == 0
        assert viz.alive()


def test_sigint_writes_a_report_whose_summary_matches_what_was_sent(rclpy_node, tmp_path):
    report = tmp_path / 'report'
    params = dict(FAST, report_on_shutdown=True, report_dir=str(report))
    # 5 s at 200 Hz: a short stall of the node at the start or end of the run barely changes the
    # mean rate it measures against the rate sent
    forces = [0.1 * (i % 20) for i in range(1000)]   # max 1.9 N

    def ramp(probe):
        i = probe.sent
        step = 2e-3 if i % 10 == 0 else 1e-4   # 10 % miss the 1 ms deadline
        return _metrics(probe.stamp_ns, step=step, fz=forces[i], disp=0.001 * (i % 20))

    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        harness.wait_for_matching(rclpy_node, probe.pub)
        probe.run(200.0, lambda: probe.sent >= len(forces), 120, make=ramp)
        assert probe.sent == len(forces)

        # Reliable QoS: every message reaches the node; wait until it has counted them all.
        counted = str(len(forces))
        assert probe.run(0, lambda: probe.value('tissue/metrics rate', 'messages') == counted, 30), \
            probe.status('tissue/metrics rate')
        rc = viz.stop(timeout=30)
        assert rc == 0, viz.output()
        assert 'report written' in viz.output()

    summary = json.loads((report / 'summary.json').read_text())
    assert summary['steps'] == len(forces)
    assert summary['deadline_misses'] == len(forces) // 10
    assert summary['deadline_miss_pct'] == pytest.approx(10.0)
    assert summary['max_force_n'] == pytest.approx(1.9)
    assert summary['max_displacement_m'] == pytest.approx(0.019)
    assert summary['max_active_particles'] == 165
    assert summary['step_p50_s'] == pytest.approx(1e-4)
    # The rate actually sent (a loaded machine may have held the probe back), as received.
    sent_rate = (len(forces) - 1) / (probe.send_times[-1] - probe.send_times[0])
    assert summary['rates_hz']['metrics'] == pytest.approx(sent_rate, rel=0.25)
    for name in ('metrics.csv', 'index.html', 'summary.md'):
        assert (report / name).stat().st_size > 0, name
    for name in ('force_vs_time.png', 'force_vs_displacement.png', 'step_time_hist.png',
                 'rates.png'):
        with Image.open(report / name) as img:
            rgb = np.asarray(img.convert('RGB'), dtype=int)
        assert rgb.shape[:2] == (450, 800), name
        assert 0.02 < np.mean(rgb.sum(axis=2) < 750) < 0.8, name   # drawn on, not blank


def _ask_for_a_report(rclpy_node):
    """Call ``viz/write_report``; its answer."""
    from std_srvs.srv import Trigger

    client = rclpy_node.create_client(Trigger, 'viz/write_report')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    assert rclpy_node.spin_until(future.done, 10)
    return future.result()


def _stream_then_ask_for_a_report(rclpy_node, viz, n_poses: int):
    """Wait for ``viz``, stream ``n_poses`` poses at 200 Hz, then :func:`_ask_for_a_report`."""
    viz.wait_for_output(r'ready:', timeout=30)
    probe = Probe(rclpy_node)
    harness.wait_for_matching(rclpy_node, probe.pub)
    probe.run(200.0, lambda: probe.sent >= n_poses, 20)
    return _ask_for_a_report(rclpy_node)


def test_write_report_service_writes_a_folder_while_running(rclpy_node, tmp_path):
    report = tmp_path / 'on_request'
    params = dict(FAST, report_dir=str(report))
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        answer = _stream_then_ask_for_a_report(rclpy_node, viz, 100)
        assert answer.success, answer.message
        assert str(report) in answer.message
        assert rclpy_node.spin_until(lambda: (report / 'summary.json').is_file(), 30), viz.output()
        assert viz.alive()
    summary = json.loads((report / 'summary.json').read_text())
    assert summary['steps'] >= 1


@pytest.mark.parametrize('frame_params, frame, tip, end', [
    # the stylus tip and the force sent to the device, as the pose and the wrench give them
    ({}, 'omni_base', (0.01, 0.02, 0.03), (0.01, 0.02, 0.03 + 0.1 * 2.0)),
    # the simulated tool and the reaction on it, as tissue/metrics reports them (no device map here)
    ({'tool_in_tissue_frame': True}, 'tissue', (0.12, -0.06, 0.09), (0.12, -0.06 + 0.1 * 0.5, 0.09)),
], ids=['device_frame', 'tissue_frame'])
def test_markers_show_the_tool_at_the_pose_and_the_force_arrow(rclpy_node, frame_params, frame,
                                                                tip, end):
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from tissue_msgs.msg import SimMetrics
    from visualization_msgs.msg import Marker, MarkerArray

    params = dict(FAST, marker_rate=20.0, force_arrow_scale=0.1, **frame_params)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        pose_pub = rclpy_node.create_publisher(PoseStamped, 'omni/pose', qos)
        force_pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', qos)
        metrics_pub = rclpy_node.create_publisher(SimMetrics, 'tissue/metrics', 10)
        got = []
        sub = rclpy_node.create_subscription(MarkerArray, 'viz/markers', got.append, 10)
        for endpoint in (pose_pub, force_pub, metrics_pub, sub):
            harness.wait_for_matching(rclpy_node, endpoint)
        metrics = _metrics(5_000_000_000, fz=0.0)
        metrics.contact_force.y = 0.5
        metrics.tool_position.x, metrics.tool_position.y, metrics.tool_position.z = 0.12, -0.06, 0.09
        metrics.tool_axis.z, metrics.tool_length, metrics.tool_radius = 1.0, 0.05, 0.004

        def send():
            pose = PoseStamped()
            pose.header.frame_id = 'omni_base'
            pose.header.stamp.sec = 5
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = 0.01, 0.02, 0.03
            pose.pose.orientation.w = 1.0
            pose_pub.publish(pose)
            wrench = WrenchStamped()
            wrench.header = pose.header
            wrench.wrench.force.z = 2.0
            force_pub.publish(wrench)
            metrics_pub.publish(metrics)

        def have_arrow():
            send()
            return any(len(a.markers) >= 2 for a in got)
        assert rclpy_node.spin_until(have_arrow, 15), viz.output()
        array = next(a for a in got if len(a.markers) >= 2)
        tool = next(m for m in array.markers if m.ns == 'tool')
        arrow = next(m for m in array.markers if m.type == Marker.ARROW)
        assert tool.type == Marker.SPHERE and tool.header.frame_id == frame
        assert arrow.header.frame_id == frame
        assert (tool.pose.position.x, tool.pose.position.y, tool.pose.position.z) == \
            pytest.approx(tip)
        a, b = arrow.points
        assert (a.x, a.y, a.z) == pytest.approx(tip)
        assert (b.x, b.y, b.z) == pytest.approx(end)
        shafts = [m for m in array.markers if m.type == Marker.CYLINDER]
        if frame == 'tissue':         # the simulated capsule's shaft, up from its tip
            (shaft,) = shafts
            assert shaft.scale.z == pytest.approx(0.05) and shaft.scale.x == pytest.approx(0.008)
            p = shaft.pose.position
            assert (p.x, p.y, p.z) == pytest.approx((0.12, -0.06, 0.09 + 0.025))
        else:
            assert not shafts


def test_two_instruments_each_get_their_diagnostics_tools_and_held_particles(rclpy_node):
    """instruments [left, right]: each namespace's metrics, poses and forces reach a status and a
    marker of that instrument; the cloud's held byte marks the particles each one holds, its severed
    byte the cut faces (one marker)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from sph_tissue_sim.cloud import CloudBuffer
    from tissue_msgs.msg import SimMetrics
    from visualization_msgs.msg import Marker, MarkerArray

    names = ('left', 'right')
    params = dict(FAST, instruments=list(names), marker_rate=20.0, tool_in_tissue_frame=True)
    fast = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    cloud = CloudBuffer(6, 'tissue')
    xyz = np.arange(18, dtype=float).reshape(6, 3) * 1e-3
    # left (instrument 0) holds particles 1 and 2, right holds particle 4; a cut took bonds from 3 and 5
    # and removed 0
    removed = np.zeros(6, dtype=np.bool_)
    removed[0] = True
    cloud.pack(xyz, xyz, np.zeros(6), np.zeros(6, dtype=np.int8), [np.array([1, 2]), np.array([4])],
               np.array([4, 0, 0, 2, 0, 3], dtype=np.int32), removed)
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        pubs = {name: (rclpy_node.create_publisher(SimMetrics, f'{name}/tissue/metrics', reliable),
                       rclpy_node.create_publisher(PoseStamped, f'{name}/omni/pose', fast),
                       rclpy_node.create_publisher(WrenchStamped, f'{name}/omni/force_feedback', fast))
                for name in names}
        cloud_pub = rclpy_node.create_publisher(PointCloud2, 'tissue/particles', fast)
        arrays, markers = [], []
        subs = [rclpy_node.create_subscription(DiagnosticArray, '/diagnostics', arrays.append, 10),
                rclpy_node.create_subscription(MarkerArray, 'viz/markers', markers.append, 10)]
        for endpoint in (*(p for trio in pubs.values() for p in trio), cloud_pub, *subs):
            harness.wait_for_matching(rclpy_node, endpoint)
        stamp = [1_000_000_000]

        def send():
            stamp[0] += 5_000_000
            for k, (metrics_pub, pose_pub, force_pub) in enumerate(pubs.values()):
                m = _metrics(stamp[0], fz=0.5 + k)            # left 0.5 N, right 1.5 N
                m.tool_position.x, m.tool_radius = 0.01 * (k + 1), 0.004
                metrics_pub.publish(m)
                pose = PoseStamped()
                pose.header.frame_id = 'omni_base'
                pose.header.stamp.sec, pose.header.stamp.nanosec = divmod(stamp[0], 1_000_000_000)
                pose.pose.orientation.w = 1.0
                pose_pub.publish(pose)
                wrench = WrenchStamped()
                wrench.header = pose.header                   # answers that pose: a latency sample
                wrench.wrench.force.z = 0.5 + k
                force_pub.publish(wrench)
            cloud_pub.publish(cloud.message(pose.header.stamp))

        def status(name: str):
            return next((s for a in reversed(arrays) for s in a.status if s.name == name), None)

        def both_seen():
            send()
            tissue = [status(f'viz_node: tissue ({n})') for n in names]
            latency = [status(f'viz_node: pose to force latency ({n})') for n in names]
            spaces = {m.ns for a in markers[-3:] for m in a.markers}
            return (all(s is not None and s.message.startswith('active') for s in tissue)
                    and all(s is not None and 'p50' in s.message for s in latency)
                    and {'left/tool', 'right/tool', 'left/held', 'right/held', 'cut'} <= spaces)
        assert rclpy_node.spin_until(both_seen, 30), (viz.output(), [s.name for s in arrays[-1].status]
                                                      if arrays else None)
        names_seen = {s.name for s in arrays[-1].status}
        for n in names:
            assert {f'viz_node: {n}/tissue/metrics rate', f'viz_node: {n}/omni/pose rate',
                    f'viz_node: {n}/omni/force_feedback rate', f'viz_node: haptic rendering ({n})',
                    f'viz_node: input ({n})'} <= names_seen
        assert {'viz_node: tissue/particles rate', 'viz_node: step time'} <= names_seen
        assert 'viz_node: tissue' not in names_seen               # no status without its instrument
        forces = {n: {kv.key: kv.value for kv in status(f'viz_node: tissue ({n})').values}['force [N]']
                  for n in names}
        assert forces == {'left': '0.500', 'right': '1.500'}
        latest = {m.ns: m for a in markers[-3:] for m in a.markers}
        assert latest['left/tool'].pose.position.x == pytest.approx(0.01)
        assert latest['right/tool'].pose.position.x == pytest.approx(0.02)
        assert latest['left/tool'].color != latest['right/tool'].color
        held = {n: sorted(round(p.x * 1e3) for p in latest[f'{n}/held'].points) for n in names}
        assert held == {'left': [3, 6], 'right': [12]}                    # x of particles 1, 2 and 4
        assert latest['left/held'].type == Marker.SPHERE_LIST and latest['left/held'].header.frame_id == 'tissue'
        # the cut faces: particles 3 and 5 (x 9 and 15 mm); 0 was removed, so it is not drawn
        assert sorted(round(p.x * 1e3) for p in latest['cut'].points) == [9, 15]
        assert viz.alive() and 'Traceback' not in viz.output(), viz.output()


def test_haptic_rendering_status_is_ok_for_direct_and_passive_metrics_and_warns_on_negative_e_in(
        rclpy_node):
    def multirate(energy_in: float):
        def make(probe):
            msg = _metrics(probe.stamp_ns)
            msg.haptic_mode = msg.HAPTIC_MULTIRATE
            msg.solver_rate, msg.model_age, msg.coupling_stretch = 400.0, 2.5e-3, 1e-4
            msg.energy_in, msg.energy_in_min = energy_in, min(energy_in, 0.0)
            msg.added_damping = 0.75
            return msg
        return make

    def says(level: int, start: str):
        def check():
            s = probe.status('haptic rendering')
            return s is not None and _level(s) == level and s.message.startswith(start)
        return check

    with harness.NodeProcess('tissue_viz', 'viz_node', params=FAST) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        harness.wait_for_matching(rclpy_node, probe.pub)
        harness.wait_for_matching(rclpy_node, probe.diag_sub)
        assert probe.run(200.0, says(0, 'direct'), 20), probe.status('haptic rendering')
        assert probe.run(200.0, says(0, 'E_in 5.000 uJ'), 20, make=multirate(5e-6)), \
            probe.status('haptic rendering')
        assert probe.value('haptic rendering', 'solver rate [Hz]') == '400.0'
        assert probe.value('haptic rendering', 'model age [ms]') == '2.500'
        assert probe.value('haptic rendering', 'added damping [N s/m]') == '0.750'
        # 3 uJ given back, below the default -1 uJ target: WARN.
        assert probe.run(200.0, says(1, 'gave energy back'), 20, make=multirate(-3e-6)), \
            probe.status('haptic rendering')
        assert viz.alive() and 'Traceback' not in viz.output(), viz.output()


def test_inconsistent_rate_targets_are_rejected_at_start_with_a_clear_message():
    params = dict(FAST, metrics_min_rate=500.0, metrics_max_rate=100.0)
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        rc = viz.wait(timeout=30)
        assert rc == 2                                   # the documented code
        assert 'min_rate <= max_rate' in viz.output()


@pytest.mark.parametrize('ros_args', [['-p', 'report_dir:='], ['-p', ':=1']])
def test_an_unparsable_command_line_exits_2_with_a_sentence(ros_domain, ros_args):
    with harness.NodeProcess('tissue_viz', 'viz_node', params=FAST, ros_args=ros_args) as viz:
        assert viz.wait(timeout=30) == 2
        out = viz.output()
    assert 'invalid command-line argument' in out and '[FATAL]' in out, out
    assert 'Traceback' not in out and 'RCLError' not in out


def test_pose_to_force_latency_is_matched_by_stamp_and_lost_replies_raise_an_error(rclpy_node):
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    # Generous latency limits: the point is the matching, not this loaded machine's DDS speed.
    params = dict(FAST, pose_required=True, force_required=True, pose_min_rate=100.0,
                  pose_max_rate=250.0, force_min_rate=50.0, force_max_rate=250.0,
                  latency_timeout=0.2, latency_p50_warn=0.1, latency_p99_warn=0.4,
                  latency_p99_error=0.5, reply_loss_warn_pct=5.0, reply_loss_error_pct=20.0)
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        pose_pub = rclpy_node.create_publisher(PoseStamped, 'omni/pose', qos)
        force_pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', qos)
        for endpoint in (probe.pub, pose_pub, force_pub, probe.diag_sub):
            harness.wait_for_matching(rclpy_node, endpoint)

        def loop(answer_every: int):
            def make(p):
                pose = PoseStamped()
                pose.header.frame_id = 'omni_base'
                pose.header.stamp.sec, pose.header.stamp.nanosec = divmod(p.stamp_ns, 1_000_000_000)
                pose.pose.position.z = -0.001
                pose.pose.orientation.w = 1.0
                pose_pub.publish(pose)
                if p.sent % answer_every == 0:
                    wrench = WrenchStamped()
                    wrench.header = pose.header      # the simulator answers with the pose's stamp
                    wrench.wrench.force.z = 0.4
                    force_pub.publish(wrench)
                return _metrics(p.stamp_ns, fz=0.4)
            return make

        def latency(level: int):
            def check():
                s = probe.status('pose to force latency')
                return s is not None and _level(s) == level
            return check

        # Every pose answered: OK with a measured median.
        assert probe.run(200.0, latency(0), 20, make=loop(1)), probe.status('pose to force latency')
        assert 0.0 <= float(probe.value('pose to force latency', 'p50 [ms]')) < 100.0
        assert float(probe.value('pose to force latency', 'poses without reply [%]')) < 5.0
        # the pose stream is measured (its level depends on how evenly a busy machine let the probe
        # publish: a burst after a stall reads as a rate above pose_max_rate)
        assert int(probe.value('omni/pose rate', 'messages')) > 0

        # Only every 2nd pose answered: half the replies are lost in the window, ERROR.
        assert probe.run(200.0, latency(2), 20, make=loop(2)), probe.status('pose to force latency')
        assert 'without reply' in probe.status('pose to force latency').message
        assert float(probe.value('pose to force latency', 'poses without reply [%]')) > 20.0
        assert viz.alive() and 'Traceback' not in viz.output(), viz.output()


def test_inconsistent_targets_set_at_run_time_are_refused_and_consistent_ones_applied(rclpy_node):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    def set_param(client, name, value):
        request = SetParameters.Request(parameters=[Parameter(
            name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value))])
        future = client.call_async(request)
        assert rclpy_node.spin_until(future.done, 10)
        return future.result().results[0]

    with harness.NodeProcess('tissue_viz', 'viz_node', params=FAST) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        client = rclpy_node.create_client(SetParameters, 'viz_node/set_parameters')
        assert client.wait_for_service(timeout_sec=10)
        refused = set_param(client, 'metrics_min_rate', 5000.0)      # above metrics_max_rate 250
        assert not refused.successful and 'min_rate <= max_rate' in refused.reason
        out_of_range = set_param(client, 'rate_tolerance', 2.0)      # descriptor range [0, 0.99]
        assert not out_of_range.successful
        probe = Probe(rclpy_node)
        harness.wait_for_matching(rclpy_node, probe.diag_sub)
        assert set_param(client, 'metrics_min_rate', 20.0).successful

        assert probe.run(0, lambda: probe.value('tissue/metrics rate', 'min rate [Hz]') == '20.0',
                         10), probe.status('tissue/metrics rate')
        assert viz.alive()


# -- absurd input and unwritable reports ------------------------------------------------------------
U32, I32_MIN = 4_294_967_295, -2_147_483_648
REPORT_FILES = {'force_vs_time.png', 'force_vs_displacement.png', 'step_time_hist.png', 'rates.png',
                'latency_hist.png', 'energy_in.png', 'metrics.csv', 'force.csv', 'latency.csv',
                'rates.csv', 'summary.md', 'index.html', 'summary.json'}


def _absurd_metrics() -> list[tuple[str, dict]]:
    """(LIMITS key the viz counts it under or '' for a field it does not use, field values)."""
    inf, nan = math.inf, math.nan
    bad = [('step_wall_time', {'step_wall_time': v}) for v in (1e308, inf, -inf, nan, -1e-3)]
    bad += [('contact_force', {'contact_force.x': 1e308}),
            ('contact_force', {'contact_force.y': nan}),
            ('contact_force', {'contact_force.z': -inf}),
            ('max_displacement', {'max_displacement': 1e308}), ('penetration', {'penetration': nan}),
            ('kinetic_energy', {'kinetic_energy': -inf}),
            ('active_particles', {'n_interaction': U32}),
            ('active_particles', {'n_layer': [U32] * 4}), ('active_particles', {'n_relaxing': U32}),
            ('substeps', {'substeps': U32}), ('contact_index', {'contact_index': I32_MIN}),
            ('solver_rate', {'solver_rate': nan}), ('model_age', {'model_age': -1e-3}),
            ('coupling_stretch', {'coupling_stretch': inf}),
            ('energy_in', {'energy_in': -1e308}), ('energy_in', {'energy_in_min': nan}),
            ('added_damping', {'added_damping': -inf}),
            ('', {'sim_time': inf, 'substep_dt': nan, 'n_particles': U32, 'scheme': 255,
                  'mode': 255})]
    return bad


def _set(msg, fields: dict):
    for name, value in fields.items():
        target = msg
        *path, last = name.split('.')
        for part in path:
            target = getattr(target, part)
        setattr(target, last, value)
    return msg


def _publish_normal_and_absurd_input(rclpy_node, viz) -> dict:
    """Twenty normal metrics, every absurd one, twenty normal again, plus absurd poses and wrenches;
    waits until the node has counted every metrics message.

    Returns the bad values sent per LIMITS key, and the number of usable steps sent.
    """
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    absurd = _absurd_metrics()
    plan = [('', {})] * 20 + absurd + [('', {})] * 20
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    probe = Probe(rclpy_node)
    pose_pub = rclpy_node.create_publisher(PoseStamped, 'omni/pose', qos)
    force_pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', qos)
    for endpoint in (probe.pub, pose_pub, force_pub, probe.diag_sub):
        harness.wait_for_matching(rclpy_node, endpoint)

    def make(p):
        i = p.sent
        if i < len(absurd):          # a pose and a wrench with NaN/inf beside the metrics
            pose, wrench = PoseStamped(), WrenchStamped()
            pose.header.stamp.sec = wrench.header.stamp.sec = 100 + i
            pose.pose.position.x = (math.nan, math.inf, 1e308)[i % 3]
            wrench.wrench.force.z = (-1e308, math.nan, -math.inf)[i % 3]
            pose_pub.publish(pose)
            force_pub.publish(wrench)
        return _set(_metrics(p.stamp_ns), plan[i][1])
    probe.run(100.0, lambda: probe.sent >= len(plan), 30, make=make)
    assert probe.sent == len(plan)
    assert probe.run(0, lambda: probe.value('tissue/metrics rate', 'messages') == str(len(plan)),
                     20), (probe.status('tissue/metrics rate'), viz.output())
    expected = {}
    for key, _ in absurd:
        if key:
            expected[key] = expected.get(key, 0) + 1
    return expected, sum(1 for key, _ in plan if not key)


def _assert_report_counts(report, expected: dict, steps: int) -> None:
    assert REPORT_FILES <= {p.name for p in report.iterdir()}
    summary = json.loads((report / 'summary.json').read_text())
    assert summary['failed_files'] == {} and summary['plot_failures'] == {}
    assert summary['steps'] == steps                    # the usable messages only
    assert summary['step_max_s'] == pytest.approx(1e-4)
    metrics_keys = set(expected)
    assert {k: v for k, v in summary['bad_values'].items() if k in metrics_keys} == expected
    md = (report / 'summary.md').read_text()
    assert f"- step times: {expected['step_wall_time']} not finite or out of range" in md
    assert f"- active particle counts: {expected['active_particles']} not finite" in md
    for png in ('step_time_hist.png', 'force_vs_time.png', 'rates.png'):
        with Image.open(report / png) as img:
            rgb = np.asarray(img.convert('RGB'), dtype=int)
        assert 0.02 < np.mean(rgb.sum(axis=2) < 750) < 0.8, png


def test_absurd_metrics_neither_cost_the_report_on_request_nor_the_one_at_shutdown(rclpy_node,
                                                                                  tmp_path):
    report = tmp_path / 'report'
    params = dict(FAST, report_on_shutdown=True, report_dir=str(report))
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        expected, steps = _publish_normal_and_absurd_input(rclpy_node, viz)
        answer = _ask_for_a_report(rclpy_node)
        assert answer.success, answer.message
        assert rclpy_node.spin_until(lambda: (report / 'summary.json').is_file(), 60), viz.output()
        _assert_report_counts(report, expected, steps)
        assert viz.alive()

        # The shutdown report goes into the same folder: remove the first one to see it appear.
        for path in report.iterdir():
            path.unlink()
        rc = viz.stop(timeout=60)
        output = viz.output()
    assert rc == 0, output
    assert 'report written' in output and 'Traceback' not in output, output
    _assert_report_counts(report, expected, steps)


def test_an_unwritable_report_folder_is_refused_by_the_service_and_exits_3_at_shutdown(
        rclpy_node, tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('a file where the report folder should go')
    params = dict(FAST, report_on_shutdown=True, report_dir=str(blocker / 'report'))
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        answer = _stream_then_ask_for_a_report(rclpy_node, viz, 50)
        assert not answer.success
        assert 'cannot create report folder' in answer.message and 'a_file' in answer.message
        assert viz.alive()
        rc = viz.stop(timeout=60)
        output = viz.output()
    assert rc == 3, output                               # the documented code
    assert 'report failed: cannot create report folder' in output, output
    assert 'Traceback' not in output, output


# -- a demo-length session: stopped within launch's SIGINT grace -----------------------------------
#: ``ros2 launch`` sends SIGTERM this long after SIGINT (its sigterm_timeout default)
LAUNCH_SIGTERM_AFTER = 5.0
#: the demo's session (bags/long): 63 s of poses, forces and metrics at 1 kHz, clouds at 30 Hz
DEMO_FRAMES = 63_000


def _cloud(k: int, n_clouds: int):
    """A 3 584-particle block pressed at its top and released over ``n_clouds`` clouds (the liver
    has 3 670): displacement a bowl under the tool, von Mises proportional to it."""
    from sensor_msgs.msg import PointCloud2, PointField

    grid = np.stack(np.meshgrid(np.arange(16), np.arange(16), np.arange(14), indexing='ij'), -1)
    rest = grid.reshape(-1, 3) * 0.004
    top = np.array([0.03, 0.03, 0.052])
    depth = 0.006 * math.sin(math.pi * k / (n_clouds - 1))
    disp = depth * np.exp(-np.sum((rest - top) ** 2, axis=1) / 0.012 ** 2)
    points = np.column_stack([rest - np.outer(disp, [0.0, 0.0, 1.0]), disp, 3e5 * disp])
    msg = PointCloud2()
    msg.header.frame_id = 'tissue'
    msg.height, msg.width = 1, len(points)
    msg.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, name in enumerate(('x', 'y', 'z', 'displacement', 'von_mises'))]
    msg.point_step, msg.row_step = 20, 20 * len(points)
    msg.data = points.astype(np.float32).tobytes()
    return msg


def _stream_a_session(rclpy_node, probe, frames: int, rate: float, clouds: int,
                      seconds: float) -> None:
    """Up to ``frames`` poses, their force replies (same stamps) and metrics, 1 ms apart in stamp
    time, with ``clouds`` clouds among them: published at up to ``rate`` frames per second of wall
    time but never far ahead of what the node has counted (its queues hold 100 messages per topic),
    for at most ``seconds``; then waits until the node has counted everything that reached it."""
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    pose_pub = rclpy_node.create_publisher(PoseStamped, 'omni/pose', qos)
    force_pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', qos)
    cloud_pub = rclpy_node.create_publisher(PointCloud2, 'tissue/particles', qos)
    for endpoint in (probe.pub, pose_pub, force_pub, cloud_pub, probe.diag_sub):
        harness.wait_for_matching(rclpy_node, endpoint)
    pose, wrench, metrics = PoseStamped(), WrenchStamped(), _metrics(0)
    pose.header.frame_id = wrench.header.frame_id = 'omni_base'
    pose.pose.orientation.w = 1.0
    metrics.haptic_mode = metrics.HAPTIC_MULTIRATE
    metrics.solver_rate, metrics.model_age = 400.0, 2.5e-3
    cloud_every = frames // clouds
    executor = rclpy_node.executor_for_test

    def counted(topic: str = 'omni/pose') -> int:
        return int(probe.value(f'{topic} rate', 'messages') or 0)

    def publish(i: int) -> None:
        sec, nanosec = divmod(1_000_000_000 + i * 1_000_000, 1_000_000_000)
        for header in (pose.header, wrench.header, metrics.header):
            header.stamp.sec, header.stamp.nanosec = sec, nanosec
        z = 0.002 - 0.006 * math.sin(math.pi * i / 7000.0) ** 2      # nine presses
        force = 400.0 * max(0.0, -z) + 0.002 * math.sin(i)
        pose.pose.position.z = z
        wrench.wrench.force.z = metrics.contact_force.z = force
        metrics.step_wall_time = 2e-3 if i % 50 == 0 else 1e-4 + 1e-4 * (i % 7) / 7
        metrics.max_displacement = metrics.penetration = 0.5 * max(0.0, -z)
        metrics.energy_in = 0.5 * force * max(0.0, -z)
        pose_pub.publish(pose)
        force_pub.publish(wrench)
        probe.pub.publish(metrics)
        if i % cloud_every == 0:
            cloud = _cloud(i // cloud_every, clouds)
            cloud.header.stamp = pose.header.stamp
            cloud_pub.publish(cloud)

    # The first frame until the node has counted it on every topic: a reader drops what arrives
    # before it has matched the writer (which may have matched the reader earlier), and the pace
    # below waits for the node's count.
    topics = ('omni/pose', 'omni/force_feedback', 'tissue/metrics', 'tissue/particles')
    handshake = time.monotonic() + 20.0
    while not all(counted(t) for t in topics):
        assert time.monotonic() < handshake, {t: counted(t) for t in topics}
        publish(0)
        probe.run(0, lambda: False, 0.05)
    start = time.monotonic()
    deadline = start + seconds
    for i in range(1, frames):
        if i % 50 == 0:
            executor.spin_once(timeout_sec=0)
            while ((time.monotonic() < start + i / rate or i - counted() > 150)
                   and time.monotonic() < deadline):
                executor.spin_once(timeout_sec=0.002)
            if time.monotonic() >= deadline:
                break
        publish(i)
    # everything that arrived is counted once the count stands still for a few diagnostics
    last = {'count': None, 'since': time.monotonic()}

    def settled():
        count = counted()
        if count != last['count']:
            last.update(count=count, since=time.monotonic())
        return count > 0 and time.monotonic() - last['since'] > 0.5
    assert probe.run(0, settled, 30), (last, len(probe.arrays), sorted({
        (st.name, tuple(kv.value for kv in st.values if kv.key == 'messages'))
        for array in probe.arrays[-3:] for st in array.status}))


def test_sigint_after_a_demo_length_session_exits_with_the_report_before_launch_sends_sigterm(
        rclpy_node, tmp_path):
    report = tmp_path / 'report'
    # the node's count of poses in /diagnostics paces the stream: the fresher, the faster
    params = dict(FAST, report_on_shutdown=True, report_dir=str(report), diagnostics_rate=50.0,
                  summary_period=0.0, marker_rate=0.0)
    with harness.NodeProcess('tissue_viz', 'viz_node', params=params) as viz:
        viz.wait_for_output(r'ready:', timeout=30)
        probe = Probe(rclpy_node)
        # up to five times real time; a busy machine sends a part of the session in the time given
        _stream_a_session(rclpy_node, probe, DEMO_FRAMES, rate=5000.0, clouds=60, seconds=18.0)
        sigint = time.monotonic()
        viz.send_signal(signal.SIGINT)
        rc = viz.wait(timeout=30)
        elapsed = time.monotonic() - sigint
        output = viz.output()
    assert rc == 0, output
    assert 'report written' in output and 'Traceback' not in output, output
    summary = json.loads((report / 'summary.json').read_text())
    assert summary['failed_files'] == {} and summary['plot_failures'] == {}
    files = {p.name for p in report.iterdir()}
    assert REPORT_FILES | {png for png, _ in PLOTS} | {ANIMATION[0], SNAPSHOTS} <= files
    # a long session arrived (the whole of it unless the machine is busy)
    assert summary['poses'] > 25_000 and summary['steps'] > 25_000, summary
    assert elapsed < LAUNCH_SIGTERM_AFTER, (f'{elapsed:.2f} s from SIGINT to exit after '
                                            f'{summary["poses"]} poses', output)
