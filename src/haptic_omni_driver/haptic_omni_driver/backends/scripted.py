"""Scripted backend: synthetic, human-like stylus motion (pure generator + a timed backend).

The script is a sequence of minimum-jerk segments (Flash & Hogan 1985: the position profile
x(s) = x0 + (x1 - x0)(10 s^3 - 15 s^4 + 6 s^5), s = t/T, which has zero velocity and zero
acceleration at both ends, the smoothest point-to-point human reach):

    approach  home -> above the target (approach_height along -press_axis)
    press     -> press_depth below the target surface point, along press_axis
    hold      stay (hold_time)
    pull      drag laterally by pull_distance along pull_axis while pressed
    release   back up above the surface
    sweep     down to sweep_depth at -sweep_length/2, stroke to +sweep_length/2, up again
    return    back home

A script of one's own replaces it with the parameter ``script`` (:func:`parse_script`): one step
per entry, ``move|press|lift x y z T`` (a minimum-jerk move to an absolute device-frame point) or
``hold|close|open T`` (stay, the jaw = button 1 as it was, closed or open).

Optional physiological tremor (sum of sinusoids at 8-12 Hz, a few tenths of a millimetre peak) and
encoder quantisation (the Omni resolves ~0.055 mm) make it look like a real hand on a real device.
Everything is deterministic for a given seed. Positions are in the device frame ``omni_base``
(OpenHaptics: x right, y up, z towards the user), metres.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .base import Backend, BackendSink, Sample


def min_jerk(s: np.ndarray | float) -> np.ndarray | float:
    """Normalised minimum-jerk profile: 0 at s=0, 1 at s=1 (s clipped to [0, 1])."""
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)


def min_jerk_derivatives(p0, p1, duration: float, t):
    """Position, velocity and acceleration of a minimum-jerk move p0 -> p1 in ``duration`` at ``t``.

    Args:
        p0, p1: (3,) start and end points [m].
        duration: T [s] > 0.
        t: time(s) [s] since the start (scalar or (M,)); clipped to [0, T].

    Returns:
        (pos, vel, acc), each (M, 3) (or (3,) for scalar t).
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    t = np.asarray(t, float)
    s = np.clip(t / duration, 0.0, 1.0)[..., None]
    d = p1 - p0
    pos = p0 + d * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
    vel = d * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration
    acc = d * (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration ** 2
    return pos, vel, acc


#: [s] allowed duration of a segment (a zero one has no minimum-jerk profile)
DURATION_RANGE = (0.01, 600.0)
#: [m] largest |coordinate| of a scripted point: well beyond the Omni's reach (about 0.16 x 0.12 x
#: 0.07 m around its origin), so only a typo (mm for m) trips it
WORKSPACE_BOUND = 0.2
#: steps of a custom script that move to x y z in T seconds (the name only labels the phase)
MOVE_STEPS = ('move', 'press', 'lift')
#: steps that stay put for T seconds, and what they do to the jaw (None: leave it as it is)
STAY_STEPS = {'hold': None, 'close': True, 'open': False}


@dataclass
class Segment:
    """One minimum-jerk move (a hold is a move to the same point)."""

    name: str
    start: np.ndarray
    end: np.ndarray
    duration: float
    button1: bool = False


@dataclass
class ScriptConfig:
    """Parameters of the script (device frame, SI units)."""

    home: list = field(default_factory=lambda: [0.0, 0.06, 0.0])     # [m] start/end point
    target: list = field(default_factory=lambda: [0.0, 0.0, 0.0])    # [m] surface point to press
    press_axis: list = field(default_factory=lambda: [0.0, -1.0, 0.0])  # pressing direction
    pull_axis: list = field(default_factory=lambda: [1.0, 0.0, 0.0])    # lateral pull direction
    approach_height: float = 0.01   # [m] above the surface before pressing
    press_depth: float = 0.008      # [m] indentation below the surface point
    pull_distance: float = 0.01     # [m] lateral drag while pressed
    sweep_depth: float = 0.003      # [m] indentation during the sweep
    sweep_length: float = 0.04      # [m] length of the sweep stroke
    approach_time: float = 1.0      # [s]
    press_time: float = 0.8         # [s]
    hold_time: float = 1.0          # [s]
    pull_time: float = 0.8          # [s]
    release_time: float = 0.6       # [s]
    sweep_time: float = 2.0         # [s] for the stroke (descent/ascent take release_time each)
    return_time: float = 1.0        # [s]
    tremor_amplitude: float = 1.5e-4  # [m] peak per axis; 0 = no tremor
    tremor_band: tuple = (8.0, 12.0)  # [Hz]
    quantisation: float = 0.0       # [m] encoder resolution; 0 = continuous
    seed: int = 0
    script: list = field(default_factory=list)  # steps of parse_script; empty: the built-in script

    def validate(self) -> 'ScriptConfig':
        """Raise :class:`ConfigError` on inconsistent values; return self."""
        for name in ('home', 'target', 'press_axis', 'pull_axis'):
            vec = np.asarray(getattr(self, name), float)
            if vec.shape != (3,) or not np.all(np.isfinite(vec)):
                raise ConfigError(f'{name} must be 3 finite numbers, got {getattr(self, name)!r}')
        for name in ('press_axis', 'pull_axis'):
            if np.linalg.norm(np.asarray(getattr(self, name), float)) < 1e-9:
                raise ConfigError(f'{name} must not be the zero vector')
        for name in ('approach_height', 'press_depth', 'pull_distance', 'sweep_depth', 'sweep_length',
                     'tremor_amplitude', 'quantisation'):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 0.2):
                raise ConfigError(f'{name} must be in [0, 0.2] m, got {value}')
        for name in ('approach_time', 'press_time', 'hold_time', 'pull_time', 'release_time',
                     'sweep_time', 'return_time'):
            value = getattr(self, name)
            if not (np.isfinite(value) and DURATION_RANGE[0] <= value <= DURATION_RANGE[1]):
                raise ConfigError(f'{name} must be in [{DURATION_RANGE[0]:g}, {DURATION_RANGE[1]:g}] s, '
                                  f'got {value}')
        lo, hi = self.tremor_band
        if not (0.0 < lo <= hi < 100.0):
            raise ConfigError(f'tremor_band must be 0 < low <= high < 100 Hz, got {self.tremor_band}')
        return self


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def build_script(cfg: ScriptConfig) -> list[Segment]:
    """The press/hold/pull/release/sweep script as a list of minimum-jerk segments."""
    cfg.validate()
    home, target = np.asarray(cfg.home, float), np.asarray(cfg.target, float)
    down, lateral = _unit(cfg.press_axis), _unit(cfg.pull_axis)
    above = target - cfg.approach_height * down
    pressed = target + cfg.press_depth * down
    pulled = pressed + cfg.pull_distance * lateral
    released = pulled - (cfg.press_depth + cfg.approach_height) * down
    sweep_a = target - 0.5 * cfg.sweep_length * lateral
    sweep_b = target + 0.5 * cfg.sweep_length * lateral
    segs = [
        Segment('approach', home, above, cfg.approach_time),
        Segment('press', above, pressed, cfg.press_time),
        Segment('hold', pressed, pressed, cfg.hold_time),
        Segment('pull', pressed, pulled, cfg.pull_time),
        Segment('release', pulled, released, cfg.release_time),
        Segment('sweep', released, sweep_a - cfg.approach_height * down, cfg.release_time),
        Segment('sweep', sweep_a - cfg.approach_height * down, sweep_a + cfg.sweep_depth * down,
                cfg.release_time),
        Segment('sweep', sweep_a + cfg.sweep_depth * down, sweep_b + cfg.sweep_depth * down,
                cfg.sweep_time),
        Segment('sweep', sweep_b + cfg.sweep_depth * down, sweep_b - cfg.approach_height * down,
                cfg.release_time),
        Segment('return', sweep_b - cfg.approach_height * down, home, cfg.return_time),
    ]
    return segs


