"""Rolling statistics of the running simulation (pure Python + numpy, no rclpy).

Every method takes the current time ``now`` explicitly (seconds on a monotonic clock), so the
statistics can be fed hand-made series in tests and the node stays a thin adapter. Callbacks at
1 kHz only append to deques; percentiles are computed when a snapshot is asked for (about 1 Hz).
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import asdict, dataclass, field
from typing import Iterable, Sequence

import numpy as np

from tissue_common.feel import feel
from tissue_viz.errors import VizConfigError

TOPICS = ('metrics', 'particles', 'pose', 'force')
#: each instrument's figures in the report when there are several (keys of VizStats.summary):
#: the force it got, its pose -> force round trip and the lowest E_in of its rendering
INSTRUMENT_SUMMARY_KEYS = ('max_force_n', 'latency_p50_s', 'latency_p99_s', 'replies_missed_pct',
                           'energy_in_min_j')
# tissue_msgs/SimMetrics.HAPTIC_MULTIRATE (kept here so the statistics and the report need no
# message import): a haptic renderer answers each pose and the solver refreshes its contact model.
HAPTIC_MULTIRATE = 1


@dataclass(frozen=True)
class Limit:
    """The plausible range of one input quantity; a value outside it, NaN or inf is bad."""

    lo: float
    hi: float
    what: str            # plural noun for the report, e.g. 'step times'
    unit: str = ''

    def ok(self, *values: float) -> bool:
        """True if every value is finite and inside [lo, hi]."""
        return all(within(v, self.lo, self.hi) for v in values)

    def mask(self, values) -> np.ndarray:
        """Element-wise :meth:`ok` of an array (False for NaN and inf)."""
        arr = np.asarray(values, dtype=float)
        with np.errstate(invalid='ignore'):
            return np.isfinite(arr) & (arr >= self.lo) & (arr <= self.hi)

    def describe(self) -> str:
        unit = f' {self.unit}' if self.unit else ''
        return f'{self.lo:g} to {self.hi:g}{unit}'


def within(value, lo: float, hi: float) -> bool:
    """True if ``value`` is a finite number inside [lo, hi] (False for anything else)."""
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):   # e.g. an integer too large for a float
        return False
    return math.isfinite(x) and lo <= x <= hi


# Far beyond anything a working simulator or device sends (a 3 670-particle liver, forces of a few
# newtons, a 0.1 m workspace), so they only catch garbage: one step time of 1e308 would otherwise
# overflow the report's arithmetic and squash every plot.
MAX_SECONDS = 1e5
MAX_FORCE = 1e6          # [N] per component
MAX_LENGTH = 1e3         # [m]
MAX_ENERGY = 1e9         # [J]
MAX_COUNT = 1_000_000_000
MAX_RATE = 1e7           # [Hz]
MAX_DAMPING = 1e9        # [N s/m]
LIMITS: dict[str, Limit] = {
    'step_wall_time': Limit(0.0, MAX_SECONDS, 'step times', 's'),
    'contact_force': Limit(-MAX_FORCE, MAX_FORCE, 'metrics contact forces', 'N per component'),
    'max_displacement': Limit(0.0, MAX_LENGTH, 'max displacements', 'm'),
    'penetration': Limit(0.0, MAX_LENGTH, 'penetrations', 'm'),
    'kinetic_energy': Limit(0.0, MAX_ENERGY, 'kinetic energies', 'J'),
    'active_particles': Limit(0, MAX_COUNT, 'active particle counts'),
    'substeps': Limit(0, MAX_COUNT, 'sub-step counts'),
    'contact_index': Limit(-1, MAX_COUNT, 'contact indices'),
    'pose_position': Limit(-MAX_LENGTH, MAX_LENGTH, 'tool positions', 'm per component'),
    'wrench_force': Limit(-MAX_FORCE, MAX_FORCE, 'device forces', 'N per component'),
    'latency': Limit(0.0, MAX_SECONDS, 'latencies', 's'),
    # Haptic rendering (zero in direct mode). E_in may be negative: that is what it is watched for.
    'haptic_mode': Limit(0, 255, 'haptic modes'),
    'solver_rate': Limit(0.0, MAX_RATE, 'solver rates', 'Hz'),
    'model_age': Limit(0.0, MAX_SECONDS, 'contact model ages', 's'),
    'coupling_stretch': Limit(0.0, MAX_LENGTH, 'coupling stretches', 'm'),
    'energy_in': Limit(-MAX_ENERGY, MAX_ENERGY, 'haptic input energies (E_in and its minimum)',
                       'J'),
    'added_damping': Limit(0.0, MAX_DAMPING, 'added dampings', 'N s/m'),
}


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The q-th percentile (0..100, linear interpolation) of ``values``; NaN when empty."""
    arr = np.asarray(values, dtype=float)
    if arr.size == 0:
        return math.nan
    return float(np.percentile(arr, q))


