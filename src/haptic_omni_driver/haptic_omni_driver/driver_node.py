"""omni_driver: the ROS 2 node that speaks for the haptic device.

Publishes ``omni/pose`` (geometry_msgs/PoseStamped, stylus tip in ``omni_base``, metres) and
``omni/state`` (tissue_msgs/DeviceState, at ``state_rate`` and on every button change: that one
stamped with the sample's stamp and sent before its pose), subscribes
``omni/force_feedback`` (geometry_msgs/WrenchStamped) and passes every force command through the
safety chain (:mod:`haptic_omni_driver.safety`) before it reaches the device. Backends (parameter
``backend``): ``openhaptics`` (libHD), ``replay`` (rosbag2 MCAP bag), ``scripted`` (synthetic motion).

With ``crtk`` (the default) it also speaks the CRTK names a dVRK graph uses, beside ``omni/pose``
(so ``/omni/measured_cp`` at the root namespace, ``/<ns>/omni/measured_cp`` in one): ``measured_cp``,
``measured_cv`` (the tracking filter's velocity), ``measured_js`` (OpenHaptics joint and gimbal
angles), ``servo_cf`` (a force setpoint through the same safety chain), ``operating_state`` and
``state_command`` (:mod:`haptic_omni_driver.crtk`: only ENABLED renders force), and a jaw made of a
stylus button: ``jaw/measured_js`` (closed 0 rad while ``jaw_button`` is down, a change stamped with
its sample and sent before its pose, like the button's state) and ``jaw/servo_jp`` (an angle the jaw
takes until the button next changes).

Force commands are not dispatched by the executor: the servo tick takes them straight from the DDS
reader before it evaluates the watchdog, and dates each one by its DDS reception time. A command that
has arrived is therefore never missed, nor counted old, because the executor thread (or the GIL) was
busy: the watchdog measures the command's true age.

Exit codes: 0 normal (Ctrl-C, or end of replay/script with exit_on_end), 1 bad input or device
failure (missing/corrupt bag, libHD absent, ...), 2 invalid parameters, 3 lockstep reply timeout
with lockstep_timeout_action abort.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from crtk_msgs.msg import OperatingState as CrtkOperatingState
from crtk_msgs.msg import StringStamped
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from tissue_common.estimator import TrackingFilter
from tissue_common.frames import TfBroadcaster, Transform
from tissue_common.node_start import (EXIT_PARAMS, build_node, init_rclpy, spin_until_stopped,
                                      stop_on_signals)
from tissue_common.params import check_choice, declare_all, descriptor
from tissue_common.stamps import set_stamp, stamp_to_ns
from tissue_common.throttle import EventThrottle
from tissue_common.transport import shared_memory_warning
from tissue_msgs.msg import DeviceState

from .backends.base import Backend, Sample
from .crtk import Jaw, OperatingStateMachine
from .errors import ConfigError, DriverError
from .params import DRIVER_PARAMS, STRING_ARRAYS
from .safety import ForceSafety, SafetyConfig

EXIT_OK, EXIT_INPUT = 0, 1
SAFETY_PARAMS = ('force_limit', 'ramp_time', 'watchdog_timeout', 'max_command_lag',
                 'accept_empty_frame', 'max_force_rate')
#: [s] how often a lockstep replay looks for the reply it waits for
LOCKSTEP_POLL = 0.0002
#: [ns] a pause between two samples after which the CRTK velocity filter starts afresh
CRTK_MAX_GAP_NS = 100_000_000
#: log text of each rejection reason of the safety chain
REJECTION_TEXT = {
    'nan': 'non-finite component',
    'stale': 'stale: its stamp answers no pose within max_command_lag of the newest',
    'future': 'stamped in the future: newer than the newest pose',
    'no_pose': 'no pose published yet, so it answers none (max_command_lag is on)',
}


def declare_driver_params(node: Node) -> dict:
    """Declare DRIVER_PARAMS on ``node``; return name -> value (raises ConfigError when refused)."""
    p = declare_all(node, {name: spec for name, spec in DRIVER_PARAMS.items()
                           if name not in STRING_ARRAYS}, ConfigError)
    for name in STRING_ARRAYS:
        try:
            value = node.declare_parameter(name, Parameter.Type.STRING_ARRAY,
                                           descriptor(name, DRIVER_PARAMS[name])).value
        except (ParameterException, TypeError, ValueError) as exc:
            raise ConfigError(f'parameter {name}: {exc}') from exc
        # not given, or given as [] (which rcl reads as no value): the default
        p[name] = list(value) if value is not None else list(DRIVER_PARAMS[name][0])
    return p


def make_backend(p: dict) -> Backend:
    """Construct the backend selected by the parameters (raises DriverError on bad input)."""
    kind = p['backend']
    if kind == 'replay':
        from .backends.replay import ReplayBackend

        return ReplayBackend(p['bag'], p['pose_topic_in_bag'], p['state_topic_in_bag'],
                             p['replay_mode'], p['rate'], p['loop'], p['lockstep_timeout'],
                             p['lockstep_timeout_action'], p['lockstep_max_resends'])
    if kind == 'scripted':
        from .backends.scripted import ScriptConfig, ScriptedBackend

        names = ('home', 'target', 'press_axis', 'pull_axis', 'approach_height', 'press_depth',
                 'pull_distance', 'sweep_depth', 'sweep_length', 'approach_time', 'press_time',
                 'hold_time', 'pull_time', 'release_time', 'sweep_time', 'return_time',
                 'tremor_amplitude', 'quantisation', 'seed', 'script')
        cfg = ScriptConfig(**{n: (list(p[n]) if isinstance(p[n], (list, tuple, np.ndarray))
                                  else p[n]) for n in names})
        return ScriptedBackend(cfg, p['publish_rate'], p['loop'], p['exit_on_end'])
    if kind == 'openhaptics':
        from .backends.openhaptics import OpenHapticsBackend

        return OpenHapticsBackend(p['library'], p['device_name'], p['require_calibration'])
    raise ConfigError(f'unknown backend {kind!r}')


class OmniDriver(Node):
    """Haptic device node: backend -> omni/pose, omni/force_feedback -> safety -> device."""

    def __init__(self, **kwargs) -> None:
        super().__init__('omni_driver', **kwargs)
        self.p = declare_driver_params(self)
        p = self.p
        self.safety = ForceSafety(self._safety_config(p))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.finished = threading.Event()
        self.exit_code = EXIT_OK
        self._lockstep = p['backend'] == 'replay' and p['replay_mode'] == 'lockstep'

        # Backend first: a bad bag or a missing libHD fails before anything is advertised.
        self.backend = make_backend(p)
        if self.backend.name == 'openhaptics':
            dev_max = getattr(self.backend, 'max_force', None)
            if dev_max and p['force_limit'] > dev_max:
                self.get_logger().warn(f'force_limit {p["force_limit"]} N above the device '
                                       f'nominal max {dev_max} N: using {dev_max} N')
                cfg = self._safety_config(p)
                cfg.force_limit = dev_max
                self.safety.set_config(cfg)

        if self._lockstep:
            qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST)
        else:
            qos = QoSProfile(depth=p['qos_depth'], history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE if p['reliable']
                             else ReliabilityPolicy.BEST_EFFORT)
        self.pose_pub = self.create_publisher(PoseStamped, 'omni/pose', qos)
        self.state_pub = self.create_publisher(DeviceState, 'omni/state', 10)
        # taken by the servo tick itself (take_commands); `subscriptions` hides it from the executor
        self.force_sub = self.create_subscription(WrenchStamped, 'omni/force_feedback',
                                                  lambda _msg: None, qos)
        self.diag_pub = None
        if p['diagnostics_rate'] > 0:
            self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
            self.create_timer(1.0 / p['diagnostics_rate'], self._publish_diagnostics)
        self.create_timer(1.0 / p['state_rate'], self._publish_state)

        self._state_lock = threading.Lock()
        self._buttons = (False, False)
        self._last_flags = None
        self._reply_cond = threading.Condition()
        self._replies: set[int] = set()
        self._take_lock = threading.Lock()
        self._last_take: float | None = None
        #: (monotonic [s], system clock [ns]) now; tests inject their own
        self._now_clocks = lambda: (time.monotonic(), time.time_ns())
        #: next (message, message info) from the command reader, None when empty; tests inject
        self._take = self._take_from_reader
        self._pose_msg = PoseStamped()
        self._pose_msg.header.frame_id = p['frame_id']
        self.n_poses = 0
        self.n_commands = 0
        self._rejected_logged = 0
        self._reject_log = EventThrottle()
        self._servo_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._t_start = time.monotonic()
        self._setup_crtk(p, qos)

    def _setup_crtk(self, p: dict, qos: QoSProfile) -> None:
        """The CRTK names beside omni/pose (relative: in the node's namespace, like it)."""
        if p['start_state'] == 'DISABLED' and not p['crtk']:
            raise ConfigError('start_state DISABLED needs crtk true: only omni/state_command can '
                              'enable the device')
        self.op_state = OperatingStateMachine(p['start_state'])
        self._op_lock = threading.Lock()
        self.safety.allow_output(self.op_state.current.renders_force, self._now_clocks()[0])
        #: next setpoint (message, message info) from servo_cf, None when empty; tests inject
        self._take_setpoint = lambda: None
        self.servo_cf_sub = None
        if not p['crtk']:
            return
        self._velocity = TrackingFilter(p['velocity_cutoff'])
        self._last_sample_ns: int | None = None
        self._crtk_period_ns = int(round(1e9 / p['crtk_rate']))
        self._next_crtk_ns: int | None = None
        self.cp_pub = self.create_publisher(PoseStamped, 'omni/measured_cp', qos)
        self.cv_pub = self.create_publisher(TwistStamped, 'omni/measured_cv', qos)
        self.js_pub = (self.create_publisher(JointState, 'omni/measured_js', qos)
                       if self.backend.joint_names else None)
        self._cv_msg = TwistStamped()
        self._cv_msg.header.frame_id = p['frame_id']
        self._js_msg = JointState(name=list(self.backend.joint_names))
        # the state now and on every change; a late subscriber gets the last one (transient local)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.op_pub = self.create_publisher(CrtkOperatingState, 'omni/operating_state', latched)
        self.create_subscription(StringStamped, 'omni/state_command', self._on_state_command, 10)
        # taken by the servo tick like omni/force_feedback, hidden from the executor
        self.servo_cf_sub = self.create_subscription(WrenchStamped, 'omni/servo_cf',
                                                     lambda _msg: None, qos)
        self._take_setpoint = self._take_setpoint_from_reader
        # the jaw beside the arm, as a dVRK arm's: omni/jaw/*, with the pose's QoS like measured_*
        self.jaw = Jaw(p['jaw_button'], p['jaw_open_angle'])
        self._jaw_sent: float | None = None
        self._jaw_msg = JointState(name=['jaw'])
        self.jaw_pub = self.create_publisher(JointState, 'omni/jaw/measured_js', qos)
        self.jaw_sub = self.create_subscription(JointState, 'omni/jaw/servo_jp', self._on_jaw_command, qos)
        # the stylus tip as a frame (omni_base -> omni_stylus) where tf2 is installed
        self.tf = TfBroadcaster(self, static=False)
        self._publish_operating_state()

    @property
    def subscriptions(self):
        """Subscriptions the executor dispatches: all but the force commands (see take_commands)."""
        taken = (getattr(self, 'force_sub', None), getattr(self, 'servo_cf_sub', None))
        return (sub for sub in super().subscriptions if sub not in taken)

    # -- parameters ----------------------------------------------------------------------------
    @staticmethod
    def _safety_config(p: dict) -> SafetyConfig:
        return SafetyConfig(force_limit=p['force_limit'], ramp_time=p['ramp_time'],
                            watchdog_timeout=p['watchdog_timeout'],
                            max_command_lag=p['max_command_lag'], frame_id=p['frame_id'],
                            accept_empty_frame=p['accept_empty_frame'],
                            max_force_rate=p['max_force_rate'])

    def _on_set_parameters(self, params) -> SetParametersResult:
        new = dict(self.p)
        for param in params:
            if param.name in DRIVER_PARAMS:
                err = check_choice(DRIVER_PARAMS, param.name, param.value)
                if err:
                    return SetParametersResult(successful=False, reason=err)
                new[param.name] = param.value
        if any(param.name in SAFETY_PARAMS for param in params):
            try:
                self.safety.set_config(self._safety_config(new))
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self.get_logger().info(
                'safety parameters updated: force_limit %.3f N, ramp_time %.3f s, watchdog_timeout '
                '%.3f s, max_command_lag %.3f s, max_force_rate %g N/s'
                % (new['force_limit'], new['ramp_time'], new['watchdog_timeout'],
                   new['max_command_lag'], new['max_force_rate']))
        self.p = new
        return SetParametersResult(successful=True)

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the backend (and the virtual servo loop for backends without a device)."""
        b = self.backend
        self.get_logger().info(
            f'ready: backend {b.name}, source {b.source}, force_limit '
            f'{self.safety.config.force_limit:g} N, watchdog {self.safety.config.watchdog_timeout:g}'
            f' s, max_force_rate {self.safety.config.max_force_rate:g} N/s, pose QoS {"reliable" if self._lockstep or self.p["reliable"] else "best effort"}'
            + (', lockstep' if self._lockstep else ''))
        transport_warning = shared_memory_warning(os.environ)
        if transport_warning:
            self.get_logger().warn(transport_warning)
        if not b.has_device:
            self._servo_thread = threading.Thread(target=self._virtual_servo, daemon=True,
                                                  name='virtual_servo')
            self._servo_thread.start()
        b.start(self)
        self._publish_operating_state()     # is_homed: the calibration the backend found at start

    def shutdown(self) -> None:
        """Stop the backend and the servo loop (force zeroed on the device)."""
        self._stop.set()
        with self._reply_cond:
            self._reply_cond.notify_all()
        self.backend.stop()
        if self._servo_thread is not None:
            self._servo_thread.join(1.0)

    def flush(self, timeout: float = 5.0) -> None:
        """Wait until reliable subscribers acknowledged every pose, so exiting at the end loses none."""
        if not self.pose_pub.wait_for_all_acked(Duration(seconds=timeout)):
            self.get_logger().warn(f'not every pose was acknowledged within {timeout:g} s')

    def _virtual_servo(self) -> None:
        period = 1.0 / self.p['servo_rate']
        t0, k = time.monotonic(), 0
        while not self._stop.is_set():
            self.servo()
            k += 1
            delay = t0 + k * period - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -0.1:
                t0, k = time.monotonic(), 0

    # -- BackendSink ---------------------------------------------------------------------------
    def on_sample(self, sample: Sample) -> None:
        """Publish one pose (called from the backend / servo thread)."""
        # noted before it is published: its reply may come back before publish() returns
        self.safety.note_pose(sample.stamp_ns * 1e-9)
        if sample.buttons is not None and sample.buttons != self._buttons:
            # before the pose and with its stamp: a simulation that grasps on a button applies the
            # change from the next pose on, in a lockstep replay always at the same one
            self._buttons = sample.buttons
            self._publish_state(sample.stamp_ns)
        if self.p['crtk'] and self.jaw.sample(sample.buttons) != self._jaw_sent:
            self._publish_jaw(sample.stamp_ns)       # a change: like the button's, before the pose
        if sample.raw is not None:
            self.pose_pub.publish(sample.raw)
        else:
            msg = self._pose_msg
            set_stamp(msg.header.stamp, sample.stamp_ns)
            pos, q = msg.pose.position, msg.pose.orientation
            pos.x, pos.y, pos.z = (float(v) for v in sample.position)
            q.x, q.y, q.z, q.w = (float(v) for v in sample.orientation)
            self.pose_pub.publish(msg)
        self.n_poses += 1
        if self.p['crtk']:
            self._publish_measured(sample)

    def _publish_measured(self, sample: Sample) -> None:
        """CRTK measured_cp / measured_cv / measured_js of a sample, at ``crtk_rate``.

        The velocity filter takes every sample; the messages go out when due by the samples' own
        stamps (a replay's clock), and at once after a stamp that went backwards (a loop)."""
        stamp, last = sample.stamp_ns, self._last_sample_ns
        self._last_sample_ns = stamp
        if last is None or stamp < last or stamp - last > CRTK_MAX_GAP_NS:
            # a loop, a clock step or a pause: the filter's past is not this motion's
            self._velocity.reset()
            dt = 0.0
        else:
            dt = (stamp - last) * 1e-9
        _, v = self._velocity.update(sample.position, dt)
        due, period = self._next_crtk_ns, self._crtk_period_ns
        if due is not None and due - period <= stamp < due:
            return
        # on the schedule's ticks (the mean rate is crtk_rate); anew after a gap or a loop
        on_time = due is not None and due <= stamp < due + period
        self._next_crtk_ns = (due if on_time else stamp) + period
        self.cp_pub.publish(sample.raw if sample.raw is not None else self._pose_msg)
        cv = self._cv_msg
        set_stamp(cv.header.stamp, stamp)
        cv.twist.linear.x, cv.twist.linear.y, cv.twist.linear.z = (float(c) for c in v)
        self.cv_pub.publish(cv)
        if self.js_pub is not None and sample.joints is not None:
            js = self._js_msg
            set_stamp(js.header.stamp, stamp)
            js.position = [float(a) for a in sample.joints]
            self.js_pub.publish(js)
        self._publish_jaw(stamp)
        if self.tf.available:
            tip = Transform(self.p['frame_id'], self.p['stylus_frame'], sample.position,
                            sample.orientation)
            self.tf.send([tip.to_msg(cv.header.stamp)])

    def _publish_jaw(self, stamp_ns: int) -> None:
        msg = self._jaw_msg
        set_stamp(msg.header.stamp, stamp_ns)
        msg.position = [self.jaw.angle]
        self.jaw_pub.publish(msg)
        self._jaw_sent = self.jaw.angle

    def _on_jaw_command(self, msg: JointState) -> None:
        """A CRTK jaw/servo_jp: the jaw takes the angle at the next sample, unless it is not one."""
        kind, why = self.jaw.command(msg.position)
        # one line per kind and second at most: a client streaming bad commands must not flood the log
        if kind and (n := self._reject_log.event(f'jaw {kind}', self._now_clocks()[0], 1.0)) is not None:
            self.get_logger().warn(f'ignored a {self.jaw_sub.topic_name} command: {why} ({n} such '
                                   f'so far)')

    def _on_state_command(self, msg: StringStamped) -> None:
        """A CRTK state_command: enable, disable, pause, resume, home, unhome."""
        with self._op_lock:      # a fault from the backend thread cannot slip in between
            old = self.op_state.current
            new, why = self.op_state.command(msg.string, homed_now=bool(self.backend.calibrated))
            self.safety.allow_output(new.renders_force, self._now_clocks()[0])
        if why:
            self.get_logger().warn(f'state_command {msg.string!r}: {why}')
        if new != old:
            self.get_logger().info(f'operating state {old.state} -> {new.state}'
                                   + ('' if new.renders_force else ': no force is rendered'))
        self._publish_operating_state()
        self._publish_state()

    def _publish_operating_state(self) -> None:
        if not self.p['crtk']:
            return
        s = self.op_state.current
        msg = CrtkOperatingState(state=s.state, is_homed=bool(s.is_homed and self.backend.calibrated),
                                 is_busy=s.is_busy)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.p['frame_id']
        self.op_pub.publish(msg)

    def servo(self) -> np.ndarray:
        """One safety tick: the force the device renders now; state published on flag changes.

        The commands received up to now are taken first, so the watchdog sees every one of them.
        """
        now = self.take_commands()
        force = self.safety.output(now)
        status = self.safety.status(now)
        flags = status.flags()
        if flags != self._last_flags:
            # the first tick compares with all flags off: a command taken before the servo thread
            # first ran (a busy machine) may already be clamped, and that is still worth a line
            old = self._last_flags or tuple(False for _ in flags)
            self._last_flags = flags
            self._log_flag_change(old, flags, status)
            self._publish_state()
        return force

    def _log_flag_change(self, old, new, status) -> None:
        log = self.get_logger()
        if new[2] and not old[2]:
            log.warn('watchdog: no valid force command for %.1f ms (timeout %.1f ms): force zeroed'
                     % (status.command_age * 1e3, self.safety.config.watchdog_timeout * 1e3))
        if old[2] and not new[2]:
            log.info('watchdog: force commands resumed, ramping up over %.3f s'
                     % self.safety.config.ramp_time)
        if new[0] and not old[0] and not old[2]:
            log.info('force output enabled (a valid command, operating state ENABLED), ramping up '
                     'over %.3f s'
                     % self.safety.config.ramp_time)
        if new[1] and not old[1]:
            log.warn('force command above %.3f N: clamped' % self.safety.config.force_limit)

    def wait_for_reply(self, stamp_ns: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not self._stop.is_set():
            # take the replies here too: waiting for the next servo tick would slow lockstep down
            self.take_commands()
            with self._reply_cond:
                if stamp_ns in self._replies:
                    self._replies.discard(stamp_ns)
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._reply_cond.wait(min(remaining, LOCKSTEP_POLL))
        return False

    def wait_for_subscribers(self) -> bool:
        need = self.p['wait_for_subscribers']
        if self._lockstep:
            need = max(need, 1)
        logged = False
        while not self._stop.is_set():
            ok = self.pose_pub.get_subscription_count() >= need
            if ok and self._lockstep:
                ok = self.force_sub.get_publisher_count() >= 1
            if ok:
                return True
            if not logged:
                self.get_logger().info(
                    f'waiting for {need} subscriber(s) on {self.pose_pub.topic_name}'
                    + (f' and a publisher on {self.force_sub.topic_name}' if self._lockstep else ''))
                logged = True
            self._stop.wait(0.01)
        return False

    def on_finished(self, summary: str, exit_code: int) -> None:
        if exit_code != 0 and not self.context.ok():
            # Ctrl-C shut the context down while the backend thread was publishing: its publish
            # fails, but that is the shutdown, not a device or input failure (exit code stays 0)
            self.get_logger().debug(f'{summary} (during shutdown)')
            return
        if exit_code == 0:
            self.get_logger().info(summary)
        else:
            self.get_logger().error(summary)
            with self._op_lock:
                self.op_state.fault(summary)
                self.safety.allow_output(False, self._now_clocks()[0])
            self._publish_operating_state()
        if exit_code != 0 or self.p['exit_on_end']:
            self.exit_code = exit_code
            self.finished.set()

    def log(self, level: str, text: str) -> None:
        getattr(self.get_logger(), {'warn': 'warn', 'error': 'error', 'info': 'info'}.get(
            level, 'debug'))(text)

    # -- force commands ------------------------------------------------------------------------
    def take_commands(self) -> float:
        """Pass every force command received so far through the safety chain; returns the time.

        Called by the servo tick before it evaluates the watchdog (and by a lockstep replay waiting
        for its reply). Each command counts from its DDS reception time, not from when it is taken.
        """
        with self._take_lock:
            now, wall_ns = self._now_clocks()
            since, self._last_take = self._last_take, now
            # replies to poses, then CRTK setpoints (servo_cf), which answer none
            for take, answers_pose in ((self._take, True), (self._take_setpoint, False)):
                while (taken := take()) is not None:
                    msg, info = taken
                    self._on_command(msg, received_at(info, now, wall_ns, since), now, answers_pose)
        return now

    def _take_from_reader(self):
        with self.force_sub.handle:
            return self.force_sub.handle.take_message(WrenchStamped, False)

    def _take_setpoint_from_reader(self):
        with self.servo_cf_sub.handle:
            return self.servo_cf_sub.handle.take_message(WrenchStamped, False)

    def _on_command(self, msg: WrenchStamped, received: float, now: float,
                    answers_pose: bool = True) -> None:
        self.n_commands += 1
        f = msg.wrench.force
        stamp_ns = stamp_to_ns(msg.header.stamp)
        result = self.safety.command((f.x, f.y, f.z), msg.header.frame_id, received,
                                     stamp_ns * 1e-9, answers_pose)
        if not result.accepted:
            self._log_rejection(result.reason, msg, now)
        if self._lockstep and answers_pose:
            with self._reply_cond:
                if len(self._replies) > 10000:
                    self._replies.clear()
                self._replies.add(stamp_ns)
                self._reply_cond.notify_all()

    def _log_rejection(self, reason: str, msg: WrenchStamped, now: float) -> None:
        # At most one line per reason and second: a flood of bad commands must not flood the log.
        if self._reject_log.event(reason, now, 1.0) is None:
            return
        text = REJECTION_TEXT.get(reason) or (
            f'frame {msg.header.frame_id!r} is not {self.p["frame_id"]!r}')
        f, stamp = msg.wrench.force, msg.header.stamp
        self.get_logger().warn(
            f'rejected force command ({text}): ({f.x}, {f.y}, {f.z}), stamp {stamp.sec}.'
            f'{stamp.nanosec:09d}; {self.safety.status(now).rejected_commands} rejected so far')

    def _publish_state(self, stamp_ns: int | None = None) -> None:
        """DeviceState, stamped ``stamp_ns`` (a button change: its sample's) or now."""
        now = time.monotonic()
        status = self.safety.status(now)
        msg = DeviceState()
        if stamp_ns is None:
            msg.header.stamp = self.get_clock().now().to_msg()
        else:
            set_stamp(msg.header.stamp, stamp_ns)
        msg.header.frame_id = self.p['frame_id']
        msg.button1, msg.button2 = (bool(b) for b in self._buttons)
        msg.force_enabled = bool(status.force_enabled)
        msg.force_clamped = bool(status.force_clamped)
        msg.watchdog_tripped = bool(status.watchdog_tripped)
        msg.calibrated = bool(self.backend.calibrated)
        fx, fy, fz = (float(v) for v in status.commanded_force)
        msg.commanded_force.x, msg.commanded_force.y, msg.commanded_force.z = fx, fy, fz
        msg.force_limit = float(self.safety.config.force_limit)
        msg.command_age = float(status.command_age)
        msg.rejected_commands = int(status.rejected_commands)
        msg.backend = self.backend.name
        msg.source = str(self.backend.source)
        with self._state_lock:
            self.state_pub.publish(msg)

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        status = self.safety.status(now)
        elapsed = max(now - self._t_start, 1e-9)
        d = DiagnosticStatus(name=f'{self.get_name()}: haptic device', hardware_id=str(
            self.backend.source))
        if status.watchdog_tripped:
            d.level, d.message = DiagnosticStatus.WARN, 'watchdog tripped: force zeroed'
        elif not self.backend.calibrated:
            d.level, d.message = DiagnosticStatus.WARN, 'device not calibrated'
        else:
            d.level, d.message = DiagnosticStatus.OK, 'ok'
        d.values = [KeyValue(key=k, value=str(v)) for k, v in (
            ('backend', self.backend.name), ('operating state', self.op_state.current.state),
            ('poses published', self.n_poses),
            ('mean pose rate [Hz]', f'{self.n_poses / elapsed:.1f}'),
            ('force commands', self.n_commands), ('rejected commands', status.rejected_commands),
            *((f'rejected ({reason})', n) for reason, n in sorted(
                status.rejected_by_reason.items())),
            ('watchdog trips', self.safety.trip_count), ('force enabled', status.force_enabled),
            ('rate-limited outputs', self.safety.rate_limited_count),
            ('commanded force [N]', np.round(status.commanded_force, 4).tolist()))]
        arr = DiagnosticArray(status=[d])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(arr)


def received_at(info: dict | None, now: float, wall_ns: int, since: float | None) -> float:
    """Monotonic time [s] a command arrived, from its DDS reception stamp (system clock [ns]).

    ``now`` and ``wall_ns`` are the same instant on both clocks. The result lies between the previous
    take ``since`` (it was not there yet) and ``now``, so a system clock step cannot move it further;
    without a reception stamp it is ``now``.
    """
    recv_ns = (info or {}).get('received_timestamp') or 0
    t = now - (wall_ns - recv_ns) * 1e-9 if recv_ns > 0 else now
    if since is not None:
        t = max(t, since)
    return min(t, now)


def main(args=None) -> int:
    """Entry point of ``omni_driver``; returns the exit code."""
    if not init_rclpy(args, 'omni_driver'):
        return EXIT_PARAMS
    node = None
    code = EXIT_OK
    try:
        node, refused = build_node(OmniDriver, 'omni_driver', {ConfigError: ('error', EXIT_PARAMS),
                                                               DriverError: ('error', EXIT_INPUT)})
        if node is None:
            return refused
        stop = stop_on_signals()
        try:
            spin_until_stopped(node, stop, node.finished, on_spinning=node.start)
        except DriverError as exc:
            node.get_logger().fatal(f'error: {exc}')
            return EXIT_INPUT
        code = node.exit_code
        if node.finished.is_set() and code == EXIT_OK:
            node.flush()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
