"""omni_record: record omni/pose, omni/force_feedback and omni/state into a rosbag2 MCAP bag.

Messages are recorded as the CDR bytes received (raw subscriptions), with their receive time as log
time, the offered QoS of the publishers and the RIHS01 type hashes, as ``ros2 bag record`` does;
the replay backend plays them back byte-identically. The bag is finalised on Ctrl-C (SIGINT) or
SIGTERM, at ``duration`` or after ``max_messages``. It is written in chunks flushed and fsynced
every ``flush_period``, so a crash (SIGKILL, power loss) loses at most about that much;
``omni_bag_recover`` makes such an unfinished bag complete.

    ros2 run haptic_omni_driver omni_record --ros-args -p output:=session1

Exit codes: 0 normal, 1 the bag cannot be created or written (exists, read-only, not a directory,
disk full), 2 invalid parameters (out of range, unknown topic). A refused start creates nothing.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tissue_common.node_start import EXIT_PARAMS, init_rclpy, stop_on_signals
from tissue_common.params import declare_all

from .bag_types import POSE_TYPE, STATE_TYPE, WRENCH_TYPE, typestore
from .bag_writer import BagWriter, qos_profile
from .errors import ConfigError, DriverError
from .params import RECORDER_PARAMS

EXIT_OK, EXIT_OUTPUT = 0, 1
#: [s] how often the publishers matched to each subscription are counted (for the log)
MATCH_POLL = 0.05

#: message types of the topics this recorder knows (by last name component)
KNOWN_TYPES = {
    'pose': ('geometry_msgs.msg', 'PoseStamped', POSE_TYPE),
    'force_feedback': ('geometry_msgs.msg', 'WrenchStamped', WRENCH_TYPE),
    'state': ('tissue_msgs.msg', 'DeviceState', STATE_TYPE),
}


def _qos_to_rosbags(info_qos):
    """rosbags Qos of an rclpy QoSProfile (what the publisher offers)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                    QosTime)

    def t(d):
        ns = d.nanoseconds
        return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)

    return Qos(QosHistory(int(info_qos.history)), int(info_qos.depth),
               QosReliability(int(info_qos.reliability)), QosDurability(int(info_qos.durability)),
               t(info_qos.deadline), t(info_qos.lifespan), QosLiveliness(int(info_qos.liveliness)),
               t(info_qos.liveliness_lease_duration),
               bool(info_qos.avoid_ros_namespace_conventions))