def parse_script(steps: list[str], home) -> list[Segment]:
    """A custom script, one step per entry, as minimum-jerk segments starting at ``home``.

    Grammar (whitespace-separated; positions absolute in the device frame [m], durations [s]):

        move x y z T     minimum-jerk move to (x, y, z) in T
        press x y z T    the same (the name labels the phase: pressing into the tissue)
        lift x y z T     the same (lifting what the jaw holds)
        hold T           stay T
        close T          close the jaw (button 1 down) and stay T
        open T           open the jaw (button 1 up) and stay T

    The jaw starts open and stays as the last close/open left it, through moves and holds. T lies
    in DURATION_RANGE and every coordinate within +-WORKSPACE_BOUND.

    Raises:
        ConfigError: naming the entry, for an unknown step, a wrong count of numbers, a number that
            is not one or not finite, a duration out of range or a point beyond the bound.
    """
    here = np.asarray(home, float)
    closed = False
    segments = []
    for k, entry in enumerate(steps):
        where = f'script[{k}] {entry!r}'
        words = str(entry).split()
        if not words:
            raise ConfigError(f'{where}: empty step')
        name, args = words[0], words[1:]
        if name not in MOVE_STEPS and name not in STAY_STEPS:
            raise ConfigError(f'{where}: unknown step {name!r} (one of '
                              f'{", ".join(MOVE_STEPS + tuple(STAY_STEPS))})')
        want = 4 if name in MOVE_STEPS else 1
        if len(args) != want:
            usage = f'{name} x y z T' if want == 4 else f'{name} T'
            raise ConfigError(f'{where}: {name} takes {want} number{"s" * (want > 1)} ({usage}), '
                              f'got {len(args)}')
        try:
            numbers = [float(a) for a in args]
        except ValueError:
            raise ConfigError(f'{where}: not a number in {" ".join(args)!r}') from None
        if not all(np.isfinite(numbers)):
            raise ConfigError(f'{where}: non-finite number')
        duration = numbers[-1]
        if not DURATION_RANGE[0] <= duration <= DURATION_RANGE[1]:
            raise ConfigError(f'{where}: duration {duration:g} s outside [{DURATION_RANGE[0]:g}, '
                              f'{DURATION_RANGE[1]:g}] s')
        if name in MOVE_STEPS:
            end = np.array(numbers[:3])
            if np.abs(end).max() > WORKSPACE_BOUND:
                raise ConfigError(f'{where}: point beyond the workspace (|coordinate| <= '
                                  f'{WORKSPACE_BOUND:g} m; positions are in metres)')
        else:
            end = here
            if STAY_STEPS[name] is not None:
                closed = STAY_STEPS[name]
        segments.append(Segment(name, here, end, duration, closed))
        here = end
    return segments


