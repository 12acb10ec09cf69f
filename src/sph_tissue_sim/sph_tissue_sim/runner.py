"""sim_node's run loop without ROS: poses in, forces, metrics and clouds out.

:class:`Runner` owns what happens between a pose and its answer: the stamp clock, the checks that
refuse a pose, the haptic renderer and its hand-off to the solver (:mod:`.haptics.multirate`), the
pose inbox and the stepping threads, the interrupt that lets a reset or a parameter change take the
solver at once, and the run-time parameter changes. It speaks to the outside through four
callables (``send_force``, ``send_metrics``, ``send_cloud``, ``log``), so :mod:`.sim_node` only
translates messages and parameters, and the loop is tested without ROS.

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
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import dataclasses
import os
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from tissue_common.force import clamp_norm
from tissue_common.throttle import EventThrottle

from .channel import Channel
from .cloud import CloudBuffer
from .core.errors import ConfigError, SimError
from .core.solver import InvalidInput, Solver, SolverConfig, StepInterrupted, StepResult, check_material
from .haptics.multirate import MultiRate, SolverJob
from .haptics.renderer import HapticRenderer
from .mapping import DeviceMapping, anchor_point, check_position
from .params import (NEXT_STEP_SETTINGS, SIM_PARAMS, build_config, build_material, build_renderer,
                     check_value, instrument_tools, instrument_translations, solves_in_background)
from .timing import BACKWARDS, JUMP, REPEAT, StampClock

STEP_TIME_HISTORY = 100_000
#: [s] how long the shutdown waits for a stepping thread to leave its interrupted step
SHUTDOWN_JOIN = 5.0
TOOL_LAG_LOG = 1e-3  # [m] a lag behind the device worth telling the operator about
LOCKSTEP_MIN_DEPTH = 1000
MULTIRATE_MIN_DEPTH = 10  # [poses] 10 ms at 1 kHz: a stall of the executor thread, not a backlog


@dataclass(frozen=True)
class Pose:
    """One device sample as the node read it: ``stamp`` is echoed in the answer as it came."""

    stamp: Any
    stamp_ns: int
    frame_id: str
    position: tuple
    orientation: tuple


@dataclass
class Change:
    """What a parameter change did: refused (``reason``), or applied with a summary."""

    successful: bool
    reason: str = ''
    changed: frozenset = frozenset()
    remapped: bool = False      # the device map (or the frame) changed: republish it
    what: str = 'applied'


def make_solver(model, material, config: SolverConfig, nominal_dt: float, background: bool = False,
                instruments: int = 1, tools=None) -> Solver:
    """A solver whose scheme can actually step (a probe step without tool, then back to rest).
    ``background``: the organ's far field solves its responses on a worker thread; ``tools``: each
    instrument's tool (``Solver``'s, None: the config's).

    Raises:
        ConfigError: invalid settings, or a scheme this build cannot run yet.
    """
    solver = Solver(model, material, config, background=background, instruments=instruments, tools=tools)
    solver.step_tools([None] * instruments, nominal_dt)
    solver.reset()
    return solver


def make_mapping(p: dict, solver: Solver, k: int = 0) -> DeviceMapping:
    """Instrument ``k``'s device -> tissue map of the parameters, anchored on ``solver``'s model."""
    anchor = anchor_point(solver.model.positions, solver.model.spacing, solver.contact_reach, p['anchor'])
    return DeviceMapping.build(p['rotation'], instrument_translations(p)[k], p['workspace_scale'],
                               p['force_scale'], anchor)


def pose_history(p: dict, runner: 'Runner') -> tuple[int, bool, str]:
    """The pose reader's (history depth, reliable, a warning or ''): lockstep keeps every pose;
    live keeps a short history when answering is cheap (multirate) and none when the callback
    steps each pose the reader holds (a deeper history would be a backlog)."""
    if runner.lockstep:
        return max(p['qos_depth'], LOCKSTEP_MIN_DEPTH), True, ''
    depth, note = p['qos_depth'], ''
    if runner.haptic is not None:
        # a short history carries the poses over a stall of the executor thread (a cloud, a
        # service, the GIL) instead of dropping them, and the renderer sees every sample
        depth = max(depth, MULTIRATE_MIN_DEPTH)
    elif not runner.use_thread and depth != 1:
        note = (f'live mode stepping in the callback: pose history depth {depth} -> 1 (never a backlog); '
                f'use step_thread for a deeper transport queue')
        depth = 1
    return depth, bool(p['reliable']), note


def metrics_values(res: StepResult, solver: Solver, haptic, k: int = 0) -> dict:
    """SimMetrics' fields of a step for instrument ``k`` (vectors as (x, y, z) tuples) but the haptic
    mode; ``haptic``: its renderer's :class:`~.haptics.multirate.HapticStatus`, or None (direct)."""
    tool = res.tools[k]
    v = {'step_wall_time': float(res.wall_time), 'sim_time': float(solver.sim_time),
         'substeps': int(res.substeps), 'substep_dt': float(res.substep_dt),
         'n_particles': int(solver.n_particles), 'n_interaction': int(res.n_interaction),
         'n_layer': [int(n) for n in res.n_layer], 'n_relaxing': int(res.n_relaxing),
         'contact_index': int(tool.contact_index), 'penetration': float(tool.penetration),
         'contact_force': tuple(float(f) for f in tool.force),
         'tool_radius': float(solver.instruments[k].tool.radius),
         'max_displacement': float(res.max_displacement), 'kinetic_energy': float(res.kinetic_energy),
         'scheme': solver.config.scheme_index, 'mode': solver.config.mode_index}
    v.update(tool_position=(0.0, 0.0, 0.0), tool_axis=(0.0, 0.0, 0.0), tool_length=0.0,
             n_grasped=int(tool.grasped),      # a lifted tool's (the message is reused)
             n_bonds_cut=int(tool.bonds_cut), crack_area=float(solver.crack_area(k)),
             cut_length=float(solver.cut_length(k)), needle_state=int(solver.needle_state(k)),
             needle_depth=float(solver.needle_depth(k)))
    if tool.tool_segment is not None:
        tip, shaft = tool.tool_segment[0], tool.tool_segment[1] - tool.tool_segment[0]
        length = float(np.linalg.norm(shaft))
        axis = shaft / length if length > 0.0 else shaft
        v.update(tool_position=tuple(float(x) for x in tip), tool_axis=tuple(float(x) for x in axis),
                 tool_length=length)
    if haptic is not None:
        v.update(solver_rate=haptic.solver_rate, model_age=haptic.model_age, coupling_stretch=haptic.stretch,
                 energy_in=haptic.energy, energy_in_min=haptic.energy_min, added_damping=haptic.damping)
    return v