class OmniRecorder(Node):
    """Raw subscriptions -> :class:`BagWriter`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('omni_record', **kwargs)
        self.p = declare_all(self, RECORDER_PARAMS, ConfigError)
        p = self.p
        topics = resolve_topics(p['topics'])  # ConfigError before anything exists on disk
        typestore()  # built now (~1 s): in the first callback it stalled the stream that long
        out = p['output'] or time.strftime('omni_%Y%m%d_%H%M%S')
        self.path = Path(out).expanduser().resolve()
        self.finished = threading.Event()
        self.failure: DriverError | None = None
        self._lock = threading.Lock()
        self._t_first: float | None = None
        self._t_created = time.monotonic()
        self.writer: BagWriter | None = None
        rel = ReliabilityPolicy.RELIABLE if p['reliable'] else ReliabilityPolicy.BEST_EFFORT
        self._subs = []
        for topic, key, msg_cls, msgtype in topics:
            reliability = ReliabilityPolicy.RELIABLE if key == 'state' else rel
            qos = QoSProfile(depth=p['qos_depth'], history=HistoryPolicy.KEEP_LAST,
                             reliability=reliability, durability=DurabilityPolicy.VOLATILE)
            try:
                sub = self.create_subscription(msg_cls, topic,
                                               self._callback(len(self._subs), msgtype), qos,
                                               raw=True)
            except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad names
                raise ConfigError(f'cannot record {topic!r}: {exc}') from exc
            self._subs.append(sub)
        # last: only a start that is going to record creates the bag (OutputError if it cannot)
        self.writer = BagWriter(self.path, p['metadata_version'],
                                flush_period=p['flush_period'])
        self.get_logger().info(f'recording {", ".join(s.topic_name for s in self._subs)} to '
                               f'{self.path}')
        self._matched = [0] * len(self._subs)
        self.create_timer(MATCH_POLL, self._check_matches)
        if p['duration'] > 0:
            self.create_timer(0.05, self._check_duration)
        self._logged_count = 0
        if p['progress_period'] > 0:
            self.create_timer(p['progress_period'], self._log_progress)

    def _callback(self, index: int, msgtype: str):
        def record(data: bytes) -> None:
            topic = self._subs[index].topic_name
            stamp = self.get_clock().now().nanoseconds
            with self._lock:
                if self.finished.is_set():
                    return
                try:
                    if topic not in self.writer.counts:
                        self.writer.add_topic(topic, msgtype, self._offered_qos(topic))
                    self.writer.write(topic, msgtype, stamp, data)
                except DriverError as exc:  # disk full, medium gone: stop, keep what is flushed
                    self.failure = exc
                    self.finished.set()
                    return
                if self._t_first is None:
                    self._t_first = time.monotonic()
                if 0 < self.p['max_messages'] <= self.writer.count:
                    self.finished.set()
        return record

    def _check_matches(self) -> None:
        # A caller that needs every message (a lockstep recording) waits for the matched line, not
        # for 'recording': a subscription exists before DDS matches it to a publisher. Polled, since
        # a match event that comes before the executor takes the node is lost.
        for i, sub in enumerate(self._subs):
            n = sub.get_publisher_count()
            if n != self._matched[i]:
                what = 'matched a publisher' if n > self._matched[i] else 'a publisher left'
                self.get_logger().info(f'{sub.topic_name}: {what} ({n} now)')
                self._matched[i] = n

    def _offered_qos(self, topic: str) -> list:
        """The publishers' offered QoS profiles, as rosbag2 stores them."""
        try:
            infos = self.get_publishers_info_by_topic(topic)
            profiles = [_qos_to_rosbags(i.qos_profile) for i in infos]
        except Exception:  # noqa: BLE001 - QoS metadata is informative only
            profiles = []
        return profiles or [qos_profile()]

    def _check_duration(self) -> None:
        start = self._t_first if self.p['wait_for_topics'] else self._t_created
        if start is not None and time.monotonic() - start >= self.p['duration']:
            self.finished.set()

    def _counts(self) -> str:
        return ', '.join(f'{t}: {n}' for t, n in self.writer.counts.items()) or 'nothing'

    def _log_progress(self) -> None:
        with self._lock:
            if self.writer.count == self._logged_count:
                return
            self._logged_count = self.writer.count
            counts = self._counts()
        self.get_logger().info(f'recorded {self._logged_count} messages ({counts})')

    def close(self) -> bool:
        """Finalise the bag (MCAP summary + metadata.yaml); False if it could not be finalised."""
        with self._lock:
            self.finished.set()
            try:
                self.writer.close()
            except DriverError as exc:
                self.get_logger().error(
                    f'error: {exc}; the bag is unfinished: recover the messages written so far '
                    f'with: omni_bag_recover {self.path}')
                return False
        self.get_logger().info(f'bag closed: {self.writer.count} messages ({self._counts()}) in '
                               f'{self.path}')
        return True


def resolve_topics(topics: list[str]) -> list[tuple[str, str, type, str]]:
    """(topic, key, message class, bag type) per topic; ConfigError for a topic it cannot record."""
    if not topics:
        raise ConfigError('topics is empty: nothing to record')
    resolved = []
    for topic in topics:
        key = topic.rstrip('/').rsplit('/', 1)[-1]
        if key not in KNOWN_TYPES:
            raise ConfigError(f'cannot record {topic!r}: known topics end in '
                              f'{", ".join(KNOWN_TYPES)}')
        module, cls, msgtype = KNOWN_TYPES[key]
        resolved.append((topic, key, getattr(__import__(module, fromlist=[cls]), cls), msgtype))
    return resolved


def main(args=None) -> int:
    """Entry point of ``omni_record``; returns the exit code (see the module docstring)."""
    if not init_rclpy(args, 'omni_record'):
        return EXIT_PARAMS
    logger = rclpy.logging.get_logger('omni_record')
    node = None
    code = EXIT_OK
    try:
        try:
            node = OmniRecorder()
        except DriverError as exc:
            logger.fatal(f'error: {exc}')
            return EXIT_PARAMS if isinstance(exc, ConfigError) else EXIT_OUTPUT
        from rclpy.experimental import EventsExecutor

        stop = stop_on_signals()
        executor = EventsExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop.is_set() and not node.finished.is_set():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            if node.failure is not None:
                logger.fatal(f'error: {node.failure}')
                code = EXIT_OUTPUT
            if not node.close():
                code = EXIT_OUTPUT
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
