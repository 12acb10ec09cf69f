"""viz_node: live statistics, /diagnostics, tool/force markers and a run report.

Subscribes ``tissue/metrics``, ``tissue/particles``, ``omni/pose`` and ``omni/force_feedback``;
publishes ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) and ``viz/markers``
(visualization_msgs/MarkerArray); serves ``viz/write_report`` (std_srvs/Trigger). With several
instruments (parameter ``instruments``, as sim_node's) each name is a namespace of its own
``tissue/metrics``, ``omni/pose`` and ``omni/force_feedback``, with statistics, diagnostics and
markers of its own; ``tissue/particles`` stays the node's. On shutdown
(Ctrl-C) it leaves the ROS graph, then writes the report folder (see :mod:`tissue_viz.report`) in
two processes, well within the 5 s ``ros2 launch`` grants between SIGINT and SIGTERM.

The callbacks only hand plain values to :class:`tissue_viz.stats.VizStats`; everything heavier runs
in timers at a few hertz.
"""

from __future__ import annotations

import functools
import gc
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from tissue_common.instruments import check_instruments, topic_within
from tissue_common.node_start import EXIT_PARAMS, init_rclpy, spin_until_stopped, stop_on_signals
from tissue_common.params import declare_all
from tissue_common.stamps import stamp_to_ns
from tissue_msgs.msg import SimMetrics
from visualization_msgs.msg import Marker, MarkerArray

from tissue_viz import figures
from tissue_viz.diagnostics import RateTarget, Status, Targets, worst_level, evaluate_instruments
from tissue_viz.errors import ReportError, VizConfigError
from tissue_viz.markers import CUT_COLOUR, ToolShape, cut_faces, force_arrow, held_positions, instrument_colour
from tissue_viz.report import ReportData, default_report_dir, prepare_report_dir, write_report
from tissue_viz.stats import TOPICS, VizStats, summary_line
from tissue_viz.tissue_images import TissueSnapshots, cloud_arrays

_F, _I, _B, _S, _FA = (Parameter.Type.DOUBLE, Parameter.Type.INTEGER, Parameter.Type.BOOL,
                       Parameter.Type.STRING, Parameter.Type.DOUBLE_ARRAY)
_RATE_DEFAULTS = {'metrics': (900.0, 1100.0), 'particles': (25.0, 35.0),
                  'pose': (900.0, 1100.0), 'force': (900.0, 1100.0)}