class RateMeter:
    """Message rate over a sliding time window, like diagnostic_updater's FrequencyStatus.

    Once the topic has been seen for a whole window the rate is ``count_in_window / window``, so
    it falls when messages thin out or stop; before that (start-up) it is ``(n - 1) / span`` over
    the messages seen so far, which is exact for a regular stream.
    """

    def __init__(self, window: float) -> None:
        if not window > 0:
            raise VizConfigError(f'rate window must be > 0 s, got {window}')
        self.window = float(window)
        self._times: deque[float] = deque()
        self.first: float | None = None
        self.last: float | None = None
        self.count = 0

    def tick(self, now: float) -> None:
        """Record one message received at ``now``."""
        if self.first is None:
            self.first = now
        self.last = now
        self.count += 1
        self._times.append(now)
        self._prune(now)

    def _prune(self, now: float) -> None:
        horizon = now - self.window
        times = self._times
        while times and times[0] <= horizon:
            times.popleft()

    def rate(self, now: float) -> float:
        """Messages per second over the window ending at ``now`` (0 if never or no longer seen)."""
        self._prune(now)
        if self.first is None:
            return 0.0
        n = len(self._times)
        if now - self.first >= self.window:
            return n / self.window
        if n < 2:
            return 0.0
        span = self._times[-1] - self._times[0]
        return (n - 1) / span if span > 0 else 0.0

    def age(self, now: float) -> float | None:
        """Seconds since the last message, None if none arrived yet."""
        return None if self.last is None else now - self.last

    def mean_rate(self) -> float:
        """Average rate over the whole run, ``(count - 1) / (last - first)``."""
        if self.count < 2 or self.last is None or self.first is None or self.last <= self.first:
            return 0.0
        return (self.count - 1) / (self.last - self.first)


class WindowedSeries:
    """Values with their receive times, keeping only those inside the last ``window`` seconds."""

    def __init__(self, window: float) -> None:
        if not window > 0:
            raise VizConfigError(f'series window must be > 0 s, got {window}')
        self.window = float(window)
        self._t: deque[float] = deque()
        self._v: deque[float] = deque()

    def add(self, now: float, value: float) -> None:
        self._t.append(now)
        self._v.append(value)

    def values(self, now: float) -> np.ndarray:
        """The values received in (now - window, now]."""
        horizon = now - self.window
        while self._t and self._t[0] <= horizon:
            self._t.popleft()
            self._v.popleft()
        return np.fromiter(self._v, dtype=float, count=len(self._v))

    def __len__(self) -> int:
        return len(self._v)


def csv_rows(rows: np.ndarray) -> str:
    """CSV lines of a (n, columns) array: 12 significant digits per value, NaN (no value) as an
    empty cell."""
    rows = np.asarray(rows, dtype=float)
    if rows.size == 0:
        return ''
    line = ','.join(['%.12g'] * rows.shape[1]) + '\n'
    # one format call for all the rows, not one per row as np.savetxt: a third faster
    return ((line * len(rows)) % tuple(rows.ravel().tolist())).replace('nan', '')


