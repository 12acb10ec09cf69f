"""Instrument names: the ``instruments`` parameter of sim_node and viz_node (no rclpy).

``['']`` is one instrument without a namespace (the topics keep their plain names); several are
distinct names, each a namespace of its own ``omni/pose``, ``omni/force_feedback``, grasp input
(``omni/state`` or ``omni/jaw/measured_js``), ``tissue/metrics`` and ``tissue/device_frame``. The order is the simulator's instrument index (``held`` in the particle
cloud counts from it).
"""

from __future__ import annotations

import re

#: an instrument's name: one namespace token (a letter, then letters, digits and underscores)
INSTRUMENT_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*')


def check_instruments(names) -> str | None:
    """Error text unless ``names`` is [''] (one instrument, no namespace) or distinct valid names."""
    given = names
    try:
        names = [str(n) for n in names] if not isinstance(names, str) else None
    except TypeError:
        names = None
    if not names:
        return f'parameter instruments must be a list of names, got {given!r}'
    if names == ['']:
        return None
    bad = [n for n in names if not INSTRUMENT_NAME.fullmatch(n)]
    if bad:
        return (f'parameter instruments: {bad[0]!r} is not a valid namespace (a letter, then letters, digits '
                f'and underscores)')
    if len(set(names)) != len(names):
        twice = sorted(n for n in set(names) if names.count(n) > 1)
        return f'parameter instruments: {twice[0]!r} is named twice'
    return None


def topic_within(namespace: str, topic: str) -> str:
    """``topic`` in an instrument's namespace (relative, so the node's own namespace still applies)."""
    return f'{namespace}/{topic}' if namespace else topic
