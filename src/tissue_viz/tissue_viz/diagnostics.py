"""Diagnostic levels of the running simulation against targets (pure Python, no rclpy).

The functions here return plain :class:`Status` records; the node converts them into
``diagnostic_msgs/DiagnosticStatus``. Rate checks follow diagnostic_updater's FrequencyStatus:
a rate below ``min_rate * (1 - tolerance)`` or above ``max_rate * (1 + tolerance)`` is WARN, a
topic that never arrived or stopped for longer than ``stale_timeout`` is ERROR with "no data".
Statuses derived from a topic that has no data in the window are STALE (OK when that topic is not
required, so a graph without a device can still be all OK).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tissue_common.instruments import topic_within
from tissue_viz.errors import VizConfigError
from tissue_viz.stats import HAPTIC_MULTIRATE, LIMITS, TOPICS, Snapshot

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}

# Topic names as the node subscribes them (relative, so namespaces and remaps apply).
TOPIC_NAMES = {'metrics': 'tissue/metrics', 'particles': 'tissue/particles',
               'pose': 'omni/pose', 'force': 'omni/force_feedback'}


@dataclass
class RateTarget:
    """Expected rate window of one topic; ``required=False`` makes its absence OK."""

    min_rate: float
    max_rate: float
    required: bool = True


@dataclass
class Targets:
    """Thresholds the diagnostics compare the rolling statistics against (SI units)."""

    rates: dict = field(default_factory=lambda: {
        'metrics': RateTarget(900.0, 1100.0),
        'particles': RateTarget(25.0, 35.0),
        'pose': RateTarget(900.0, 1100.0),
        'force': RateTarget(900.0, 1100.0),
    })
    rate_tolerance: float = 0.1
    stale_timeout: float = 2.0           # [s] no message for this long: "no data" ERROR
    step_p99_warn: float = 0.0008        # [s]
    step_p99_error: float = 0.001        # [s] (the 1 kHz haptic period)
    deadline_miss_warn_pct: float = 1.0  # [%]
    deadline_miss_error_pct: float = 5.0
    latency_p50_warn: float = 0.001      # [s] DESIGN.md section 6: median <= 1 ms
    latency_p99_warn: float = 0.003      # [s] p99 <= 3 ms
    latency_p99_error: float = 0.010     # [s]
    reply_loss_warn_pct: float = 1.0     # [%] poses without a reply
    reply_loss_error_pct: float = 10.0
    force_limit: float = 3.3             # [N] device peak force (PHANTOM Omni)
    energy_in_min: float = -1e-6         # [J] lowest E_in of a passive rendering (round-off slack)
    model_age_warn: float = 0.02         # [s] an older contact model is WARN (see haptic_status)

    def validate(self) -> 'Targets':
        """Raise VizConfigError on inconsistent thresholds; return self."""
        for topic, target in self.rates.items():
            if topic not in TOPICS:
                raise VizConfigError(f'unknown topic {topic!r} in rate targets (known: {TOPICS})')
            if not (0.0 <= target.min_rate <= target.max_rate):
                raise VizConfigError(f'{topic}: need 0 <= min_rate <= max_rate, got '
                                     f'{target.min_rate} and {target.max_rate}')
        if not 0.0 <= self.rate_tolerance < 1.0:
            raise VizConfigError(f'rate_tolerance must be in [0, 1), got {self.rate_tolerance}')
        if not self.stale_timeout > 0:
            raise VizConfigError(f'stale_timeout must be > 0 s, got {self.stale_timeout}')
        pairs = (('step_p99_warn', 'step_p99_error'),
                 ('deadline_miss_warn_pct', 'deadline_miss_error_pct'),
                 ('latency_p99_warn', 'latency_p99_error'),
                 ('reply_loss_warn_pct', 'reply_loss_error_pct'))
        for warn, error in pairs:
            w, e = getattr(self, warn), getattr(self, error)
            if not (0 < w <= e):
                raise VizConfigError(f'need 0 < {warn} <= {error}, got {w} and {e}')
        if not self.latency_p50_warn > 0:
            raise VizConfigError(f'latency_p50_warn must be > 0 s, got {self.latency_p50_warn}')
        if not self.force_limit > 0:
            raise VizConfigError(f'force_limit must be > 0 N, got {self.force_limit}')
        if not self.model_age_warn > 0:
            raise VizConfigError(f'model_age_warn must be > 0 s, got {self.model_age_warn}')
        if not self.energy_in_min <= 0:    # above zero even a passive rendering would warn
            raise VizConfigError(f'energy_in_min must be <= 0 J, got {self.energy_in_min}')
        return self


@dataclass
class Status:
    """One diagnostic status: name, level (OK/WARN/ERROR/STALE), message and key/value pairs."""

    name: str
    level: int
    message: str
    values: list = field(default_factory=list)   # [(key, str value)]

    @property
    def level_name(self) -> str:
        return LEVEL_NAMES[self.level]


NO_VALUE = 'n/a'    # what a person reads where there is no number (never 'nan')


def _name(prefix: str, item: str, instrument: str = '') -> str:
    """A status name: ``viz_node: tissue``, or with several instruments ``viz_node: tissue (left)``."""
    return f'{prefix}: {item} ({instrument})' if instrument else f'{prefix}: {item}'


def _num(x: float | None, digits: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return NO_VALUE
    if abs(x) >= 1e9:    # fixed point would print hundreds of digits for an absurd value
        return f'{x:.3g}'
    return f'{x:.{digits}f}'


def _ms(x: float | None) -> str:
    return NO_VALUE if x is None or not math.isfinite(x) else _num(x * 1e3, 3)


def _uj(x: float | None) -> str:
    """Joules as microjoules: the scale of the energy a hand exchanges with soft tissue."""
    return NO_VALUE if x is None or not math.isfinite(x) else _num(x * 1e6, 3)


def rate_status(topic: str, snap: Snapshot, targets: Targets, prefix: str = 'viz_node',
                instrument: str = '') -> Status:
    """FrequencyStatus-like check of one topic's rate (named by the topic in ``instrument``'s
    namespace)."""
    target: RateTarget = targets.rates[topic]
    rate, age, count = snap.rates.get(topic, 0.0), snap.ages.get(topic), snap.counts.get(topic, 0)
    lo = target.min_rate * (1.0 - targets.rate_tolerance)
    hi = target.max_rate * (1.0 + targets.rate_tolerance)
    values = [('rate [Hz]', _num(rate, 1)), ('min rate [Hz]', _num(target.min_rate, 1)),
              ('max rate [Hz]', _num(target.max_rate, 1)), ('tolerance', _num(targets.rate_tolerance, 2)),
              ('messages', str(count)),
              ('since last [s]', 'never' if age is None else _num(age, 3)),
              ('window [s]', _num(snap.window, 1))]
    name = f'{prefix}: {topic_within(instrument, TOPIC_NAMES[topic])} rate'
    if age is None:
        if target.required:
            return Status(name, ERROR, 'no data', values)
        return Status(name, OK, 'no data (not required)', values)
    if age > targets.stale_timeout:
        level = ERROR if target.required else OK
        return Status(name, level, f'no data for {_num(age, 1)} s', values)
    if rate < lo:
        return Status(name, WARN, f'rate too low ({_num(rate, 1)} Hz < {_num(lo, 1)} Hz)', values)
    if rate > hi:
        return Status(name, WARN, f'rate too high ({_num(rate, 1)} Hz > {_num(hi, 1)} Hz)', values)
    return Status(name, OK, f'rate ok ({_num(rate, 1)} Hz)', values)


def step_status(snap: Snapshot, targets: Targets, prefix: str = 'viz_node') -> Status:
    """Step wall time percentiles and deadline misses against the haptic period."""
    values = [('p50 [ms]', _ms(snap.step_p50)), ('p99 [ms]', _ms(snap.step_p99)),
              ('max [ms]', _ms(snap.step_max)), ('deadline misses', str(snap.deadline_misses)),
              ('sub-steps per step p50', _num(snap.substeps_p50, 1)),
              ('sub-steps per step max', _num(snap.substeps_max, 0)),
              ('deadline miss [%]', _num(snap.deadline_miss_pct, 2)),
              ('p99 warn [ms]', _ms(targets.step_p99_warn)),
              ('p99 error [ms]', _ms(targets.step_p99_error))]
    name = f'{prefix}: step time'
    if not math.isfinite(snap.step_p99):
        if targets.rates['metrics'].required:
            return Status(name, STALE, 'no data', values)
        return Status(name, OK, 'no data (metrics not required)', values)
    miss = snap.deadline_miss_pct
    text = f'p99 {_ms(snap.step_p99)} ms, {_num(miss, 1)} % deadline misses'
    if snap.step_p99 > targets.step_p99_error or miss > targets.deadline_miss_error_pct:
        return Status(name, ERROR, 'too slow: ' + text, values)
    if snap.step_p99 > targets.step_p99_warn or miss > targets.deadline_miss_warn_pct:
        return Status(name, WARN, 'slow: ' + text, values)
    return Status(name, OK, text, values)


def latency_status(snap: Snapshot, targets: Targets, prefix: str = 'viz_node',
                   instrument: str = '') -> Status:
    """Pose→force latency percentiles and the share of poses without a reply."""
    loss = snap.replies_missed_pct
    values = [('p50 [ms]', _ms(snap.latency_p50)), ('p99 [ms]', _ms(snap.latency_p99)),
              ('max [ms]', _ms(snap.latency_max)), ('poses without reply [%]', _num(loss, 2)),
              ('p50 warn [ms]', _ms(targets.latency_p50_warn)),
              ('p99 warn [ms]', _ms(targets.latency_p99_warn)),
              ('p99 error [ms]', _ms(targets.latency_p99_error))]
    name = _name(prefix, 'pose to force latency', instrument)
    if not math.isfinite(snap.latency_p50):
        if targets.rates['pose'].required and targets.rates['force'].required:
            return Status(name, STALE, 'no data', values)
        return Status(name, OK, 'no data (pose and force not both required)', values)
    loss = 0.0 if not math.isfinite(loss) else loss
    text = (f'p50 {_num(snap.latency_p50 * 1e3, 2)} ms '
            f'p99 {_num(snap.latency_p99 * 1e3, 2)} ms, '
            f'{_num(loss, 1)} % poses without reply')
    if snap.latency_p99 > targets.latency_p99_error or loss > targets.reply_loss_error_pct:
        return Status(name, ERROR, 'too late: ' + text, values)
    if (snap.latency_p50 > targets.latency_p50_warn or snap.latency_p99 > targets.latency_p99_warn
            or loss > targets.reply_loss_warn_pct):
        return Status(name, WARN, 'late: ' + text, values)
    return Status(name, OK, text, values)


def tissue_status(snap: Snapshot, targets: Targets, prefix: str = 'viz_node',
                  instrument: str = '') -> Status:
    """Active particles, force and displacement; WARN when the force reaches the device limit."""
    values = [('active particles', _num(snap.active, 0)),
              ('interaction particles', _num(snap.n_interaction, 0)),
              ('force [N]', _num(snap.force, 3)), ('max force in window [N]', _num(snap.force_max, 3)),
              ('force limit [N]', _num(targets.force_limit, 2)),
              ('max displacement [mm]', _ms(snap.displacement))]
    name = _name(prefix, 'tissue', instrument)
    if not (math.isfinite(snap.active) or math.isfinite(snap.force)):
        if targets.rates['metrics'].required or targets.rates['force'].required:
            return Status(name, STALE, 'no data', values)
        return Status(name, OK, 'no data (metrics and force not required)', values)
    if math.isfinite(snap.force_max) and snap.force_max >= targets.force_limit * (1.0 - 1e-6):
        return Status(name, WARN, f'force at the device limit ({_num(snap.force_max, 2)} N)',
                      values)
    text = (f'active {_num(snap.active, 0)}, F {_num(snap.force, 2)} N, '
            f'disp {_num(snap.displacement * 1e3 if math.isfinite(snap.displacement) else math.nan, 1)} mm')
    return Status(name, OK, text, values)


def haptic_status(snap: Snapshot, targets: Targets, prefix: str = 'viz_node',
                  instrument: str = '') -> Status:
    """Multirate haptic rendering: WARN when the lowest E_in in the window is below
    ``energy_in_min`` (the rendering gave energy back to the hand, i.e. it is not passive), or when
    the contact model the renderer answered from was older than ``model_age_warn`` (the solver is
    falling behind the hand: replayed with the reaction 24 poses late, the poke bag gave energy
    back at a first touch; 20 or fewer did not, benchmarks/haptic_quality.py ``--delays``)."""
    values = [('solver rate [Hz]', _num(snap.solver_rate, 1)),
              ('model age [ms]', _ms(snap.model_age)),
              ('model age warn [ms]', _ms(targets.model_age_warn)),
              ('coupling stretch [mm]', _ms(snap.coupling_stretch)),
              ('E_in [uJ]', _uj(snap.energy_in)),
              ('lowest E_in in window [uJ]', _uj(snap.energy_in_low)),
              ('lowest E_in since reset [uJ]', _uj(snap.energy_in_min)),
              ('E_in warn below [uJ]', _uj(targets.energy_in_min)),
              ('added damping [N s/m]', _num(snap.added_damping, 3))]
    name = _name(prefix, 'haptic rendering', instrument)
    # Optional, like a topic that is not required: without a multirate renderer there is nothing
    # to judge, and the step and tissue statuses already speak for missing metrics.
    if snap.haptic_mode is None:
        return Status(name, OK, 'no metrics yet', values)
    if snap.haptic_mode != HAPTIC_MULTIRATE:
        return Status(name, OK, 'direct (no haptic renderer)', values)
    if not math.isfinite(snap.energy_in_low):
        return Status(name, OK, 'no multirate metrics in the window', values)
    text = (f'E_in {_uj(snap.energy_in)} uJ (lowest {_uj(snap.energy_in_low)} uJ), '
            f'solver {_num(snap.solver_rate, 0)} Hz, '
            f'added damping {_num(snap.added_damping, 2)} N s/m')
    if snap.energy_in_low < targets.energy_in_min:
        return Status(name, WARN, 'gave energy back: ' + text, values)
    if snap.model_age > targets.model_age_warn:
        return Status(name, WARN, f'contact model {_ms(snap.model_age)} ms old: ' + text, values)
    return Status(name, OK, text, values)


def input_status(snap: Snapshot, prefix: str = 'viz_node', instrument: str = '') -> Status:
    """Bad input seen in the window: messages with NaN/inf or out-of-range values (with the count
    of each kind of bad value since start), header stamps going backwards."""
    values = [('bad messages in window', str(snap.bad_in_window)),
              ('bad messages total', str(snap.bad_total)),
              ('backwards stamps in window', str(snap.backwards_in_window)),
              ('backwards stamps total', str(snap.backwards_total))]
    values += [(f'bad {LIMITS[key].what} total', str(count))
               for key, count in snap.bad_values.items() if count and key in LIMITS]
    name = _name(prefix, 'input', instrument)
    problems = []
    if snap.bad_in_window:
        problems.append(f'{snap.bad_in_window} messages with NaN/inf or out-of-range values '
                        'ignored')
    if snap.backwards_in_window:
        problems.append(f'{snap.backwards_in_window} stamps went backwards')
    if problems:
        return Status(name, WARN, '; '.join(problems), values)
    return Status(name, OK, 'clean', values)


def evaluate(snap: Snapshot, targets: Targets, prefix: str = 'viz_node') -> list[Status]:
    """Every status of the viz node for one snapshot, in a stable order."""
    statuses = [rate_status(topic, snap, targets, prefix) for topic in TOPICS]
    statuses += [step_status(snap, targets, prefix), latency_status(snap, targets, prefix),
                 tissue_status(snap, targets, prefix), haptic_status(snap, targets, prefix),
                 input_status(snap, prefix)]
    return statuses


def evaluate_instruments(snaps: dict[str, Snapshot], targets: Targets,
                         prefix: str = 'viz_node') -> list[Status]:
    """Every status for one snapshot per instrument (name -> snapshot, in the order of the
    ``instruments`` parameter). One instrument without a name (``['']``) is :func:`evaluate`. With
    several, the cloud's rate and the step time (the tissue's, the same step in every
    instrument's metrics) come once, from the first instrument's snapshot; each instrument has its
    own topic rates (``viz_node: left/omni/pose rate``) and its own latency, tissue (force),
    haptic rendering (E_in) and input statuses, named with the instrument (``viz_node: tissue
    (left)``)."""
    names = list(snaps)
    if names == ['']:
        return evaluate(snaps[''], targets, prefix)
    first = snaps[names[0]]
    statuses = [rate_status('particles', first, targets, prefix)]
    statuses += [rate_status(topic, snap, targets, prefix, name)
                 for name, snap in snaps.items() for topic in TOPICS if topic != 'particles']
    statuses.append(step_status(first, targets, prefix))
    for name, snap in snaps.items():
        statuses += [latency_status(snap, targets, prefix, name),
                     tissue_status(snap, targets, prefix, name),
                     haptic_status(snap, targets, prefix, name), input_status(snap, prefix, name)]
    return statuses


def worst_level(statuses: list[Status]) -> int:
    """Highest level among ``statuses`` (STALE counts above ERROR, as in diagnostic_aggregator)."""
    return max((s.level for s in statuses), default=OK)