class DecimatingRecorder:
    """A whole-run table of rows with bounded memory.

    When ``max_rows`` is reached every other stored row is dropped and only every ``stride``-th
    new row is kept from then on (stride doubles each time), so a long run keeps an evenly
    thinned history for the report instead of its first or last minutes only.

    With ``csv_text`` each block of rows is written as CSV lines (:func:`csv_rows`) once it is
    full: a report, written on the way out, then formats only the rows of the last block.
    """

    #: rows per preallocated block: a row goes straight into an array, so a report of a long run
    #: needs no conversion of hundreds of thousands of tuples (nor an exit that frees them)
    BLOCK = 4096

    def __init__(self, columns: Sequence[str], max_rows: int, csv_text: bool = False) -> None:
        if max_rows < 2:
            raise VizConfigError(f'max_rows must be >= 2, got {max_rows}')
        self.columns = tuple(columns)
        self.max_rows = int(max_rows)
        self.stride = 1
        self._seen = 0
        self._blocks: list[np.ndarray] = []
        self._n = 0
        # the rows as one array, until the next row is kept: a report asks for it several times
        self._array: np.ndarray | None = None
        self._csv_text = csv_text
        self._text: list[str] = []      # CSV lines of the first full blocks, in order

    def append(self, row: Iterable[float]) -> None:
        row = tuple(row)
        if len(row) != len(self.columns):
            raise ValueError(f'row has {len(row)} values, table has {len(self.columns)} columns')
        keep = self._seen % self.stride == 0
        self._seen += 1
        if not keep:
            return
        at = self._n % self.BLOCK
        if at == 0:
            self._blocks.append(np.empty((self.BLOCK, len(self.columns))))
        self._blocks[-1][at] = row
        self._n += 1
        self._array = None
        if self._csv_text and at == self.BLOCK - 1 and len(self._text) == len(self._blocks) - 1:
            self._text.append(csv_rows(self._blocks[-1]))     # about 20 ms per 4096 x 20 values
        if self._n >= self.max_rows:
            self._refill(self._joined()[::2])
            self.stride *= 2

    def _joined(self) -> np.ndarray:
        if not self._blocks:
            return np.empty((0, len(self.columns)))
        return np.concatenate(self._blocks)[:self._n]

    def _refill(self, rows: np.ndarray) -> None:
        self._n = len(rows)
        self._text = []                 # the blocks change; a report formats them itself
        self._blocks = [np.array(rows[a:a + self.BLOCK]) for a in range(0, self._n, self.BLOCK)]
        if self._blocks and len(self._blocks[-1]) < self.BLOCK:
            last = np.empty((self.BLOCK, len(self.columns)))
            last[:len(self._blocks[-1])] = self._blocks[-1]
            self._blocks[-1] = last

    def __len__(self) -> int:
        return self._n

    def array(self) -> np.ndarray:
        """Rows as a (n, n_columns) float array (a copy: the caller may change it)."""
        if self._array is None:
            self._array = self._joined()
        return self._array.copy()

    def as_dict(self) -> dict[str, np.ndarray]:
        arr = self.array()
        return {name: arr[:, i] for i, name in enumerate(self.columns)}

    def csv_head(self) -> tuple[int, str]:
        """(rows, their CSV lines) of the rows already written as CSV lines (``csv_text``), from
        the first; (0, '') without."""
        return len(self._text) * self.BLOCK, ''.join(self._text)


class LatencyMatcher:
    """Pose→force latency: match a force's header stamp to the pose with the same stamp.

    Latency is the receive time of the force minus the receive time of that pose (both here, so
    one clock). Poses not answered within ``timeout`` count as missed replies; forces whose stamp
    matches no pending pose are counted as unmatched (e.g. the pose was dropped on the way here).
    """

    def __init__(self, timeout: float, max_pending: int = 10000) -> None:
        if not timeout > 0:
            raise VizConfigError(f'latency timeout must be > 0 s, got {timeout}')
        self.timeout = float(timeout)
        self.max_pending = int(max_pending)
        self._pending: OrderedDict[int, tuple[float, tuple[float, float, float]]] = OrderedDict()
        self.answered = 0
        self.missed = 0
        self.unmatched_forces = 0

    def on_pose(self, stamp_ns: int, now: float, position: tuple[float, float, float]) -> None:
        if stamp_ns in self._pending:
            # A repeated stamp: keep the first arrival, that is when the request went out.
            return
        self._pending[stamp_ns] = (now, position)
        while len(self._pending) > self.max_pending:
            self._pending.popitem(last=False)
            self.missed += 1

    def on_force(self, stamp_ns: int, now: float) -> tuple[float, tuple[float, float, float]] | None:
        """Return (latency [s], pose position) or None when no pending pose has this stamp."""
        entry = self._pending.pop(stamp_ns, None)
        if entry is None:
            self.unmatched_forces += 1
            return None
        self.answered += 1
        t_pose, position = entry
        return now - t_pose, position

    def expire(self, now: float) -> int:
        """Count poses older than the timeout as missed; returns how many expired now."""
        expired = 0
        horizon = now - self.timeout
        pending = self._pending
        # Receive order is insertion order, so the oldest are at the front.
        while pending:
            key, (t_pose, _) = next(iter(pending.items()))
            if t_pose > horizon:
                break
            pending.popitem(last=False)
            expired += 1
        self.missed += expired
        return expired

    @property
    def pending(self) -> int:
        return len(self._pending)


class StampOrder:
    """Counts header stamps that go backwards on one topic (equal stamps are not out of order).

    A backwards stamp counts once and restarts the order from it: a publisher whose clock was reset
    (a replay started again, a simulation reset) is one event, not a fault on every later message.
    """

    def __init__(self) -> None:
        self.last: int | None = None
        self.backwards = 0

    def check(self, stamp_ns: int) -> bool:
        """True if ``stamp_ns`` is not older than the previous stamp on the topic."""
        ok = self.last is None or stamp_ns >= self.last
        if not ok:
            self.backwards += 1
        self.last = stamp_ns
        return ok


