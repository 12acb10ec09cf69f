"""omni_driver's safety chain as a real process: stale replies, force rate, process stalls, bad arguments."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tissue_testing import harness
from test_driver_ros import PKG, StateWatch, driver, reliable_qos, stamp_ns

pytestmark = pytest.mark.ros


class DiagnosticsWatch:
    """The newest key/value pairs of the driver's /diagnostics status."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray

        self.values: dict[str, str] = {}
        self.sub = node.create_subscription(DiagnosticArray, '/diagnostics', self._on, 10)

    def _on(self, msg) -> None:
        for status in msg.status:
            if 'haptic device' in status.name:
                self.values = {kv.key: kv.value for kv in status.values}


def wrench(force, stamp_ns_: int, frame: str = 'omni_base'):
    from geometry_msgs.msg import WrenchStamped

    msg = WrenchStamped()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns_, 1_000_000_000)
    msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(f) for f in force)
    return msg


def norm(v) -> float:
    return float(np.linalg.norm([v.x, v.y, v.z]))


# -- stale replies (max_command_lag) -------------------------------------------------------------
def test_replies_stamped_zero_negative_future_or_old_are_rejected_and_counted(rclpy_node):
    from geometry_msgs.msg import PoseStamped, WrenchStamped

    poses: list[int] = []
    rclpy_node.create_subscription(PoseStamped, 'omni/pose', lambda m: poses.append(
        stamp_ns(m.header)), reliable_qos(10))
    pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', reliable_qos(100))
    watch, diag = StateWatch(rclpy_node), DiagnosticsWatch(rclpy_node)
    with driver({'backend': 'scripted', 'loop': True, 'reliable': True, 'qos_depth': 100,
                 'max_command_lag': 1.0, 'ramp_time': 0.0, 'max_force_rate': 0.0,
                 'watchdog_timeout': 0.05, 'diagnostics_rate': 10.0}) as proc:
        proc.wait_for_output(r'ready:', 30)
        harness.wait_for_matching(rclpy_node, pub)
        assert rclpy_node.spin_until(lambda: poses, 20), proc.output()
        watch.wait_for_first(rclpy_node, proc)
        newest = poses[-1]
        pub.publish(wrench((0.1, 0, 0), newest))                        # a valid reply
        assert rclpy_node.spin_until(lambda: any(m.force_enabled for _, m in watch.msgs), 10)
        bad = [0, -5 * 1_000_000_000, newest + 5_000_000_000, newest - 5_000_000_000]
        for stamp in bad:
            pub.publish(wrench((0.5, 0, 0), stamp))
        assert rclpy_node.spin_until(
            lambda: any(m.rejected_commands >= 4 for _, m in watch.msgs)
            and diag.values.get('rejected commands') == '4', 10), (diag.values, proc.output())
        out = proc.output()
    assert max(m.rejected_commands for _, m in watch.msgs) == 4
    assert diag.values['rejected (stale)'] == '3' and diag.values['rejected (future)'] == '1'
    assert all(norm(m.commanded_force) <= 0.1 + 1e-12 for _, m in watch.msgs)
    assert 'rejected force command (stale' in out and 'stamped in the future' in out


def test_commands_before_the_first_pose_are_rejected_by_default(rclpy_node):
    from geometry_msgs.msg import WrenchStamped

    pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', reliable_qos(100))
    watch, diag = StateWatch(rclpy_node), DiagnosticsWatch(rclpy_node)
    # waits for 100 pose subscribers: it never publishes a pose
    # the driver's own default window (not driver(), which turns it off for clock-stamped tests)
    with harness.NodeProcess(PKG, 'omni_driver', params={
            'backend': 'scripted', 'reliable': True, 'qos_depth': 100,
            'wait_for_subscribers': 100, 'diagnostics_rate': 10.0}) as proc:
        proc.wait_for_output(r'ready:', 30)
        harness.wait_for_matching(rclpy_node, pub)
        harness.wait_for_matching(rclpy_node, watch.sub)
        for _ in range(3):
            pub.publish(wrench((0.2, 0, 0), time.time_ns()))
        assert rclpy_node.spin_until(lambda: diag.values.get('rejected (no_pose)') == '3', 10), (
            diag.values, proc.output())
        assert rclpy_node.spin_until(lambda: any(m.rejected_commands == 3 for _, m in watch.msgs),
                                     10)
        assert 'no pose published yet' in proc.output()
    assert not any(m.force_enabled for _, m in watch.msgs)


