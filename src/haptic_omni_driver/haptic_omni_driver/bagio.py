"""rosbag2 (MCAP storage) bags read with ``rosbags`` and written with ``mcap`` (no rclpy needed).

Bags are folders holding ``metadata.yaml`` (rosbag2 version 9 by default, version 8 on request) and
one ``.mcap`` file, with per-topic message definitions, RIHS01 type hashes and offered QoS profiles, so
``ros2 bag info`` / ``ros2 bag play`` on a ROS install accept them. Messages are stored as CDR bytes;
reading with ``raw=True`` gives those bytes back untouched. The writer flushes whole chunks as it
goes and :func:`recover_bag` turns a bag whose writer was killed into a complete one.

Example::

    from haptic_omni_driver import bagio
    bagio.write_bag('session', [('/omni/pose', 'geometry_msgs/msg/PoseStamped', t_ns, msg), ...])
    for topic, msgtype, stamp_ns, msg in bagio.read_bag('session', topics=['/omni/pose']):
        ...
"""

from __future__ import annotations

import os
import shutil
import threading
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple, Sequence

import yaml

from .errors import BagError, OutputError

POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
STATE_TYPE = 'tissue_msgs/msg/DeviceState'
_CUSTOM_TYPES = {STATE_TYPE: 'DeviceState.msg'}
#: chunks are closed at this size, or earlier by a flush
CHUNK_SIZE = 1024 * 1024
#: name of the MCAP metadata record (written first) that keeps the rosbag2 metadata version
VERSION_RECORD = 'haptic_omni_driver.bag'


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


class _Topic(NamedTuple):
    """A topic of a bag being written: its MCAP channel and what metadata.yaml says about it."""

    name: str
    msgtype: str
    channel_id: int
    qos: list
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
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
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


