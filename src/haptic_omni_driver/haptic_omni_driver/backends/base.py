"""Backend interface: where stylus samples come from and where the safe force goes (no rclpy).

A backend produces :class:`Sample` objects (stylus tip pose in the device frame, metres) on its own
thread and hands them to a :class:`BackendSink` (the node). Backends without a device (replay,
scripted) let the node run a virtual servo loop; the OpenHaptics backend calls ``sink.servo`` from the
device's own 1 kHz scheduler callback and renders the returned force.
"""

from __future__ import annotations

import abc
import threading
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass
class Sample:
    """One stylus sample.

    Attributes:
        stamp_ns: header stamp [ns] (device time for live backends, the bag's stamp for replay).
        position: (3,) stylus tip position [m] in the device frame.
        orientation: (4,) quaternion x, y, z, w of the stylus in the device frame.
        buttons: (button1, button2) or None when the source has no button information.
        raw: serialized PoseStamped (CDR) to publish as-is (replay keeps bag bytes identical).
        phase: name of the script phase (scripted backend), for logs.
        joints: joint and gimbal angles [rad] in :attr:`Backend.joint_names` order, where the
            source has them (OpenHaptics), else None.
    """

    stamp_ns: int
    position: np.ndarray
    orientation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    buttons: tuple[bool, bool] | None = None
    raw: bytes | None = None
    phase: str = ''
    joints: np.ndarray | None = None


class BackendSink(Protocol):
    """What a backend may call on the node."""

    def on_sample(self, sample: Sample) -> None:
        """Publish a pose (and buttons)."""

    def servo(self) -> np.ndarray:
        """Run one safety-chain tick; returns the force [N] the device must render now."""

    def wait_for_reply(self, stamp_ns: int, timeout: float) -> bool:
        """Block until a force reply with header stamp ``stamp_ns`` arrives (lockstep)."""

    def wait_for_subscribers(self) -> bool:
        """Block until the pose topic has the configured subscriber count (False if stopping)."""

    def on_finished(self, summary: str, exit_code: int) -> None:
        """The source is exhausted (or failed while running)."""

    def log(self, level: str, text: str) -> None:
        """Log through the node's logger (level: debug, info, warn, error)."""


class Backend(abc.ABC):
    """A source of stylus samples, and for a real device, the force sink."""

    #: backend name as in the ``backend`` parameter and DeviceState.backend
    name: str = ''
    #: True if the backend renders forces itself (servo in its own loop); False = virtual device
    has_device: bool = False
    #: names of :attr:`Sample.joints` (CRTK measured_js); empty: the source has no joint angles
    joint_names: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.source = ''
        self.calibrated = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @abc.abstractmethod
    def run(self, sink: BackendSink) -> None:
        """Produce samples until exhausted or :meth:`stop` (runs in the backend thread)."""

    def start(self, sink: BackendSink) -> None:
        """Start the backend thread."""
        self._thread = threading.Thread(target=self._main, args=(sink,), name=f'{self.name}_backend',
                                        daemon=True)
        self._thread.start()

    def _main(self, sink: BackendSink) -> None:
        try:
            self.run(sink)
        except Exception as exc:  # noqa: BLE001 - reported, the node exits non-zero
            sink.on_finished(f'{self.name} backend failed: {exc}', 1)

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the backend to stop and wait for its thread."""
        self._stop.set()
        if self._thread is not None and self._thread.is_alive() and \
                self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()