@dataclass
class Snapshot:
    """Rolling statistics at one instant; NaN where there is no data in the window."""

    now: float
    window: float
    rates: dict = field(default_factory=dict)          # topic -> Hz over the window
    ages: dict = field(default_factory=dict)           # topic -> s since last message (None never)
    counts: dict = field(default_factory=dict)         # topic -> messages since start
    step_p50: float = math.nan                         # [s] step wall time
    step_p99: float = math.nan
    step_max: float = math.nan
    deadline_misses: int = 0                           # steps in window longer than the period
    deadline_miss_pct: float = math.nan
    substeps_p50: float = math.nan                     # integration sub-steps per solver step
    substeps_max: float = math.nan
    latency_p50: float = math.nan                      # [s] pose -> force
    latency_p99: float = math.nan
    latency_max: float = math.nan
    replies_missed_pct: float = math.nan               # poses without a force reply (in window)
    active: float = math.nan                           # particles computed in the latest step
    n_interaction: float = math.nan
    force: float = math.nan                            # [N] latest force magnitude
    force_max: float = math.nan                        # [N] max in the window
    displacement: float = math.nan                     # [m] latest max displacement
    haptic_mode: int | None = None                     # SimMetrics.HAPTIC_* of the latest metrics
    solver_rate: float = math.nan                      # [Hz] latest multirate values (NaN direct)
    model_age: float = math.nan                        # [s]
    coupling_stretch: float = math.nan                 # [m]
    energy_in: float = math.nan                        # [J] E_in, hand -> rendered tissue
    energy_in_min: float = math.nan                    # [J] lowest E_in since start or reset
    energy_in_low: float = math.nan                    # [J] lowest E_in in the window
    added_damping: float = math.nan                    # [N s/m]
    bad_in_window: int = 0                             # messages with a bad value (ignored)
    bad_total: int = 0
    bad_values: dict = field(default_factory=dict)     # LIMITS key -> bad values since start
    backwards_in_window: int = 0
    backwards_total: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


