"""Reading rosbag2 bags (MCAP storage) with ``rosbags`` (no rclpy needed).

Messages come in log-time order, deserialized to rosbags messages or, with ``raw=True``, as the CDR
bytes stored in the bag, untouched. A bag that cannot be read raises :class:`~.errors.BagError`;
when it looks unfinished (a killed recorder) the message names the recovery command.

Example::

    from haptic_omni_driver.bag_reader import read_bag
    for topic, msgtype, stamp_ns, msg in read_bag('session', topics=['/omni/pose']):
        ...
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Sequence

from .bag_types import typestore
from .errors import BagError

if TYPE_CHECKING:
    from rosbags.rosbag2 import Reader

__all__ = ['RECOVER_HINT', 'BagTopic', 'bag_topics', 'normalise_topic', 'open_reader', 'read_bag']


@dataclass
class BagTopic:
    """One topic of a bag."""

    name: str
    msgtype: str
    count: int


#: the command that completes an unfinished bag, named in the errors
RECOVER_HINT = 'omni_bag_recover'


def open_reader(path: str | Path) -> Reader:
    """An opened rosbags Reader of the bag folder ``path``; the caller closes it.

    Raises:
        BagError: missing, a file, no metadata.yaml (unfinished: names the recovery command),
            corrupt or unreadable.
    """
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
    reader = open_reader(path)
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
    reader = open_reader(path)
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
