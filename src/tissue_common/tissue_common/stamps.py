"""ROS time stamps (``builtin_interfaces/Time``: ``sec``, ``nanosec``) as integer nanoseconds."""

from __future__ import annotations


def stamp_to_ns(stamp) -> int:
    """Nanoseconds since the epoch of a ``builtin_interfaces/Time`` (exact: no float)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def set_stamp(stamp, ns: int) -> None:
    """Write integer nanoseconds ``ns`` into a ``builtin_interfaces/Time`` in place."""
    stamp.sec, stamp.nanosec = divmod(int(ns), 1_000_000_000)