class VizStats:
    """All the statistics the viz node keeps, fed by plain values.

    Args:
        window: sliding window [s] for rates and distributions.
        haptic_rate: haptic loop rate [Hz]; a step longer than 1/haptic_rate misses its deadline.
        latency_timeout: a pose without a force reply after this many seconds is a missed reply.
        max_report_rows: memory bound of each whole-run table kept for the report.
    """

    # Multirate haptic rendering values, named as in SimMetrics (zero in direct mode).
    HAPTIC_COLUMNS = ('solver_rate', 'model_age', 'coupling_stretch', 'energy_in', 'energy_in_min',
                      'added_damping')
    METRICS_COLUMNS = ('t', 'step_wall_time', 'substeps', 'n_interaction', 'n_active',
                       'contact_index', 'penetration', 'fx', 'fy', 'fz', 'force',
                       'max_displacement', 'kinetic_energy', 'haptic_mode') + HAPTIC_COLUMNS
    FORCE_COLUMNS = ('t', 'fx', 'fy', 'fz', 'force', 'px', 'py', 'pz')
    #: every answered pose, in stamp order: what the hand got (never thinned, see ``felt``)
    FEEL_COLUMNS = ('stamp', 'fx', 'fy', 'fz', 'px', 'py', 'pz')
    LATENCY_COLUMNS = ('t', 'latency')
    RATE_COLUMNS = ('t',) + TOPICS

    def __init__(self, window: float = 5.0, haptic_rate: float = 1000.0,
                 latency_timeout: float = 0.5, max_report_rows: int = 200000) -> None:
        if not haptic_rate > 0:
            raise VizConfigError(f'haptic_rate must be > 0 Hz, got {haptic_rate}')
        self.window = float(window)
        self.period = 1.0 / float(haptic_rate)
        self.meters = {topic: RateMeter(window) for topic in TOPICS}
        self.order = {topic: StampOrder() for topic in TOPICS}
        self.step = WindowedSeries(window)
        self.latency = WindowedSeries(window)
        self.substeps_window = WindowedSeries(window)
        self.force_window = WindowedSeries(window)
        self.bad_window = WindowedSeries(window)
        self.backwards_window = WindowedSeries(window)
        self.matcher = LatencyMatcher(latency_timeout)
        self.missed_window = WindowedSeries(window)    # one entry per expiry, value = poses missed
        self._missed_seen = 0
        self.bad_total = 0
        self.bad_values = {key: 0 for key in LIMITS}
        self.steps_total = 0
        self.deadline_misses_total = 0
        self.force_max_total = 0.0
        self.displacement_max_total = 0.0
        self.active_max_total = 0
        self.points_last = 0
        self.last_force: float = math.nan
        self.last_metrics_force: float = math.nan
        self.last_displacement: float = math.nan
        self.last_active: float = math.nan
        self.last_interaction: float = math.nan
        self.last_haptic_mode: int | None = None
        self.last_haptic: dict[str, float] = {}        # HAPTIC_COLUMNS -> value, multirate only
        self.energy_window = WindowedSeries(window)    # E_in of multirate metrics
        self.last_pose: tuple[float, float, float] | None = None
        self.last_force_vec: tuple[float, float, float] | None = None
        self.t0: float | None = None
        self.metrics_table = DecimatingRecorder(self.METRICS_COLUMNS, max_report_rows,
                                                csv_text=True)
        self.force_table = DecimatingRecorder(self.FORCE_COLUMNS, max_report_rows, csv_text=True)
        # (pose stamp [s], force, pose position) of every answered pose, for what the hand felt
        # (tissue_common.feel: frame to frame, so never thinned; the first max_report_rows)
        self.felt: list[tuple[float, ...]] = []
        self.max_felt = int(max_report_rows)
        self._feel_rows: tuple[int, np.ndarray] | None = None
        self.latency_table = DecimatingRecorder(self.LATENCY_COLUMNS, max_report_rows,
                                                csv_text=True)
        self.rate_table = DecimatingRecorder(self.RATE_COLUMNS, max_report_rows)

    # -- inputs -----------------------------------------------------------------------------------
    def _rel(self, now: float) -> float:
        if self.t0 is None:
            self.t0 = now
        return now - self.t0

    def _check_order(self, topic: str, now: float, stamp_ns: int) -> None:
        if not self.order[topic].check(stamp_ns):
            self.backwards_window.add(now, 1.0)

    def _accept(self, now: float, fields: dict[str, Sequence[float]]) -> bool:
        """True if every field is inside its :data:`LIMITS`; else count each bad field and the
        message (which is then ignored as a whole: one garbage value makes the rest suspect)."""
        bad = [key for key, values in fields.items() if not LIMITS[key].ok(*values)]
        for key in bad:
            self.bad_values[key] += 1
        if bad:
            self.bad_total += 1
            self.bad_window.add(now, 1.0)
        return not bad

    def on_metrics(self, now: float, stamp_ns: int, step_wall_time: float, force: Sequence[float],
                   max_displacement: float, n_interaction: int = 0, n_layer: Sequence[int] = (),
                   n_relaxing: int = 0, substeps: int = 0, contact_index: int = -1,
                   penetration: float = 0.0, kinetic_energy: float = 0.0, haptic_mode: int = 0,
                   solver_rate: float = 0.0, model_age: float = 0.0,
                   coupling_stretch: float = 0.0, energy_in: float = 0.0,
                   energy_in_min: float = 0.0, added_damping: float = 0.0) -> bool:
        """One SimMetrics message; returns False (and counts it) if a value is NaN/inf or out of
        its :data:`LIMITS`. The haptic values (``haptic_mode`` .. ``added_damping``) are those of
        the multirate rendering, zero in direct mode."""
        t = self._rel(now)
        self.meters['metrics'].tick(now)
        self._check_order('metrics', now, stamp_ns)
        fx, fy, fz = (float(v) for v in force)
        active = int(n_interaction) + sum(int(v) for v in n_layer) + int(n_relaxing)
        if not self._accept(now, {
                'step_wall_time': (step_wall_time,), 'contact_force': (fx, fy, fz),
                'max_displacement': (max_displacement,), 'penetration': (penetration,),
                'kinetic_energy': (kinetic_energy,), 'active_particles': (active,),
                'substeps': (substeps,), 'contact_index': (contact_index,),
                'haptic_mode': (haptic_mode,), 'solver_rate': (solver_rate,),
                'model_age': (model_age,), 'coupling_stretch': (coupling_stretch,),
                'energy_in': (energy_in, energy_in_min), 'added_damping': (added_damping,)}):
            return False
        fmag = math.sqrt(fx * fx + fy * fy + fz * fz)
        self.step.add(now, step_wall_time)
        self.substeps_window.add(now, float(substeps))
        self.steps_total += 1
        if step_wall_time > self.period:
            self.deadline_misses_total += 1
        self.force_max_total = max(self.force_max_total, fmag)
        self.displacement_max_total = max(self.displacement_max_total, max_displacement)
        self.active_max_total = max(self.active_max_total, active)
        self.last_metrics_force = fmag
        self.last_displacement = max_displacement
        self.last_active = active
        self.last_interaction = n_interaction
        if self.meters['force'].count == 0:
            self.force_window.add(now, fmag)
        haptic = (solver_rate, model_age, coupling_stretch, energy_in, energy_in_min, added_damping)
        self.last_haptic_mode = int(haptic_mode)
        # Direct mode sends zeros: they are no measurements, so the snapshot shows none.
        self.last_haptic = {}
        if self.last_haptic_mode == HAPTIC_MULTIRATE:
            self.last_haptic = dict(zip(self.HAPTIC_COLUMNS, (float(v) for v in haptic)))
            self.energy_window.add(now, energy_in)
        self.metrics_table.append((t, step_wall_time, substeps, n_interaction, active,
                                   contact_index, penetration, fx, fy, fz, fmag,
                                   max_displacement, kinetic_energy, haptic_mode, *haptic))
        return True

    def on_particles(self, now: float, stamp_ns: int, n_points: int) -> None:
        self._rel(now)
        self.meters['particles'].tick(now)
        self._check_order('particles', now, stamp_ns)
        self.points_last = int(n_points)

    def on_pose(self, now: float, stamp_ns: int, position: Sequence[float]) -> bool:
        """One tool pose; returns False (and counts it) if the position is not finite or absurd."""
        self._rel(now)
        self.meters['pose'].tick(now)
        self._check_order('pose', now, stamp_ns)
        px, py, pz = (float(v) for v in position)
        if not self._accept(now, {'pose_position': (px, py, pz)}):
            return False
        self.last_pose = (px, py, pz)
        self.matcher.on_pose(stamp_ns, now, self.last_pose)
        return True

    def on_force(self, now: float, stamp_ns: int, force: Sequence[float]) -> float | None:
        """One force command; returns its latency [s] if its stamp matched a pose."""
        t = self._rel(now)
        self.meters['force'].tick(now)
        self._check_order('force', now, stamp_ns)
        fx, fy, fz = (float(v) for v in force)
        if not self._accept(now, {'wrench_force': (fx, fy, fz)}):
            return None
        fmag = math.sqrt(fx * fx + fy * fy + fz * fz)
        self.last_force = fmag
        self.last_force_vec = (fx, fy, fz)
        self.force_max_total = max(self.force_max_total, fmag)
        self.force_window.add(now, fmag)
        matched = self.matcher.on_force(stamp_ns, now)
        pos = (math.nan,) * 3
        latency = None
        if matched is not None:
            latency, pos = matched
            self.latency.add(now, latency)
            self.latency_table.append((t, latency))
            if len(self.felt) < self.max_felt:
                self.felt.append((stamp_ns * 1e-9, fx, fy, fz, *pos))
        self.force_table.append((t, fx, fy, fz, fmag, *pos))
        return latency

    # -- outputs ----------------------------------------------------------------------------------
    def _expire(self, now: float) -> None:
        """Expire unanswered poses and note the new misses in the window."""
        self.matcher.expire(now)
        new = self.matcher.missed - self._missed_seen
        if new:
            self.missed_window.add(now, float(new))
            self._missed_seen = self.matcher.missed

    def snapshot(self, now: float) -> Snapshot:
        """Rolling statistics over the window ending at ``now`` (also expires unanswered poses)."""
        self._expire(now)
        snap = Snapshot(now=now, window=self.window, haptic_mode=self.last_haptic_mode,
                        **self.last_haptic)
        for topic, meter in self.meters.items():
            snap.rates[topic] = meter.rate(now)
            snap.ages[topic] = meter.age(now)
            snap.counts[topic] = meter.count
        steps = self.step.values(now)
        if steps.size:
            snap.step_p50 = percentile(steps, 50)
            snap.step_p99 = percentile(steps, 99)
            snap.step_max = float(steps.max())
            snap.deadline_misses = int(np.count_nonzero(steps > self.period))
            snap.deadline_miss_pct = 100.0 * snap.deadline_misses / steps.size
        subs = self.substeps_window.values(now)
        if subs.size:
            snap.substeps_p50 = percentile(subs, 50)
            snap.substeps_max = float(subs.max())
        lat = self.latency.values(now)
        if lat.size:
            snap.latency_p50 = percentile(lat, 50)
            snap.latency_p99 = percentile(lat, 99)
            snap.latency_max = float(lat.max())
        # Poses decided in the window: answered (a latency sample each) or expired unanswered.
        missed = float(self.missed_window.values(now).sum())
        if missed + lat.size:
            snap.replies_missed_pct = 100.0 * missed / (missed + lat.size)
        snap.active = self.last_active
        snap.n_interaction = self.last_interaction
        snap.force = self.last_force if self.meters['force'].count else self.last_metrics_force
        forces = self.force_window.values(now)
        if forces.size:
            snap.force_max = float(forces.max())
        snap.displacement = self.last_displacement
        energies = self.energy_window.values(now)
        if energies.size:
            snap.energy_in_low = float(energies.min())
        snap.bad_in_window = len(self.bad_window.values(now))
        snap.bad_total = self.bad_total
        snap.bad_values = dict(self.bad_values)
        snap.backwards_in_window = len(self.backwards_window.values(now))
        snap.backwards_total = sum(o.backwards for o in self.order.values())
        return snap

    def sample_rates(self, now: float) -> None:
        """Record the current windowed rates in the whole-run rate table (call at ~1 Hz)."""
        t = self._rel(now)
        self.rate_table.append((t, *(self.meters[topic].rate(now) for topic in TOPICS)))

    def summary(self, now: float) -> dict:
        """Whole-run summary (the content of summary.json)."""
        self._expire(now)
        metrics = self.metrics_table.as_dict()
        lat = self.latency_table.as_dict()['latency']
        steps = metrics['step_wall_time']
        decided = self.matcher.answered + self.matcher.missed

        def num(x: float) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            'duration_s': num(0.0 if self.t0 is None else now - self.t0),
            'window_s': self.window,
            'haptic_period_s': self.period,
            'rates_hz': {t: num(self.meters[t].mean_rate()) for t in TOPICS},
            'messages': {t: self.meters[t].count for t in TOPICS},
            'poses': self.meters['pose'].count,
            'forces': self.meters['force'].count,
            'steps': self.steps_total,
            'step_p50_s': num(percentile(steps, 50)),
            'step_p99_s': num(percentile(steps, 99)),
            'step_max_s': num(float(steps.max()) if steps.size else math.nan),
            'deadline_misses': self.deadline_misses_total,
            'deadline_miss_pct': num(100.0 * self.deadline_misses_total / self.steps_total
                                     if self.steps_total else math.nan),
            'latency_p50_s': num(percentile(lat, 50)),
            'latency_p99_s': num(percentile(lat, 99)),
            'latency_max_s': num(float(lat.max()) if lat.size else math.nan),
            'replies_answered': self.matcher.answered,
            'replies_missed': self.matcher.missed,
            'replies_missed_pct': num(100.0 * self.matcher.missed / decided if decided else math.nan),
            'unmatched_forces': self.matcher.unmatched_forces,
            'max_force_n': num(self.force_max_total),
            'max_displacement_m': num(self.displacement_max_total),
            'max_active_particles': self.active_max_total,
            'points_last': self.points_last,
            'bad_messages': self.bad_total,
            'bad_values': dict(self.bad_values),
            'backwards_stamps': {t: self.order[t].backwards for t in TOPICS},
            **{key: num(value) for key, value in haptic_summary(metrics).items()},
            **{key: num(value) for key, value in self.feel_summary().items()},
        }

    def instrument_summary(self, now: float) -> dict:
        """What a report says of one of several instruments: :data:`INSTRUMENT_SUMMARY_KEYS` of
        :meth:`summary` (None where there is no value, e.g. E_in of a direct run)."""
        full = self.summary(now)
        return {key: full.get(key) for key in INSTRUMENT_SUMMARY_KEYS}

    def feel_table(self) -> dict[str, np.ndarray]:
        """The answered poses (``FEEL_COLUMNS``, stamp [s] relative to the first) in stamp order."""
        # ``felt`` only grows: its length tells whether the sorted table is still current
        if self._feel_rows is None or self._feel_rows[0] != len(self.felt):
            rows = np.array(sorted(self.felt)).reshape(-1, len(self.FEEL_COLUMNS))
            if len(rows):
                rows[:, 0] -= rows[0, 0]
            self._feel_rows = (len(self.felt), rows)
        rows = self._feel_rows[1].copy()
        return {c: rows[:, i] for i, c in enumerate(self.FEEL_COLUMNS)}

    def feel_summary(self) -> dict[str, float]:
        """What the hand felt (:func:`feel_summary_of` the answered poses)."""
        return feel_summary_of(self.feel_table(), self.period)