# -- force-rate limit ----------------------------------------------------------------------------
class Sender(harness.Ticker):
    """Publishes one force command about every millisecond from its own thread; records send times."""

    def __init__(self, pub, force):
        super().__init__()
        self.pub, self.force = pub, force
        self.times: list[float] = []

    def tick(self) -> None:
        self.pub.publish(wrench(self.force, time.time_ns()))
        self.times.append(time.monotonic())

    def max_gap(self, t0: float, t1: float) -> float:
        """Longest interval without a send within [t0, t1]."""
        t = np.array([x for x in self.times if t0 <= x <= t1])
        return float(np.diff(np.r_[t0, t, t1]).max())


def test_force_step_is_rendered_no_faster_than_max_force_rate(rclpy_node):
    from geometry_msgs.msg import WrenchStamped

    rate, target = 1.0, 0.5          # [N/s], [N]: the step takes at least 0.5 s
    pub = rclpy_node.create_publisher(WrenchStamped, 'omni/force_feedback', reliable_qos(10))
    watch = StateWatch(rclpy_node)
    with driver({'backend': 'scripted', 'loop': True, 'reliable': True, 'ramp_time': 0.0,
                 'force_limit': target, 'max_force_rate': rate, 'watchdog_timeout': 0.05,
                 'state_rate': 200.0}) as proc:
        proc.wait_for_output(r'ready:', 30)
        harness.wait_for_matching(rclpy_node, pub)
        watch.wait_for_first(rclpy_node, proc)   # so the zero force before the rise is seen
        with Sender(pub, (0.0, 0.0, 3.0)):           # far above the limit: clamped to 0.5 N
            assert rclpy_node.spin_until(lambda: any(
                norm(m.commanded_force) >= target - 1e-9 for _, m in watch.msgs), 30), proc.output()
    states = [m for _, m in watch.msgs]
    full = next(k for k, m in enumerate(states) if norm(m.commanded_force) >= target - 1e-9)
    # the rise that reached the full force started after the last zero output before it
    start = max(k for k in range(full) if norm(states[k].commanded_force) == 0.0) + 1
    f0 = norm(states[start].commanded_force)
    rise = (stamp_ns(states[full].header) - stamp_ns(states[start].header)) * 1e-9
    assert any(0.0 < norm(m.commanded_force) < target for m in states[start:full])
    # a lower bound only (a loaded machine renders it later, never sooner); 0.2 s of slack for
    # the time between taking a state's force and stamping it
    assert rise >= (target - f0) / rate - 0.2, (rise, f0)
    assert all(norm(m.commanded_force) <= target for m in states)


# -- a stall of the driver process must not trip the watchdog on a clean stream --------------------
class SenderProcess:
    """force_sender.py as a process: a 1 kHz stream that shares no GIL with this test."""

    def __init__(self, tmp_path, force, domain: int):
        self.out = tmp_path / 'send_times.txt'
        script = Path(__file__).resolve().parent / 'force_sender.py'
        self.cmd = [sys.executable, str(script), str(self.out), *map(str, force)]
        self.env = harness.ros_env(domain)
        self.proc: subprocess.Popen | None = None
        self.times = np.zeros(0)

    def __enter__(self) -> 'SenderProcess':
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=subprocess.PIPE, text=True,
                                     stdin=subprocess.DEVNULL)
        assert self.proc.stdout.readline().strip() == 'sending'
        return self

    def __exit__(self, *exc) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self.proc.stdout.close()
        if self.out.exists():
            self.times = np.loadtxt(self.out, ndmin=1)

    def max_gap(self, t0: float, t1: float) -> float:
        """Longest interval without a send within [t0, t1]."""
        t = self.times[(self.times >= t0) & (self.times <= t1)]
        return float(np.diff(np.r_[t0, t, t1]).max())


