"""Writing rosbag2 bags (MCAP storage) with the ``mcap`` library (no rclpy needed).

A bag is a folder holding ``metadata.yaml`` (rosbag2 version 9 by default, version 8 on request)
and one ``.mcap`` file, with per-topic message definitions, RIHS01 type hashes and offered QoS
profiles, so ``ros2 bag info`` / ``ros2 bag play`` on a ROS install accept it. Messages are stored
as CDR bytes. The writer flushes whole chunks as it goes, and
:func:`~haptic_omni_driver.bag_recovery.recover_bag` turns a bag whose writer was killed into a
complete one.

Example::

    from haptic_omni_driver.bag_writer import write_bag
    write_bag('session', [('/omni/pose', 'geometry_msgs/msg/PoseStamped', t_ns, msg), ...])
"""

from __future__ import annotations

import os
import shutil
import threading
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator, NamedTuple, Sequence

import yaml

from .bag_types import typestore
from .errors import BagError, OutputError

if TYPE_CHECKING:
    from mcap.writer import Writer as McapWriter
    from rosbags.interfaces import Qos

__all__ = ['CHUNK_SIZE', 'VERSION_RECORD', 'BagWriter', 'fsync_dir', 'qos_profile', 'write_bag']

#: chunks are closed at this size, or earlier by a flush
CHUNK_SIZE = 1024 * 1024
#: name of the MCAP metadata record (written first) that keeps the rosbag2 metadata version
VERSION_RECORD = 'haptic_omni_driver.bag'


def qos_profile(reliable: bool = True, depth: int = 1000) -> Qos:
    """A rosbags QoS profile (keep last ``depth``, volatile) for ``offered_qos_profiles``."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                    QosTime)

    zero = QosTime(0, 0)  # rmw default: no deadline, lifespan or lease
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def _to_cdr(msgtype: str, msg: object) -> bytes:
    """CDR bytes of ``msg``: bytes pass through; rosbags and rclpy messages are serialized."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    if hasattr(msg, 'get_fields_and_field_types'):  # an rclpy message
        from rclpy.serialization import serialize_message

        return serialize_message(msg)
    return bytes(typestore().serialize_cdr(msg, msgtype))


class _Topic(NamedTuple):
    """A topic of a bag being written: its MCAP channel and what metadata.yaml says about it."""

    name: str
    msgtype: str
    channel_id: int
    qos: list[Qos]
    digest: str


def _blocking_file(path: Path) -> Path | None:
    """The nearest existing ancestor of ``path`` when it is a file (why mkdir says ENOTDIR)."""
    for parent in path.parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def _make_bag_dir(path: Path) -> None:
    """Create the bag folder (and missing parents), with a clear error when that is refused."""
    if path.exists() or path.is_symlink():
        raise OutputError(f'bag output {path} already exists (rosbag2 never overwrites a bag)')
    try:
        path.mkdir(parents=True)
    except FileExistsError:
        raise OutputError(f'bag output {path} already exists (rosbag2 never overwrites a bag)'
                          ) from None
    except NotADirectoryError:
        blocker = _blocking_file(path)
        raise OutputError(f'cannot create bag folder {path}: '
                          f'{blocker or "a parent"} is a file, not a folder') from None
    except OSError as exc:
        raise OutputError(f'cannot create bag folder {path}: {exc.strerror or exc}') from None
    fsync_dir(path.parent)


