"""One instrument's path through sim_node: its device's poses in, its forces out.

sim_node serves one instrument or several on one tissue (parameter ``instruments``). Each has a
:class:`Channel`: its device map, the clock of its pose stamps, its haptic renderer, the last force
it sent, its newest pose's stamp, where it last asked the solver to put its tool and whether its
jaw should be closed. The
:class:`~.runner.Runner` steps the solver once for all of them.
"""

from __future__ import annotations

import collections
import threading
from dataclasses import dataclass, field

import numpy as np
from tissue_common.instruments import topic_within

from .haptics.multirate import MultiRate
from .mapping import DeviceMapping
from .timing import StampClock


@dataclass
class Channel:
    """One instrument (see the module docstring); ``index`` is its slot in the solver."""

    index: int
    name: str                               # its namespace ('': none)
    mapping: DeviceMapping
    clock: StampClock
    haptic: MultiRate | None                # None: direct (one instrument only)
    last_force: np.ndarray = field(default_factory=lambda: np.zeros(3))   # device frame [N]
    tool: tuple | None = None               # (point, rotation) it last asked for (tissue frame)
    closed: bool = False                    # the jaw should hold (the device's button)
    gripping: bool = False                  # the solver was told so (it grasped, since it last opened)
    newest_ns: int | None = None            # the stamp of its newest pose answered [ns]
    inbox: collections.deque = field(default_factory=collections.deque)   # poses waiting for a round
    grasps: list = field(default_factory=list)  # lockstep: the button's changes (stamp ns, closed), in order
    grasp_lock: threading.Lock = field(default_factory=threading.Lock)

    def device_frame(self, shared: str) -> str:
        """Its device's frame: ``shared`` (the ``device_frame`` parameter) in its namespace."""
        return topic_within(self.name, shared)

    @property
    def label(self) -> str:
        """How logs name it."""
        return f'instrument {self.name}' if self.name else 'the instrument'