def script_segments(cfg: ScriptConfig) -> list[Segment]:
    """The script the backend plays: ``cfg.script`` if it has steps, else the built-in one."""
    cfg.validate()
    return parse_script(cfg.script, cfg.home) if cfg.script else build_script(cfg)


def script_duration(segments: list[Segment]) -> float:
    """Total duration [s] of a script."""
    return float(sum(s.duration for s in segments))


def tremor(t: np.ndarray, amplitude: float, band=(8.0, 12.0), seed: int = 0,
           n_components: int = 3) -> np.ndarray:
    """Physiological tremor [m], (M, 3): per axis a sum of sinusoids with frequencies in ``band``.

    The components' amplitudes add up to ``amplitude``, so the peak never exceeds it.
    """
    t = np.atleast_1d(np.asarray(t, float))
    if amplitude <= 0.0:
        return np.zeros((t.size, 3))
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(band[0], band[1], size=(3, n_components))
    phases = rng.uniform(0.0, 2 * np.pi, size=(3, n_components))
    weights = rng.uniform(0.5, 1.0, size=(3, n_components))
    weights *= amplitude / weights.sum(axis=1, keepdims=True)
    arg = 2 * np.pi * freqs[None] * t[:, None, None] + phases[None]
    return np.sum(weights[None] * np.sin(arg), axis=2)


def quantise(positions: np.ndarray, resolution: float) -> np.ndarray:
    """Round positions to the encoder resolution [m] (no-op for resolution 0)."""
    if resolution <= 0.0:
        return positions
    return np.round(positions / resolution) * resolution