def fsync_dir(path: Path) -> None:
    """Make a new directory entry in ``path`` durable (best effort: not every file system can)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _qos_text(qos: Sequence[Qos], version: int) -> str:
    """offered_qos_profiles as rosbag2 stores them in MCAP channel metadata (a YAML string)."""
    from rosbags.rosbag2.metadata import dump_qos_v8, dump_qos_v9

    if version >= 9:
        return yaml.safe_dump(dump_qos_v9(list(qos)), sort_keys=False).strip()
    return dump_qos_v8(list(qos))


class BagWriter:
    """Incremental, crash-tolerant rosbag2 MCAP bag writer (used by the recorder).

    The ``.mcap`` is written with the ``mcap`` library in chunks. :meth:`flush` closes the open
    chunk, hands it to the file and fsyncs it; with ``flush_period`` > 0 a background thread does
    that every ``flush_period`` seconds, so a killed process (or a power loss) loses at most about
    that much of the recording. ``metadata.yaml`` is written by :meth:`close`; everything it holds is in
    the ``.mcap`` too (schemas, channels with QoS and type hash, a record naming the metadata
    version), so :func:`~haptic_omni_driver.bag_recovery.recover_bag` rebuilds an unfinished bag
    from the flushed chunks. Connections are added on first use. Thread-safe.

    Raises:
        OutputError: the folder exists or cannot be created, or a write fails (disk full, ...).
    """

    def __init__(self, path: str | Path, version: int = 9, *, flush_period: float = 0.0,
                 mcap_name: str | None = None) -> None:
        from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

        if version not in (8, 9):
            raise BagError(f'rosbag2 metadata version must be 8 or 9, got {version}')
        self.path = Path(path)
        self.version = version
        _make_bag_dir(self.path)
        self.mcap_path = self.path / (mcap_name or f'{self.path.name}.mcap')
        try:
            self._stream = open(self.mcap_path, 'xb')
        except OSError as exc:
            shutil.rmtree(self.path, ignore_errors=True)  # created above and still empty
            raise OutputError(f'cannot create {self.mcap_path}: {exc.strerror or exc}') from None
        self._lock = threading.RLock()
        self._mcap: McapWriter | None = Writer(self._stream, chunk_size=CHUNK_SIZE,
                                               compression=CompressionType.NONE)
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._span = [2 ** 63 - 1, 0]  # first and last log time
        self._dirty = False
        self._error: OutputError | None = None
        self.count = 0
        self.counts: dict[str, int] = {}
        with self._io('cannot write'):
            self._mcap.start(profile='ros2', library=f'haptic_omni_driver, {LIBRARY_IDENTIFIER}')
            self._mcap.add_metadata(VERSION_RECORD, {'metadata_version': str(version)})
            self._dirty = True
        self.flush()
        fsync_dir(self.path)
        self._stop_flusher = threading.Event()
        self._flusher: threading.Thread | None = None
        if flush_period > 0:
            self._flusher = threading.Thread(target=self._flush_every, args=(flush_period,),
                                             name='bag_flush', daemon=True)
            self._flusher.start()

    @contextmanager
    def _io(self, what: str) -> Iterator[None]:
        """Turn an OSError of the file system into an OutputError naming the file."""
        try:
            yield
        except OSError as exc:
            raise OutputError(f'{what} {self.mcap_path}: {exc.strerror or exc}') from None

    def _check_writable(self) -> None:
        if self._error is not None:
            raise self._error
        if self._mcap is None:
            raise BagError(f'bag {self.path} is closed')

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] | None = None, *,
                  msgdef: str | None = None, digest: str | None = None) -> None:
        """Register a topic (no-op if it exists); ``qos``: rosbags Qos profiles offered on it.

        ``msgdef``/``digest`` (message definition text and RIHS01 hash) default to the typestore's.
        """
        with self._lock:
            if topic in self._topics:
                return
            self._check_writable()
            if msgdef is None:
                store = typestore()
                if msgtype not in store.fielddefs:
                    raise BagError(f'unknown message type {msgtype}')
                msgdef, _ = store.generate_msgdef(msgtype, ros_version=2)
                digest = store.hash_rihs01(msgtype) if digest is None else digest
            qos = list(qos) if qos is not None else [qos_profile()]
            with self._io('cannot write'):
                if msgtype not in self._schemas:
                    encoding = 'ros2idl' if msgdef.startswith('=' * 80 + '\nIDL: ') else 'ros2msg'
                    self._schemas[msgtype] = self._mcap.register_schema(msgtype, encoding,
                                                                        msgdef.encode())
                channel = self._mcap.register_channel(
                    topic, 'cdr', self._schemas[msgtype],
                    {'offered_qos_profiles': _qos_text(qos, self.version),
                     'topic_type_hash': digest or ''})
            self._topics[topic] = _Topic(topic, msgtype, channel, qos, digest or '')
            self.counts[topic] = 0

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: object,
              publish_ns: int | None = None) -> None:
        """Append one message (CDR bytes, rosbags or rclpy message) at log time ``stamp_ns``."""
        data = _to_cdr(msgtype, msg)
        stamp_ns = int(stamp_ns)
        with self._lock:
            self.add_topic(topic, msgtype)
            self._check_writable()
            with self._io('cannot write'):
                self._mcap.add_message(self._topics[topic].channel_id, stamp_ns, data,
                                       stamp_ns if publish_ns is None else int(publish_ns))
            self._dirty = True
            self._span = [min(self._span[0], stamp_ns), max(self._span[1], stamp_ns)]
            self.count += 1
            self.counts[topic] += 1

    def flush(self, sync: bool = True) -> None:
        """Write the open chunk to the file and (``sync``) fsync it: survives a kill/power loss."""
        with self._lock:
            if self._mcap is None or not self._dirty:
                return
            with self._io('cannot write'):
                self._mcap.flush()
            self._dirty = False
            fd = self._stream.fileno()
        if sync:
            with self._io('cannot sync'):
                os.fsync(fd)

    def _flush_every(self, period: float) -> None:
        while not self._stop_flusher.wait(period):
            try:
                self.flush()
            except OutputError as exc:
                self._error = exc  # raised by the next write
                return

    def _stop_flushing(self) -> None:
        if self._flusher is not None:
            self._stop_flusher.set()
            self._flusher.join()
            self._flusher = None

    def metadata(self) -> dict:
        """The rosbag2 ``metadata.yaml`` content of what was written so far."""
        from rosbags.rosbag2.metadata import dump_qos_v8, dump_qos_v9

        dump_qos = dump_qos_v9 if self.version >= 9 else dump_qos_v8
        start = self._span[0] if self.count else 0
        duration = self._span[1] - self._span[0] if self.count else 0
        return {'rosbag2_bagfile_information': {
            'version': self.version,
            'storage_identifier': 'mcap',
            'relative_file_paths': [self.mcap_path.name],
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': self.count,
            'topics_with_message_count': [
                {'topic_metadata': {'name': t.name, 'type': t.msgtype,
                                    'serialization_format': 'cdr',
                                    'offered_qos_profiles': dump_qos(t.qos),
                                    'type_description_hash': t.digest},
                 'message_count': self.counts[t.name]}
                for t in self._topics.values()],
            'compression_format': '',
            'compression_mode': '',
            'files': [{'path': self.mcap_path.name,
                       'starting_time': {'nanoseconds_since_epoch': start},
                       'duration': {'nanoseconds': duration},
                       'message_count': self.count}],
            'custom_data': None,
            'ros_distro': 'jazzy',
        }}

    def close(self) -> None:
        """Finalise the bag: MCAP summary and end magic, then metadata.yaml (both fsynced)."""
        self._stop_flushing()
        with self._lock:
            if self._mcap is None:
                return
            info = self.metadata()
            try:
                with self._io('cannot finalise'):
                    self._mcap.flush()
                    self._mcap.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(
                        info['rosbag2_bagfile_information'], sort_keys=False).strip()})
                    self._mcap.finish()
                    self._stream.flush()
                    os.fsync(self._stream.fileno())
            finally:
                self._mcap = None
                with suppress(OSError):
                    self._stream.close()
            tmp = self.path / 'metadata.yaml.tmp'
            with self._io('cannot write metadata.yaml next to'):
                with open(tmp, 'w', encoding='utf8') as out:
                    yaml.safe_dump(info, out, sort_keys=False)
                    out.flush()
                    os.fsync(out.fileno())
                os.replace(tmp, self.path / 'metadata.yaml')
            fsync_dir(self.path)

    def abort(self) -> None:
        """Stop writing without finalising (the file stays as flushed; see :func:`recover_bag`)."""
        self._stop_flushing()
        with self._lock:
            self._mcap = None
            with suppress(OSError):
                self._stream.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_bag(path: str | Path, messages: Iterable[tuple[str, str, int, object]],
              version: int = 9, qos: dict[str, Sequence[Qos]] | None = None) -> Path:
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
