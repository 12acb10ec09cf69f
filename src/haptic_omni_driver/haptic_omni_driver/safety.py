"""Force safety chain between the simulator's force commands and the device (no rclpy).

Every force that reaches a device (or, for the replay and scripted backends, the virtual device whose
output DeviceState reports) passes through :class:`ForceSafety`:

* commands with NaN/inf components, or in a frame other than the device frame, are rejected;
* the force norm is clamped to ``force_limit`` (itself never above :data:`HARD_FORCE_LIMIT`);
* force output is enabled only by the first valid command, and the output then ramps up linearly over
  ``ramp_time`` (again after each watchdog trip), so a device never jumps to a large force;
* a watchdog zeroes the output when the newest valid command is older than ``watchdog_timeout`` (the
  simulator stopped or went silent), and optionally when a command answers a pose older than
  ``max_command_lag`` (a stale reply).

The class is thread-safe: commands come from the ROS executor thread, the output is polled by the servo
loop (1 kHz) thread.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError

#: [N] PHANTOM Omni nominal peak force; no parameter can raise the clamp above this.
HARD_FORCE_LIMIT = 3.3
#: [N] PHANTOM Omni nominal continuous force (the default clamp).
CONTINUOUS_FORCE_LIMIT = 0.88
#: [s] allowed watchdog range: below 10 ms a 1 kHz loop with DDS jitter trips spuriously; above
#: 50 ms a runaway force is felt.
WATCHDOG_RANGE = (0.005, 0.05)


@dataclass
class SafetyConfig:
    """Parameters of the safety chain (SI units)."""

    force_limit: float = CONTINUOUS_FORCE_LIMIT   # [N] norm clamp
    ramp_time: float = 0.5                        # [s] linear ramp after enabling; 0 = none
    watchdog_timeout: float = 0.02                # [s] zero the force when commands stop this long
    max_command_lag: float = 0.0                  # [s] reject replies older than newest pose; 0 = off
    frame_id: str = 'omni_base'                   # device frame commands must be expressed in
    accept_empty_frame: bool = True               # treat frame_id '' as the device frame

    def validate(self) -> 'SafetyConfig':
        """Raise :class:`ConfigError` for an out-of-range value; return self."""
        if not (math.isfinite(self.force_limit) and 0.0 <= self.force_limit <= HARD_FORCE_LIMIT):
            raise ConfigError(f'force_limit must be in [0, {HARD_FORCE_LIMIT}] N, got {self.force_limit}')
        if not (math.isfinite(self.ramp_time) and 0.0 <= self.ramp_time <= 10.0):
            raise ConfigError(f'ramp_time must be in [0, 10] s, got {self.ramp_time}')
        lo, hi = WATCHDOG_RANGE
        if not (math.isfinite(self.watchdog_timeout) and lo <= self.watchdog_timeout <= hi):
            raise ConfigError(f'watchdog_timeout must be in [{lo}, {hi}] s, got {self.watchdog_timeout}')
        if not (math.isfinite(self.max_command_lag) and 0.0 <= self.max_command_lag <= 10.0):
            raise ConfigError(f'max_command_lag must be in [0, 10] s, got {self.max_command_lag}')
        if not self.frame_id:
            raise ConfigError('frame_id must not be empty')
        return self


@dataclass
class CommandResult:
    """Outcome of one force command."""

    accepted: bool
    reason: str = ''          # why it was rejected ('nan', 'frame', 'stale'), '' if accepted
    clamped: bool = False


@dataclass
class SafetyStatus:
    """Snapshot of the safety chain, as DeviceState reports it."""

    force_enabled: bool = False
    force_clamped: bool = False
    watchdog_tripped: bool = False
    commanded_force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    command_age: float = -1.0   # [s], -1 before the first valid command
    rejected_commands: int = 0
    ramp: float = 0.0           # current ramp factor 0..1

    def flags(self) -> tuple:
        """The boolean part, used to publish DeviceState on change."""
        return (self.force_enabled, self.force_clamped, self.watchdog_tripped)


class ForceSafety:
    """Clamp, ramp, watchdog and input validation for device force commands.

    Times are seconds on one monotonic clock chosen by the caller (``time.monotonic()`` in the node).
    """

    def __init__(self, config: SafetyConfig | None = None) -> None:
        self.config = (config or SafetyConfig()).validate()
        self._lock = threading.Lock()
        self._force = np.zeros(3)         # newest accepted (clamped) command
        self._last_cmd_time: float | None = None
        self._enable_time: float | None = None
        self._enabled = False
        self._clamped = False
        self._tripped = False
        self._rejected = 0
        self._newest_pose_stamp: float | None = None
        self._output = np.zeros(3)
        self._ramp = 0.0
        self.trip_count = 0

    def set_config(self, config: SafetyConfig) -> None:
        """Replace the parameters (validated first; the state is kept)."""
        config.validate()
        with self._lock:
            self.config = config

    def note_pose(self, stamp: float) -> None:
        """Record the stamp [s] of the newest published pose (for the stale-reply check)."""
        with self._lock:
            self._newest_pose_stamp = stamp

    def command(self, force, frame_id: str, now: float, stamp: float | None = None) -> CommandResult:
        """Offer a force command [N] in ``frame_id`` received at ``now``; ``stamp`` = its header stamp."""
        vec = np.asarray(force, dtype=float).reshape(-1)
        cfg = self.config
        with self._lock:
            if vec.shape != (3,) or not np.all(np.isfinite(vec)):
                self._rejected += 1
                return CommandResult(False, 'nan')
            if frame_id != cfg.frame_id and not (cfg.accept_empty_frame and frame_id == ''):
                self._rejected += 1
                return CommandResult(False, 'frame')
            if (cfg.max_command_lag > 0.0 and stamp is not None and stamp > 0.0
                    and self._newest_pose_stamp is not None
                    and self._newest_pose_stamp - stamp > cfg.max_command_lag):
                self._rejected += 1
                return CommandResult(False, 'stale')
            norm = float(np.linalg.norm(vec))
            limit = min(cfg.force_limit, HARD_FORCE_LIMIT)
            clamped = norm > limit
            if clamped:
                vec = vec * (limit / norm)
            self._force = vec
            self._clamped = clamped
            self._last_cmd_time = now
            if not self._enabled or self._tripped:
                # Enable (first valid command) or re-enable after a trip: ramp up from zero.
                self._enabled = True
                self._tripped = False
                self._enable_time = now
            return CommandResult(True, '', clamped)

    def output(self, now: float) -> np.ndarray:
        """The force [N] the device must render at ``now`` (zero when disabled or tripped)."""
        cfg = self.config
        with self._lock:
            if not self._enabled:
                out = np.zeros(3)
                self._ramp = 0.0
            else:
                if not self._tripped and now - self._last_cmd_time > cfg.watchdog_timeout:
                    self._tripped = True
                    self.trip_count += 1
                if self._tripped:
                    out = np.zeros(3)
                    self._ramp = 0.0
                else:
                    if cfg.ramp_time > 0.0:
                        self._ramp = min(1.0, max(0.0, (now - self._enable_time) / cfg.ramp_time))
                    else:
                        self._ramp = 1.0
                    out = self._force * self._ramp
            self._output = out
            return out.copy()

    def status(self, now: float) -> SafetyStatus:
        """Snapshot for DeviceState (``commanded_force`` is the last :meth:`output`)."""
        with self._lock:
            age = -1.0 if self._last_cmd_time is None else max(0.0, now - self._last_cmd_time)
            return SafetyStatus(self._enabled and not self._tripped, self._clamped, self._tripped,
                                self._output.copy(), age, self._rejected, self._ramp)
