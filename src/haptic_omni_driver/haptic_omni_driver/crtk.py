"""The CRTK operating state and jaw of the device (no rclpy).

The Collaborative Robotics Toolkit (CRTK, the names the dVRK and sawSensablePhantom use) gives a
device four meta-states and six commands, sent as strings on ``state_command``:

    DISABLED --enable--> ENABLED --pause--> PAUSED --resume--> ENABLED
    any state --disable--> DISABLED;   a device failure --> FAULT --disable--> DISABLED

``home`` sets ``is_homed`` (in DISABLED or ENABLED, as cisst's prmOperatingState accepts it),
``unhome`` clears it in any state. Only ENABLED renders force: in every other state the safety
chain outputs zero and, back in ENABLED, ramps up again from zero. A command that does not apply to
the current state changes nothing and says why (CRTK devices ignore it with a warning). For the
Omni, homed means calibrated: the OpenHaptics backend reports the calibration it found at start;
replay and scripted sources are always homed. omni_driver exits when its device fails, after
publishing FAULT (a supervisor restarting it sees why).

The Omni has no jaw; :class:`Jaw` makes one of its stylus buttons one, as a dVRK arm's ``jaw``
(``jaw/measured_js``, ``jaw/servo_jp``): closed (0 rad) while the button is down, open
(``jaw_open_angle``) while it is up, or at the angle ``jaw/servo_jp`` last asked for until the
button next changes: the newest of the two wins, so the hand can always take the jaw back.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

STATES = ('DISABLED', 'ENABLED', 'PAUSED', 'FAULT')
COMMANDS = ('enable', 'disable', 'pause', 'resume', 'home', 'unhome')
#: command -> (states it applies in, state it leads to; None = unchanged)
TRANSITIONS = {
    'enable': (('DISABLED', 'ENABLED'), 'ENABLED'),
    'disable': (STATES, 'DISABLED'),
    'pause': (('ENABLED', 'PAUSED'), 'PAUSED'),
    'resume': (('PAUSED', 'ENABLED'), 'ENABLED'),
    'home': (('DISABLED', 'ENABLED'), None),
    'unhome': (STATES, None),
}


@dataclass(frozen=True)
class OperatingState:
    """One snapshot, as ``crtk_msgs/OperatingState`` carries it."""

    state: str
    is_homed: bool
    is_busy: bool = False

    @property
    def renders_force(self) -> bool:
        return self.state == 'ENABLED'


class OperatingStateMachine:
    """The device's CRTK state; thread-safe (commands from the executor, faults from a backend)."""

    def __init__(self, start: str = 'ENABLED', homed: bool = True) -> None:
        if start not in ('DISABLED', 'ENABLED'):
            raise ValueError(f'a device starts DISABLED or ENABLED, not {start!r}')
        self._lock = threading.Lock()
        self._state = OperatingState(start, homed)
        self.fault_reason = ''

    @property
    def current(self) -> OperatingState:
        with self._lock:
            return self._state

    def command(self, text: str, homed_now: bool = True) -> tuple[OperatingState, str]:
        """Apply a ``state_command`` string; returns (the state after, '' or why nothing changed).

        ``homed_now``: what homing finds (the device's calibration) for ``home``."""
        cmd = text.strip().lower()
        with self._lock:
            old = self._state
            if cmd not in TRANSITIONS:
                return old, f'unknown command {text!r} (one of {", ".join(COMMANDS)})'
            valid_in, to = TRANSITIONS[cmd]
            if old.state not in valid_in:
                return old, f'{cmd!r} does not apply in state {old.state}'
            homed = old.is_homed
            if cmd == 'home':
                homed = homed_now
            elif cmd == 'unhome':
                homed = False
            if cmd == 'disable':
                self.fault_reason = ''
            self._state = OperatingState(to or old.state, homed)
            if cmd == 'home' and not homed_now:
                return self._state, 'homing did not succeed (the device is not calibrated)'
            return self._state, ''

    def fault(self, reason: str) -> OperatingState:
        """The device failed: FAULT until ``disable``."""
        with self._lock:
            self.fault_reason = reason
            self._state = OperatingState('FAULT', self._state.is_homed)
            return self._state


class Jaw:
    """The jaw angle [rad] from a stylus button and ``jaw/servo_jp`` commands; thread-safe (commands
    from the executor, samples from the backend thread)."""

    def __init__(self, button: int, open_angle: float) -> None:
        self.index = button - 1          # in Sample.buttons
        self.open_angle = open_angle
        self.angle = open_angle          # the button starts up
        self._pressed = False
        self._command: float | None = None
        self._lock = threading.Lock()

    def command(self, position: Sequence[float]) -> tuple[str, str]:
        """A ``jaw/servo_jp`` position, applied at the next sample; ('', '') or (the kind of refusal:
        length, nan, range; why it is ignored)."""
        if len(position) != 1:
            return 'length', f'{len(position)} positions, but the jaw is one joint'
        angle = float(position[0])
        if not math.isfinite(angle):
            return 'nan', f'non-finite angle {angle}'
        if not 0.0 <= angle <= self.open_angle:
            return 'range', f'angle {angle:g} rad outside 0 (closed) … jaw_open_angle {self.open_angle:g} rad'
        with self._lock:
            self._command = angle
        return '', ''

    def sample(self, buttons: tuple[bool, bool] | None) -> float:
        """The angle at a sample with these buttons (None: the source has none, the button stays)."""
        with self._lock:
            command, self._command = self._command, None
        pressed = self._pressed if buttons is None else bool(buttons[self.index])
        if pressed != self._pressed:
            # the hand acted at this sample, after any command that came before it
            self._pressed = pressed
            self.angle = 0.0 if pressed else self.open_angle
        elif command is not None:
            self.angle = command
        return self.angle
