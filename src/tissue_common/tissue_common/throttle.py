"""Log throttling by kind of event: a flood of bad input must not flood the log."""

from __future__ import annotations

import collections


class EventThrottle:
    """Counts events by kind and says when one may be logged: at most once per ``period`` seconds
    per kind (the first one always)."""

    def __init__(self) -> None:
        self.counts: collections.Counter = collections.Counter()
        self._last: dict[str, float] = {}

    def event(self, kind: str, now: float, period: float) -> int | None:
        """Count an event of ``kind`` at ``now`` [s]; the count so far if it may be logged, else None."""
        self.counts[kind] += 1
        if now - self._last.get(kind, -1e18) < period:
            return None
        self._last[kind] = now
        return self.counts[kind]