def _qos_text(qos: Sequence, version: int) -> str:
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
    version), so :func:`recover_bag` rebuilds an unfinished bag from the flushed chunks.
    Connections are added on first use. Thread-safe.

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
        self._mcap = Writer(self._stream, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
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
        _fsync_dir(self.path)
        self._stop_flusher = threading.Event()
        self._flusher: threading.Thread | None = None
        if flush_period > 0:
            self._flusher = threading.Thread(target=self._flush_every, args=(flush_period,),
                                             name='bag_flush', daemon=True)
            self._flusher.start()

    @contextmanager
    def _io(self, what: str):
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

    def add_topic(self, topic: str, msgtype: str, qos: Sequence | None = None, *,
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

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg,
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
            _fsync_dir(self.path)

    def abort(self) -> None:
        """Stop writing without finalising (the file stays as flushed; see :func:`recover_bag`)."""
        self._stop_flushing()
        with self._lock:
            self._mcap = None
            with suppress(OSError):
                self._stream.close()

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


RECOVER_HINT = 'omni_bag_recover'


def _open_reader(path: str | Path):
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if not path.is_dir():
        raise BagError(f'bag must be a rosbag2 folder (metadata.yaml + .mcap), got a file: {path}')
    if not (path / 'metadata.yaml').is_file():
        if any(path.glob('*.mcap')):
            raise BagError(f'unfinished bag (an .mcap without metadata.yaml: was the recorder '
                           f'killed?): {path}; recover it with: {RECOVER_HINT} {path}')
        raise BagError(f'not a rosbag2 bag (no metadata.yaml): {path}')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for corrupt files
        raise BagError(f'corrupt or unreadable bag {path}: {exc} (an unfinished or truncated '
                       f'recording can be recovered with: {RECOVER_HINT} {path})') from exc
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


# -- recovery of unfinished bags -------------------------------------------------------------------
@dataclass
class Recovery:
    """What :func:`recover_bag` did."""

    path: Path                     # the complete bag (the input folder, or ``output``)
    source: Path                   # the .mcap that was salvaged
    counts: dict[str, int] = field(default_factory=dict)  # recovered messages per topic
    complete: bool = False         # the input was already a complete, readable bag: nothing done
    stop: str = ''                 # why salvaging stopped before the end ('' = it did not)
    skipped: int = 0               # messages whose channel record was lost (not recoverable)

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def _single_mcap(path: Path) -> Path:
    """The one .mcap file of a bag folder (BagError otherwise)."""
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if not path.is_dir():
        raise BagError(f'bag must be a rosbag2 folder (metadata.yaml + .mcap), got a file: {path}')
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise BagError(f'no .mcap file in {path}: not an MCAP bag')
    if len(files) > 1:
        raise BagError(f'{path} holds several .mcap files ({", ".join(f.name for f in files)}); '
                       f'split bags are not supported')
    return files[0]


def _is_complete(path: Path, source: Path) -> dict[str, int] | None:
    """Topic counts if ``path`` opens as a bag whose metadata.yaml counts match its .mcap's."""
    from rosbags.rosbag2.storage_mcap import McapReader

    try:
        reader = _open_reader(path)
    except BagError:
        return None
    try:
        counts = {c.topic: c.msgcount for c in reader.connections}
    finally:
        reader.close()
    storage = McapReader(source)
    try:
        storage.open()
    except Exception:  # noqa: BLE001 - rosbags raises several types for damaged files
        return None
    try:
        stored = {c.topic: c.msgcount for c in storage.connections}
    finally:
        storage.close()
    return counts if stored == counts else None


def salvage_records(mcap_path: str | Path, outcome: Recovery | None = None) -> Iterator:
    """Yield every complete, intact MCAP record of a possibly truncated or damaged file, in order.

    Chunks are opened (their records yielded) only when whole and, if they carry one, with a
    matching CRC; reading stops at the first truncated or damaged record, whose reason goes to
    ``outcome.stop``. Raises BagError if the file is empty or not MCAP at all.
    """
    import struct

    from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
    from mcap.stream_reader import StreamReader

    mcap_path = Path(mcap_path)
    size = mcap_path.stat().st_size
    if size == 0:
        raise BagError(f'{mcap_path} is empty (0 bytes): the recorder stopped before writing '
                       f'anything, nothing to recover')
    with open(mcap_path, 'rb') as stream:
        records = StreamReader(stream, validate_crcs=True, record_size_limit=size).records
        first = True
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except InvalidMagic as exc:
                if first:
                    raise BagError(f'{mcap_path} is not an MCAP file ({exc})') from None
                stop = 'damaged end magic'
            except (EndOfFile, RecordLengthLimitExceeded, struct.error):
                if first:  # the magic and header are written (and flushed) first
                    raise BagError(f'{mcap_path} is too short ({size} bytes) to hold an MCAP '
                                   f'header: nothing to recover') from None
                stop = 'truncated record at the end of the file'
            except (McapError, ValueError, UnicodeDecodeError, KeyError, IndexError,
                    OverflowError, MemoryError) as exc:
                stop = f'damaged record ({type(exc).__name__}: {exc})'
            else:
                first = False
                yield record
                continue
            if outcome is not None:
                outcome.stop = stop
            return


def _rosbag2_version(record) -> int | None:
    """The rosbag2 metadata version named by an MCAP metadata record, if it names one."""
    try:
        if record.name == VERSION_RECORD:
            return int(record.metadata['metadata_version'])
        if record.name == 'rosbag2':  # as rosbag2 and rosbags write it at close
            return int(yaml.safe_load(record.metadata['serialized_metadata'])['version'])
    except (KeyError, TypeError, ValueError, yaml.YAMLError):
        pass
    return None


class _Salvager:
    """Feeds salvaged records into a new BagWriter (created at the first message)."""

    def __init__(self, dest: Path, mcap_name: str, outcome: Recovery) -> None:
        self.dest, self.mcap_name, self.outcome = dest, mcap_name, outcome
        self.version = 9
        self.profile: str | None = None
        self.schemas: dict[int, object] = {}
        self.channels: dict[int, object] = {}
        self.writer: BagWriter | None = None

    def feed(self, record) -> None:
        from mcap.records import Channel, Header, Message, Metadata, Schema

        if isinstance(record, Header):
            self.profile = record.profile
            if record.profile not in ('ros2', ''):
                raise BagError(f'{self.outcome.source} is an MCAP file of profile '
                               f'{record.profile!r}, not a rosbag2 bag')
        elif isinstance(record, Metadata):
            self.version = _rosbag2_version(record) or self.version
        elif isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self._message(record)

    def _message(self, msg) -> None:
        channel = self.channels.get(msg.channel_id)
        schema = self.schemas.get(channel.schema_id) if channel is not None else None
        if schema is None:
            self.outcome.skipped += 1
            return
        if self.writer is None:
            self.writer = BagWriter(self.dest, self.version if self.version in (8, 9) else 9,
                                    mcap_name=self.mcap_name)
        if channel.topic not in self.writer.counts:
            self.writer.add_topic(channel.topic, schema.name, _channel_qos(channel),
                                  msgdef=schema.data.decode(errors='replace'),
                                  digest=_channel_digest(channel, schema.name))
        self.writer.write(channel.topic, schema.name, msg.log_time, msg.data, msg.publish_time)


def _channel_qos(channel) -> list:
    from rosbags.rosbag2.metadata import parse_qos

    try:
        return parse_qos(channel.metadata.get('offered_qos_profiles', ''))
    except Exception:  # noqa: BLE001 - QoS metadata is informative only
        return []


def _channel_digest(channel, msgtype: str) -> str:
    """The channel's RIHS01 type hash, or the typestore's for a type it knows ('' otherwise)."""
    digest = channel.metadata.get('topic_type_hash', '')
    if digest:
        return digest
    try:
        store = typestore()
        return store.hash_rihs01(msgtype) if msgtype in store.fielddefs else ''
    except BagError:
        return ''


def recover_bag(path: str | Path, output: str | Path | None = None) -> Recovery:
    """Make an unfinished bag (writer killed, power lost, disk full) complete and readable.

    Every complete record of the ``.mcap`` up to the first truncated or damaged one is copied into a
    new MCAP file with summary and end magic, and ``metadata.yaml`` is written from what was
    recovered (counts, times, QoS and type hashes from the MCAP channel records). With ``output``
    the result is a new bag folder and the input is left alone; without, the input is replaced in
    place (the new file is completed beside it first, so an interrupted recovery loses nothing). A
    bag that is already complete is left untouched (``Recovery.complete``).

    Raises:
        BagError: not a bag folder, no .mcap, not MCAP, not rosbag2, or no complete message.
        OutputError: the recovered bag cannot be written (read-only input: give ``output``).
    """
    path = Path(path)
    source = _single_mcap(path)
    outcome = Recovery(path=Path(output) if output is not None else path, source=source)
    if output is not None and (Path(output).exists() or Path(output).is_symlink()):
        raise OutputError(f'bag output {output} already exists (rosbag2 never overwrites a bag)')
    counts = _is_complete(path, source)
    if counts is not None and output is None:
        outcome.complete, outcome.counts = True, counts
        return outcome
    work = Path(output) if output is not None else path / '.recovering'
    if output is None and work.exists():
        shutil.rmtree(work)  # left by an interrupted recovery
    salvager = _Salvager(work, source.name, outcome)
    try:
        for record in salvage_records(source, outcome):
            salvager.feed(record)
        if salvager.writer is None:
            raise BagError(f'no complete message in {source} ({outcome.stop or "no messages"}): '
                           f'nothing to recover')
        salvager.writer.close()
    except BaseException:
        if salvager.writer is not None:
            salvager.writer.abort()
            shutil.rmtree(work, ignore_errors=True)
        raise
    outcome.counts = dict(salvager.writer.counts)
    if output is None:
        _replace_in_place(work, path, source.name)
    return outcome


def _replace_in_place(work: Path, path: Path, mcap_name: str) -> None:
    """Move the recovered .mcap over the original, then its metadata.yaml, then drop ``work``."""
    try:
        os.replace(work / mcap_name, path / mcap_name)
        os.replace(work / 'metadata.yaml', path / 'metadata.yaml')
    except OSError as exc:
        raise OutputError(f'cannot replace the files of {path}: {exc.strerror or exc}') from None
    _fsync_dir(path)
    shutil.rmtree(work, ignore_errors=True)
