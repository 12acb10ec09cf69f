"""rosbag2 (MCAP storage) bags read and written with ``rosbags`` (no rclpy, no rosbag2 needed).

Bags are folders holding ``metadata.yaml`` (rosbag2 version 9 by default, version 8 on request) and
one ``.mcap`` file, with per-topic message definitions, RIHS01 type hashes and offered QoS profiles, so
``ros2 bag info`` / ``ros2 bag play`` on a ROS install accept them. Messages are stored as CDR bytes;
reading with ``raw=True`` gives those bytes back untouched.

Example::

    from haptic_omni_driver import bagio
    bagio.write_bag('session', [('/omni/pose', 'geometry_msgs/msg/PoseStamped', t_ns, msg), ...])
    for topic, msgtype, stamp_ns, msg in bagio.read_bag('session', topics=['/omni/pose']):
        ...
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Iterator, Sequence

from .errors import BagError

POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
STATE_TYPE = 'tissue_msgs/msg/DeviceState'
_CUSTOM_TYPES = {STATE_TYPE: 'DeviceState.msg'}


def _find_msg_file(filename: str) -> Path:
    """The tissue_msgs .msg file: installed share/ copy (ament prefixes) or the source tree."""
    candidates = []
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        candidates.append(Path(prefix) / 'share' / 'tissue_msgs' / 'msg' / filename)
    here = Path(__file__).resolve()
    for parent in here.parents:
        candidates.append(parent / 'src' / 'tissue_msgs' / 'msg' / filename)
        candidates.append(parent / 'tissue_msgs' / 'msg' / filename)
    for path in candidates:
        if path.is_file():
            return path
    raise BagError(f'cannot find tissue_msgs/msg/{filename} (is tissue_msgs built and sourced?)')


@lru_cache(maxsize=1)
def typestore():
    """A ROS 2 Jazzy typestore with the tissue_msgs types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for msgtype, filename in _CUSTOM_TYPES.items():
        types.update(get_types_from_msg(_find_msg_file(filename).read_text(), msgtype))
    store.register(types)
    return store


def qos_profile(reliable: bool = True, depth: int = 1000):
    """A rosbags QoS profile (keep last ``depth``, volatile) for ``offered_qos_profiles``."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                    QosTime)

    zero = QosTime(0, 0)  # rmw default: no deadline, lifespan or lease
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def _to_cdr(msgtype: str, msg) -> bytes:
    """CDR bytes of ``msg``: bytes pass through; rosbags and rclpy messages are serialized."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    if hasattr(msg, 'get_fields_and_field_types'):  # an rclpy message
        from rclpy.serialization import serialize_message

        return serialize_message(msg)
    return bytes(typestore().serialize_cdr(msg, msgtype))


class BagWriter:
    """Incremental MCAP bag writer (used by the recorder): connections are added on first use."""

    def __init__(self, path: str | Path, version: int = 9) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'bag output {self.path} already exists (rosbag2 never overwrites a bag)')
        if version not in (8, 9):
            raise BagError(f'rosbag2 metadata version must be 8 or 9, got {version}')
        self._writer = Writer(self.path, version=version, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[str, object] = {}
        self.count = 0
        self.counts: dict[str, int] = {}

    def add_topic(self, topic: str, msgtype: str, qos: Sequence | None = None) -> None:
        """Register a topic (no-op if it exists); ``qos``: rosbags Qos profiles offered on it."""
        if topic in self._connections:
            return
        store = typestore()
        if msgtype not in store.fielddefs:
            raise BagError(f'unknown message type {msgtype}')
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=store,
            offered_qos_profiles=list(qos) if qos is not None else [qos_profile()])
        self.counts[topic] = 0

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg) -> None:
        """Append one message (CDR bytes, rosbags or rclpy message) at log time ``stamp_ns``."""
        self.add_topic(topic, msgtype)
        self._writer.write(self._connections[topic], int(stamp_ns), _to_cdr(msgtype, msg))
        self.count += 1
        self.counts[topic] += 1

    def close(self) -> None:
        """Finalise the bag (MCAP summary and metadata.yaml)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_bag(path: str | Path, messages: Iterable[tuple], version: int = 9,
              qos: dict | None = None) -> Path:
    """Write ``[(topic, msgtype, stamp_ns, msg), ...]`` to a new MCAP bag folder ``path``.

    ``msg`` may be CDR bytes, a rosbags message or an rclpy message. ``qos`` maps topic -> rosbags
    Qos list (default: reliable, keep last 1000). Returns the bag path.
    """
    with BagWriter(path, version) as writer:
        for topic, msgtype, stamp_ns, msg in messages:
            if qos and topic in qos:
                writer.add_topic(topic, msgtype, qos[topic])
            writer.write(topic, msgtype, stamp_ns, msg)
    return Path(path)


@dataclass
class BagTopic:
    """One topic of a bag."""

    name: str
    msgtype: str
    count: int


def _open_reader(path: str | Path):
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if not path.is_dir():
        raise BagError(f'bag must be a rosbag2 folder (metadata.yaml + .mcap), got a file: {path}')
    if not (path / 'metadata.yaml').is_file():
        raise BagError(f'not a rosbag2 bag (no metadata.yaml): {path}')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for corrupt files
        raise BagError(f'corrupt or unreadable bag {path}: {exc}') from exc
    return reader


def bag_topics(path: str | Path) -> dict[str, BagTopic]:
    """Topics of a bag (name -> BagTopic); raises :class:`BagError` if it is not a readable bag."""
    reader = _open_reader(path)
    try:
        return {c.topic: BagTopic(c.topic, c.msgtype, c.msgcount) for c in reader.connections}
    finally:
        reader.close()


def normalise_topic(name: str) -> str:
    """Topic name compared without the leading slash ('/omni/pose' == 'omni/pose')."""
    return name.lstrip('/')


def read_bag(path: str | Path, topics: Sequence[str] | None = None,
             raw: bool = False) -> Iterator[tuple[str, str, int, object]]:
    """Yield ``(topic, msgtype, log_time_ns, msg)`` in log-time order.

    Args:
        path: bag folder.
        topics: only these topics (leading slash optional); None = all.
        raw: yield the CDR bytes instead of a deserialized rosbags message.

    Raises:
        BagError: missing, not a bag, corrupt (also when a corrupt chunk is hit while iterating).
    """
    reader = _open_reader(path)
    try:
        wanted = None if topics is None else {normalise_topic(t) for t in topics}
        conns = [c for c in reader.connections
                 if wanted is None or normalise_topic(c.topic) in wanted]
        store = typestore() if not raw else None
        try:
            for conn, stamp, data in reader.messages(connections=conns):
                if raw:
                    yield conn.topic, conn.msgtype, stamp, bytes(data)
                else:
                    yield conn.topic, conn.msgtype, stamp, store.deserialize_cdr(data, conn.msgtype)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise BagError(f'corrupt bag {path}: {exc}') from exc
    finally:
        reader.close()