# name: (default, description, (low, high) or None, read_only) -- the one place parameters are
# declared (the format of tissue_common.params).
PARAMETERS: dict[str, tuple] = {
    'instruments': ([''], 'the instruments on the tissue, as sim_node\'s: each name a namespace of its '
                          'own tissue/metrics, omni/pose and omni/force_feedback ([""]: one, no '
                          'namespace), in sim_node\'s order', None, True),
    'window': (5.0, 'sliding window of the rolling statistics [s]', (0.1, 600.0), True),
    'haptic_rate': (1000.0, 'haptic loop rate [Hz]; a step longer than 1/haptic_rate misses '
                    'its deadline', (1.0, 10000.0), False),
    'diagnostics_rate': (1.0, 'rate of /diagnostics [Hz]', (0.1, 50.0), True),
    'summary_period': (5.0, 'period of the one-line summary in the log [s], 0 = off',
                       (0.0, 3600.0), True),
    'marker_rate': (30.0, 'rate of viz/markers [Hz], 0 = off', (0.0, 120.0), True),
    'latency_timeout': (0.5, 'a pose without a force reply after this long counts as missed [s]',
                        (0.001, 60.0), True),
    'max_report_rows': (200000, 'rows kept per report table; longer runs are evenly thinned',
                        (100, 10000000), True),
    'metrics_reliable': (True, 'subscribe tissue/metrics reliable (the contract) instead of best '
                         'effort', None, True),
    'stale_timeout': (2.0, 'a topic silent for longer than this is "no data" (ERROR) [s]',
                      (0.01, 3600.0), False),
    'rate_tolerance': (0.1, 'relative tolerance on min/max rates (as diagnostic_updater)',
                       (0.0, 0.99), False),
    'step_p99_warn': (0.0008, 'step wall time p99 above this is WARN [s]', (1e-6, 10.0), False),
    'step_p99_error': (0.001, 'step wall time p99 above this is ERROR [s]', (1e-6, 10.0), False),
    'deadline_miss_warn_pct': (1.0, 'deadline misses above this share are WARN [%]',
                               (0.001, 100.0), False),
    'deadline_miss_error_pct': (5.0, 'deadline misses above this share are ERROR [%]',
                                (0.001, 100.0), False),
    'latency_p50_warn': (0.001, 'pose->force latency median above this is WARN [s]',
                         (1e-6, 10.0), False),
    'latency_p99_warn': (0.003, 'pose->force latency p99 above this is WARN [s]', (1e-6, 10.0),
                         False),
    'latency_p99_error': (0.010, 'pose->force latency p99 above this is ERROR [s]',
                          (1e-6, 10.0), False),
    'reply_loss_warn_pct': (1.0, 'poses without a force reply above this share are WARN [%]',
                            (0.001, 100.0), False),
    'reply_loss_error_pct': (10.0, 'poses without a force reply above this share are ERROR [%]',
                             (0.001, 100.0), False),
    'force_limit': (3.3, 'device force limit [N]; reaching it is WARN', (0.01, 100.0), False),
    'energy_in_min': (-1e-6, 'energy the hand put into the multirate rendering below this is WARN '
                      '(the rendering gave energy back) [J]', (-1000.0, 0.0), False),
    'model_age_warn': (0.02, 'a multirate contact model older than this (the pose time between two '
                       'solver jobs) is WARN: the solver falls behind the hand [s]', (1e-4, 10.0), False),
    'report_dir': ('', 'report folder; empty = ./reports/<timestamp> for each report', None, False),
    'report_on_shutdown': (True, 'write the report when the node shuts down', None, False),
    'report_title': ('SPH soft-tissue simulation run', 'title of the report', None, False),
    'contact_threshold': (0.01, 'force that counts as first contact in the report [N]',
                          (0.0, 100.0), False),
    'tissue_images': (True, 'keep the tissue/particles clouds at rest, at the deepest press and '
                            'around it, and draw them in the report (images and an animation)',
                      None, False),
    'tool_in_tissue_frame': (False, 'draw the simulated tool and its force in the tissue frame, as '
                             'tissue/metrics reports them (else the stylus tip and the device '
                             'force in the pose frame, omni_base)', None, False),
    'tool_radius': (0.003, 'radius of the stylus tip marker in the pose frame [m] (in the tissue '
                           'frame the simulated tool has its own)', (1e-5, 1.0), False),
    'force_arrow_scale': (0.02, 'force arrow length per newton [m/N]', (0.0, 10.0), False),
}
for _topic, (_lo, _hi) in _RATE_DEFAULTS.items():
    PARAMETERS[f'{_topic}_min_rate'] = (_lo, f'lowest expected rate of {_topic} [Hz]',
                                        (0.0, 100000.0), False)
    PARAMETERS[f'{_topic}_max_rate'] = (_hi, f'highest expected rate of {_topic} [Hz]',
                                        (0.0, 100000.0), False)
    PARAMETERS[f'{_topic}_required'] = (True, f'a missing {_topic} topic is ERROR (else OK)',
                                        None, False)

# Exit codes (documented in the package README).
EXIT_OK = 0
EXIT_BAD_PARAMETERS = EXIT_PARAMS   # inconsistent or out-of-range parameters at start
EXIT_REPORT_FAILED = 3        # the shutdown report could not be written completely

#: processes that draw the shutdown report: ``ros2 launch`` escalates to SIGTERM 5 s after SIGINT
REPORT_PROCESSES = max(1, min(2, os.cpu_count() or 1))

#: [m] diameter of the dots that mark the particles an instrument holds
HELD_DOT = 0.002

