"""Recovery of unfinished rosbag2 MCAP bags (writer killed, power lost, disk full).

:func:`recover_bag` copies every complete, intact record of a bag's ``.mcap`` (what
:class:`~haptic_omni_driver.bag_writer.BagWriter` had flushed) into a new ``.mcap`` with summary
and end magic and writes the ``metadata.yaml`` that matches it; ``omni_bag_recover``
(:mod:`.recover`) is its command line.

Example::

    from haptic_omni_driver.bag_recovery import recover_bag
    result = recover_bag('session')  # in place
    print(result.messages, result.stop)
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import yaml

from .bag_reader import open_reader
from .bag_types import typestore
from .bag_writer import VERSION_RECORD, BagWriter, fsync_dir
from .errors import BagError, OutputError

if TYPE_CHECKING:
    from mcap.records import Channel, McapRecord, Message, Metadata, Schema
    from rosbags.interfaces import Qos

__all__ = ['Recovery', 'recover_bag', 'salvage_records']


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
        reader = open_reader(path)
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


def salvage_records(mcap_path: str | Path,
                    outcome: Recovery | None = None) -> Iterator[McapRecord]:
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


def _rosbag2_version(record: Metadata) -> int | None:
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
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.writer: BagWriter | None = None

    def feed(self, record: McapRecord) -> None:
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

    def _message(self, msg: Message) -> None:
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


def _channel_qos(channel: Channel) -> list[Qos]:
    from rosbags.rosbag2.metadata import parse_qos

    try:
        return parse_qos(channel.metadata.get('offered_qos_profiles', ''))
    except Exception:  # noqa: BLE001 - QoS metadata is informative only
        return []


def _channel_digest(channel: Channel, msgtype: str) -> str:
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
    fsync_dir(path)
    shutil.rmtree(work, ignore_errors=True)
