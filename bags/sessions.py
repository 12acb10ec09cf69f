"""Device sessions of the bundled bags: human-like stylus scripts built from the scripted backend.

Each session is a list of minimum-jerk segments (``haptic_omni_driver.backends.scripted``: the same
generator the ``scripted`` backend plays), sampled at the device rate with the scripted backend's
physiological tremor (8-12 Hz) and the Omni's encoder quantisation. Positions are in the device
frame ``omni_base`` (x right, y up, z towards the user) relative to a surface point ``surface`` of
the tissue and a pressing direction ``down`` (default -y). Deterministic for a given seed.

A session of several instruments (``bimanual``) has one script per instrument, keyed by the
instrument's name (its namespace: ``/<name>/omni/pose``); a session of one instrument is keyed by
``''`` (``/omni/pose``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from haptic_omni_driver.backends.scripted import Segment, quantise, sample_script, tremor

#: [m] the Omni's encoder resolution (~0.055 mm)
OMNI_QUANTISATION = 5.5e-5
#: [m] peak physiological tremor per axis
TREMOR = 1.5e-4


@dataclass
class Geometry:
    """Where the tissue is in the device frame."""

    surface: tuple = (0.0, 0.0, 0.0)   # [m] a point on the tissue surface (device frame)
    down: tuple = (0.0, -1.0, 0.0)     # pressing direction (into the tissue)
    lateral: tuple = (1.0, 0.0, 0.0)   # first in-surface direction (pull, sweep)
    lateral2: tuple = (0.0, 0.0, 1.0)  # second in-surface direction

    def point(self, a: float = 0.0, b: float = 0.0, depth: float = 0.0) -> np.ndarray:
        """Surface point + a along lateral + b along lateral2 + depth along down [m]."""
        return (np.asarray(self.surface, float) + a * np.asarray(self.lateral, float)
                + b * np.asarray(self.lateral2, float) + depth * np.asarray(self.down, float))


class _Path:
    """Builds a segment list from consecutive targets."""

    def __init__(self, start: np.ndarray) -> None:
        self.pos = np.asarray(start, float)
        self.segments: list[Segment] = []

    def move(self, name: str, end, duration: float, button1: bool = False) -> '_Path':
        end = np.asarray(end, float)
        self.segments.append(Segment(name, self.pos, end, float(duration), button1))
        self.pos = end
        return self

    def hold(self, duration: float, button1: bool = False) -> '_Path':
        return self.move('hold', self.pos, duration, button1)


def press(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """Approach, press 6 mm into the surface, hold 1 s, release, retreat (3.6 s)."""
    p = _Path(g.point(depth=-0.02))
    p.move('approach', g.point(depth=-0.005), 0.6)
    p.move('press', g.point(depth=0.006), 0.8)
    p.hold(1.0)
    p.move('release', g.point(depth=-0.005), 0.6)
    p.move('retreat', g.point(depth=-0.02), 0.6)
    return p.segments


def pull(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """Press 5 mm, drag 12 mm laterally while pressed, hold, release (3.9 s)."""
    p = _Path(g.point(-0.006, depth=-0.02))
    p.move('approach', g.point(-0.006, depth=-0.005), 0.5)
    p.move('press', g.point(-0.006, depth=0.005), 0.7)
    p.move('pull', g.point(0.006, depth=0.005), 1.2)
    p.hold(0.4)
    p.move('release', g.point(0.006, depth=-0.005), 0.6)
    p.move('retreat', g.point(0.006, depth=-0.02), 0.5)
    return p.segments


def sweep(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """Descend 3 mm into the surface and stroke 40 mm across it, then lift (3.9 s)."""
    p = _Path(g.point(-0.02, depth=-0.015))
    p.move('approach', g.point(-0.02, depth=-0.004), 0.5)
    p.move('descend', g.point(-0.02, depth=0.003), 0.5)
    p.move('sweep', g.point(0.02, depth=0.003), 2.0)
    p.move('lift', g.point(0.02, depth=-0.004), 0.5)
    p.move('retreat', g.point(0.02, depth=-0.015), 0.4)
    return p.segments


def poke(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """Five quick 4 mm pokes at spots 5 mm apart (3.9 s)."""
    spots = (-0.01, -0.005, 0.0, 0.005, 0.01)
    p = _Path(g.point(spots[0], depth=-0.015))
    p.move('approach', g.point(spots[0], depth=-0.004), 0.4)
    for k, a in enumerate(spots):
        if k:
            p.move('shift', g.point(a, depth=-0.004), 0.2)
        p.move('poke', g.point(a, depth=0.004), 0.25)
        p.move('withdraw', g.point(a, depth=-0.004), 0.25)
    p.move('retreat', g.point(spots[-1], depth=-0.015), 0.5)
    return p.segments


def long_session(g: Geometry, rng: np.random.Generator, duration: float = 66.0) -> list[Segment]:
    """About a minute of mixed work over a 40 x 30 mm patch: presses, pulls, sweeps, pokes, pauses.

    Targets, depths (2-7 mm) and speeds are drawn from ``rng``; every move is minimum-jerk.
    """
    p = _Path(g.point(depth=-0.02))
    total = 0.0

    def spot():
        return rng.uniform(-0.02, 0.02), rng.uniform(-0.015, 0.015)

    while total < duration - 6.0:
        kind = rng.choice(['press', 'pull', 'sweep', 'poke', 'pause'], p=[0.3, 0.2, 0.2, 0.2, 0.1])
        a, b = spot()
        before = len(p.segments)
        if kind == 'pause':
            p.hold(rng.uniform(0.5, 1.5))
        else:
            p.move('approach', g.point(a, b, -0.005), rng.uniform(0.5, 0.9))
        if kind == 'press':
            d = rng.uniform(0.003, 0.007)
            p.move('press', g.point(a, b, d), rng.uniform(0.5, 1.0))
            p.hold(rng.uniform(0.5, 1.5))
            p.move('release', g.point(a, b, -0.005), rng.uniform(0.4, 0.8))
        elif kind == 'pull':
            d = rng.uniform(0.003, 0.006)
            ang = rng.uniform(0.0, 2 * np.pi)
            a2, b2 = a + 0.01 * np.cos(ang), b + 0.01 * np.sin(ang)
            p.move('press', g.point(a, b, d), rng.uniform(0.5, 0.9))
            p.move('pull', g.point(a2, b2, d), rng.uniform(0.8, 1.4))
            p.move('release', g.point(a2, b2, -0.005), rng.uniform(0.4, 0.8))
        elif kind == 'sweep':
            d = rng.uniform(0.002, 0.004)
            a2, b2 = -a, b + rng.uniform(-0.005, 0.005)
            p.move('descend', g.point(a, b, d), rng.uniform(0.4, 0.7))
            p.move('sweep', g.point(a2, b2, d), rng.uniform(1.5, 2.5))
            p.move('lift', g.point(a2, b2, -0.005), rng.uniform(0.4, 0.7))
        elif kind == 'poke':
            for _ in range(int(rng.integers(2, 5))):
                d = rng.uniform(0.003, 0.005)
                p.move('poke', g.point(a, b, d), rng.uniform(0.2, 0.35))
                p.move('withdraw', g.point(a, b, -0.004), rng.uniform(0.2, 0.35))
        total += sum(s.duration for s in p.segments[before:])
    p.move('retreat', g.point(depth=-0.02), 1.0)
    return p.segments


def grasp(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """Touch the top 10 mm from an edge, close the jaw (button 1), lift 15 mm, hold 0.5 s, open,
    retreat (3.4 s); replayed with ``grasp_input: button1`` (``system_graph.BAG_SIM_PARAMS``)."""
    p = _Path(g.point(0.03, depth=-0.02))
    p.move('approach', g.point(0.03, depth=-0.004), 0.6)
    p.move('touch', g.point(0.03, depth=0.001), 0.4)
    p.hold(0.2, True)
    p.move('lift', g.point(0.03, depth=-0.015), 0.8, True)
    p.hold(0.5, True)
    p.hold(0.3)
    p.move('retreat', g.point(0.03, depth=-0.03), 0.6)
    return p.segments


def bimanual(g: Geometry, rng: np.random.Generator) -> dict[str, list[Segment]]:
    """Two instruments, 2.8 s each: ``left`` touches the top 10 mm from an edge, closes its jaw
    (button 1), lifts 12 mm while retracting 10 mm outwards, holds, opens, retreats; ``right`` waits
    while the tissue is lifted, then presses 5 mm, 35 mm beside where the grasp took hold, holds and
    releases. Positions are each device's own; ``instrument_offsets`` (``system_graph.BAG_SIM_PARAMS``)
    place the two devices 20 mm either side of the model centre."""
    left = _Path(g.point(-0.01, depth=-0.02))
    left.move('approach', g.point(-0.01, depth=-0.004), 0.4)
    left.move('touch', g.point(-0.01, depth=0.001), 0.3)
    left.hold(0.1, True)
    left.move('retract', g.point(-0.02, depth=-0.012), 0.6, True)
    left.hold(0.9, True)
    left.hold(0.2)
    left.move('retreat', g.point(-0.02, depth=-0.03), 0.3)
    right = _Path(g.point(-0.015, depth=-0.02))
    right.hold(0.9)
    right.move('approach', g.point(-0.015, depth=-0.004), 0.3)
    right.move('press', g.point(-0.015, depth=0.005), 0.4)
    right.hold(0.4)
    right.move('release', g.point(-0.015, depth=-0.004), 0.4)
    right.move('retreat', g.point(-0.015, depth=-0.02), 0.4)
    return {'left': left.segments, 'right': right.segments}


def cut(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """A blade held upright (:data:`ORIENTATIONS`): approach above the top 15 mm left of the
    centre, plunge 5 mm, draw 30 mm across the top at 15 mm/s, lift out, retreat (3.9 s); replayed
    with a 20 mm blade (``system_graph.BAG_SIM_PARAMS``)."""
    p = _Path(g.point(-0.015, depth=-0.02))
    p.move('approach', g.point(-0.015, depth=-0.002), 0.5)
    p.move('plunge', g.point(-0.015, depth=0.005), 0.5)
    p.move('cut', g.point(0.015, depth=0.005), 2.0)
    p.move('lift', g.point(0.015, depth=-0.004), 0.4)
    p.move('retreat', g.point(0.015, depth=-0.02), 0.5)
    return p.segments


def needle(g: Geometry, rng: np.random.Generator) -> list[Segment]:
    """A needle held upright (:data:`ORIENTATIONS`): approach above the top 10 mm left of the
    centre, insert 25 mm at about 18 mm/s (it dents the surface, punctures, slides in), hold 0.4 s,
    withdraw, retreat (4.5 s); replayed with a 0.5 mm needle (``system_graph.BAG_SIM_PARAMS``)."""
    p = _Path(g.point(-0.01, depth=-0.02))
    p.move('approach', g.point(-0.01, depth=-0.003), 0.5)
    p.move('insert', g.point(-0.01, depth=0.025), 1.6)
    p.hold(0.4)
    p.move('withdraw', g.point(-0.01, depth=-0.004), 1.6)
    p.move('retreat', g.point(-0.01, depth=-0.02), 0.4)
    return p.segments


#: the stylus orientation (x, y, z, w) of a session's poses, device frame (others: identity): the
#: cut's and the needle's hold the stylus +z (the blade's edge, the needle's shaft) along the
#: device's +y, up out of the tissue
UPRIGHT = (-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))
ORIENTATIONS = {'cut': UPRIGHT, 'needle': UPRIGHT}


#: name -> (builder, description); a builder returns one script, or one per instrument by name
SESSIONS: dict[str, tuple[Callable, str]] = {
    'press': (press, 'press 6 mm, hold 1 s, release'),
    'pull': (pull, 'press 5 mm and drag 12 mm sideways'),
    'sweep': (sweep, 'stroke 40 mm across the surface at 3 mm depth'),
    'poke': (poke, 'five quick 4 mm pokes 5 mm apart'),
    'long': (long_session, 'about a minute of presses, pulls, sweeps and pokes over the surface'),
    'grasp': (grasp, 'grasp the top 10 mm from an edge, lift 15 mm, hold, release'),
    'bimanual': (bimanual, 'left grasps the top near an edge and retracts it, right presses beside it'),
    'cut': (cut, 'a blade plunged 5 mm and drawn 30 mm across the top'),
    'needle': (needle, 'a needle inserted 25 mm, held and withdrawn'),
}


def session_scripts(name: str, geometry: Geometry | None = None,
                    seed: int = 0) -> dict[str, list[Segment]]:
    """Each instrument's script of a session, by instrument name (``''``: the one instrument)."""
    scripts = SESSIONS[name][0](geometry or Geometry(), np.random.default_rng(seed))
    return scripts if isinstance(scripts, dict) else {'': scripts}