_LEVEL_BYTES = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR,
                3: DiagnosticStatus.STALE}


def targets_from(values: dict) -> Targets:
    """Targets from a parameter dict (raises VizConfigError when inconsistent)."""
    rates = {t: RateTarget(values[f'{t}_min_rate'], values[f'{t}_max_rate'],
                           values[f'{t}_required']) for t in TOPICS}
    keys = ('rate_tolerance', 'stale_timeout', 'step_p99_warn', 'step_p99_error',
            'deadline_miss_warn_pct', 'deadline_miss_error_pct', 'latency_p50_warn',
            'latency_p99_warn', 'latency_p99_error', 'reply_loss_warn_pct', 'reply_loss_error_pct',
            'force_limit', 'energy_in_min', 'model_age_warn')
    return Targets(rates=rates, **{k: float(values[k]) for k in keys}).validate()


class VizNode(Node):
    """Rolling statistics, diagnostics, markers and reports for the tissue simulator."""

    def __init__(self, **kwargs) -> None:
        super().__init__('viz_node', **kwargs)
        self.p = declare_all(self, PARAMETERS, VizConfigError,
                             lambda name, value: check_instruments(value) if name == 'instruments' else None)
        # Cross-parameter checks (min <= max, warn <= error): fail at start with a clear message.
        self.targets = targets_from(self.p)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.names = [str(n) for n in self.p['instruments']]
        n = len(self.names)
        # one set of statistics per instrument; the first also counts the cloud (the node's)
        self.instrument_stats = [VizStats(window=self.p['window'], haptic_rate=self.p['haptic_rate'],
                                          latency_timeout=self.p['latency_timeout'],
                                          max_report_rows=self.p['max_report_rows']) for _ in range(n)]
        self.stats = self.instrument_stats[0]
        self.pose_frames = ['omni_base'] * n
        # each simulated tool (tissue frame) and the force on it, from its newest tissue/metrics
        self.sim_tools: list[tuple[str, ToolShape, np.ndarray] | None] = [None] * n
        # the cloud's frame and, per instrument, the positions of the particles it holds
        self.held: tuple[str, list[np.ndarray]] | None = None
        self.cut_faces: tuple[str, np.ndarray] | None = None    # the particles a cut left bonds short
        self.tissue = TissueSnapshots()
        self._report_lock = threading.Lock()
        self._report_thread: threading.Thread | None = None
        self.last_statuses: list[Status] = []
        self.errors = 0

        # Pose/force/particles best effort so the viz can never slow the loop down (a best-effort
        # reader also matches reliable writers); metrics reliable as the contract says.
        fast = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.BEST_EFFORT)
        metrics_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                 reliability=ReliabilityPolicy.RELIABLE
                                 if self.p['metrics_reliable'] else ReliabilityPolicy.BEST_EFFORT)
        cloud_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2,
                               reliability=ReliabilityPolicy.BEST_EFFORT)
        guard = self._guarded

        def of(method, k: int):
            """``method`` for instrument ``k``, guarded (and named as the method in its log)."""
            return guard(functools.update_wrapper(functools.partial(method, k=k), method))

        for k, name in enumerate(self.names):
            self.create_subscription(SimMetrics, topic_within(name, 'tissue/metrics'),
                                     of(self._on_metrics, k), metrics_qos)
            self.create_subscription(PoseStamped, topic_within(name, 'omni/pose'), of(self._on_pose, k),
                                     fast)
            self.create_subscription(WrenchStamped, topic_within(name, 'omni/force_feedback'),
                                     of(self._on_force, k), fast)
        self.create_subscription(PointCloud2, 'tissue/particles', guard(self._on_particles),
                                 cloud_qos)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.marker_pub = self.create_publisher(MarkerArray, 'viz/markers', 10)
        self.create_service(Trigger, 'viz/write_report', self._on_write_report)

        # A report is written on the way out: matplotlib is imported now, not then. Without it
        # the statistics still run, and the report's plots are placeholders naming the failure.
        try:
            figures.warm_up()
        except Exception as exc:  # noqa: BLE001 -- logged with its type; the node keeps running
            self.get_logger().warning(f'plotting unavailable ({type(exc).__name__}: {exc}): the '
                                      f'report will show placeholders')
        self.create_timer(1.0 / self.p['diagnostics_rate'], guard(self._on_diagnostics_timer))
        if self.p['summary_period'] > 0:
            self.create_timer(self.p['summary_period'], guard(self._on_summary_timer))
        if self.p['marker_rate'] > 0:
            self.create_timer(1.0 / self.p['marker_rate'], guard(self._on_marker_timer))
        self.get_logger().info(
            f'ready: window {self.p["window"]} s, haptic period {self.stats.period * 1e3:.3f} ms, '
            f'diagnostics at {self.p["diagnostics_rate"]} Hz')

    def _guarded(self, callback):
        """``callback`` that logs (throttled) instead of raising: a monitor must never take itself down.

        The wrapper has the callback's own arity (message or none), since executors may look at a
        timer callback's signature.
        """
        def failed(exc: Exception) -> None:
            self.errors += 1
            self.get_logger().error(f'{callback.__name__} failed ({self.errors} errors so far): '
                                    f'{type(exc).__name__}: {exc}', throttle_duration_sec=5.0)

        if callback.__name__.endswith('_timer'):
            def run_timer() -> None:
                try:
                    callback()
                except Exception as exc:  # noqa: BLE001 -- logged with its type, node keeps running
                    failed(exc)
            return run_timer

        def run(msg) -> None:
            try:
                callback(msg)
            except Exception as exc:  # noqa: BLE001 -- logged with its type, node keeps running
                failed(exc)
        return run

    # -- parameters -------------------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        values = dict(self.p)
        values.update({p.name: p.value for p in params if p.name in values})
        try:
            targets = targets_from(values)
        except VizConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        except (TypeError, ValueError, KeyError) as exc:
            return SetParametersResult(successful=False, reason=f'invalid value: {exc}')
        self.p, self.targets = values, targets
        for stats in self.instrument_stats:
            stats.period = 1.0 / values['haptic_rate']
        return SetParametersResult(successful=True)

    # -- callbacks: hand plain values to the statistics --------------------------------------------
    def _on_metrics(self, msg: SimMetrics, k: int = 0) -> None:
        f = msg.contact_force
        self.instrument_stats[k].on_metrics(time.monotonic(), stamp_to_ns(msg.header.stamp), msg.step_wall_time,
                              (f.x, f.y, f.z), msg.max_displacement, msg.n_interaction,
                              msg.n_layer, msg.n_relaxing, msg.substeps, msg.contact_index,
                              msg.penetration, msg.kinetic_energy, haptic_mode=msg.haptic_mode,
                              solver_rate=msg.solver_rate, model_age=msg.model_age,
                              coupling_stretch=msg.coupling_stretch, energy_in=msg.energy_in,
                              energy_in_min=msg.energy_in_min, added_damping=msg.added_damping)
        tool = ToolShape.from_metrics(msg)
        if tool is not None:
            self.sim_tools[k] = (msg.header.frame_id, tool, np.array([f.x, f.y, f.z]))

    def _on_particles(self, msg: PointCloud2) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.stats.on_particles(time.monotonic(), stamp, msg.width * msg.height)
        # the markers show the held particles, the report the clouds: else no need to unpack
        if not (self.p['tissue_images'] or self.p['marker_rate'] > 0):
            return
        frame = msg.header.frame_id
        columns = cloud_arrays([(f.name, f.offset, f.datatype) for f in msg.fields], bytes(msg.data),
                               msg.width * msg.height, msg.point_step, msg.is_bigendian)
        held, severed = columns.get('held'), columns.get('severed')
        xyz = np.column_stack([columns['x'], columns['y'], columns['z']])
        self.held = (frame, held_positions(xyz, held, len(self.names))) if held is not None and held.any() else None
        self.cut_faces = (frame, cut_faces(xyz, severed)) if severed is not None and severed.any() else None
        if not self.p['tissue_images']:
            return
        tools = tuple((t[1].tip, t[1].axis, t[1].length, t[1].radius)
                      if t is not None and t[0] == frame else None for t in self.sim_tools)
        self.tissue.add(columns, stamp, tools)

    def _on_pose(self, msg: PoseStamped, k: int = 0) -> None:
        p = msg.pose.position
        if msg.header.frame_id:
            self.pose_frames[k] = msg.header.frame_id
        self.instrument_stats[k].on_pose(time.monotonic(), stamp_to_ns(msg.header.stamp),
                                         (p.x, p.y, p.z))

    def _on_force(self, msg: WrenchStamped, k: int = 0) -> None:
        f = msg.wrench.force
        self.instrument_stats[k].on_force(time.monotonic(), stamp_to_ns(msg.header.stamp),
                                          (f.x, f.y, f.z))

    def _snapshots(self, now: float) -> dict:
        """Instrument name -> its statistics' snapshot at ``now``."""
        return {name: stats.snapshot(now) for name, stats in zip(self.names, self.instrument_stats)}

    # -- timers -----------------------------------------------------------------------------------
    def _on_diagnostics_timer(self) -> None:
        now = time.monotonic()
        snaps = self._snapshots(now)
        for stats in self.instrument_stats:
            stats.sample_rates(now)
        statuses = evaluate_instruments(snaps, self.targets, prefix=self.get_name())
        self.last_statuses = statuses
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        for s in statuses:
            array.status.append(DiagnosticStatus(
                level=_LEVEL_BYTES[s.level], name=s.name, message=s.message,
                hardware_id='sph_tissue_sim',
                values=[KeyValue(key=k, value=v) for k, v in s.values]))
        self.diag_pub.publish(array)

    def _on_summary_timer(self) -> None:
        snaps = self._snapshots(time.monotonic())
        level = worst_level(self.last_statuses) if self.last_statuses else 0
        line = summary_line(snaps[self.names[0]], snaps if len(self.names) > 1 else None)
        # rclpy binds one severity to each logging call site, so the two levels need two calls.
        if level == 0:
            self.get_logger().info(line)
        else:
            self.get_logger().warning(line)

    def _on_marker_timer(self) -> None:
        stamp = self.get_clock().now().to_msg()
        markers = MarkerArray()
        for k in range(len(self.names)):
            markers.markers += self._instrument_markers(k, stamp)
        if self.cut_faces is not None and len(self.cut_faces[1]):
            faces = Marker(type=Marker.SPHERE_LIST, action=Marker.ADD, ns='cut', id=0)
            faces.header.frame_id, faces.header.stamp = self.cut_faces[0], stamp
            faces.pose.orientation.w = 1.0
            faces.lifetime.nanosec = 500_000_000
            faces.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in self.cut_faces[1]]
            faces.scale.x = faces.scale.y = faces.scale.z = HELD_DOT
            faces.color.r, faces.color.g, faces.color.b, faces.color.a = (*CUT_COLOUR, 1.0)
            markers.markers.append(faces)
        if markers.markers:
            self.marker_pub.publish(markers)

    def _instrument_markers(self, k: int, stamp) -> list[Marker]:
        """Instrument ``k``'s tool, force arrow and label, and the particles it holds. With several
        instruments each has its namespaces (``left/tool``, ``left/force``, ``left/held``) and its
        colour (:func:`~tissue_viz.markers.instrument_colour`); one alone keeps ``tool``, ``force``
        and ``held`` and a grey tool."""
        name, several = self.names[k], len(self.names) > 1
        out: list[Marker] = []

        def marker(kind: int, ns: str, mid: int, frame_id: str) -> Marker:
            m = Marker(type=kind, action=Marker.ADD, ns=topic_within(name, ns), id=mid)
            m.header.frame_id, m.header.stamp = frame_id, stamp
            m.pose.orientation.w = 1.0
            m.lifetime.nanosec = 500_000_000
            return m

        if self.held is not None and len(self.held[1][k]):
            dots = marker(Marker.SPHERE_LIST, 'held', 4, self.held[0])
            dots.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in self.held[1][k]]
            dots.scale.x = dots.scale.y = dots.scale.z = HELD_DOT
            dots.color.r, dots.color.g, dots.color.b = instrument_colour(k)
            dots.color.a = 1.0
            out.append(dots)
        if self.p['tool_in_tissue_frame']:
            if self.sim_tools[k] is None:
                return out
            frame_id, tool, fvec = self.sim_tools[k]
        else:
            stats = self.instrument_stats[k]
            if stats.last_pose is None:
                return out
            frame_id, fvec = self.pose_frames[k], stats.last_force_vec
            tool = ToolShape(np.asarray(stats.last_pose, dtype=float), np.zeros(3), 0.0,
                             self.p['tool_radius'])

        tip = tool.tip
        d = 2.0 * tool.radius
        sphere = marker(Marker.SPHERE, 'tool', 0, frame_id)
        sphere.pose.position = Point(x=float(tip[0]), y=float(tip[1]), z=float(tip[2]))
        sphere.scale.x = sphere.scale.y = sphere.scale.z = d
        sphere.color.r, sphere.color.g, sphere.color.b = instrument_colour(k) if several else (0.8, 0.8, 0.9)
        sphere.color.a = 1.0
        out.append(sphere)
        shaft_pose = tool.shaft_pose()
        if shaft_pose is not None:
            centre, q = shaft_pose
            shaft = marker(Marker.CYLINDER, 'tool', 3, frame_id)
            shaft.pose.position = Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2]))
            o = shaft.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            shaft.scale.x = shaft.scale.y = d
            shaft.scale.z = tool.length
            shaft.color = sphere.color
            out.append(shaft)
        if fvec is not None:
            start, end = force_arrow(tip, fvec, self.p['force_arrow_scale'])
            arrow = marker(Marker.ARROW, 'force', 1, frame_id)
            arrow.points = [Point(x=float(start[0]), y=float(start[1]), z=float(start[2])),
                            Point(x=float(end[0]), y=float(end[1]), z=float(end[2]))]
            arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.3 * d, 0.6 * d, 0.8 * d
            arrow.color.r, arrow.color.g, arrow.color.b, arrow.color.a = 1.0, 0.3, 0.1, 1.0
            text = marker(Marker.TEXT_VIEW_FACING, 'force', 2, frame_id)
            text.pose.position = Point(x=float(end[0]), y=float(end[1]), z=float(end[2]) + d)
            text.scale.z = 1.5 * d
            text.color.r = text.color.g = text.color.b = text.color.a = 1.0
            label = f'{math.sqrt(sum(v * v for v in fvec)):.2f} N'
            text.text = f'{name} {label}' if several else label
            out += [arrow, text]
        return out

    # -- report -----------------------------------------------------------------------------------
    def _report_target(self) -> Path:
        return Path(self.p['report_dir']) if self.p['report_dir'] else default_report_dir()

    def report_data(self) -> ReportData:
        targets = {t: (r.min_rate, r.max_rate) for t, r in self.targets.rates.items()}
        several = dict(zip(self.names, self.instrument_stats)) if len(self.names) > 1 else None
        return ReportData.from_stats(self.stats, time.monotonic(), instruments=several,
                                     title=self.p['report_title'],
                                     rate_targets=targets,
                                     contact_threshold=self.p['contact_threshold'],
                                     tissue=self.tissue.copy() if self.p['tissue_images'] else None)

    def _on_write_report(self, request: Trigger.Request, response: Trigger.Response):
        # Plotting takes a second or two: do it off the executor so the statistics keep flowing.
        # What can be checked quickly (a report in progress, an unwritable folder) is answered now.
        if self._report_thread is not None and self._report_thread.is_alive():
            response.success, response.message = False, 'a report is already being written'
            return response
        try:
            target = prepare_report_dir(self._report_target())
            data = self.report_data()   # copied now, so the report is of this instant
        except ReportError as exc:
            response.success, response.message = False, f'report not written: {exc}'
            return response
        except Exception as exc:  # noqa: BLE001 -- a service must answer, with the reason
            response.success = False
            response.message = f'report not written: {type(exc).__name__}: {exc}'
            return response

        self._report_thread = threading.Thread(target=self._write_in_background,
                                               args=(target, data), name='report', daemon=True)
        self._report_thread.start()
        response.success = True
        response.message = f'writing report to {target} (summary.json appears last)'
        return response

    def _write_in_background(self, target: Path, data: ReportData) -> None:
        try:
            with self._report_lock:
                write_report(target, data)
            self.get_logger().info(f'report written: {target / "index.html"}')
        except Exception as exc:  # noqa: BLE001 -- logged with its type; the node keeps running
            self.get_logger().error(f'report failed: {type(exc).__name__}: {exc}')

    def shutdown_report(self) -> tuple[Path, ReportData] | None:
        """Wait for a report in progress; then the folder and the data of the shutdown report (of
        this instant), or None when ``report_on_shutdown`` is off."""
        if self._report_thread is not None:
            self._report_thread.join(timeout=30.0)
        if not self.p['report_on_shutdown']:
            return None
        return self._report_target(), self.report_data()

    def write_shutdown_report(self, target: Path, data: ReportData) -> int:
        """Write the shutdown report, in REPORT_PROCESSES processes: call it once the node is
        destroyed (no DDS thread left, see :mod:`tissue_viz.forked`).

        Returns:
            The exit code: 0, or EXIT_REPORT_FAILED when the report could not be written
            completely (what could be written is there; the failures are printed).
        """
        # a report on request still drawing after shutdown_report's wait: no fork beside its thread
        busy = self._report_thread is not None and self._report_thread.is_alive()
        try:
            with self._report_lock:
                out = write_report(target, data, processes=1 if busy else REPORT_PROCESSES)
        except Exception as exc:  # noqa: BLE001 -- said in one line; a traceback helps nobody here
            return _report_failed(exc)
        print(f'[viz_node] report written: {out / "index.html"}', flush=True)
        return EXIT_OK


