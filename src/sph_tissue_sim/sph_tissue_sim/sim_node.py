"""sim_node: the SPH soft-tissue simulation in the ROS 2 graph.

Subscribes ``omni/pose`` (geometry_msgs/PoseStamped, stylus tip in the device frame), maps the tip
into the tissue frame, advances the tissue by the time since the previous pose (sub-stepped by the
core) and answers every step with ``omni/force_feedback`` (geometry_msgs/WrenchStamped: the reaction
of the tissue on the tool in the device frame, clamped to ``force_limit``; header stamp and frame
are the pose's, so the round trip can be measured). Publishes ``tissue/particles``
(sensor_msgs/PointCloud2, see :mod:`.cloud`) at ``particles_rate`` and ``tissue/metrics``
(tissue_msgs/SimMetrics) per step; serves ``tissue/reset`` (tissue_msgs/srv/ResetTissue). The
jaw grasps the tissue in reach of the tool until it opens, closed as ``grasp_input`` says: ``button1``
or ``button2`` that stylus button (``omni/state``, tissue_msgs/DeviceState), ``jaw`` the driver's
CRTK jaw (``omni/jaw/measured_js``, sensor_msgs/JointState: closed at most ``JAW_CLOSED_MAX``).

Several instruments on one tissue (parameter ``instruments``, e.g. ``[left, right]``): each name is
a namespace with its own ``<name>/omni/pose``, ``<name>/omni/force_feedback``, grasp input,
``<name>/tissue/metrics`` and ``<name>/tissue/device_frame`` (frame ``<name>/<device_frame>``); the
particles, the reset and the parameters stay the node's.

The haptic and timing modes (parameters ``haptic_mode``, ``timing_mode``) and the threads they
use are described in :mod:`.runner`, which runs the loop; this module translates messages and
parameters.

Exit codes: 0 normal (Ctrl-C), 1 the model cannot be built (missing mesh, ...), 2 invalid parameters.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, TransformStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, PointCloud2
from tissue_common.frames import TfBroadcaster, Transform
from tissue_common.instruments import topic_within
from tissue_common.node_start import (EXIT_PARAMS, build_node, init_rclpy, spin_until_stopped,
                                      stop_on_signals)
from tissue_common.params import declare_all
from tissue_common.stamps import stamp_to_ns
from tissue_msgs.msg import DeviceState, SimMetrics
from tissue_msgs.srv import ResetTissue

from .core.compliance import close_all
from .core.errors import ConfigError, ModelError, SimError
from .core.solver import warmup
from .params import (JAW_CLOSED_MAX, SIM_PARAMS, build_config, build_material, build_model, check_value,
                     instrument_tools, solves_in_background)
from .runner import Pose, Runner, make_solver, metrics_values, pose_history
from .startup import numba_cache_stats, one_blas_thread, startup_report

EXIT_OK, EXIT_INPUT = 0, 1
SWITCH_INTERVAL = 2e-4  # [s]


class SimNode(Node):
    """omni/pose -> tissue step -> omni/force_feedback, plus particles, metrics and reset: the
    translation between messages, parameters and the :class:`~.runner.Runner`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('sim_node', **kwargs)
        self.p = p = declare_all(self, SIM_PARAMS, ConfigError, check_value)
        log = self.get_logger()
        self.model = build_model(p)
        config = build_config(p)
        t0 = time.perf_counter()
        if p['warmup']:
            log.info('numba warm-up: the SPH kernels load from numba\'s cache, or compile (about 30 s '
                     'on 2 cores) at the first start after a change of the core')
            try:
                warmup(config.scheme, config.integrator, len(p['instruments']))
            except SimError as exc:  # the probe step below still compiles what this model needs
                log.warn(f'numba warm-up on the test block failed ({exc}); continuing')
        names = list(p['instruments'])
        solver = make_solver(self.model, build_material(p), config, p['nominal_dt'],
                             background=solves_in_background(p), instruments=len(names), tools=instrument_tools(p))
        self.runner = Runner(p, self.model, solver, self._send_force, self._send_metrics, self._send_cloud,
                             self._log)
        self.compile_time = time.perf_counter() - t0
        self.kernels_compiled, self.kernels_loaded = numba_cache_stats()
        self._wrench_msg = WrenchStamped()
        self._metrics_msg = SimMetrics()
        depth, reliable, note = pose_history(p, self.runner)
        if note:
            log.warning(note)
        io_qos = QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
        self.io_qos = io_qos
        metrics_qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                 reliability=ReliabilityPolicy.RELIABLE)
        self.force_pubs = [self.create_publisher(WrenchStamped, topic_within(name, 'omni/force_feedback'), io_qos)
                           for name in names]
        self.metrics_pubs = [self.create_publisher(SimMetrics, topic_within(name, 'tissue/metrics'), metrics_qos)
                             for name in names]
        self.cloud_pub = self.create_publisher(PointCloud2, 'tissue/particles', QoSProfile(
            depth=2, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE))
        # where the device sits in the tissue scene: latched, and on /tf_static where tf2 is installed
        self.frame_pubs = [self.create_publisher(TransformStamped, topic_within(name, 'tissue/device_frame'), QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
            for name in names]
        self.tf_static = TfBroadcaster(self, static=True)
        if self.runner.mapping.scale != 1.0:
            log.warn(f'workspace_scale {self.runner.mapping.scale:g}: the {p["device_frame"]} frame on '
                     f'tissue/device_frame and /tf_static has the map\'s rotation and origin only (a '
                     f'transform cannot scale), so a stylus drawn through it sits at its unscaled offset')
        self._publish_device_frame()
        self.reset_srv = self.create_service(ResetTissue, 'tissue/reset', self._on_reset)
        self.cloud_timer = None
        self._set_cloud_timer(p['particles_rate'])
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.pose_subs = [self.create_subscription(PoseStamped, topic_within(name, 'omni/pose'),
                                                   lambda msg, k=k: self._on_pose(msg, k), io_qos)
                          for k, name in enumerate(names)]
        self.grasp_subs = self._grasp_subscriptions(p['grasp_input'], names)

    def _grasp_subscriptions(self, source: str, names: list[str]) -> list:
        """Each instrument's grasp input (``grasp_input``; '' none)."""
        if source == 'jaw':
            # the driver sends it with the pose's QoS, as measured_cp
            return [self.create_subscription(JointState, topic_within(name, 'omni/jaw/measured_js'),
                                             lambda msg, k=k: self._on_jaw(msg, k), self.io_qos)
                    for k, name in enumerate(names)]
        if source:      # button1 | button2: that DeviceState field
            return [self.create_subscription(
                DeviceState, topic_within(name, 'omni/state'),
                lambda msg, k=k: self.runner.on_grasp(k, getattr(msg, source), stamp_to_ns(msg.header.stamp)), 10)
                for k, name in enumerate(names)]
        return []

    def _on_jaw(self, msg: JointState, k: int) -> None:
        if len(msg.position) != 1 or not np.isfinite(msg.position[0]):
            self.runner.throttled('jaw', 'warn', f'{self.grasp_subs[k].topic_name}: not one finite jaw angle '
                                  f'({list(msg.position)}): ignored')
            return
        self.runner.on_grasp(k, msg.position[0] <= JAW_CLOSED_MAX, stamp_to_ns(msg.header.stamp))

    def _publish_device_frame(self) -> None:
        """Where each instrument's device sits in the tissue scene: its frame (``device_frame``, or
        ``<name>/<device_frame>`` for a named instrument) on its ``tissue/device_frame`` and on
        /tf_static."""
        now = self.get_clock().now().to_msg()
        frames = []
        for ch, pub in zip(self.runner.channels, self.frame_pubs):
            m = ch.mapping
            frame = Transform.from_matrix(self.p['tissue_frame'], ch.device_frame(self.p['device_frame']),
                                          m.rotation, m.origin).to_msg(now)
            pub.publish(frame)
            frames.append(frame)
        self.tf_static.send(frames)

    def _set_cloud_timer(self, rate: float) -> None:
        if self.cloud_timer is not None:
            self.destroy_timer(self.cloud_timer)
            self.cloud_timer = None
        if rate > 0.0:
            self.cloud_timer = self.create_timer(1.0 / rate, self.runner.cloud_tick)

    def describe(self) -> str:
        reliable = self.io_qos.reliability == ReliabilityPolicy.RELIABLE
        return (f'{self.runner.describe()}, pose QoS {"reliable" if reliable else "best effort"} '
                f'depth {self.io_qos.depth}')

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the stepping thread (if configured) and report ready."""
        self.runner.start()
        for level, text in startup_report(self.compile_time, self.kernels_compiled, self.kernels_loaded,
                                          self.runner.lockstep):
            self._log(level, text)
        self.get_logger().info('ready: ' + self.describe())

    def shutdown(self) -> bool:
        """Stop the runner and log its totals; False if a thread of it is still inside a step."""
        stopped = self.runner.shutdown()
        # not the node logger: after Ctrl-C the context is shut down and rosout would fail
        log = rclpy.logging.get_logger(self.get_name() + '.shutdown')
        for line in self.runner.totals():
            log.info(line)
        if not stopped:
            log.warning('a stepping thread, or the far field\'s worker, is still inside a step or a solve '
                        'after its wait: exiting without waiting for it')
        return stopped

    # -- messages ----------------------------------------------------------------------------------
    def _log(self, level: str, text: str) -> None:
        # one call site per severity: rclpy refuses a call site whose severity changes
        log = self.get_logger()
        if level == 'error':
            log.error(text)
        elif level == 'warn':
            log.warning(text)
        else:
            log.info(text)

    def _on_pose(self, msg: PoseStamped, k: int = 0) -> None:
        h, pos, q = msg.header, msg.pose.position, msg.pose.orientation
        self.runner.on_pose(Pose(h.stamp, stamp_to_ns(h.stamp), h.frame_id, (pos.x, pos.y, pos.z),
                                 (q.x, q.y, q.z, q.w)), k)

    def _send_force(self, stamp, frame_id: str, force: np.ndarray, k: int = 0) -> None:
        msg = self._wrench_msg  # reused: building a message costs more than the step of a small area
        msg.header.stamp = stamp
        msg.header.frame_id = frame_id
        f = msg.wrench.force
        f.x, f.y, f.z = (float(v) for v in force)
        self.force_pubs[k].publish(msg)

    def _send_metrics(self, stamp, res, solver, haptic, k: int = 0) -> None:
        m = self._metrics_msg
        m.header.stamp = stamp
        m.header.frame_id = self.p['tissue_frame']
        m.haptic_mode = SimMetrics.HAPTIC_DIRECT if haptic is None else SimMetrics.HAPTIC_MULTIRATE
        for name, value in metrics_values(res, solver, haptic, k).items():
            if isinstance(value, tuple):
                target = getattr(m, name)
                target.x, target.y, target.z = value
            else:
                setattr(m, name, value)
        self.metrics_pubs[k].publish(m)

    def _send_cloud(self, stamp) -> None:
        if stamp is None:
            # lockstep time is the poses' stamps (a bag's, often long past): before the first
            # pose it has none yet, and a wall-clock stamp would make the replay's go backwards
            stamp = Time() if self.runner.lockstep else self.get_clock().now().to_msg()
        self.cloud_pub.publish(self.runner.cloud.message(stamp))

    def _on_reset(self, request: ResetTissue.Request, response: ResetTissue.Response):
        response.success, response.message, response.sim_time, response.n_particles = self.runner.reset(
            request.keep_material)
        if response.success:
            self.get_logger().info(response.message)
        else:
            self.get_logger().error(response.message)
        return response

    def _on_set_parameters(self, params) -> SetParametersResult:
        change = self.runner.apply({param.name: param.value for param in params})
        if not change.successful:
            if change.changed:
                self.get_logger().warn(f'parameter change {sorted(change.changed)} {change.reason}')
            return SetParametersResult(successful=False, reason=change.reason)
        if not change.changed:
            return SetParametersResult(successful=True)
        self.p = self.runner.p
        if 'particles_rate' in change.changed:
            self._set_cloud_timer(self.p['particles_rate'])
        if change.remapped:
            self._publish_device_frame()      # the latched transform follows the map
        self.get_logger().info(f'parameters {sorted(change.changed)} changed: {change.what}; now '
                               + self.describe())
        return SetParametersResult(successful=True)


def main(args=None) -> int:
    """Entry point of ``sim_node``; returns the exit code."""
    if not init_rclpy(args, 'sim_node'):
        return EXIT_PARAMS
    node = None
    code = EXIT_OK
    stopped = True
    # before the organ's factorisation too: its bits must not depend on the host's core count
    one_blas_thread()
    try:
        try:
            node, refused = build_node(SimNode, 'sim_node', {
                ConfigError: ('invalid parameters', EXIT_PARAMS),
                ModelError: ('cannot build the tissue', EXIT_INPUT),
                SimError: ('cannot build the tissue', EXIT_INPUT)})
        except Exception:
            if not rclpy.ok():  # Ctrl-C during the warm-up shut the context down under us
                rclpy.logging.get_logger('sim_node').info('interrupted during start-up')
                return EXIT_OK
            raise
        if node is None:
            return refused
        stop = stop_on_signals()
        # the stepping thread's Python work between kernels holds the GIL; hand it to the executor
        # (poses, services) within a fraction of a 1 kHz frame instead of CPython's 5 ms
        sys.setswitchinterval(SWITCH_INTERVAL)
        spin_until_stopped(node, stop, on_spinning=node.start)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        try:
            if node is not None:
                stopped = node.shutdown()
                node.destroy_node()
            rclpy.try_shutdown()
        except KeyboardInterrupt:  # a second Ctrl-C while shutting down
            pass
        if not stopped:
            # the interpreter's finalisation under a thread still in native code (a step) failed
            # to flush stdout and exited 120: leave without it, everything said and closed
            close_all()
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    return code


if __name__ == '__main__':
    sys.exit(main())
