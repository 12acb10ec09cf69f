"""The whole node graph as real processes: driver, sim, viz (and the recorder), for system tests,
the bag generator, the demo and the live benchmark.

Every node is started from its installed executable (what ``ros2 run`` starts) with
:class:`harness.NodeProcess`, in its own process group, on the ROS_DOMAIN_ID of ``env``.
"""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path
from typing import Mapping

import numpy as np

from tissue_common.feel import feel

from . import harness

# A shell runs background jobs with SIGINT ignored, and child processes inherit an ignored signal:
# the nodes would then ignore the SIGINT that stops them cleanly. A handler here (reset to the
# default at exec) gives them back their Ctrl-C.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO_ROOT = harness.REPO_ROOT
BAGS = REPO_ROOT / 'bags'
#: sim_node parameters the goldens in bags/ were recorded with (a ROS 2 params file)
GOLDEN_SIM_PARAMS = BAGS / 'golden_sim_params.yaml'
SHORT_BAGS = ('press', 'pull', 'sweep', 'poke', 'grasp', 'bimanual', 'cut', 'needle')
#: sim_node parameters a golden was recorded with beyond GOLDEN_SIM_PARAMS (button 1, the default
#: grasp_input, is pressed only by the grasp sessions)
BAG_SIM_PARAMS = {
    'bimanual': {'instruments': ['left', 'right'],
                 'instrument_offsets': [-0.02, 0.0, 0.0, 0.02, 0.0, 0.0]},
    'cut': {'tool_shape': 'blade', 'tool_radius': 0.0005, 'tool_length': 0.02},
    'needle': {'tool_shape': 'needle', 'tool_radius': 0.0005, 'tool_length': 0.06},
}
#: the kind of CPU the goldens were made on (:func:`host_kind`), written by bags/make_bags.py
GOLDEN_HOST = BAGS / 'golden_host.json'


def host_kind() -> dict[str, str]:
    """What a lockstep force's last bits depend on besides the code and the parameters: the CPU
    (numba's code is compiled for one level everywhere, but OpenBLAS and the C libraries it calls
    pick their code for the CPU; see bags/README.md)."""
    kind = {'machine': os.uname().machine}
    wanted = {'vendor_id': 'vendor', 'cpu family': 'family', 'model': 'model', 'model name': 'name'}
    try:
        with open('/proc/cpuinfo', encoding='ascii', errors='replace') as f:
            for line in f:
                key, _, value = line.partition(':')
                key = key.strip()
                if key in wanted and wanted[key] not in kind:
                    kind[wanted[key]] = value.strip()
                if not line.strip():   # the first processor's block is enough
                    break
    except OSError:
        pass
    return kind

SIM_READY = r'ready: '
#: frame of the monitor's probe poses (rejected by the sim: see :meth:`Monitor.probe_sim`)
PROBE_FRAME = 'system_monitor_probe'
DRIVER_READY = r'ready: backend'
VIZ_READY = r'ready: window'
RECORD_READY = r'recording '


def bag_instruments(name: str) -> tuple[str, ...]:
    """The instruments (namespaces) of a bundled bag; ``('',)``: one, at the root namespace."""
    return tuple(BAG_SIM_PARAMS.get(name, {}).get('instruments', ['']))


def record_matched(topic: str) -> str:
    """omni_record's line once its subscription to ``topic`` (resolved, e.g. ``/omni/pose``) has
    matched a publisher: from then on nothing that publisher sends is missed."""
    return re.escape(topic) + r': matched a publisher'


def sim(mode: str = 'lockstep', env: Mapping[str, str] | None = None, golden: bool = True,
        params: Mapping[str, object] | None = None, name: str = 'sim_node',
        params_file: str | Path | None = None, ros_args=()) -> harness.NodeProcess:
    """sim_node in ``mode`` (lockstep | live), with the golden parameters unless ``golden`` is False,
    then ``params_file``, then ``params`` (``ros_args``: e.g. a namespace, ``['-r', '__ns:=/left']``)."""
    p = {'timing_mode': mode}
    p.update(params or {})
    files = [GOLDEN_SIM_PARAMS] if golden else []
    files += [params_file] if params_file is not None else []
    return harness.NodeProcess('sph_tissue_sim', 'sim_node', env=env, name=name, params_file=files,
                               params=p, ros_args=ros_args)


