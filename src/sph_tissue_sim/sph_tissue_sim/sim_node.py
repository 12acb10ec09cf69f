"""sim_node: the SPH soft-tissue simulation in the ROS 2 graph.

Subscribes ``omni/pose`` (geometry_msgs/PoseStamped, stylus tip in the device frame), maps the tip
into the tissue frame, advances the tissue by the time since the previous pose (sub-stepped by the
core) and answers every step with ``omni/force_feedback`` (geometry_msgs/WrenchStamped: the reaction
of the tissue on the tool in the device frame, clamped to ``force_limit``; header stamp and frame
are the pose's, so the round trip can be measured). Publishes ``tissue/particles``
(sensor_msgs/PointCloud2, see :mod:`.cloud`) at ``particles_rate`` and ``tissue/metrics``
(tissue_msgs/SimMetrics) per step; serves ``tissue/reset`` (tissue_msgs/srv/ResetTissue).

Haptic modes (parameter ``haptic_mode``):

- ``multirate`` (default): each pose is answered at once by the haptic renderer
  (:mod:`.haptics`: velocity filter, virtual coupling to the simulated tool, passivity control)
  from a local contact model; the solver steps at the coupling's proxy and refreshes that model.
  Live: the subscription callback answers every pose (best effort, history depth at least 10, so
  a short stall of the executor delays poses instead of dropping them) and a solver thread steps as
  fast as it can. Lockstep:
  the solver steps after every ``solver_every``-th pose in the pose's thread, so replays stay
  bit-identical.
- ``direct``: one solver step per pose; its reaction is the force (the timing modes below).

Timing modes (parameter ``timing_mode``):

- ``live``: (direct) only the newest pose is stepped; poses that arrive during a step are dropped, so there
  is never a backlog. By default (``step_thread: true``) the callback only stores the newest pose
  in an inbox and a stepping thread steps (drops are counted), so the executor thread is always
  free for services: a reset or parameter change interrupts a long step (the frame kernels release
  the GIL) instead of waiting behind it. With ``step_thread: false`` the callback steps and the
  pose reader's history (best effort, depth ``qos_depth`` = 1) keeps only the newest pose.
- ``lockstep``: every pose is processed in order with ``dt`` from its stamp (reliable QoS, depth
  >= 1000; with ``step_thread`` a FIFO inbox), so replaying the same poses gives bit-identical forces.

Bad input never stops the node and never sends an unsafe force: a pose that is non-finite, too far
from the device origin or in a foreign frame is answered with a zero force (the device gets a
defined, safe command and a lockstep replay its reply) and does not advance the tissue; a repeated
stamp is answered with the previous force; a stamp going backwards steps with ``nominal_dt``; a
gap longer than ``max_dt`` is clamped to it; an unstable step answers zero and resets the tissue.

Exit codes: 0 normal (Ctrl-C), 1 the model cannot be built (missing mesh, ...), 2 invalid parameters.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import sys
import threading
import time
import traceback

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, TransformStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from tissue_common.force import clamp_norm
from tissue_common.frames import TfBroadcaster, Transform
from tissue_common.node_start import (EXIT_PARAMS, build_node, init_rclpy, spin_until_stopped,
                                      stop_on_signals)
from tissue_common.params import declare_all
from tissue_common.stamps import stamp_to_ns
from tissue_common.throttle import EventThrottle
from tissue_msgs.msg import SimMetrics
from tissue_msgs.srv import ResetTissue

from . import blas_kernels
from .cloud import CloudBuffer
from .core.compliance import close_all
from .core.errors import ConfigError, ModelError, SimError
from .core.solver import InvalidInput, Solver, SolverConfig, StepInterrupted, StepResult, warmup
from .mapping import DeviceMapping, anchor_point, check_position
from .haptics.multirate import MultiRate, SolverJob
from .haptics.renderer import HapticRenderer
from .params import (NEXT_STEP_SETTINGS, SIM_PARAMS, build_config, build_material, build_model,
                     build_renderer, check_value, solves_in_background)
from .timing import BACKWARDS, JUMP, REPEAT, StampClock

EXIT_OK, EXIT_INPUT = 0, 1
REEXEC_ENV = 'SPH_SIM_NODE_REEXEC'
LOCKSTEP_MIN_DEPTH = 1000
MULTIRATE_MIN_DEPTH = 10  # [poses] 10 ms at 1 kHz: a stall of the executor thread, not a backlog
STEP_TIME_HISTORY = 100_000
SWITCH_INTERVAL = 2e-4  # [s]
#: [s] how long the shutdown waits for a stepping thread to leave its interrupted step
SHUTDOWN_JOIN = 5.0
TOOL_LAG_LOG = 1e-3  # [m] a lag behind the device worth telling the operator about


def make_solver(model, material, config: SolverConfig, nominal_dt: float, background: bool = False) -> Solver:
    """A solver whose scheme can actually step (a probe step without tool, then back to rest).
    ``background``: the organ's far field solves its responses on a worker thread.

    Raises:
        ConfigError: invalid settings, or a scheme this build cannot run yet.
    """
    solver = Solver(model, material, config, background=background)
    solver.step(None, nominal_dt)
    solver.reset()
    return solver


def one_blas_thread() -> None:
    """Let the BLAS libraries (numpy's and scipy's OpenBLAS) use one thread each.

    Their extra threads spin while they wait for work: beside the organ's sparse solves (a
    response per touched particle) they took the core the other threads need (a 0.24 ms numba loop
    beside repeated solves: p99 4.3 ms, with one BLAS thread 0.29 ms), and the solves gain
    nothing from them (49 ms either way on the 3670 liver).
    """
    import scipy.sparse.linalg  # noqa: F401  (loads scipy's own OpenBLAS, so the limit reaches it)
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api='blas')


def numba_cache_stats() -> tuple[int, int]:
    """(kernels compiled in this process, kernels loaded from numba's disk cache) of the core."""
    from numba.core.registry import CPUDispatcher

    compiled = loaded = 0
    for name, mod in list(sys.modules.items()):
        if mod is None or not name.startswith('sph_tissue_sim.core'):
            continue
        for obj in vars(mod).values():
            if isinstance(obj, CPUDispatcher):
                compiled += sum(obj.stats.cache_misses.values())
                loaded += sum(obj.stats.cache_hits.values())
    return compiled, loaded


class Reexec(Exception):
    """Start the process again (its kernels were compiled here, see SimNode.__init__)."""


class SimNode(Node):
    """omni/pose -> tissue step -> omni/force_feedback, plus particles, metrics and reset."""

    def __init__(self, **kwargs) -> None:
        super().__init__('sim_node', **kwargs)
        self.p = declare_all(self, SIM_PARAMS, ConfigError, check_value)
        p = self.p
        log = self.get_logger()
        self._log_throttle = EventThrottle()
        self.counts = collections.Counter()

        self.model = build_model(p)
        self.material = build_material(p)
        config = build_config(p)
        t0 = time.perf_counter()
        if p['warmup']:
            log.info('numba warm-up: the SPH kernels load from numba\'s cache, or compile (about 30 s '
                     'on 2 cores) at the first start after a change of the core')
            try:
                warmup(config.scheme, config.contact_integration, config.integrator)
            except SimError as exc:  # the probe step below still compiles what this model needs
                log.warn(f'numba warm-up on the test block failed ({exc}); continuing')
        self.solver = make_solver(self.model, self.material, config, p['nominal_dt'],
                                  background=solves_in_background(p))
        self._cloud = CloudBuffer(self.solver.n_particles, p['tissue_frame'])
        self._pack_cloud()  # compiles (or loads) its kernel now, not at the first cloud
        self.compile_time = time.perf_counter() - t0
        self.kernels_compiled, self.kernels_loaded = numba_cache_stats()
        if (self.kernels_compiled and p['timing_mode'] == 'lockstep'
                and not os.environ.get(REEXEC_ENV)):
            # A kernel compiled in this process and the same kernel loaded from numba's cache can
            # differ in the last bits (measured: 4e-15 N); every later start loads from the cache,
            # so run cached code now too, or the first replay after a core change is not identical.
            log.warning(f'{self.kernels_compiled} numba kernels were compiled in this process: '
                        f'restarting once to run them from the cache (bit-identical lockstep)')
            raise Reexec()
        self.mapping = self._make_mapping(p, self.solver)
        self.clock = StampClock(p['nominal_dt'], p['max_dt'])
        self.lockstep = p['timing_mode'] == 'lockstep'
        self.use_thread = p['step_thread']
        # multirate: the renderer answers each pose; the solver refreshes its contact model after
        # every solver_every-th pose (lockstep, in order) or from its own thread (live)
        self.haptic: MultiRate | None = None
        if p['haptic_mode'] == 'multirate':
            self.haptic = MultiRate(HapticRenderer(build_renderer(p)),
                                    p['solver_every'] if self.lockstep else 0, p['max_dt'])
        self._pose_lock = threading.Lock()       # the stamp clock and the last answer (multirate)
        self._wake = threading.Event()           # a pose came: the live solver thread has a job

        self._lock = threading.Lock()            # the solver and its state
        self._retired: list[Solver] = []         # replaced solvers whose far field is still solving
        self._cv = threading.Condition()         # the pose inbox
        self._inbox: collections.deque = collections.deque()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._solver_thread: threading.Thread | None = None
        self._last_force_dev = np.zeros(3)
        self._last_stamp = None
        self._step_count = 0
        self._cloud_lock = threading.Lock()      # one cloud packed and published at a time
        self._wrench_msg = WrenchStamped()
        self._wall = np.zeros(STEP_TIME_HISTORY)   # ring of step wall times [s] for the totals
        self._metrics_msg = SimMetrics()
        self._cloud_due = False                  # a cloud was due while a step held the solver

        if self.lockstep:
            io_qos = QoSProfile(depth=max(p['qos_depth'], LOCKSTEP_MIN_DEPTH),
                                history=HistoryPolicy.KEEP_LAST,
                                reliability=ReliabilityPolicy.RELIABLE)
        else:
            depth = p['qos_depth']
            if self.haptic is not None:
                # answering costs microseconds: a short history carries the poses over a stall of
                # the executor thread (a cloud, a service, the GIL) instead of dropping them, and the
                # renderer's velocity filter and energy observer see every sample
                depth = max(depth, MULTIRATE_MIN_DEPTH)
            elif not self.use_thread and depth != 1:
                # the callback steps every pose the reader holds: a deeper history is a backlog
                log.warning(f'live mode stepping in the callback: pose history depth {depth} -> 1 '
                            f'(never a backlog); use step_thread for a deeper transport queue')
                depth = 1
            io_qos = QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                                reliability=ReliabilityPolicy.RELIABLE if p['reliable']
                                else ReliabilityPolicy.BEST_EFFORT)
        self.io_qos = io_qos
        self.force_pub = self.create_publisher(WrenchStamped, 'omni/force_feedback', io_qos)
        self.metrics_pub = self.create_publisher(
            SimMetrics, 'tissue/metrics',
            QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.RELIABLE))
        self.cloud_pub = self.create_publisher(
            PointCloud2, 'tissue/particles',
            QoSProfile(depth=2, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.RELIABLE))
        # where the device sits in the tissue scene: latched, and on /tf_static where tf2 is installed
        self.frame_pub = self.create_publisher(
            TransformStamped, 'tissue/device_frame',
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.tf_static = TfBroadcaster(self, static=True)
        if self.mapping.scale != 1.0:
            self.get_logger().warn(
                f'workspace_scale {self.mapping.scale:g}: the {p["device_frame"]} frame on '
                f'tissue/device_frame and /tf_static has the map\'s rotation and origin only (a '
                f'transform cannot scale), so a stylus drawn through it sits at its unscaled offset')
        self._publish_device_frame()
        self.reset_srv = self.create_service(ResetTissue, 'tissue/reset', self._on_reset)
        self.cloud_timer = None
        self._set_cloud_timer(p['particles_rate'])
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.pose_sub = self.create_subscription(PoseStamped, 'omni/pose', self._on_pose, io_qos)

    # -- set-up helpers ----------------------------------------------------------------------------
    @staticmethod
    def _make_mapping(p: dict, solver: Solver) -> DeviceMapping:
        anchor = anchor_point(solver.model.positions, solver.model.spacing, solver.contact_reach,
                              p['anchor'])
        return DeviceMapping.build(p['rotation'], p['translation'], p['workspace_scale'],
                                   p['force_scale'], anchor)

    def _publish_device_frame(self) -> None:
        m = self.mapping
        frame = Transform.from_matrix(self.p['tissue_frame'], self.p['device_frame'], m.rotation,
                                      m.origin).to_msg(self.get_clock().now().to_msg())
        self.frame_pub.publish(frame)
        self.tf_static.send([frame])

    def _set_cloud_timer(self, rate: float) -> None:
        if self.cloud_timer is not None:
            self.destroy_timer(self.cloud_timer)
            self.cloud_timer = None
        if rate > 0.0:
            self.cloud_timer = self.create_timer(1.0 / rate, self._publish_cloud)

    def describe(self) -> str:
        s, m, c = self.solver, self.solver.material, self.solver.config
        o = self.mapping.origin
        return (f'model {self.model.name} ({s.n_particles} particles, {int(s.fixed.sum())} fixed, '
                f'spacing {self.model.spacing * 1e3:.2f} mm, h {s.smoothing_length * 1e3:.2f} mm), '
                f'tool {s.tool.name} (radius {s.tool.radius * 1e3:g} mm), '
                f'scheme {c.scheme}, mode {c.mode}, {self._describe_contact()}, '
                f'material {m.name} '
                f'(E {m.E:.4g} Pa, nu {m.nu:g}, '
                f'eta_shear {m.eta_shear:g} Pa s), timing {self.p["timing_mode"]}, pose QoS '
                f'{"reliable" if self.io_qos.reliability == ReliabilityPolicy.RELIABLE else "best effort"}'
                f' depth {self.io_qos.depth}, haptic {self._describe_haptic()}, force_limit '
                f'{self.p["force_limit"]:g} N, device origin '
                f'-> tissue ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) m')

    def _describe_contact(self) -> str:
        s = self.solver
        c = s.config
        what = (f'contact {c.contact_samples}x{c.contact_samples} samples per surface particle '
                f'(backstop), {c.contact_integration}' if c.contact_samples else
                f'contact particle balls, {c.contact_integration}')
        ff = s.far_field_in_use
        if ff == 'organ':
            how = (f'{len(s.organ.disk)} responses on disk, '
                   + ('the factor of the solver before' if s.organ.reused else 'factored when first needed'))
            return f'{what}, far field organ x{c.far_field:g} ({how})'
        if ff == 'half_space':
            return f'{what}, far field half_space x{c.far_field:g}'
        return what

    def _describe_haptic(self) -> str:
        if self.haptic is None:
            return 'direct (one solver step per pose)'
        c = self.haptic.renderer.config
        when = (f'every {self.haptic.every} poses' if self.haptic.every
                else f'on its own thread, nice +{self.p["solver_nice"]}')
        return (f'multirate (solver {when}; coupling {c.coupling_stiffness:g} N/m, '
                f'{c.coupling_damping:g} N s/m, velocity filter {c.velocity_cutoff:g} Hz)')

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the stepping thread (if configured) and report ready."""
        if self.use_thread and not (self.haptic is not None and not self.lockstep):
            self._worker = threading.Thread(target=self._work, name='sim_step', daemon=True)
            self._worker.start()
        if self.haptic is not None and not self.lockstep:
            self._solver_thread = threading.Thread(target=self._solve_loop, name='sim_solver',
                                                   daemon=True)
            self._solver_thread.start()
        self.get_logger().info(f'numba warm-up (compile or cache load) and first step: '
                               f'{self.compile_time:.2f} s ({self.kernels_compiled} kernels '
                               f'compiled, {self.kernels_loaded} loaded from the cache)')
        if self.kernels_compiled and self.lockstep:
            self.get_logger().warning('kernels compiled in this process (numba cache not writable?): '
                                      'forces may differ in the last bits from a run on cached '
                                      'kernels')
        kernels = sorted({arch for _, arch in blas_kernels.loaded()})
        self.get_logger().info(f'OpenBLAS kernels: {", ".join(kernels)}')
        if self.lockstep and kernels != [blas_kernels.CORETYPE]:
            self.get_logger().warning(
                f'OpenBLAS kernels {", ".join(kernels)}, not {blas_kernels.CORETYPE} (OPENBLAS_CORETYPE '
                f'set, numpy loaded before sph_tissue_sim, or a host without AVX2/FMA): forces may '
                f'differ in the last bits from the goldens')
        self.get_logger().info('ready: ' + self.describe())

    def shutdown(self) -> None:
        """Stop the stepping threads and log the totals; False if one of them is still inside a
        step after ``SHUTDOWN_JOIN`` seconds (the caller must then not let the interpreter
        finalise under it)."""
        self._stop.set()
        # a long step (a first deep touch solving the organ's responses on a busy machine) stops
        # at its next sub-step or response solve instead of outliving the interpreter
        self.solver.interrupt()
        with self._cv:
            self._cv.notify_all()
        self._wake.set()
        stopped = True
        for thread in (self._worker, self._solver_thread):
            if thread is not None:
                thread.join(SHUTDOWN_JOIN)
                stopped = stopped and not thread.is_alive()
        # the far field's worker, after the stepping threads (they may still ask it for a response)
        for solver in (*self._retired, self.solver):
            stopped = solver.close(SHUTDOWN_JOIN) and stopped
        c = self.counts
        # not the node logger: after Ctrl-C the context is shut down and rosout would fail
        rclpy.logging.get_logger(self.get_name() + '.shutdown').info(
            f'totals: {c["poses"]} poses, {c["steps"]} steps, {c["dropped"]} dropped (newer pose '
            f'arrived first), {c["rejected"]} rejected, {c["sim_errors"]} unstable steps, '
            f'{c["overflow"]} lockstep overflows, {c["interrupted"]} steps interrupted (by a reset, a '
            f'parameter change or the shutdown)')
        if c['steps']:
            w = self._wall[:min(c['steps'], STEP_TIME_HISTORY)] * 1e3
            rclpy.logging.get_logger(self.get_name() + '.shutdown').info(
                f'step wall time median {np.median(w):.4f} ms, p99 {np.percentile(w, 99):.4f} ms '
                f'(last {len(w)} steps)')
        if not stopped:
            rclpy.logging.get_logger(self.get_name() + '.shutdown').warning(
                f'a stepping thread, or the far field\'s worker, is still inside a step or a '
                f'solve after {SHUTDOWN_JOIN:g} s: exiting without waiting for it')
        return stopped

    # -- logging -----------------------------------------------------------------------------------
    def _throttled(self, kind: str, level: str, text: str) -> None:
        """At most one line per kind of event and ``log_throttle`` seconds (a flood must not flood
        the log); the count of such events so far is appended."""
        n = self._log_throttle.event(kind, time.monotonic(), self.p['log_throttle'])
        if n is None:
            return
        text = f'{text} ({n} so far)'
        # one call site per severity: rclpy refuses a call site whose severity changes
        log = self.get_logger()
        if level == 'error':
            log.error(text)
        elif level == 'warn':
            log.warning(text)
        else:
            log.info(text)

    # -- pose intake -------------------------------------------------------------------------------
    def _on_pose(self, msg: PoseStamped) -> None:
        if not self.use_thread or (self.haptic is not None and not self.lockstep):
            # multirate live: answering costs microseconds, so answer here; the solver has its thread
            # stepping here: poses that arrive meanwhile wait in the reader history, which keeps
            # only the newest qos_depth of them in live mode (DDS drops the rest, never a backlog)
            self.counts['poses'] += 1
            self._handle(msg)
            return
        with self._cv:
            self.counts['poses'] += 1
            if self.lockstep:
                if len(self._inbox) >= self.p['lockstep_queue_limit']:
                    self._inbox.popleft()
                    self.counts['overflow'] += 1
                    self._throttled('overflow', 'error',
                                    f'lockstep queue full ({self.p["lockstep_queue_limit"]} poses): '
                                    f'dropped the oldest')
            elif self._inbox:
                self.counts['dropped'] += len(self._inbox)
                self._inbox.clear()
            self._inbox.append(msg)
            self._cv.notify()

    def _work(self) -> None:
        while not self._stop.is_set():
            with self._cv:
                while not self._inbox and not self._stop.is_set():
                    self._cv.wait(0.1)
                if self._stop.is_set():
                    return
                msg = self._inbox.popleft()
            self._handle(msg)

    def _handle(self, msg: PoseStamped) -> None:
        try:
            self._process(msg)
        except Exception:  # noqa: BLE001  (a bug must not kill the loop or leave the device pushing)
            self._throttled('internal', 'error', 'internal error while stepping, answered zero '
                            'force:\n' + traceback.format_exc())
            self._publish_force(msg.header, np.zeros(3))

    # -- one frame ---------------------------------------------------------------------------------
    def _reject_reason(self, msg: PoseStamped) -> str | None:
        frame = msg.header.frame_id
        if frame != self.p['device_frame'] and not (frame == '' and self.p['accept_empty_frame']):
            return f'frame {frame!r} is not {self.p["device_frame"]!r}'
        pos = msg.pose.position
        return check_position((pos.x, pos.y, pos.z), self.p['max_device_distance'])

    def _process(self, msg: PoseStamped) -> None:
        header = msg.header
        reason = self._reject_reason(msg)
        if reason is not None:
            self._reject(header, f'rejected pose ({reason}): answered zero force, tissue not stepped')
            return
        stamp_ns = stamp_to_ns(header.stamp)
        if self.haptic is not None:
            self._answer(msg, stamp_ns)
            return
        with self._lock:
            pose = self._tool_pose(msg, stamp_ns)
            if pose is None:
                return
            res = self._step(*pose)
            force_dev = np.zeros(3) if res is None else self._to_device(res.force_raw)
            self._last_force_dev = force_dev
            self._last_stamp = header.stamp
            metrics = self._metrics(header.stamp, res, self.solver) if res is not None else None
        self._publish_force(header, force_dev)
        if metrics is not None:
            self.metrics_pub.publish(metrics)
        if self._cloud_due:
            self._publish_cloud_once()

    def _answer(self, msg: PoseStamped, stamp_ns: int) -> None:
        """Multirate: answer the pose from the renderer at once; the solver follows (lockstep: here,
        every solver_every poses; live: its thread is woken)."""
        header = msg.header
        with self._pose_lock:
            pose = self._tool_pose(msg, stamp_ns)
            if pose is None:
                return
            out = self.haptic.answer(*pose, header.stamp)
            force_dev = self._to_device(out.force)
            self._last_force_dev = force_dev
        self._publish_force(header, force_dev)
        if not self.lockstep:
            self._wake.set()
        elif self.haptic.due():
            self._solve()
            if self._cloud_due:
                self._publish_cloud_once()

    def _solve_loop(self) -> None:
        """Multirate live: step the solver at the newest proxy whenever a pose has come."""
        self._lower_priority(self.p['solver_nice'])
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self._solve()
                if self._cloud_due:
                    self._publish_cloud_once()
            except Exception:  # noqa: BLE001  (the poses are answered by the renderer meanwhile)
                self._throttled('internal', 'error', 'internal error in the solver thread:\n'
                                + traceback.format_exc())

    def _lower_priority(self, nice: int) -> None:
        """Make the calling thread ``nice`` steps nicer (Linux schedules threads one by one)."""
        if nice <= 0:
            return
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice, 19))
        except (OSError, AttributeError) as exc:  # not Linux, or refused: run at the same priority
            self.get_logger().warning(f'solver thread priority unchanged ({exc})')

    def _solve(self) -> None:
        job: SolverJob | None = self.haptic.take()
        if job is None:
            return
        with self._lock:
            if not self.haptic.current(job):
                return   # taken before a reset (or a rebuilt solver) while this thread waited for the lock
            res = self._step(job.point, job.dt, job.rotation)
            if res is not None:
                self.haptic.refresh(job, res)
                self._last_stamp = job.stamp
            metrics = self._metrics(job.stamp, res, self.solver) if res is not None else None
        if metrics is not None:
            self.metrics_pub.publish(metrics)

    def _reject(self, header, text: str) -> None:
        """Answer zero force for a pose that must not move the tool."""
        self.counts['rejected'] += 1
        self._throttled('reject', 'warn', text)
        if self.haptic is not None:
            self.haptic.zero_held()
        self._publish_force(header, np.zeros(3))

    def _tool_pose(self, msg: PoseStamped, stamp_ns: int) -> tuple | None:
        """(tool position, dt, rotation) in the tissue frame for a pose, or None when the pose was
        answered already (a repeated stamp, or a refused orientation)."""
        dt = self._advance(msg.header, stamp_ns)
        if dt is None:
            return None
        try:
            rot = self._rotation(msg)
        except InvalidInput as exc:
            self._reject(msg.header, f'refused the input ({exc}): answered zero force')
            return None
        pos = msg.pose.position
        return self.mapping.to_tissue((pos.x, pos.y, pos.z)), dt, rot

    def _advance(self, header, stamp_ns: int) -> float | None:
        """The pose's step [s] from its stamp, or None after answering a repeated stamp with the
        previous force."""
        dt, kind = self.clock.advance(stamp_ns)
        if kind == REPEAT:
            self._publish_force(header, self._last_force_dev)
            return None
        if kind == BACKWARDS:
            self._throttled('backwards', 'warn', f'pose stamp went backwards (to {stamp_ns} ns): '
                            f'stepping {self.clock.nominal_dt * 1e3:g} ms')
        elif kind == JUMP:
            self._throttled('jump', 'warn', f'pose stamp jumped by more than max_dt: step '
                            f'clamped to {self.clock.max_dt * 1e3:g} ms')
        return dt

    def _rotation(self, msg: PoseStamped) -> np.ndarray | None:
        """The stylus orientation in the tissue frame, for a tool that has one (else None)."""
        if not self.solver.tool.oriented:
            return None
        q = msg.pose.orientation
        try:
            return self.mapping.rotation_to_tissue((q.x, q.y, q.z, q.w))
        except ValueError as exc:
            raise InvalidInput(f'stylus orientation: {exc}') from exc

    def _to_device(self, force_tissue: np.ndarray) -> np.ndarray:
        # clamped once, as sent (force_scale may enlarge the tissue's force)
        return clamp_norm(self.mapping.force_to_device(force_tissue), self.p['force_limit'])[0]

    def _step(self, tool: np.ndarray, dt: float, rot) -> StepResult | None:
        """One solver step (caller holds the solver lock); None when it was refused or failed."""
        solver = self.solver
        try:
            res = solver.step(tool, dt, rot)
        except InvalidInput as exc:
            self.counts['rejected'] += 1
            self._throttled('invalid', 'warn', f'step refused the input ({exc}): answered zero '
                            f'force')
            return None
        except ConfigError as exc:
            self._throttled('config', 'error', f'step impossible ({exc}): answered zero force')
            return None
        except StepInterrupted:
            self.counts['interrupted'] += 1  # a reset, parameter change or shutdown took the solver
            return None
        except SimError as exc:
            self.counts['sim_errors'] += 1
            self._rest()
            self._throttled('unstable', 'error', f'{exc}: answered zero force and reset the '
                            f'tissue to rest')
            return None
        self._wall[self.counts['steps'] % STEP_TIME_HISTORY] = res.wall_time
        self.counts['steps'] += 1
        if res.tool_lag > TOOL_LAG_LOG:
            self._throttled('tool_lag', 'warn', f'the device moved faster than max_tool_speed '
                            f'({solver.config.max_tool_speed:g} m/s): the simulated tool '
                            f'follows {res.tool_lag * 1e3:.1f} mm behind')
        if res.substeps_capped:
            self._throttled('capped', 'warn', f'frame needed more than max_substeps '
                            f'({solver.config.max_substeps}): simulated time lags')
        return res

    def _rest(self) -> None:
        """The tissue back to rest and the device's past forgotten (caller holds the solver lock)."""
        self.solver.reset()
        with self._pose_lock:
            self.clock.reset()
            self._last_force_dev = np.zeros(3)
            if self.haptic is not None:
                self.haptic.reset()

    def _publish_force(self, header, force: np.ndarray) -> None:
        msg = self._wrench_msg  # reused: building a message costs more than the step of a small area
        msg.header.stamp = header.stamp
        msg.header.frame_id = header.frame_id or self.p['device_frame']
        f = msg.wrench.force
        f.x, f.y, f.z = (float(v) for v in force)
        self.force_pub.publish(msg)

    def _metrics(self, stamp, res: StepResult, solver: Solver) -> SimMetrics | None:
        self._step_count += 1
        if self._step_count % self.p['metrics_decimation']:
            return None
        m = self._metrics_msg
        m.header.stamp = stamp
        m.header.frame_id = self.p['tissue_frame']
        m.step_wall_time = float(res.wall_time)
        m.sim_time = float(solver.sim_time)
        m.substeps = int(res.substeps)
        m.substep_dt = float(res.substep_dt)
        m.n_particles = int(solver.n_particles)
        m.n_interaction = int(res.n_interaction)
        m.n_layer = [int(v) for v in res.n_layer]
        m.n_relaxing = int(res.n_relaxing)
        m.contact_index = int(res.contact_index)
        m.penetration = float(res.penetration)
        m.contact_force.x, m.contact_force.y, m.contact_force.z = (float(v) for v in res.force)
        if res.tool_segment is not None:
            tip, shaft = res.tool_segment[0], res.tool_segment[1] - res.tool_segment[0]
            length = float(np.linalg.norm(shaft))
            axis = shaft / length if length > 0.0 else shaft
            m.tool_position.x, m.tool_position.y, m.tool_position.z = (float(v) for v in tip)
            m.tool_axis.x, m.tool_axis.y, m.tool_axis.z = (float(v) for v in axis)
            m.tool_length = length
        m.tool_radius = float(solver.tool.radius)
        m.max_displacement = float(res.max_displacement)
        m.kinetic_energy = float(res.kinetic_energy)
        m.scheme = solver.config.scheme_index
        m.mode = solver.config.mode_index
        if self.haptic is None:
            m.haptic_mode = SimMetrics.HAPTIC_DIRECT
        else:
            h = self.haptic.status()
            m.haptic_mode = SimMetrics.HAPTIC_MULTIRATE
            m.solver_rate, m.model_age, m.coupling_stretch = h.solver_rate, h.model_age, h.stretch
            m.energy_in, m.energy_in_min, m.added_damping = h.energy, h.energy_min, h.damping
        return m

    # -- particles -------------------------------------------------------------------------------
    def _publish_cloud(self) -> None:
        """The cloud timer (executor thread)."""
        if self._solver_thread is not None:
            # multirate live: the solver thread packs it between two steps; this thread is for poses
            self._cloud_due = True
            self._wake.set()
            return
        self._publish_cloud_once()

    def _pack_cloud(self):
        s = self.solver
        self._cloud.pack(s.positions, s.X, s.von_mises(), s.region)

    def _publish_cloud_once(self) -> None:
        # never wait for a step here: the timer runs on the executor thread, which must stay free
        # for poses and services; the stepping thread publishes the cloud after its step instead
        if not self._cloud_lock.acquire(blocking=False):
            return  # one is being published this very moment
        try:
            if not self._lock.acquire(blocking=False):
                self._cloud_due = True
                return
            try:
                self._cloud_due = False
                self._pack_cloud()
                stamp = self._last_stamp
            finally:
                self._lock.release()
            if stamp is None:
                # lockstep time is the poses' stamps (a bag's, often long past): before the first
                # pose it has none yet, and a wall-clock stamp would make the replay's go backwards
                stamp = Time() if self.lockstep else self.get_clock().now().to_msg()
            self.cloud_pub.publish(self._cloud.message(stamp))
        except Exception:  # noqa: BLE001  (the picture is optional; the force loop must go on)
            self._throttled('cloud', 'error', 'tissue/particles not published:\n'
                            + traceback.format_exc())
        finally:
            self._cloud_lock.release()

    @contextlib.contextmanager
    def _solver_now(self):
        """The solver, at once: a step in progress stops before its next sub-step (its pose is
        answered with zero force), so a service never waits for a long step."""
        solver = self.solver
        solver.interrupt()
        with self._lock:
            try:
                yield
            finally:
                solver.clear_interrupt()  # before the lock is free: the next step runs

    # -- reset -----------------------------------------------------------------------------------
    def _on_reset(self, request: ResetTissue.Request, response: ResetTissue.Response):
        try:
            material = None if request.keep_material else build_material(self.p)
        except ConfigError as exc:
            response.success = False
            response.message = f'reset refused: the configured material cannot be loaded: {exc}'
            self.get_logger().error(response.message)
            return response
        with self._solver_now():
            response.sim_time = float(self.solver.sim_time)
            if material is not None:
                try:
                    self.solver.set_material(material)
                except SimError as exc:
                    response.success = False
                    response.message = f'reset refused: {exc}'
                    return response
            self._rest()
            response.n_particles = int(self.solver.n_particles)
        self.counts['resets'] += 1
        response.success = True
        response.message = (f'tissue reset to rest at sim time {response.sim_time:.4f} s; material '
                             f'{self.solver.material.name}'
                             + (' (kept)' if request.keep_material else ' (reloaded)'))
        self.get_logger().info(response.message)
        return response

    # -- run-time parameters -----------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        new = dict(self.p)
        for param in params:
            if param.name not in SIM_PARAMS:
                continue
            err = check_value(param.name, param.value)
            if err:
                return SetParametersResult(successful=False, reason=err)
            new[param.name] = param.value
        changed = {n for n in new if new[n] != self.p[n]}
        if not changed:
            return SetParametersResult(successful=True)
        kinds = {SIM_PARAMS[n][4] for n in changed}
        try:
            config = build_config(new)
            material = build_material(new) if 'material' in kinds else None
            renderer = build_renderer(new) if self.haptic is not None else None
            solver = None
            if 'solver' in kinds:
                solver = make_solver(self.model, material or self.solver.material, config,
                                     new['nominal_dt'], background=solves_in_background(new))
            mapping = None
            if 'mapping' in kinds or solver is not None:
                mapping = self._make_mapping(new, solver or self.solver)
            elif {'force_scale'} & changed:
                mapping = DeviceMapping(self.mapping.rotation, self.mapping.origin,
                                        self.mapping.scale, float(new['force_scale']))
        except SimError as exc:  # ConfigError, ModelError, or the probe step of a new solver failed
            reason = f'refused: {exc}'
            self.get_logger().warn(f'parameter change {sorted(changed)} {reason}')
            return SetParametersResult(successful=False, reason=reason)
        with self._solver_now():
            if solver is not None:
                self._retired = [s for s in (*self._retired, self.solver) if not s.close()]
                self.solver = solver
                self._rest()
            elif material is not None:
                self.solver.set_material(material)
            # the next-step settings, validated with the rest by build_config
            self.solver.config = dataclasses.replace(
                self.solver.config, **{n: getattr(config, n) for n in NEXT_STEP_SETTINGS})
            if mapping is not None:
                self.mapping = mapping
            self.clock.nominal_dt = float(new['nominal_dt'])
            self.clock.max_dt = float(new['max_dt'])
            if renderer is not None:
                with self._pose_lock:
                    if 'renderer' in kinds:   # new gains: the device's past no longer applies
                        self.haptic.reset()
                        self.haptic.renderer = HapticRenderer(renderer)
                    self.haptic.renderer.set_force_limit(renderer.force_limit)
                    self.haptic.max_dt = float(new['max_dt'])
                    if self.lockstep:
                        self.haptic.every = int(new['solver_every'])
            self.p = new
        if 'particles_rate' in changed:
            self._set_cloud_timer(new['particles_rate'])
        if mapping is not None or solver is not None or 'device_frame' in changed:
            self._publish_device_frame()      # the latched transform follows the map
        what = ('solver rebuilt, tissue at rest' if solver is not None else
                'material swapped' if material is not None else 'applied')
        self.get_logger().info(f'parameters {sorted(changed)} changed: {what}; now '
                               + self.describe())
        return SetParametersResult(successful=True)


def main(args=None) -> int:
    """Entry point of ``sim_node``; returns the exit code."""
    if not init_rclpy(args, 'sim_node'):
        return EXIT_PARAMS
    node = None
    code = EXIT_OK
    reexec = False
    stopped = True
    # before the organ's factorisation too: its bits must not depend on the host's core count
    one_blas_thread()
    try:
        try:
            node, refused = build_node(SimNode, 'sim_node', {
                ConfigError: ('invalid parameters', EXIT_PARAMS),
                ModelError: ('cannot build the tissue', EXIT_INPUT),
                SimError: ('cannot build the tissue', EXIT_INPUT)})
        except Reexec:
            reexec = True
            return EXIT_OK
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
        if reexec:
            sys.stdout.flush()
            sys.stderr.flush()
            os.environ[REEXEC_ENV] = '1'
            os.execv(sys.executable, [sys.executable, *sys.argv])
    return code


if __name__ == '__main__':
    sys.exit(main())