def sample_script(segments: list[Segment], t) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Noise-free positions (M, 3), button1 (M,) and phase names at times ``t`` [s] from the start.

    Times past the end hold the last point.
    """
    t = np.atleast_1d(np.asarray(t, float))
    starts = np.cumsum([0.0] + [s.duration for s in segments])
    idx = np.clip(np.searchsorted(starts, t, side='right') - 1, 0, len(segments) - 1)
    pos = np.empty((t.size, 3))
    buttons = np.zeros(t.size, bool)
    for k, seg in enumerate(segments):
        mask = idx == k
        if np.any(mask):
            pos[mask] = min_jerk_derivatives(seg.start, seg.end, seg.duration, t[mask] - starts[k])[0]
            buttons[mask] = seg.button1
    return pos, buttons, [segments[i].name for i in idx]


def generate_trajectory(cfg: ScriptConfig, rate: float = 1000.0, loops: int = 1):
    """The whole script sampled at ``rate`` [Hz] with tremor and quantisation.

    Returns:
        (t (M,) [s], positions (M, 3) [m], button1 (M,) bool, phases list[str]).
    """
    if not (np.isfinite(rate) and 1.0 <= rate <= 10000.0):
        raise ConfigError(f'rate must be in [1, 10000] Hz, got {rate}')
    segs = script_segments(cfg)
    total = script_duration(segs)
    n = int(round(total * rate * loops)) + 1
    t = np.arange(n) / rate
    pos, buttons, phases = sample_script(segs, np.mod(t, total) if loops > 1 else t)
    pos = pos + tremor(t, cfg.tremor_amplitude, cfg.tremor_band, cfg.seed)
    return t, quantise(pos, cfg.quantisation), buttons, phases


class ScriptedBackend(Backend):
    """Plays the script in real time at ``rate`` Hz (wall clock stamps).

    With ``loop`` the script starts again at its end. Without, the stylus then rests at the
    script's last point and the driver keeps publishing it, as a device held still does (the graph
    stays live and says so in one log line), unless ``exit_on_end``: then the driver ends there.
    """

    name = 'scripted'

    def __init__(self, cfg: ScriptConfig, rate: float = 1000.0, loop: bool = True,
                 exit_on_end: bool = False, clock_ns=time.time_ns) -> None:
        super().__init__()
        if not (np.isfinite(rate) and 1.0 <= rate <= 10000.0):
            raise ConfigError(f'rate must be in [1, 10000] Hz, got {rate}')
        self.cfg = cfg.validate()
        self.segments = script_segments(cfg)
        self.duration = script_duration(self.segments)
        self.rate = rate
        self.loop = loop
        self.exit_on_end = exit_on_end
        self.clock_ns = clock_ns
        steps = f'{len(cfg.script)} steps, ' if cfg.script else ''
        self.source = f'script({steps}seed={cfg.seed}, {self.duration:.2f} s)'

    def run(self, sink: BackendSink) -> None:
        if not sink.wait_for_subscribers():
            return
        period = 1.0 / self.rate
        t0 = time.monotonic()
        k = 0
        ended = False
        while not self.stopping:
            t = k * period
            if not self.loop and not ended and t > self.duration + 1e-9:
                ended = True
                sink.on_finished(self.summary(k), 0)
                if self.exit_on_end:
                    return
            # past the end (no loop) the script holds its last point: the hand at rest
            ts = np.mod(t, self.duration) if self.loop else t
            pos, buttons, phases = sample_script(self.segments, ts)
            p = pos[0] + tremor(t, self.cfg.tremor_amplitude, self.cfg.tremor_band, self.cfg.seed)[0]
            p = quantise(p, self.cfg.quantisation)
            sink.on_sample(Sample(self.clock_ns(), p, buttons=(bool(buttons[0]), False),
                                  phase='rest' if ended else phases[0]))
            k += 1
            # Absolute deadlines: no drift, and a late tick is not followed by a burst.
            delay = t0 + k * period - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -0.1:
                t0 = time.monotonic() - k * period

    def summary(self, poses: int) -> str:
        """The line logged when the script (one pass, ``poses`` samples) has been played."""
        text = f'script finished: {poses} poses, one pass of {self.duration:.2f} s'
        if self.exit_on_end:
            return text
        return (text + '; the stylus now rests at its last point and the driver keeps publishing '
                'it (loop:=true repeats the script, exit_on_end:=true ends the driver here)')


def script_messages(cfg: ScriptConfig, rate: float = 1000.0, t0_ns: int = 1_700_000_000_000_000_000,
                    loops: int = 1, frame_id: str = 'omni_base', state_rate: float = 100.0) -> list:
    """The script as bag messages ``[(topic, msgtype, log_time_ns, rosbags_msg), ...]``.

    Poses on ``/omni/pose`` at ``rate`` (header stamp = log time = ``t0_ns`` + t) and, if
    ``state_rate`` > 0, DeviceState on ``/omni/state`` carrying the script's button1 (no force
    fields: a scripted session has no device). Feed the result to :func:`.bag_writer.write_bag`.
    """
    from ..bag_types import POSE_TYPE, STATE_TYPE, typestore

    types = typestore().types
    Time, Header = types['builtin_interfaces/msg/Time'], types['std_msgs/msg/Header']
    Pose, Point, Quat = (types['geometry_msgs/msg/Pose'], types['geometry_msgs/msg/Point'],
                         types['geometry_msgs/msg/Quaternion'])
    PoseStamped, State = types[POSE_TYPE], types[STATE_TYPE]
    Vec = types['geometry_msgs/msg/Vector3']
    t, pos, buttons, _ = generate_trajectory(cfg, rate, loops)
    out = []
    state_every = max(1, int(round(rate / state_rate))) if state_rate > 0 else 0
    for k in range(t.size):
        stamp = int(t0_ns + round(t[k] * 1e9))
        header = Header(Time(*divmod(stamp, 1_000_000_000)), frame_id)
        out.append(('/omni/pose', POSE_TYPE, stamp,
                    PoseStamped(header, Pose(Point(*map(float, pos[k])), Quat(0.0, 0.0, 0.0, 1.0)))))
        if state_every and k % state_every == 0:
            out.append(('/omni/state', STATE_TYPE, stamp, State(
                header, bool(buttons[k]), False, False, False, False, True, Vec(0.0, 0.0, 0.0),
                0.0, -1.0, 0, 'scripted', f'script(seed={cfg.seed})')))
    return out


def write_script_bag(path, cfg: ScriptConfig, rate: float = 1000.0, **kw):
    """Write the script to a new rosbag2 MCAP bag folder (see :func:`script_messages`)."""
    from ..bag_writer import write_bag

    return write_bag(path, script_messages(cfg, rate, **kw))