def driver_replay(bag: str | Path, mode: str = 'lockstep', env: Mapping[str, str] | None = None,
                  rate: float = 1.0, loop: bool = False, subscribers: int = 1,
                  params: Mapping[str, object] | None = None,
                  params_file: str | Path | None = None, instrument: str = '') -> harness.NodeProcess:
    """omni_driver replaying ``bag`` (lockstep: reliable, wait for each reply; timed: 1 kHz);
    ``instrument``: the one it plays, in that namespace, from the bag's topics of that name."""
    p = {'backend': 'replay', 'bag': str(bag), 'replay_mode': mode, 'rate': float(rate),
         'loop': loop, 'exit_on_end': not loop, 'wait_for_subscribers': subscribers,
         'lockstep_timeout': 30.0, 'lockstep_timeout_action': 'continue'}
    ros_args: list[str] = []
    if instrument:
        p.update(pose_topic_in_bag=f'/{instrument}/omni/pose', state_topic_in_bag=f'/{instrument}/omni/state')
        ros_args = ['-r', f'__ns:=/{instrument}']
    p.update(params or {})
    return harness.NodeProcess('haptic_omni_driver', 'omni_driver', env=env, params=p,
                               params_file=params_file, name=f'omni_driver_{instrument}' if instrument
                               else 'omni_driver', ros_args=ros_args)


def driver_device(backend: str, env: Mapping[str, str] | None = None, subscribers: int = 1,
                  params: Mapping[str, object] | None = None,
                  params_file: str | Path | None = None) -> harness.NodeProcess:
    """omni_driver on a live source: ``scripted`` (one pass of its script, then it exits) or
    ``openhaptics`` (the device, until stopped)."""
    p = {'backend': backend, 'wait_for_subscribers': subscribers}
    if backend == 'scripted':
        p.update(loop=False, exit_on_end=True)
    p.update(params or {})
    return harness.NodeProcess('haptic_omni_driver', 'omni_driver', env=env, params=p,
                               params_file=params_file)


def viz(report_dir: str | Path | None = None, env: Mapping[str, str] | None = None,
        params: Mapping[str, object] | None = None,
        params_file: str | Path | None = None) -> harness.NodeProcess:
    """viz_node writing its report to ``report_dir`` on shutdown (no report if None)."""
    p = {'report_on_shutdown': report_dir is not None, 'summary_period': 1.0}
    if report_dir is not None:
        p['report_dir'] = str(report_dir)
    p.update(params or {})
    return harness.NodeProcess('tissue_viz', 'viz_node', env=env, params=p, params_file=params_file)


def recorder(output: str | Path, env: Mapping[str, str] | None = None,
             params: Mapping[str, object] | None = None) -> harness.NodeProcess:
    """omni_record writing pose, force and state to the new bag ``output`` (reliable, no loss)."""
    p = {'output': str(output), 'reliable': True, 'qos_depth': 10000}
    p.update(params or {})
    return harness.NodeProcess('haptic_omni_driver', 'omni_record', env=env, params=p)