def feel_summary_of(table: dict[str, np.ndarray], period: float) -> dict[str, float]:
    """:func:`tissue_common.feel.feel` of a ``FEEL_COLUMNS`` table: |dF| per frame p99 and max in
    steady contact [mN], one-frame reversals, E_in min [uJ]; empty below three rows."""
    x = np.column_stack([table[c] for c in ('px', 'py', 'pz')])
    f = np.column_stack([table[c] for c in ('fx', 'fy', 'fz')])
    # a table read back from a folder may hold anything: only rows a live run could have recorded
    ok = (np.isfinite(table['stamp']) & LIMITS['wrench_force'].mask(f).all(axis=1)
          & LIMITS['pose_position'].mask(x).all(axis=1))
    if np.count_nonzero(ok) < 3:
        return {}
    q = feel(x[ok], f[ok], table['stamp'][ok], period)
    return {'feel_dF_p99_mN': q['dF_p99_mN'], 'feel_dF_max_mN': q['dF_max_mN'],
            'feel_reversals': q['reversals'], 'feel_E_in_min_uJ': q['E_in_min_uJ'],
            'feel_steady_frames': q['steady_frames']}


def haptic_summary(metrics: dict[str, np.ndarray]) -> dict[str, float]:
    """Whole-run figures of the multirate haptic rendering from a metrics table (column -> array,
    every :attr:`VizStats.METRICS_COLUMNS`): lowest and final E_in [J], largest added damping
    [N s/m] and median solver rate [Hz], NaN where no valid value. Empty without multirate rows
    (a direct run, or a table from before the haptic columns: its ``haptic_mode`` is NaN)."""
    multirate = np.asarray(metrics['haptic_mode'], dtype=float) == HAPTIC_MULTIRATE
    if not multirate.any():
        return {}

    def valid(column: str, key: str) -> np.ndarray:
        values = np.asarray(metrics[column], dtype=float)[multirate]
        return values[LIMITS[key].mask(values)]

    energy = valid('energy_in', 'energy_in')
    # The simulator's running minimum also catches dips between (decimated) metrics rows.
    lowest = np.concatenate([energy, valid('energy_in_min', 'energy_in')])
    damping = valid('added_damping', 'added_damping')
    return {
        'energy_in_min_j': float(lowest.min()) if lowest.size else math.nan,
        'energy_in_final_j': float(energy[-1]) if energy.size else math.nan,
        'max_added_damping_n_s_per_m': float(damping.max()) if damping.size else math.nan,
        'solver_rate_p50_hz': percentile(valid('solver_rate', 'solver_rate'), 50),
    }