def _report_failed(exc: Exception) -> int:
    reason = str(exc) if isinstance(exc, ReportError) else f'{type(exc).__name__}: {exc}'
    print(f'[viz_node] report failed: {reason}', flush=True)
    return EXIT_REPORT_FAILED


def main(args=None) -> None:
    """Run the node until Ctrl-C / SIGTERM; exit with EXIT_OK, EXIT_REPORT_FAILED or
    EXIT_BAD_PARAMETERS (an unexpected error exits 1 with its traceback, as any Python program)."""
    # Ctrl-C / SIGTERM only set a flag: a KeyboardInterrupt raised inside a callback called from the
    # EventsExecutor's C++ surfaces as a RuntimeError from spin_once, not as KeyboardInterrupt.
    if not init_rclpy(args, 'viz_node'):
        raise SystemExit(EXIT_BAD_PARAMETERS)
    stop = stop_on_signals()
    node = None
    code = EXIT_OK
    try:
        node = VizNode()
        spin_until_stopped(node, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (VizConfigError, InvalidParameterValueException) as exc:
        print(f'[viz_node] invalid parameters: {exc}', flush=True)
        code = EXIT_BAD_PARAMETERS
    finally:
        pending = None
        if node is not None:
            try:
                pending = node.shutdown_report()
            except Exception as exc:  # noqa: BLE001 -- the node still leaves the graph cleanly
                code = _report_failed(exc)
            # Out of the graph before drawing: the other nodes see it go at once, and the report
            # may fork once the DDS threads are gone.
            node.destroy_node()
        rclpy.try_shutdown()
        if pending is not None:
            code = node.write_shutdown_report(*pending) or code
    # The interpreter's last collection would walk every object the run left for nothing (a
    # quarter of a second after a long run): the process ends here.
    gc.freeze()
    if code != EXIT_OK:
        raise SystemExit(code)


if __name__ == '__main__':
    main()
