"""Replay backend: stylus poses (and buttons) from a rosbag2 MCAP bag (no rclpy).

The bag's pose messages are published as their original CDR bytes, so header stamps (and everything
else) are exactly those recorded: forces computed from a replay can be compared with golden bags.
Modes:

* ``timed``: at the recorded log-time spacing divided by ``rate`` (2.0 = twice as fast);
* ``lockstep``: each pose waits for the force reply carrying its header stamp before the next is
  sent (deterministic, independent of machine speed); on a timeout ``lockstep_timeout_action``
  decides: ``continue`` (warn, go on), ``resend`` (publish the same pose again, up to
  ``lockstep_max_resends`` times, then continue) or ``abort`` (stop with exit code 3).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tissue_common.stamps import stamp_to_ns

from ..bag_reader import bag_topics, normalise_topic, read_bag
from ..bag_types import POSE_TYPE, STATE_TYPE, typestore
from ..errors import BagError, ConfigError
from .base import Backend, BackendSink, Sample

REPLAY_MODES = ('timed', 'lockstep')
TIMEOUT_ACTIONS = ('continue', 'resend', 'abort')
#: exit code when a lockstep reply times out and the action is 'abort'
EXIT_LOCKSTEP_ABORT = 3


@dataclass
class ReplayEvent:
    """A pose (published) or a button change (reported in DeviceState), at bag log time."""

    log_ns: int
    sample: Sample | None = None
    buttons: tuple[bool, bool] | None = None


def load_replay(path: str | Path, pose_topic: str = '/omni/pose',
                state_topic: str = '/omni/state') -> list[ReplayEvent]:
    """Read a bag into replay events, validating it.

    Raises:
        BagError: missing/corrupt/empty bag, no pose topic, wrong pose type, no poses.
    """
    topics = bag_topics(path)
    by_norm = {normalise_topic(name): t for name, t in topics.items()}
    pose = by_norm.get(normalise_topic(pose_topic))
    if pose is None:
        have = ', '.join(f'{t.name} [{t.msgtype}]' for t in topics.values()) or 'none'
        raise BagError(f'bag {path} has no pose topic {pose_topic!r} (topics: {have}); '
                       f'set pose_topic_in_bag')
    if pose.msgtype != POSE_TYPE:
        raise BagError(f'bag {path}: topic {pose.name} has type {pose.msgtype}, '
                       f'expected {POSE_TYPE}')
    state = by_norm.get(normalise_topic(state_topic)) if state_topic else None
    if state is not None and state.msgtype != STATE_TYPE:
        state = None  # buttons are optional: ignore a foreign state topic
    wanted = [pose.name] + ([state.name] if state is not None else [])
    store = typestore()
    events: list[ReplayEvent] = []
    for topic, msgtype, log_ns, raw in read_bag(path, wanted, raw=True):
        try:
            msg = store.deserialize_cdr(raw, msgtype)
        except Exception as exc:  # noqa: BLE001
            raise BagError(f'bag {path}: undecodable {msgtype} message on {topic}: {exc}') from exc
        if topic == pose.name:
            p, q = msg.pose.position, msg.pose.orientation
            stamp = stamp_to_ns(msg.header.stamp)
            events.append(ReplayEvent(log_ns, Sample(stamp, np.array([p.x, p.y, p.z]),
                                                     np.array([q.x, q.y, q.z, q.w]), raw=raw)))
        else:
            events.append(ReplayEvent(log_ns, buttons=(bool(msg.button1), bool(msg.button2))))
    if not any(e.sample is not None for e in events):
        raise BagError(f'bag {path} is empty: no messages on {pose.name}')
    return events


class ReplayBackend(Backend):
    """Publishes a bag's poses in timed or lockstep mode, optionally looping."""

    name = 'replay'

    def __init__(self, path: str | Path, pose_topic: str = '/omni/pose',
                 state_topic: str = '/omni/state', mode: str = 'timed', rate: float = 1.0,
                 loop: bool = False, lockstep_timeout: float = 1.0,
                 timeout_action: str = 'continue', max_resends: int = 3) -> None:
        super().__init__()
        if mode not in REPLAY_MODES:
            raise ConfigError(f'replay_mode must be one of {REPLAY_MODES}, got {mode!r}')
        if not (np.isfinite(rate) and 0.01 <= rate <= 100.0):
            raise ConfigError(f'rate must be in [0.01, 100], got {rate}')
        if timeout_action not in TIMEOUT_ACTIONS:
            raise ConfigError(f'lockstep_timeout_action must be one of {TIMEOUT_ACTIONS}, '
                              f'got {timeout_action!r}')
        if not str(path):
            raise BagError('no bag given: set the bag parameter to a rosbag2 folder')
        self.path = Path(path)
        self.mode, self.rate, self.loop = mode, rate, loop
        self.lockstep_timeout, self.timeout_action = lockstep_timeout, timeout_action
        self.max_resends = max_resends
        self.events = load_replay(self.path, pose_topic, state_topic)
        self.n_poses = sum(1 for e in self.events if e.sample is not None)
        self.source = str(self.path)
        self.sent = 0
        self.timeouts = 0
        self.replies = 0

    def run(self, sink: BackendSink) -> None:
        if not sink.wait_for_subscribers():
            return
        t_start = time.monotonic()
        passes = 0
        code = 0
        while not self.stopping:
            code = self._play_once(sink)
            passes += 1
            if code or not self.loop:
                break
        if self.stopping:
            return  # shut down from outside: no summary, the node is going away
        wall = time.monotonic() - t_start
        extra = (f', {self.replies} replies, {self.timeouts} timeouts'
                 if self.mode == 'lockstep' else '')
        sink.on_finished(f'replay finished: {self.sent} poses in {wall:.3f} s ({passes} pass(es), '
                         f'mode {self.mode}, rate {self.rate:g}{extra}) from {self.path}', code)

    def _play_once(self, sink: BackendSink) -> int:
        t0_log = self.events[0].log_ns
        t0_wall = time.monotonic()
        buttons = None
        for event in self.events:
            if self.stopping:
                return 0
            if event.buttons is not None:
                buttons = event.buttons
                continue
            sample = event.sample
            if self.mode == 'timed':
                delay = t0_wall + (event.log_ns - t0_log) * 1e-9 / self.rate - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return 0
            sample.buttons = buttons
            sink.on_sample(sample)
            self.sent += 1
            if self.mode == 'lockstep':
                code = self._await_reply(sink, sample)
                if code:
                    return code
        return 0

    def _await_reply(self, sink: BackendSink, sample: Sample) -> int:
        resends = 0
        while not self.stopping:
            if sink.wait_for_reply(sample.stamp_ns, self.lockstep_timeout):
                self.replies += 1
                return 0
            if self.stopping:
                return 0
            self.timeouts += 1
            stamp = f'{sample.stamp_ns // 1_000_000_000}.{sample.stamp_ns % 1_000_000_000:09d}'
            if self.timeout_action == 'abort':
                sink.log('error', f'lockstep: no force reply to pose {stamp} within '
                                  f'{self.lockstep_timeout} s: aborting replay')
                return EXIT_LOCKSTEP_ABORT
            if self.timeout_action == 'resend' and resends < self.max_resends:
                resends += 1
                sink.log('warn', f'lockstep: no force reply to pose {stamp} within '
                                 f'{self.lockstep_timeout} s: resending ({resends}/{self.max_resends})')
                sink.on_sample(sample)
                continue
            sink.log('warn', f'lockstep: no force reply to pose {stamp} within '
                             f'{self.lockstep_timeout} s: continuing')
            return 0
        return 0