def _fmt(value: float, scale: float, digits: int, unit: str) -> str:
    if value is None or not math.isfinite(value):
        return '-'
    return f'{value * scale:.{digits}f} {unit}'


def summary_line(snap: Snapshot, instruments: dict[str, Snapshot] | None = None) -> str:
    """Compact one-line status, e.g. ``haptic 998 Hz | step p50 0.08 ms p99 0.2 ms | ...``.

    ``instruments`` (name -> snapshot, several instruments): latency and force per instrument
    (``left lat p50 .. p99 .. F ..``) instead of ``snap``'s; the rest is ``snap``'s (the first
    instrument's, which also counts the cloud)."""
    # The haptic loop's output is the force stream; without it, the (per-step) metrics stream.
    haptic = snap.rates.get('force', 0.0) if snap.counts.get('force') else snap.rates.get('metrics', 0.0)

    def lat(s: Snapshot) -> str:
        return f'lat p50 {_fmt(s.latency_p50, 1e3, 2, "ms")} p99 {_fmt(s.latency_p99, 1e3, 2, "ms")}'

    parts = [
        f'haptic {haptic:.0f} Hz',
        f'step p50 {_fmt(snap.step_p50, 1e3, 2, "ms")} p99 {_fmt(snap.step_p99, 1e3, 2, "ms")}',
        f'miss {_fmt(snap.deadline_miss_pct, 1.0, 1, "%")}',
    ]
    if instruments:
        parts += [f'{name} {lat(s)} F {_fmt(s.force, 1.0, 2, "N")}' for name, s in instruments.items()]
    else:
        parts.append(lat(snap))
    parts.append(f'active {snap.active:.0f}' if math.isfinite(snap.active) else 'active -')
    if not instruments:
        parts.append(f'F {_fmt(snap.force, 1.0, 2, "N")}')
    parts += [f'disp {_fmt(snap.displacement, 1e3, 1, "mm")}',
              f'cloud {snap.rates.get("particles", 0.0):.0f} Hz']
    bad = [snap] if not instruments else list(instruments.values())
    bad_total = sum(s.bad_total for s in bad)
    backwards = sum(s.backwards_total for s in bad)
    if bad_total or backwards:
        parts.append(f'bad input {bad_total} msgs {backwards} stamps backwards')
    return ' | '.join(parts)