def _nothing(*_args) -> None:
    return None


class Runner:
    """The loop of one tissue: ``on_pose`` for every pose (of instrument ``k``), ``cloud_tick`` at the
    cloud's rate, ``on_grasp`` when a jaw closes or opens.

    Several instruments (parameter ``instruments``, multirate only): each pose is answered at once
    by its instrument's renderer (:class:`~.channel.Channel`) and the solver steps all the tools
    together: live from its thread at each one's newest proxy (an instrument without a new pose
    stays where it was); lockstep in rounds, one pose of each instrument in the instruments' order,
    in the thread that delivered the round's last pose, so a replay repeats bit for bit.
    ``send_force(stamp, frame_id, force, k)`` and ``send_metrics(stamp, result, solver, haptic, k)``
    name the instrument ``k``.
    """

    def __init__(self, p: dict, model, solver: Solver, send_force: Callable = _nothing,
                 send_metrics: Callable = _nothing, send_cloud: Callable = _nothing,
                 log: Callable[[str, str], None] = _nothing) -> None:
        self.p = p
        self.model = model
        self.solver = solver
        self.send_force, self.send_metrics, self.send_cloud, self.log = send_force, send_metrics, send_cloud, log
        self.lockstep = p['timing_mode'] == 'lockstep'
        names = list(p['instruments'])
        if len(names) != solver.n_instruments:
            raise ConfigError(f'{len(names)} instruments but a solver for {solver.n_instruments}')
        # several instruments step in rounds (lockstep) or from the solver thread (live)
        self.use_thread = p['step_thread'] and len(names) == 1
        # multirate: the renderer answers each pose; the solver refreshes its contact model after
        # every solver_every-th pose (lockstep, in order) or from its own thread (live)
        self.channels = [Channel(k, name, make_mapping(p, solver, k), StampClock(p['nominal_dt'], p['max_dt']),
                                 self._make_haptic(p)) for k, name in enumerate(names)]
        self.counts = collections.Counter()
        self._log_throttle = EventThrottle()
        self._pose_lock = threading.Lock()       # the stamp clock and the last answer (multirate)
        self._wake = threading.Event()           # a pose came: the live solver thread has a job
        self._lock = threading.Lock()            # the solver and its state
        self._retired: list[Solver] = []         # replaced solvers whose far field is still solving
        self._cv = threading.Condition()         # the pose inbox
        self._inbox: collections.deque = collections.deque()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._solver_thread: threading.Thread | None = None
        self.last_stamp = None                   # the stamp of the newest step (the cloud's)
        self._rounds = 0                         # lockstep rounds of several instruments
        self._stepped_ns: int | None = None      # several instruments: the newest pose stamp stepped
        self._step_count = 0
        self._cloud_lock = threading.Lock()      # one cloud packed and sent at a time
        self._wall = np.zeros(STEP_TIME_HISTORY)   # ring of step wall times [s] for the totals
        self._cloud_due = False                  # a cloud was due while a step held the solver
        self.cloud = CloudBuffer(solver.n_particles, p['tissue_frame'])
        self._pack_cloud()  # compiles (or loads) its kernel now, not at the first cloud

    def _make_haptic(self, p: dict) -> MultiRate | None:
        if p['haptic_mode'] != 'multirate':
            return None
        return MultiRate(HapticRenderer(build_renderer(p)), p['solver_every'] if self.lockstep else 0, p['max_dt'])

    @property
    def haptic(self) -> MultiRate | None:
        """The first instrument's renderer hand-off (None: direct)."""
        return self.channels[0].haptic

    @property
    def mapping(self) -> DeviceMapping:
        """The first instrument's device map."""
        return self.channels[0].mapping

    @property
    def clock(self) -> StampClock:
        return self.channels[0].clock

    @property
    def live_multirate(self) -> bool:
        return self.haptic is not None and not self.lockstep

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the stepping thread of the mode (if any)."""
        if self.use_thread and not self.live_multirate:
            self._worker = threading.Thread(target=self._work, name='sim_step', daemon=True)
            self._worker.start()
        if self.live_multirate:
            self._solver_thread = threading.Thread(target=self._solve_loop, name='sim_solver', daemon=True)
            self._solver_thread.start()

    def shutdown(self) -> bool:
        """Stop the stepping threads; False if one of them (or a far field's worker) is still inside
        a step after ``SHUTDOWN_JOIN`` seconds (the caller must then not let the interpreter
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
        return stopped

    def totals(self) -> list[str]:
        """The run's counts and step times, one line each."""
        c = self.counts
        lines = [f'totals: {c["poses"]} poses, {c["steps"]} steps, {c["dropped"]} dropped (newer pose '
                 f'arrived first), {c["rejected"]} rejected, {c["sim_errors"]} unstable steps, '
                 f'{c["overflow"]} lockstep overflows, {c["interrupted"]} steps interrupted (by a reset, a '
                 f'parameter change or the shutdown)']
        if c['steps']:
            w = self._wall[:min(c['steps'], STEP_TIME_HISTORY)] * 1e3
            lines.append(f'step wall time median {np.median(w):.4f} ms, p99 {np.percentile(w, 99):.4f} ms '
                         f'(last {len(w)} steps)')
        return lines

    def throttled(self, kind: str, level: str, text: str) -> None:
        """At most one line per kind of event and ``log_throttle`` seconds (a flood must not flood
        the log); the count of such events so far is appended."""
        n = self._log_throttle.event(kind, time.monotonic(), self.p['log_throttle'])
        if n is not None:
            self.log(level, f'{text} ({n} so far)')

    # -- pose intake -------------------------------------------------------------------------------
    def on_pose(self, pose: Pose, k: int = 0) -> None:
        """A pose of instrument ``k`` (its index in ``instruments``)."""
        if not 0 <= k < len(self.channels):
            self.throttled('instrument', 'error', f'a pose for instrument {k}, which is not configured: ignored')
            return
        if len(self.channels) > 1:
            self._on_instrument_pose(pose, self.channels[k])
            return
        if not self.use_thread or self.live_multirate:
            # multirate live: answering costs microseconds, so answer here; the solver has its thread
            # stepping here: poses that arrive meanwhile wait in the reader history, which keeps
            # only the newest qos_depth of them in live mode (DDS drops the rest, never a backlog)
            self.counts['poses'] += 1
            self.handle(pose)
            return
        with self._cv:
            self.counts['poses'] += 1
            if self.lockstep:
                self._make_room(self._inbox, 'lockstep queue full')
            elif self._inbox:
                self.counts['dropped'] += len(self._inbox)
                self._inbox.clear()
            self._inbox.append(pose)
            self._cv.notify()

    def _make_room(self, inbox: collections.deque, why: str) -> None:
        """Drop ``inbox``'s oldest pose when it holds ``lockstep_queue_limit`` (caller holds ``_cv``)."""
        if len(inbox) >= self.p['lockstep_queue_limit']:
            inbox.popleft()
            self.counts['overflow'] += 1
            self.throttled('overflow', 'error', f'{why} ({self.p["lockstep_queue_limit"]} poses): dropped the oldest')

    def _on_instrument_pose(self, pose: Pose, ch: Channel) -> None:
        """Several instruments: live, answer at once (the solver thread follows); lockstep, wait for
        a round (one pose of each instrument) and answer it in the instruments' order."""
        self.counts['poses'] += 1
        if not self.lockstep:
            self.handle(pose, ch)
            return
        reason = self._frame_reason(pose, ch)
        if reason is not None:
            # not this device's pose (a probe in a foreign frame): answered now, outside the rounds and
            # without touching the renderer, so the device's own poses still pair as sent
            self.counts['rejected'] += 1
            self.throttled('reject', 'warn', f'rejected pose ({reason}): answered zero force, tissue not stepped')
            self._answer_with(pose, np.zeros(3), ch)
            return
        with self._cv:
            self._make_room(ch.inbox, f'lockstep: {ch.label} is that far ahead of the others')
            ch.inbox.append(pose)
            while all(c.inbox for c in self.channels):
                for c in self.channels:
                    self.handle(c.inbox.popleft(), c)
                # rounds, not one renderer's poses: a rejected pose must not stop everyone's steps
                self._rounds += 1
                if self._rounds % self.p['solver_every'] == 0:
                    try:
                        self._solve()
                        if self._cloud_due:
                            self.send_cloud_once()
                    except Exception:  # noqa: BLE001  (the poses were answered; the loop must go on)
                        self.throttled('internal', 'error', 'internal error in a lockstep step:\n'
                                       + traceback.format_exc())

    def _work(self) -> None:
        while not self._stop.is_set():
            with self._cv:
                while not self._inbox and not self._stop.is_set():
                    self._cv.wait(0.1)
                if self._stop.is_set():
                    return
                pose = self._inbox.popleft()
            self.handle(pose)

    def handle(self, pose: Pose, ch: Channel | None = None) -> None:
        """Answer one pose of ``ch`` (default: the first instrument), and step as the mode says;
        never raises."""
        ch = ch or self.channels[0]
        try:
            self._process(pose, ch)
        except Exception:  # noqa: BLE001  (a bug must not kill the loop or leave the device pushing)
            self.throttled('internal', 'error', 'internal error while stepping, answered zero '
                           'force:\n' + traceback.format_exc())
            self._answer_with(pose, np.zeros(3), ch)

    # -- one frame ---------------------------------------------------------------------------------
    def _answer_with(self, pose: Pose, force: np.ndarray, ch: Channel) -> None:
        self.send_force(pose.stamp, pose.frame_id or self.p['device_frame'], force, ch.index)

    def _frame_reason(self, pose: Pose, ch: Channel) -> str | None:
        """Why ``pose`` is not in ``ch``'s device frame (None: it is)."""
        frame, shared = pose.frame_id, self.p['device_frame']
        # a named instrument's device may name its frame as the others do or in its namespace
        if frame not in (shared, ch.device_frame(shared)) and not (frame == '' and self.p['accept_empty_frame']):
            return f'frame {frame!r} is not {ch.device_frame(shared)!r}'
        return None

    def _reject_reason(self, pose: Pose, ch: Channel) -> str | None:
        return self._frame_reason(pose, ch) or check_position(pose.position, self.p['max_device_distance'])

    def _process(self, pose: Pose, ch: Channel) -> None:
        if ch.grasps:
            self._grasps_before(ch, pose.stamp_ns)
        reason = self._reject_reason(pose, ch)
        if reason is not None:
            self._reject(pose, f'rejected pose ({reason}): answered zero force, tissue not stepped', ch)
            return
        if ch.haptic is not None:
            self._answer(pose, ch)
            return
        with self._lock:
            tool = self._tool_pose(pose, ch)
            if tool is None:
                return
            point, dt, rot = tool
            self._grasp_as_asked()
            res = self._step([(point, rot)], dt)
            force_dev = np.zeros(3) if res is None else self._to_device(res.force_raw, ch)
            ch.last_force = force_dev
            self.last_stamp = pose.stamp
            metrics = self._metrics_due(res)
        self._answer_with(pose, force_dev, ch)
        if metrics:
            self.send_metrics(pose.stamp, res, self.solver, None, 0)
        if self._cloud_due:
            self.send_cloud_once()

    def _answer(self, pose: Pose, ch: Channel) -> None:
        """Multirate: answer the pose from the renderer at once; the solver follows (lockstep: here,
        every solver_every poses, or after the round of several instruments; live: its thread is
        woken)."""
        with self._pose_lock:
            tool = self._tool_pose(pose, ch)
            if tool is None:
                return
            out = ch.haptic.answer(*tool, pose.stamp)
            force_dev = self._to_device(out.force, ch)
            ch.last_force = force_dev
            ch.newest_ns = pose.stamp_ns
        self._answer_with(pose, force_dev, ch)
        if not self.lockstep:
            self._wake.set()
        elif len(self.channels) == 1 and ch.haptic.due():
            self._solve()
            if self._cloud_due:
                self.send_cloud_once()

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
                    self.send_cloud_once()
            except Exception:  # noqa: BLE001  (the poses are answered by the renderer meanwhile)
                self.throttled('internal', 'error', 'internal error in the solver thread:\n' + traceback.format_exc())

    def _lower_priority(self, nice: int) -> None:
        """Make the calling thread ``nice`` steps nicer (Linux schedules threads one by one)."""
        if nice <= 0:
            return
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice, 19))
        except (OSError, AttributeError) as exc:  # not Linux, or refused: run at the same priority
            self.log('warn', f'solver thread priority unchanged ({exc})')

    def _solve(self) -> None:
        """Step the solver with every instrument at its renderer's proxy (an instrument without a new
        pose where it was, one that never sent a pose lifted) and refresh the renderers that asked."""
        jobs: list[SolverJob | None] = [ch.haptic.take() for ch in self.channels]
        if not any(jobs):
            return
        with self._lock:
            if not all(ch.haptic.current(job) for ch, job in zip(self.channels, jobs) if job is not None):
                return   # taken before a reset (or a rebuilt solver) while this thread waited for the lock
            for ch, job in zip(self.channels, jobs):
                if job is not None:
                    ch.tool = (job.point, job.rotation)
            newest, dt = self._step_time(jobs)
            self._grasp_as_asked()
            res = self._step([ch.tool for ch in self.channels], dt)
            if res is not None:
                for ch, job, tool in zip(self.channels, jobs, res.tools):
                    if job is not None:
                        ch.haptic.refresh(job, tool)
                self.last_stamp = newest.stamp
            metrics = self._metrics_due(res)
        if metrics:
            for ch, job in zip(self.channels, jobs):
                self.send_metrics(job.stamp if job is not None else newest.stamp, res, self.solver,
                                  ch.haptic.status(), ch.index)

    def _step_time(self, jobs: list) -> tuple[SolverJob, float]:
        """The newest of ``jobs`` and the pose time [s] the step simulates: one instrument, the time
        its renderer served; several, the time from the newest pose stepped to the newest pose now
        (one clock: each instrument's own time since its last job would count the time between
        two devices' poses twice)."""
        if len(self.channels) == 1:
            return jobs[0], jobs[0].dt
        taken = [(ch.newest_ns, job) for ch, job in zip(self.channels, jobs) if job is not None]
        newest_ns, newest = max(taken, key=lambda pair: pair[0])
        last = self._stepped_ns
        self._stepped_ns = newest_ns if last is None else max(last, newest_ns)
        dt = max(job.dt for _, job in taken) if last is None else (newest_ns - last) * 1e-9
        if not dt > 0.0:   # no pose newer than the last step (a stamp went backwards): one nominal step
            dt = self.channels[0].clock.nominal_dt
        return newest, min(dt, self.channels[0].clock.max_dt)

    # -- grasp ---------------------------------------------------------------------------------------
    def on_grasp(self, k: int, closed: bool, stamp_ns: int | None = None) -> None:
        """Instrument ``k``'s jaw closes (``closed``) or opens at ``stamp_ns``: live, applied before the
        next solver step; lockstep, from the first pose stamped after it on (the driver sends a
        button or jaw change before the pose it came with, so a replay grasps at the same pose every
        time)."""
        if not 0 <= k < len(self.channels):
            self.throttled('instrument', 'error', f'a grasp for instrument {k}, which is not configured: ignored')
            return
        ch = self.channels[k]
        if self.lockstep and stamp_ns is not None:
            self._queue_grasp(ch, int(stamp_ns), bool(closed))
            return
        if ch.closed != bool(closed):
            ch.closed = bool(closed)
            self._wake.set()

    @staticmethod
    def _queue_grasp(ch: Channel, stamp_ns: int, closed: bool) -> None:
        """Keep ``ch.grasps`` in stamp order with only the changes: a state that repeats the jaw's
        (the driver's periodic one: a DeviceState stamped by the wall clock, a jaw/measured_js by its
        sample) changes nothing and is dropped, so a change is applied at its stamp whichever arrived
        first."""
        with ch.grasp_lock:
            q = ch.grasps
            i = bisect.bisect_right([stamp for stamp, _ in q], stamp_ns)
            before = q[i - 1][1] if i else ch.closed
            if closed == before:
                return
            q.insert(i, (stamp_ns, closed))
            if i + 1 < len(q) and q[i + 1][1] == closed:
                del q[i + 1]

    @staticmethod
    def _grasps_before(ch: Channel, stamp_ns: int) -> None:
        """Lockstep: the jaw as the changes stamped before ``stamp_ns`` left it."""
        with ch.grasp_lock:
            while ch.grasps and ch.grasps[0][0] < stamp_ns:
                ch.closed = ch.grasps.pop(0)[1]

    def _grasp_as_asked(self) -> None:
        """Close or open each instrument as its device asks (caller holds the solver lock). A jaw
        that closed on nothing, or whose grasp slipped away, holds nothing until it opens again."""
        for ch in self.channels:
            if ch.closed and not ch.gripping:
                ch.gripping = True
                n = self.solver.grasp(ch.index)
                self.counts['grasps'] += 1
                if n:
                    self.log('info', f'{ch.label} grasped {n} particles')
                else:
                    self.throttled('grasp_nothing', 'warn', f'{ch.label} closed on nothing: no particle '
                                   f'within {self.solver.grasp_reach(ch.index) * 1e3:.1f} mm of its tool')
            elif not ch.closed and ch.gripping:
                ch.gripping = False
                n = self.solver.release(ch.index)
                self.log('info', f'{ch.label} opened' + (f' and let go of {n} particles' if n else ''))

    def _metrics_due(self, res: StepResult | None) -> bool:
        if res is None:
            return False
        self._step_count += 1
        return self._step_count % self.p['metrics_decimation'] == 0

    def _reject(self, pose: Pose, text: str, ch: Channel) -> None:
        """Answer zero force for a pose that must not move the tool."""
        self.counts['rejected'] += 1
        self.throttled('reject', 'warn', text)
        if ch.haptic is not None:
            ch.haptic.zero_held()
        self._answer_with(pose, np.zeros(3), ch)

    def _tool_pose(self, pose: Pose, ch: Channel) -> tuple | None:
        """(tool position, dt, rotation) in the tissue frame for a pose, or None when the pose was
        answered already (a repeated stamp, or a refused orientation)."""
        dt = self._advance(pose, ch)
        if dt is None:
            return None
        try:
            rot = self._rotation(pose, ch)
        except InvalidInput as exc:
            self._reject(pose, f'refused the input ({exc}): answered zero force', ch)
            return None
        return ch.mapping.to_tissue(pose.position), dt, rot

    def _advance(self, pose: Pose, ch: Channel) -> float | None:
        """The pose's step [s] from its stamp, or None after answering a repeated stamp with the
        previous force."""
        dt, kind = ch.clock.advance(pose.stamp_ns)
        if kind == REPEAT:
            self._answer_with(pose, ch.last_force, ch)
            return None
        if kind == BACKWARDS:
            self.throttled('backwards', 'warn', f'pose stamp went backwards (to {pose.stamp_ns} ns): '
                           f'stepping {ch.clock.nominal_dt * 1e3:g} ms')
        elif kind == JUMP:
            self.throttled('jump', 'warn', f'pose stamp jumped by more than max_dt: step '
                           f'clamped to {ch.clock.max_dt * 1e3:g} ms')
        return dt

    def _rotation(self, pose: Pose, ch: Channel) -> np.ndarray | None:
        """The stylus orientation in the tissue frame, for a tool that has one (else None)."""
        if not self.solver.instruments[ch.index].tool.oriented:
            return None
        try:
            return ch.mapping.rotation_to_tissue(pose.orientation)
        except ValueError as exc:
            raise InvalidInput(f'stylus orientation: {exc}') from exc

    def _to_device(self, force_tissue: np.ndarray, ch: Channel) -> np.ndarray:
        # clamped once, as sent (force_scale may enlarge the tissue's force)
        return clamp_norm(ch.mapping.force_to_device(force_tissue), self.p['force_limit'])[0]

    def _step(self, poses: list, dt: float) -> StepResult | None:
        """One solver step with each instrument at its ``(point, rotation)`` or lifted (None); the
        caller holds the solver lock. None when it was refused or failed."""
        solver = self.solver
        try:
            res = solver.step_tools(poses, dt)
        except InvalidInput as exc:
            self.counts['rejected'] += 1
            self.throttled('invalid', 'warn', f'step refused the input ({exc}): answered zero force')
            return None
        except ConfigError as exc:
            self.throttled('config', 'error', f'step impossible ({exc}): answered zero force')
            return None
        except StepInterrupted:
            self.counts['interrupted'] += 1  # a reset, parameter change or shutdown took the solver
            return None
        except SimError as exc:
            self.counts['sim_errors'] += 1
            self._rest()
            self.throttled('unstable', 'error', f'{exc}: answered zero force and reset the tissue to rest')
            return None
        self._wall[self.counts['steps'] % STEP_TIME_HISTORY] = res.wall_time
        self.counts['steps'] += 1
        lag = max(tool.tool_lag for tool in res.tools)
        if lag > TOOL_LAG_LOG:
            self.throttled('tool_lag', 'warn', f'the device moved faster than max_tool_speed '
                           f'({solver.config.max_tool_speed:g} m/s): the simulated tool '
                           f'follows {lag * 1e3:.1f} mm behind')
        if res.substeps_capped:
            self.throttled('capped', 'warn', f'frame needed more than max_substeps '
                           f'({solver.config.max_substeps}): simulated time lags')
        return res

    def _rest(self) -> None:
        """The tissue back to rest and the devices' past forgotten (caller holds the solver lock);
        what was held is let go (a closed jaw grasps again at the next step)."""
        self.solver.reset()
        self._stepped_ns = None
        self._rounds = 0
        with self._pose_lock:
            for ch in self.channels:
                ch.clock.reset()
                ch.last_force = np.zeros(3)
                ch.tool = None
                ch.gripping = False
                ch.newest_ns = None
                if ch.haptic is not None:
                    ch.haptic.reset()

    # -- particles -------------------------------------------------------------------------------
    def cloud_tick(self) -> None:
        """The cloud is due (the node's timer): sent now, or by the stepping thread after its step."""
        if self._solver_thread is not None:
            # multirate live: the solver thread packs it between two steps; this thread is for poses
            self._cloud_due = True
            self._wake.set()
            return
        self.send_cloud_once()

    def _pack_cloud(self) -> None:
        s = self.solver
        # each instrument's held particles (grasped and not slipped, or along a needle) become the
        # cloud's held byte
        self.cloud.pack(s.positions, s.X, s.von_mises(), s.region,
                        [s.held_particles(k) for k in range(s.n_instruments)], s.severed, s.removed)

    def send_cloud_once(self) -> None:
        # never wait for a step here: the timer runs on the executor thread, which must stay free
        # for poses and services; the stepping thread sends the cloud after its step instead
        if not self._cloud_lock.acquire(blocking=False):
            return  # one is being sent this very moment
        try:
            if not self._lock.acquire(blocking=False):
                self._cloud_due = True
                return
            try:
                self._cloud_due = False
                self._pack_cloud()
                stamp = self.last_stamp
            finally:
                self._lock.release()
            self.send_cloud(stamp)
        except Exception:  # noqa: BLE001  (the picture is optional; the force loop must go on)
            self.throttled('cloud', 'error', 'tissue/particles not published:\n' + traceback.format_exc())
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
    def reset(self, keep_material: bool) -> tuple[bool, str, float, int]:
        """The tissue back to rest, with the configured material reloaded unless ``keep_material``:
        (success, message, sim time before, particles)."""
        try:
            material = None if keep_material else build_material(self.p)
        except ConfigError as exc:
            return False, f'reset refused: the configured material cannot be loaded: {exc}', 0.0, 0
        with self._solver_now():
            sim_time = float(self.solver.sim_time)
            if material is not None:
                try:
                    self.solver.set_material(material)
                except SimError as exc:
                    return False, f'reset refused: {exc}', sim_time, 0
            self._rest()
        self.counts['resets'] += 1
        return True, (f'tissue reset to rest at sim time {sim_time:.4f} s; material {self.solver.material.name}'
                      + (' (kept)' if keep_material else ' (reloaded)')), sim_time, int(self.solver.n_particles)

    # -- run-time parameters -----------------------------------------------------------------------
    def apply(self, values: dict) -> Change:
        """Run-time parameter changes (name -> value; names that are not sim_node's are ignored),
        validated as at start-up and applied between two steps, or refused whole."""
        new = dict(self.p)
        for name, value in values.items():
            if name not in SIM_PARAMS:
                continue
            err = check_value(name, value)
            if err:
                return Change(False, err)
            new[name] = value
        changed = frozenset(n for n in new if new[n] != self.p[n])
        if not changed:
            return Change(True)
        kinds = {SIM_PARAMS[n][4] for n in changed}
        try:
            config = build_config(new)
            material = build_material(new) if 'material' in kinds else None
            renderer = build_renderer(new) if self.haptic is not None else None
            solver = None
            if 'solver' in kinds:
                solver = make_solver(self.model, material or self.solver.material, config, new['nominal_dt'],
                                     background=solves_in_background(new), instruments=len(self.channels),
                                     tools=instrument_tools(new))
            elif material is not None:
                check_material(self.solver.config, material)
            mappings = None
            if 'mapping' in kinds or solver is not None:
                mappings = [make_mapping(new, solver or self.solver, ch.index) for ch in self.channels]
            elif 'force_scale' in changed:
                mappings = [DeviceMapping(ch.mapping.rotation, ch.mapping.origin, ch.mapping.scale,
                                          float(new['force_scale'])) for ch in self.channels]
        except SimError as exc:  # ConfigError, ModelError, or the probe step of a new solver failed
            return Change(False, f'refused: {exc}', changed)
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
            for ch in self.channels:
                if mappings is not None:
                    ch.mapping = mappings[ch.index]
                ch.clock.nominal_dt = float(new['nominal_dt'])
                ch.clock.max_dt = float(new['max_dt'])
                if renderer is not None:
                    with self._pose_lock:
                        if 'renderer' in kinds:   # new gains: the device's past no longer applies
                            ch.haptic.reset()
                            ch.haptic.renderer = HapticRenderer(renderer)
                        ch.haptic.renderer.set_force_limit(renderer.force_limit)
                        ch.haptic.max_dt = float(new['max_dt'])
                        if self.lockstep:
                            ch.haptic.every = int(new['solver_every'])
            self.p = new
        what = ('solver rebuilt, tissue at rest' if solver is not None else
                'material swapped' if material is not None else 'applied')
        return Change(True, '', changed, mappings is not None or solver is not None or 'device_frame' in changed,
                      what)

    # -- words -----------------------------------------------------------------------------------
    def describe(self) -> str:
        """The tissue, the solver, the contact and the rendering in one line."""
        s, m, c = self.solver, self.solver.material, self.solver.config
        return (f'model {self.model.name} ({s.n_particles} particles, {int(s.fixed.sum())} fixed, '
                f'spacing {self.model.spacing * 1e3:.2f} mm, h {s.smoothing_length * 1e3:.2f} mm), '
                f'tool {s.tool.name} (radius {s.tool.radius * 1e3:g} mm), scheme {c.scheme}, mode {c.mode}, '
                f'{self._describe_contact()}, material {m.name} (E {m.E:.4g} Pa, nu {m.nu:g}, eta_shear '
                f'{m.eta_shear:g} Pa s), timing {self.p["timing_mode"]}, haptic {self._describe_haptic()}, '
                f'force_limit {self.p["force_limit"]:g} N, ' + self._describe_origins())

    def _describe_origins(self) -> str:
        def at(ch: Channel) -> str:
            o = ch.mapping.origin
            return f'({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) m'
        if len(self.channels) == 1:
            return f'device origin -> tissue {at(self.channels[0])}'
        return 'instruments ' + ', '.join(f'{ch.name} (device origin -> tissue {at(ch)})' for ch in self.channels)

    def _describe_contact(self) -> str:
        s = self.solver
        c = s.config
        what = (f'contact {c.contact_samples}x{c.contact_samples} samples per surface particle (backstop)'
                if c.contact_samples else 'contact particle balls')
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