def group_alive(proc: harness.NodeProcess) -> bool:
    """True while any process of ``proc``'s process group exists (the node or a child of it)."""
    if proc.proc is None:
        return False
    try:
        os.killpg(proc.proc.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie leader that was not reaped yet still counts; reap it first.
    if proc.proc.poll() is not None:
        try:
            os.killpg(proc.proc.pid, 0)
        except ProcessLookupError:
            return False
    return True


def stop_all(procs, timeout: float = 15.0) -> dict[str, int | None]:
    """SIGINT every process (as Ctrl-C in a launch would), then wait; returns name -> exit code.

    Processes are signalled together so that none waits on a peer that is already gone; each gets
    one SIGINT only (a second one would interrupt its clean shutdown) and is escalated to
    SIGTERM/SIGKILL by :meth:`harness.NodeProcess.stop` only if it has not exited in ``timeout``.
    """
    import subprocess

    for p in procs:
        if p.alive():
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout
    for p in procs:
        if p.proc is not None:
            try:
                p.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    return {p.name: p.stop(5.0) for p in procs}


class Monitor:
    """An in-process rclpy node watching the loop: poses, forces, state, metrics, particles, diagnostics.

    Pose->force latency is measured here: receive time of the force whose header stamp equals a
    pose's stamp minus the receive time of that pose (best-effort readers by default, so it never
    slows the loop down; ``reliable=True`` for lossless lockstep checks). With ``loop=False`` it
    reads neither (two 1 kHz Python readers cost about half a core: a watcher that leaves the
    measuring to viz_node). Spins in its own thread with an EventsExecutor. Use as a context manager.
    """

    def __init__(self, domain_env: Mapping[str, str] | None = None, keep: bool = True,
                 reliable: bool = False, depth: int = 1000, loop: bool = True,
                 namespace: str = '') -> None:
        self.env = domain_env
        self.namespace = namespace   # an instrument's: its omni/* and tissue/* topics
        self.keep = keep
        self.loop = loop
        self.reliable = reliable   # reliable pose/force readers: no loss, match reliable writers only
        # reader history: with reliable readers, deeper than what this monitor may fall behind by
        # on a busy machine (a full history drops its oldest message)
        self.depth = depth
        self.lock = __import__('threading').Lock()
        self.pose_rx: dict[int, float] = {}       # stamp -> receive time
        self.pose_at: dict[int, tuple] = {}       # stamp -> stylus position (with ``keep``)
        self.force_rx: dict[int, float] = {}      # stamp -> receive time
        self.forces: list[tuple[int, float, tuple]] = []   # (stamp, rx time, force)
        self.wrenches: list[tuple[int, float, tuple]] = []  # (stamp, rx time, force + torque)
        self.n_poses = 0
        self.n_forces = 0
        self.latencies: list[float] = []
        self.states: list = []                    # (rx time, DeviceState)
        self.metrics_count = 0
        self.step_times: list[float] = []          # [s] sim step wall time per metrics message
        self.last_metrics = None
        self.particles_count = 0
        self.last_particles = None
        self.diagnostics: list = []
        self.last_force = (0.0, 0.0, 0.0)

    # -- lifecycle ----------------------------------------------------------------------------
    def start(self) -> 'Monitor':
        import threading

        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from rclpy.experimental import EventsExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from tissue_msgs.msg import DeviceState, SimMetrics

        saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
        if self.env is not None:
            for k in saved:
                if k in self.env:
                    os.environ[k] = self.env[k]
        try:
            self.context = rclpy.context.Context()
            # No rclpy signal handlers: Ctrl-C must reach the caller as KeyboardInterrupt so it
            # can stop the node processes (rclpy's handler would only shut this context down).
            rclpy.init(context=self.context,
                       signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
            self.node = rclpy.create_node('system_monitor', context=self.context,
                                          namespace=self.namespace or None)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        fast = QoSProfile(depth=self.depth, history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE if self.reliable
                          else ReliabilityPolicy.BEST_EFFORT)
        reliable = QoSProfile(depth=self.depth, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.RELIABLE)
        n = self.node
        if self.loop:
            self.pose_sub = n.create_subscription(PoseStamped, 'omni/pose', self._on_pose, fast)
            self.force_sub = n.create_subscription(WrenchStamped, 'omni/force_feedback',
                                                   self._on_force, fast)
        self.state_sub = n.create_subscription(DeviceState, 'omni/state', self._on_state, reliable)
        self.metrics_sub = n.create_subscription(SimMetrics, 'tissue/metrics', self._on_metrics,
                                                 reliable)
        # the tissue's cloud is the sim's, not an instrument's (the sims here run at the root)
        self.particles_sub = n.create_subscription(
            PointCloud2, '/tissue/particles' if self.namespace else 'tissue/particles', self._on_particles,
            QoSProfile(depth=2, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.BEST_EFFORT))
        self.diag_sub = n.create_subscription(DiagnosticArray, '/diagnostics',
                                              self.diagnostics.append, 100)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(n)
        self._stopping = False
        self._probe_replies = 0
        self._thread = threading.Thread(target=self._spin, daemon=True, name='monitor')
        self._thread.start()
        return self

    def _spin(self) -> None:
        # spin_once in a loop: EventsExecutor.spin() in a non-main thread starves the other
        # threads here (the test thread stops running), spin_once(timeout) does not.
        while not self._stopping:
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down while spinning
                if not self.context.ok():
                    return

    def stop(self) -> None:
        import rclpy

        self._stopping = True
        self._thread.join(5.0)
        try:
            self.executor.shutdown(timeout_sec=2.0)
        except Exception:  # noqa: BLE001
            pass
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> 'Monitor':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- callbacks ----------------------------------------------------------------------------
    @staticmethod
    def _ns(header) -> int:
        return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec

    def _on_pose(self, msg) -> None:
        now = time.monotonic()
        if msg.header.frame_id == PROBE_FRAME:
            return
        stamp = self._ns(msg.header)
        with self.lock:
            self.n_poses += 1
            self.pose_rx[stamp] = now
            if self.keep:
                p = msg.pose.position
                self.pose_at[stamp] = (p.x, p.y, p.z)
            t_force = self.force_rx.get(stamp)
            if t_force is not None:  # the force overtook the pose to this reader
                self.latencies.append(max(0.0, t_force - now))

    def _on_force(self, msg) -> None:
        now = time.monotonic()
        if msg.header.frame_id == PROBE_FRAME:
            self._probe_replies += 1
            return
        stamp = self._ns(msg.header)
        f = msg.wrench.force
        vec = (f.x, f.y, f.z)
        with self.lock:
            self.n_forces += 1
            self.last_force = vec
            if self.keep:
                self.forces.append((stamp, now, vec))
                t = msg.wrench.torque
                self.wrenches.append((stamp, now, vec + (t.x, t.y, t.z)))
            self.force_rx[stamp] = now
            t_pose = self.pose_rx.get(stamp)
            if t_pose is not None:
                self.latencies.append(now - t_pose)

    def feel(self) -> dict | None:
        """:func:`tissue_common.feel.feel` of the forces received, each with the position of the pose
        it answered, in stamp order (None before any such pair; needs ``keep``)."""
        with self.lock:
            pairs = sorted((stamp, self.pose_at[stamp], f) for stamp, _, f in self.forces
                           if stamp in self.pose_at)
        if len(pairs) < 3:
            return None
        t = np.array([p[0] for p in pairs]) * 1e-9
        return feel(np.array([p[1] for p in pairs]), np.array([p[2] for p in pairs]), t)

    def _on_state(self, msg) -> None:
        with self.lock:
            self.states.append((time.monotonic(), msg))

    def _on_metrics(self, msg) -> None:
        with self.lock:
            self.metrics_count += 1
            self.last_metrics = msg
            if self.keep:
                self.step_times.append(msg.step_wall_time)

    def _on_particles(self, msg) -> None:
        with self.lock:
            self.particles_count += 1
            self.last_particles = msg

    # -- queries ------------------------------------------------------------------------------
    def wait_for(self, predicate, timeout: float, what: str = 'condition') -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f'monitor: {what} not met within {timeout} s')
            time.sleep(0.02)

    def wait_matched(self, timeout: float = 30.0) -> None:
        """Wait until the pose and force topics have a publisher each (the loop is connected)."""
        self.wait_for(lambda: self.pose_sub.get_publisher_count() >= 1
                      and self.force_sub.get_publisher_count() >= 1, timeout,
                      'publishers on omni/pose and omni/force_feedback')

    def diagnostic_sources(self) -> set[str]:
        """Which nodes published /diagnostics so far: 'driver', 'viz', 'sim' (by status name)."""
        out = set()
        with self.lock:
            arrays = list(self.diagnostics)
        for array in arrays:
            for status in array.status:
                if 'omni_driver' in status.name:
                    out.add('driver')
                elif 'viz_node' in status.name:
                    out.add('viz')
                elif 'sim' in status.name:
                    out.add('sim')
        return out

    def viz_values(self) -> dict[str, dict[str, str]]:
        """viz_node's latest /diagnostics, by status name without the node's prefix (e.g. 'pose to
        force latency'): its key-value pairs ({} before the first)."""
        with self.lock:
            arrays = list(self.diagnostics)
        for array in reversed(arrays):
            if any(s.name.startswith('viz_node') for s in array.status):
                return {s.name.split(': ', 1)[-1]: {kv.key: kv.value for kv in s.values}
                        for s in array.status}
        return {}

    def probe_sim(self, timeout: float = 30.0) -> None:
        """Make sure the sim's force writer has matched this monitor's reader before a run.

        Subscriber-side matching (``get_publisher_count``) does not tell whether the *writer* has
        matched us yet, and a volatile writer drops what it sent before that. So we send the sim a
        pose in a foreign frame: sim_node rejects it without stepping the tissue and answers a zero
        force in that frame; once that answer arrives here, the writer knows this reader. Call
        it before the driver starts (the driver would count the foreign reply as rejected).
        """
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        pub = self.node.create_publisher(
            PoseStamped, 'omni/pose', QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                                                 reliability=ReliabilityPolicy.RELIABLE))
        try:
            msg = PoseStamped()
            msg.header.frame_id = PROBE_FRAME
            deadline = time.monotonic() + timeout
            while self._probe_replies == 0:
                if time.monotonic() > deadline:
                    raise AssertionError(f'monitor: no answer from the sim to a probe pose within '
                                         f'{timeout} s')
                if pub.get_subscription_count() > 0:
                    pub.publish(msg)
                time.sleep(0.1)
        finally:
            self.node.destroy_publisher(pub)

    def unanswered(self) -> int:
        """Poses seen here with no force carrying their stamp."""
        with self.lock:
            return sum(1 for s in self.pose_rx if s not in self.force_rx)