def press_displacement(force: np.ndarray, position: np.ndarray,
                       contact_threshold: float = 0.01) -> np.ndarray:
    """Tool displacement along the press direction, from the first contact.

    The press direction is opposite to the largest reaction force (the tissue pushes back against
    the tool), and displacement is measured from the tool position at the first sample whose force
    exceeds ``contact_threshold``. Samples before the contact, or without a finite position, are NaN.

    Args:
        force: (n, 3) force vectors [N].
        position: (n, 3) tool positions [m] at the same samples.
        contact_threshold: force magnitude [N] that counts as contact.

    Returns:
        (n,) displacement [m], NaN where undefined (all NaN if there never was contact).
    """
    force = np.asarray(force, dtype=float).reshape(-1, 3)
    position = np.asarray(position, dtype=float).reshape(-1, 3)
    out = np.full(len(force), np.nan)
    mags = np.linalg.norm(force, axis=1)
    ok = np.isfinite(position).all(axis=1) & np.isfinite(mags)
    contact = np.flatnonzero(ok & (mags > contact_threshold))
    if contact.size == 0:
        return out
    first = contact[0]
    i_max = contact[np.argmax(mags[contact])]
    direction = -force[i_max] / mags[i_max]
    disp = (position - position[first]) @ direction
    after = np.arange(len(force)) >= first
    sel = after & ok
    out[sel] = disp[sel]
    return out