def topic(instrument: str, name: str) -> str:
    """The absolute topic ``name`` (e.g. ``omni/pose``) of ``instrument`` (``''``: no namespace)."""
    return f'/{instrument}/{name}' if instrument else f'/{name}'


def session_trajectory(name: str, rate: float = 1000.0, geometry: Geometry | None = None,
                       seed: int = 0, tremor_amplitude: float = TREMOR,
                       quantisation: float = OMNI_QUANTISATION, instrument: str = ''):
    """Sample one instrument's script of a session: (t [s] (M,), positions [m] (M, 3), button1 (M,),
    phases list[str]). Each instrument's hand trembles on its own (seed + its index)."""
    scripts = session_scripts(name, geometry, seed)
    segments = scripts[instrument]
    total = sum(s.duration for s in segments)
    t = np.arange(int(round(total * rate)) + 1) / rate
    pos, buttons, phases = sample_script(segments, t)
    pos = pos + tremor(t, tremor_amplitude, seed=seed + list(scripts).index(instrument))
    return t, quantise(pos, quantisation), buttons, phases


def session_messages(name: str, rate: float = 1000.0, geometry: Geometry | None = None,
                     seed: int = 0, t0_ns: int = 1_700_000_000_000_000_000,
                     frame_id: str = 'omni_base', state_rate: float = 100.0) -> list:
    """A session as bag messages ``[(topic, msgtype, log_ns, rosbags msg)]`` (poses + buttons of
    each instrument, in time order)."""
    from haptic_omni_driver.bag_types import POSE_TYPE, STATE_TYPE, typestore

    types = typestore().types
    Time, Header = types['builtin_interfaces/msg/Time'], types['std_msgs/msg/Header']
    Pose, Point, Quat = (types['geometry_msgs/msg/Pose'], types['geometry_msgs/msg/Point'],
                         types['geometry_msgs/msg/Quaternion'])
    PoseStamped, State = types[POSE_TYPE], types[STATE_TYPE]
    Vec = types['geometry_msgs/msg/Vector3']
    every = max(1, int(round(rate / state_rate)))
    orientation = Quat(*ORIENTATIONS.get(name, (0.0, 0.0, 0.0, 1.0)))
    out = []
    for instrument in session_scripts(name, geometry, seed):
        t, pos, buttons, _ = session_trajectory(name, rate, geometry, seed, instrument=instrument)
        pose_topic, state_topic = topic(instrument, 'omni/pose'), topic(instrument, 'omni/state')
        for k in range(t.size):
            stamp = int(t0_ns + round(t[k] * 1e9))
            header = Header(Time(*divmod(stamp, 1_000_000_000)), frame_id)
            out.append((pose_topic, POSE_TYPE, stamp, PoseStamped(
                header, Pose(Point(*map(float, pos[k])), orientation))))
            if k % every == 0 or (k and buttons[k] != buttons[k - 1]):
                out.append((state_topic, STATE_TYPE, stamp, State(
                    header, bool(buttons[k]), False, False, False, False, True, Vec(0.0, 0.0, 0.0),
                    0.0, -1.0, 0, 'scripted', f'session {name} (seed {seed})')))
    out.sort(key=lambda m: m[2])  # stable: one instrument's pose before its state, left before right
    return out
