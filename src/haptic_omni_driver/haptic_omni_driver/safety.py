"""Force safety chain between the simulator's force commands and the device (no rclpy).

Every force that reaches a device (or, for the replay and scripted backends, the virtual device whose
output DeviceState reports) passes through :class:`ForceSafety`, in this order:

1. input checks (:meth:`ForceSafety.command`): commands with NaN/inf components, in a frame other
   than the device frame, or (with ``max_command_lag`` > 0, the default) whose stamp does not answer a recent pose
   are rejected and counted;
2. norm clamp: the command's norm is clamped to ``force_limit`` (never above
   :data:`HARD_FORCE_LIMIT`), exactly: the clamped norm never exceeds the limit by rounding;
3. watchdog (:meth:`ForceSafety.output`): the output is zeroed at once when no valid command was
   received for ``watchdog_timeout`` of the driver's running time (the simulator stopped or went
   silent). A command counts from its reception; an output more than :data:`MAX_TICK_CREDIT` after
   the previous one counts as that long, because the process was not running in between (it could
   neither receive nor render), so its own stall never trips the watchdog on a clean stream;
4. enable ramp: output starts only with the first valid command and ramps up linearly over
   ``ramp_time`` (again after each watchdog trip);
5. force-rate limit: the output moves towards the ramped command by at most ``max_force_rate`` x dt
   per output (dt counted up to :data:`MAX_TICK_CREDIT`, so a late tick earns no big step), so a
   step in the command never kicks the device; a zero output (disabled, tripped, or a zero command)
   is always applied at once;
6. final clamp of the output to the current ``force_limit`` (a lowered limit applies at once).

Above the chain, the device's operating state (:mod:`haptic_omni_driver.crtk`) may hold the output
at zero (:meth:`ForceSafety.allow_output`: a disabled or paused device renders no force); allowed
again, the output ramps up from zero as after a watchdog trip.

Times are seconds on one monotonic clock chosen by the caller. A command's time is when it was
*received*, not when it was processed: the watchdog then measures the command's true age even when
the process handles it late. The class is thread-safe: commands and outputs may come from different
threads (the servo loop, the executor).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from tissue_common.force import CONTINUOUS_FORCE_LIMIT, HARD_FORCE_LIMIT, clamp_norm

from .errors import ConfigError

#: [s] allowed watchdog range: below 10 ms a 1 kHz loop with DDS jitter trips spuriously; above
#: 50 ms a runaway force is felt.
WATCHDOG_RANGE = (0.005, 0.05)
#: [N/s] default force-rate limit: tissue contact changes well under 1 N per 10 ms pass unchanged,
#: a 0 -> 3.3 N step takes 33 ms instead of one servo tick.
DEFAULT_FORCE_RATE = 100.0
#: [N/s] allowed max_force_rate range (0 = off).
FORCE_RATE_RANGE = (0.0, 10000.0)
#: [s] longest interval between two outputs that counts in full, for the watchdog and the rate
#: limit: the slowest servo period. A later output means the process was not running (descheduled,
#: or the GIL held elsewhere): that stall neither ages the command nor earns a large force step.
MAX_TICK_CREDIT = 0.01
#: [s] how far a reply's stamp may lie ahead of the newest pose stamp. The simulator answers a pose
#: with that pose's own stamp, so a valid reply is never newer; this only absorbs float rounding.
STAMP_TOLERANCE = 1e-6
#: [s] default stale-reply window: a reply must answer a pose at most this older than the newest one
#: published (a zero, negative or future stamp answers none). The simulator answers within a few
#: milliseconds; a force that answers a pose 0.1 s old no longer belongs to where the hand is.
DEFAULT_COMMAND_LAG = 0.1


@dataclass
class SafetyConfig:
    """Parameters of the safety chain (SI units)."""

    force_limit: float = CONTINUOUS_FORCE_LIMIT   # [N] norm clamp
    ramp_time: float = 0.5                        # [s] linear ramp after enabling; 0 = none
    watchdog_timeout: float = 0.02                # [s] zero the force when commands stop this long
    max_command_lag: float = DEFAULT_COMMAND_LAG  # [s] reject replies older than newest pose; 0 = off
    frame_id: str = 'omni_base'                   # device frame commands must be expressed in
    accept_empty_frame: bool = True               # treat frame_id '' as the device frame
    max_force_rate: float = DEFAULT_FORCE_RATE    # [N/s] output rate-of-change limit; 0 = off

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
        lo, hi = FORCE_RATE_RANGE
        if not (math.isfinite(self.max_force_rate) and lo <= self.max_force_rate <= hi):
            raise ConfigError(f'max_force_rate must be in [{lo:g}, {hi:g}] N/s, got '
                              f'{self.max_force_rate}')
        if not self.frame_id:
            raise ConfigError('frame_id must not be empty')
        return self


@dataclass
class CommandResult:
    """Outcome of one force command."""

    accepted: bool
    #: why it was rejected, '' if accepted: 'nan', 'frame', 'stale' (stamp older than the newest
    #: pose by more than max_command_lag, or none), 'future' (stamp ahead of the newest pose),
    #: 'no_pose' (no pose published yet, so nothing a reply could answer)
    reason: str = ''
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
    rate_limited: bool = False  # the last output was held back by max_force_rate
    rejected_by_reason: dict = field(default_factory=dict)   # reason -> count

    def flags(self) -> tuple:
        """The boolean part, used to publish DeviceState on change."""
        return (self.force_enabled, self.force_clamped, self.watchdog_tripped)


class ForceSafety:
    """Validation, clamp, watchdog, ramp and rate limit for device force commands.

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
        self._rejected: dict[str, int] = {}
        self._newest_pose_stamp: float | None = None
        self._output = np.zeros(3)
        self._output_time: float | None = None
        self._stalled = 0.0               # [s] of the newest command's age the process was stalled
        self._ramp = 0.0
        self._rate_limited = False
        self._allowed = True              # the operating state lets the device render force
        self.trip_count = 0
        self.rate_limited_count = 0       # outputs held back by max_force_rate

    def set_config(self, config: SafetyConfig) -> None:
        """Replace the parameters (validated first; the state is kept)."""
        config.validate()
        with self._lock:
            self.config = config

    def allow_output(self, allowed: bool, now: float) -> None:
        """Let the device render force (True) or hold its output at zero (False), from ``now``.

        Allowed again, the force ramps up from zero over ``ramp_time``."""
        with self._lock:
            if allowed and not self._allowed:
                self._enable_time = now
            self._allowed = bool(allowed)

    def note_pose(self, stamp: float) -> None:
        """Record the stamp [s] of the newest pose, before it is published (stale-reply check)."""
        with self._lock:
            self._newest_pose_stamp = stamp

    # -- commands ------------------------------------------------------------------------------
    def command(self, force, frame_id: str, now: float, stamp: float | None = None,
                answers_pose: bool = True) -> CommandResult:
        """Offer a force command [N] in ``frame_id`` received at ``now``; ``stamp`` = its header stamp.

        ``answers_pose`` False: a setpoint that answers no pose (CRTK ``servo_cf``), which skips
        the stale-reply check; every other step applies."""
        vec = np.asarray(force, dtype=float).reshape(-1)
        cfg = self.config
        with self._lock:
            reason = self._rejection(vec, frame_id, stamp, cfg, answers_pose)
            if reason:
                self._rejected[reason] = self._rejected.get(reason, 0) + 1
                return CommandResult(False, reason)
            vec, clamped = clamp_norm(vec, min(cfg.force_limit, HARD_FORCE_LIMIT))
            self._force = vec
            self._clamped = clamped
            self._last_cmd_time = now
            self._stalled = 0.0
            if not self._enabled or self._tripped:
                # Enable (first valid command) or re-enable after a trip: ramp up from zero.
                self._enabled = True
                self._tripped = False
                self._enable_time = now
            return CommandResult(True, '', clamped)

    def _rejection(self, vec: np.ndarray, frame_id: str, stamp: float | None,
                   cfg: SafetyConfig, answers_pose: bool = True) -> str:
        """Why a command must be rejected ('' if it may pass)."""
        if vec.shape != (3,) or not np.all(np.isfinite(vec)):
            return 'nan'
        if frame_id != cfg.frame_id and not (cfg.accept_empty_frame and frame_id == ''):
            return 'frame'
        if cfg.max_command_lag > 0.0 and answers_pose:
            return self._stamp_problem(stamp, cfg.max_command_lag)
        return ''

    def _stamp_problem(self, stamp: float | None, max_lag: float) -> str:
        """'' if ``stamp`` answers a pose within ``max_lag`` of the newest one, else the reason."""
        newest = self._newest_pose_stamp
        if newest is None:
            return 'no_pose'
        if stamp is None or not math.isfinite(stamp) or stamp < newest - max_lag:
            return 'stale'   # a zero or negative stamp is older than any window
        if stamp > newest + STAMP_TOLERANCE:
            return 'future'
        return ''

    # -- output --------------------------------------------------------------------------------
    def output(self, now: float) -> np.ndarray:
        """The force [N] the device must render at ``now`` (zero when disabled or tripped)."""
        cfg = self.config
        with self._lock:
            target = self._ramped_command(now, cfg)
            out = self._rate_limit(target, now, cfg.max_force_rate)
            out, _ = clamp_norm(out, min(cfg.force_limit, HARD_FORCE_LIMIT))
            self._output, self._output_time = out, now
            return out.copy()

    def _ramped_command(self, now: float, cfg: SafetyConfig) -> np.ndarray:
        """Watchdog and enable ramp: the force wanted at ``now`` before the rate limit."""
        if not self._enabled or not self._allowed:
            self._ramp = 0.0
            return np.zeros(3)
        if not self._tripped and self._silence(now) > cfg.watchdog_timeout:
            self._tripped = True
            self.trip_count += 1
        if self._tripped:
            self._ramp = 0.0
            return np.zeros(3)
        if cfg.ramp_time > 0.0:
            self._ramp = min(1.0, max(0.0, (now - self._enable_time) / cfg.ramp_time))
        else:
            self._ramp = 1.0
        return self._force * self._ramp

    def _silence(self, now: float) -> float:
        """[s] of the driver's running time since the newest valid command was received."""
        if self._output_time is not None:
            # the part of the gap since the previous output (after the command) beyond a tick's
            # worth is a stall of this process: no command could be received or rendered in it
            start = max(self._output_time, self._last_cmd_time)
            self._stalled += max(0.0, now - start - MAX_TICK_CREDIT)
        return now - self._last_cmd_time - self._stalled

    def _rate_limit(self, target: np.ndarray, now: float, rate: float) -> np.ndarray:
        """``target``, or the point at most ``rate`` x dt from the previous output towards it."""
        self._rate_limited = False
        if rate <= 0.0 or not np.any(target):
            return target   # off, or a zeroing: always at once
        dt = 0.0 if self._output_time is None else min(max(0.0, now - self._output_time),
                                                       MAX_TICK_CREDIT)
        step, limited = clamp_norm(target - self._output, rate * dt)
        if not limited:
            return target
        self._rate_limited = True
        self.rate_limited_count += 1
        return self._output + step

    def status(self, now: float) -> SafetyStatus:
        """Snapshot for DeviceState (``commanded_force`` is the last :meth:`output`)."""
        with self._lock:
            age = -1.0 if self._last_cmd_time is None else max(0.0, now - self._last_cmd_time)
            return SafetyStatus(self._enabled and self._allowed and not self._tripped, self._clamped,
                                self._tripped,
                                self._output.copy(), age, sum(self._rejected.values()), self._ramp,
                                self._rate_limited, dict(self._rejected))