def test_stopping_the_driver_process_while_commands_keep_coming_does_not_trip_the_watchdog(
        rclpy_node, tmp_path):
    """SIGSTOP freezes every driver thread for 0.3 s, as a descheduled process or a held GIL does.

    The commands go on arriving meanwhile; after the resume the driver must take them before it
    judges their age. A trip that counts the stall (command_age >= the stall) is the defect; a later
    trip of ordinary silence on a loaded machine (its DDS thread waiting for a core) is not asserted.
    """
    timeout, stall, watch_after = 0.05, 0.3, 0.2
    watch = StateWatch(rclpy_node)
    rounds = []    # (t_stop, t_cont, states after the resume)
    with driver({'backend': 'scripted', 'loop': True, 'ramp_time': 0.0, 'max_force_rate': 0.0,
                 'watchdog_timeout': timeout}) as proc:
        proc.wait_for_output(r'ready:', 30)
        harness.wait_for_matching(rclpy_node, watch.sub)
        with SenderProcess(tmp_path, (0.0, 0.3, 0.0), int(os.environ['ROS_DOMAIN_ID'])) as sender:
            for _ in range(10):
                n0 = len(watch.msgs)
                assert rclpy_node.spin_until(lambda: any(
                    m.force_enabled and norm(m.commanded_force) > 0.29
                    for _, m in watch.msgs[n0:]), 30), proc.output()
                t_stop = time.monotonic()
                os.killpg(proc.proc.pid, signal.SIGSTOP)
                time.sleep(stall)
                n1, resumed_ns = len(watch.msgs), time.time_ns()
                os.killpg(proc.proc.pid, signal.SIGCONT)

                def after():
                    return [m for _, m in watch.msgs[n1:] if stamp_ns(m.header) >= resumed_ns]
                # a resumed process on a loaded machine may wait for a core: the watch window
                # starts at its first state published after the resume, not at the signal
                assert rclpy_node.spin_until(after, 30), proc.output()
                rclpy_node.spin_until(lambda: False, watch_after)
                rounds.append((t_stop, time.monotonic(), after()))
        out = proc.output()
    # a round proves something only if the stream itself had no gap a watchdog could see
    clean = [after for t_stop, t_end, after in rounds
             if sender.max_gap(t_stop - timeout, t_end) <= 0.3 * timeout]
    print(f'{len(clean)} of {len(rounds)} rounds with a clean stream')
    assert clean, 'the test stream was never clean for a whole round'
    for after in clean:
        assert not any(m.watchdog_tripped and m.command_age >= stall for m in after), (
            [m.command_age for m in after if m.watchdog_tripped], out)


# -- command-line arguments rcl refuses ------------------------------------------------------------
@pytest.mark.parametrize('exe', ['omni_driver', 'omni_record'])
@pytest.mark.parametrize('args, sentence', [
    (['-p', 'model:='], "invalid command-line argument '-p model:=': cannot parse it as a "
                        "parameter override rule (expected -p name:=value, with a value)"),
    (['-p', ':=3'], "invalid command-line argument '-p :=3'"),
    (['-r', 'foo'], "invalid command-line argument '-r foo': cannot parse it as a remap rule"),
])
def test_unparsable_ros_argument_is_one_fatal_line_and_exit_code_2(ros_domain, tmp_path, exe, args,
                                                                    sentence):
    proc = subprocess.run([str(harness.executable('haptic_omni_driver', exe)), '--ros-args', *args],
                          env=harness.ros_env(ros_domain), cwd=tmp_path, capture_output=True,
                          text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert sentence in proc.stderr
    assert '[FATAL]' in proc.stderr and 'Traceback' not in proc.stderr + proc.stdout
    assert not any(tmp_path.iterdir())          # nothing was started, nothing written
