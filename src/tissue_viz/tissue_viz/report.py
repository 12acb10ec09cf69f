"""Self-contained run report: PNG plots, CSV series, summary.md, index.html and summary.json.

Headless (matplotlib Agg), no rclpy. The viz node writes a report on shutdown and on request; the
``tissue_report`` command rebuilds one from the CSV files of an earlier report::

    tissue_report reports/20261122-210000 -o /tmp/again
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import html
import json
import math
import struct
import sys
import textwrap
import zlib
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tissue_common import feel
from tissue_viz import figures, forked
from tissue_viz.errors import ReportError
from tissue_viz.tissue_images import SnapshotFigure, TissueSnapshots, draw_animation
from tissue_viz.stats import (HAPTIC_MULTIRATE, LIMITS, MAX_RATE, MAX_SECONDS, Limit, VizStats,
                              csv_rows, feel_summary_of, haptic_summary, within, percentile,
                              press_displacement)

TABLES = {
    'metrics': VizStats.METRICS_COLUMNS,
    'force': VizStats.FORCE_COLUMNS,
    'latency': VizStats.LATENCY_COLUMNS,
    'rates': VizStats.RATE_COLUMNS,
    'feel': VizStats.FEEL_COLUMNS,
}
PLOTS = (
    ('force_vs_time.png', 'Force on the tool over time'),
    ('force_vs_displacement.png', 'Force against tool displacement along the press direction'),
    ('step_time_hist.png', 'Simulation step wall time'),
    ('rates.png', 'Topic rates over time'),
    ('latency_hist.png', 'Pose to force latency'),
    ('energy_in.png', 'Energy the hand put into the rendered tissue (multirate haptic rendering)'),
    ('force_change.png', 'What the hand got: the force sent, change from one frame to the next'),
    ('tissue_rest.png', 'The tissue at rest (the first tissue/particles cloud received)'),
    ('tissue_deepest.png', 'The tissue at the deepest press (the cloud with the largest '
                           'displacement), with the simulated tool'),
)
#: the clouds around the deepest press, and the snapshots themselves (for tissue_report); written
#: when viz_node received clouds
ANIMATION = ('tissue_press.gif', 'The deepest press, cloud by cloud: the section through the tool, '
                                 'coloured by displacement')
SNAPSHOTS = 'tissue_snapshots.npz'


@dataclass
class ReportData:
    """Everything a report is made of: whole-run tables (column -> array) and the summary."""

    tables: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    title: str = 'SPH soft-tissue simulation run'
    haptic_period: float = 1e-3          # [s] for the deadline line in the step-time histogram
    contact_threshold: float = 0.01      # [N] force that counts as first contact
    rate_targets: dict = field(default_factory=dict)   # topic -> (min, max) [Hz], drawn as bands
    tissue: TissueSnapshots | None = None               # the clouds to draw the organ from
    #: table -> (rows, CSV lines of those first rows) already formatted during the run
    csv_heads: dict = field(default_factory=dict)
    #: figures built once and drawn again by several plots of one report (not data)
    shared: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def from_stats(cls, stats: VizStats, now: float, instruments: dict[str, VizStats] | None = None,
                   **kw) -> 'ReportData':
        """The report of ``stats``; with several ``instruments`` (name -> their statistics, ``stats``
        the first's) the summary also holds each one's :meth:`~VizStats.instrument_summary` under
        ``instruments``."""
        recorders = {'metrics': stats.metrics_table, 'force': stats.force_table,
                     'latency': stats.latency_table, 'rates': stats.rate_table}
        tables = {name: rec.as_dict() for name, rec in recorders.items()}
        tables['feel'] = stats.feel_table()
        heads = {name: rec.csv_head() for name, rec in recorders.items()}
        summary = stats.summary(now)
        if instruments:
            summary['instruments'] = {name: s.instrument_summary(now) for name, s in instruments.items()}
        return cls(tables=tables, summary=summary, haptic_period=stats.period,
                   csv_heads={name: head for name, head in heads.items() if head[0]}, **kw)

    def table(self, name: str) -> dict:
        cols = TABLES[name]
        got = self.tables.get(name) or {}
        n = len(next(iter(got.values()))) if got else 0
        return {c: np.asarray(got.get(c, np.full(n, np.nan)), dtype=float) for c in cols}


# -- CSV ------------------------------------------------------------------------------------------
_CSV_BLOCK = 4096     # rows formatted per call


def write_csv(path: Path, columns: tuple, table: dict, head: tuple[int, str] | None = None) -> None:
    """One header row, then 12 significant digits per value; NaN (no value) as an empty cell.

    ``head``: (rows, their lines) of the first rows already formatted (:func:`csv_rows`).
    """
    n = len(table[columns[0]]) if columns[0] in table else 0
    with open(path, 'w', newline='') as fh:
        fh.write(','.join(columns) + '\n')
        if n:
            arr = np.column_stack([np.asarray(table[c], dtype=float) for c in columns])
            done = 0
            if head is not None and 0 < head[0] <= n:
                fh.write(head[1])
                done = head[0]
            for a in range(done, n, _CSV_BLOCK):
                fh.write(csv_rows(arr[a:a + _CSV_BLOCK]))


def read_csv(path: Path) -> dict:
    """Read a report CSV back into column -> float array (empty cells are NaN)."""
    try:
        with open(path, newline='') as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise ReportError(f'cannot read {path}: {exc}') from exc
    if not rows:
        raise ReportError(f'{path} is empty (expected a header row)')
    header, body = rows[0], rows[1:]
    try:
        data = np.array([[float(x) if x != '' else np.nan for x in row] for row in body],
                        dtype=float).reshape(len(body), len(header))
    except ValueError as exc:
        raise ReportError(f'{path}: not a numeric CSV with {len(header)} columns: {exc}') from exc
    return {name: data[:, i] for i, name in enumerate(header)}


# -- plots ----------------------------------------------------------------------------------------
# Columns the node derives from its own clock have no input limit; only absurd numbers are dropped.
_TIMES = Limit(-math.inf, math.inf, 'times', 's')
_RATES = Limit(0.0, MAX_RATE, 'rates', 'Hz')


def _figure():
    fig = figures.new_figure((8, 4.5), 100)
    ax = fig.add_subplot()
    ax.grid(True, alpha=0.3)
    return fig, ax


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    figures.save_png(fig, path)


def _no_data(ax, what: str) -> None:
    ax.text(0.5, 0.5, f'no {what} recorded', ha='center', va='center', transform=ax.transAxes,
            fontsize=14, color='0.4')


def _left_out(ax, count: int, what: str) -> None:
    """Say on the plot how many values were not drawn because they were not finite or absurd."""
    if count:
        ax.text(0.01, 0.01, f'{what} not finite or out of range, not plotted: {count}',
                transform=ax.transAxes, fontsize=8, color='tab:red', va='bottom')


def _finish(fig, ax, path: Path, xlabel: str, ylabel: str, dropped: int, what: str) -> None:
    """Label the axes, say what was left out (:func:`_left_out`) and save."""
    _left_out(ax, dropped, what)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _save(fig, path)


def _force_source(data: ReportData) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, Limit]:
    """(t, force vectors, tool positions, label, limit of the force components): force commands
    if any, else metrics forces."""
    force = data.table('force')
    if len(force['t']):
        vec = np.column_stack([force['fx'], force['fy'], force['fz']])
        pos = np.column_stack([force['px'], force['py'], force['pz']])
        return force['t'], vec, pos, 'omni/force_feedback', LIMITS['wrench_force']
    m = data.table('metrics')
    vec = np.column_stack([m['fx'], m['fy'], m['fz']])
    return (m['t'], vec, np.full_like(vec, np.nan), 'tissue/metrics contact_force',
            LIMITS['contact_force'])


def _plottable_forces(data: ReportData):
    """:func:`_force_source` restricted to rows with a finite time and a force inside its limits
    (positions outside theirs become NaN, i.e. unknown); also returns how many rows were dropped."""
    t, vec, pos, label, limit = _force_source(data)
    ok = _TIMES.mask(t) & limit.mask(vec).all(axis=1)
    pos = np.where(LIMITS['pose_position'].mask(pos).all(axis=1)[:, None], pos, np.nan)
    return t[ok], vec[ok], pos[ok], label, int(len(t) - np.count_nonzero(ok))


#: samples a plot draws of a long series at most: a plot is about 700 pixels wide, and the min and
#: max of each of 999 buckets (plus the first and last sample) keep every spike a pixel column shows
MAX_PLOT_POINTS = 2000


def _thin(n: int, keep: np.ndarray | None = None) -> np.ndarray:
    """Sorted indices of at most MAX_PLOT_POINTS of ``n`` samples: the first, the last and each
    bucket's min and max of ``keep`` (so peaks survive thinning), or evenly spaced ones without
    ``keep``."""
    if n <= MAX_PLOT_POINTS:
        return np.arange(n)
    if keep is None:
        return np.unique(np.linspace(0, n - 1, MAX_PLOT_POINTS).astype(int))
    buckets = (MAX_PLOT_POINTS - 2) // 2
    size = -(-n // buckets)
    finite = np.isfinite(keep)
    # equal buckets as rows of a matrix; the padding after the last sample never wins
    high = np.full(buckets * size, -np.inf)
    high[:n] = np.where(finite, keep, -np.inf)
    low = np.full(buckets * size, np.inf)
    low[:n] = np.where(finite, keep, np.inf)
    start = np.arange(buckets) * size
    idx = np.concatenate([[0, n - 1], start + low.reshape(buckets, size).argmin(axis=1),
                          start + high.reshape(buckets, size).argmax(axis=1)])
    return np.unique(idx[idx < n])


def _break_gaps(t: np.ndarray, *series: np.ndarray,
                sel: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """``t`` and ``series`` at the samples ``sel`` (all by default), with a NaN row where the stream
    paused (> 10 median periods and > 0.1 s) so lines do not bridge it; shorter hiccups of a loaded
    machine stay joined. The pauses are found in the whole series, so thinning hides none."""
    t = np.asarray(t, dtype=float)
    if sel is None:
        sel = np.arange(len(t))
    out = [t[sel], *(np.asarray(s, dtype=float)[sel] for s in series)]
    if len(t) < 3:
        return tuple(out)
    dt = np.diff(t)
    typical = np.median(dt[dt > 0]) if np.any(dt > 0) else 0.0
    if not typical > 0:
        return tuple(out)
    gaps = np.flatnonzero(dt > max(10.0 * typical, 0.1)) + 1
    # a pause between samples g-1 and g lies before the first drawn sample at or after g
    at = np.searchsorted(sel, gaps)
    at = np.unique(at[(at > 0) & (at < len(sel))])
    if at.size == 0:
        return tuple(out)
    return tuple(np.insert(s, at, np.nan, axis=0) for s in out)


def plot_force_vs_time(data: ReportData, path: Path) -> None:
    fig, ax = _figure()
    t, vec, _, label, dropped = _plottable_forces(data)
    if len(t):
        t, vec = _break_gaps(t, vec, sel=_thin(len(t), np.linalg.norm(vec, axis=1)))
        mag = np.linalg.norm(vec, axis=1)
        for i, (axis, colour) in enumerate(zip('xyz', ('tab:red', 'tab:green', 'tab:blue'))):
            ax.plot(t, vec[:, i], color=colour, lw=0.8, alpha=0.7, label=f'F{axis}')
        ax.plot(t, mag, color='k', lw=1.4, label='|F|')
        ax.legend(loc='upper right', fontsize=8)
        ax.set_title(f'Force on the tool ({label})')
    else:
        _no_data(ax, 'force')
        ax.set_title('Force on the tool')
    _finish(fig, ax, path, 'time [s]', 'force [N]', dropped, 'forces')


def _time_scatter(fig, ax, x, y, t, title: str) -> None:
    """Points coloured by time, with a colour bar."""
    sc = ax.scatter(x, y, c=t, s=4, cmap='viridis')
    fig.colorbar(sc, ax=ax, label='time [s]')
    ax.set_title(title)


def plot_force_vs_displacement(data: ReportData, path: Path) -> None:
    fig, ax = _figure()
    t, vec, pos, _, dropped = _plottable_forces(data)
    disp = press_displacement(vec, pos, data.contact_threshold) if len(t) else np.array([])
    ok = np.isfinite(disp)
    if ok.any():
        mag = np.linalg.norm(vec, axis=1)
        sel = np.flatnonzero(ok)
        sel = sel[_thin(len(sel), mag[sel])]
        _time_scatter(fig, ax, disp[sel] * 1e3, mag[sel], t[sel],
                      'Force against tool displacement (from first contact, along the press)')
    else:
        # Without matched tool positions fall back to the penetration reported by the simulator.
        m = data.table('metrics')
        vec = np.column_stack([m['fx'], m['fy'], m['fz']])
        rows = (_TIMES.mask(m['t']) & LIMITS['contact_force'].mask(vec).all(axis=1)
                & LIMITS['penetration'].mask(m['penetration']))
        dropped = int(len(rows) - np.count_nonzero(rows))
        pen_ok = rows & (np.where(rows, m['penetration'], 0.0) > 0)
        if pen_ok.any():
            sel = np.flatnonzero(pen_ok)
            mag = np.linalg.norm(vec[sel], axis=1)
            keep = _thin(len(sel), mag)
            sel, mag = sel[keep], mag[keep]
            _time_scatter(fig, ax, m['penetration'][sel] * 1e3, mag, m['t'][sel],
                          'Force against tool penetration (tissue/metrics)')
        else:
            _no_data(ax, 'contact')
            ax.set_title('Force against tool displacement')
    _finish(fig, ax, path, 'tool displacement [mm]', '|F| [N]', dropped, 'samples')


# Log-spaced bins span at most this many decades; anything faster lands in the first bin (a log
# axis over hundreds of decades, from a step time of 1e-300 s, would show nothing).
_LOG_DECADES = 9


def _log_bins(positive: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(values clipped to the lowest edge, log-spaced bin edges) covering ``positive``."""
    top = float(positive.max())
    low = max(float(positive.min()), top * 10.0 ** -_LOG_DECADES)
    bins = np.logspace(np.log10(low), np.log10(top), n_bins)
    bins[0], bins[-1] = low, top          # exact ends, so rounding drops no sample
    return np.clip(positive, low, top), bins


# One filled outline instead of a patch per bar: the same pixels, a third less time to draw.
_HISTTYPE = 'stepfilled'


def _hist(ax, values_s: np.ndarray, colour: str, p_lines: bool = True) -> None:
    """Histogram in milliseconds of finite, non-negative, bounded ``values_s`` [s]."""
    ms = values_s[np.isfinite(values_s)] * 1e3
    n_bins = min(80, max(10, int(np.sqrt(ms.size))))
    positive = ms[ms > 0]
    median = float(np.median(positive)) if positive.size else 0.0
    if median > 0 and positive.max() > 20.0 * median:
        # A long tail (a stalled step among fast ones): log-spaced bins on a log axis keep both
        # the bulk and the tail readable.
        clipped, bins = _log_bins(positive, n_bins)
        ax.hist(clipped, bins=bins, color=colour, alpha=0.8, histtype=_HISTTYPE)
        ax.set_xscale('log')
        from matplotlib.ticker import FuncFormatter
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f'{v:g}'))
        zeros = ms.size - positive.size
        if zeros:
            ax.text(0.99, 0.97, f'{zeros} zero values not on the log axis', ha='right', va='top',
                    transform=ax.transAxes, fontsize=8, color='0.3')
    else:
        ax.hist(ms, bins=n_bins, color=colour, alpha=0.8, histtype=_HISTTYPE)
    # Log counts: the rare slow steps that miss the deadline are the point of the plot.
    ax.set_yscale('log')
    if p_lines:
        for q, style in ((50, '--'), (99, ':')):
            v = percentile(ms, q)
            if v > 0 or ax.get_xscale() == 'linear':
                ax.axvline(v, color='k', ls=style, lw=1, label=f'p{q} {v:.3f} ms')


def plot_step_hist(data: ReportData, path: Path) -> None:
    fig, ax = _figure()
    raw = data.table('metrics')['step_wall_time']
    ok = LIMITS['step_wall_time'].mask(raw)
    steps = raw[ok]
    period = data.haptic_period
    if steps.size:
        _hist(ax, steps, 'tab:blue')
        if within(period, 0.0, MAX_SECONDS) and period > 0:
            ax.axvline(period * 1e3, color='tab:red', lw=1.2,
                       label=f'haptic period {period * 1e3:.2f} ms')
            miss = 100.0 * np.count_nonzero(steps > period) / steps.size
            ax.set_title(f'Step wall time ({steps.size} steps, {miss:.2f} % over the period)')
        else:
            ax.set_title(f'Step wall time ({steps.size} steps)')
        ax.legend(fontsize=8)
    else:
        _no_data(ax, 'step')
        ax.set_title('Step wall time')
    _finish(fig, ax, path, 'step wall time [ms]', 'steps', int(raw.size - steps.size),
            'step times')


def _rate_target(value) -> tuple[float, float] | None:
    """A (min, max) rate band if ``value`` is one, else None (nothing is drawn)."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return (lo, hi) if _RATES.ok(lo, hi) and lo <= hi else None


def plot_rates(data: ReportData, path: Path) -> None:
    """Haptic-loop topics (metrics, pose, force) above, the particle cloud below, linear scales."""
    fig = figures.new_figure((8, 4.5), 100)
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [2, 1]})
    rates = data.table('rates')
    t_ok = _TIMES.mask(rates['t'])
    colours = {'metrics': 'tab:blue', 'pose': 'tab:green', 'force': 'tab:red',
               'particles': 'tab:orange'}
    dropped = 0
    for ax, topics in ((top, ('metrics', 'pose', 'force')), (bottom, ('particles',))):
        ax.grid(True, alpha=0.3)
        ax.set_ylabel('rate [Hz]')
        if not t_ok.any():
            _no_data(ax, 'rate')
            continue
        target = _rate_target(data.rate_targets.get(topics[0]))
        if target:
            ax.axhspan(target[0], target[1], color=colours[topics[0]], alpha=0.12,
                       label=f'{topics[0]} target {target[0]:g}-{target[1]:g} Hz')
        t = rates['t'][t_ok]
        for topic in topics:
            ok = _RATES.mask(rates[topic][t_ok])
            dropped += int(ok.size - np.count_nonzero(ok))
            ax.plot(t, np.where(ok, rates[topic][t_ok], np.nan), lw=1.4, color=colours[topic],
                    marker='.' if len(t) < 30 else None, label=topic)
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=8, loc='lower right')
    _left_out(bottom, dropped + int(t_ok.size - np.count_nonzero(t_ok)), 'rate samples')
    top.set_title('Topic rates over time (sliding window)')
    bottom.set_xlabel('time [s]')
    _save(fig, path)


def plot_latency_hist(data: ReportData, path: Path) -> None:
    fig, ax = _figure()
    raw = data.table('latency')['latency']
    lat = raw[LIMITS['latency'].mask(raw)]
    if lat.size:
        _hist(ax, lat, 'tab:purple')
        ax.legend(fontsize=8)
        ax.set_title(f'Pose to force latency ({lat.size} replies)')
    else:
        _no_data(ax, 'latency')
        ax.set_title('Pose to force latency')
    _finish(fig, ax, path, 'latency [ms]', 'replies', int(raw.size - lat.size), 'latencies')


def plot_energy_in(data: ReportData, path: Path) -> None:
    """E_in of the multirate rendering against time; a passive rendering never goes below zero."""
    fig, ax = _figure()
    m = data.table('metrics')
    # A direct run, or an old CSV without the column (NaN), has no multirate rows.
    multirate = m['haptic_mode'] == HAPTIC_MULTIRATE
    t, energy = m['t'][multirate], m['energy_in'][multirate]
    ok = _TIMES.mask(t) & LIMITS['energy_in'].mask(energy)
    dropped = int(ok.size - np.count_nonzero(ok))
    if ok.any():
        t, energy = t[ok], energy[ok]
        t, energy = _break_gaps(t, energy, sel=_thin(len(t), energy))
        uj = energy * 1e6
        ax.axhline(0.0, color='k', lw=1.0)
        if np.any(uj < 0):
            ax.fill_between(t, uj, 0.0, where=uj < 0, color='tab:red', alpha=0.3,
                            label='given back (not passive)')
        ax.plot(t, uj, color='tab:blue', lw=1.2, label='E_in')
        ax.legend(loc='upper left', fontsize=8)
    else:
        _no_data(ax, 'multirate haptic rendering')
    ax.set_title('E_in: energy the hand put in (below zero the rendering gives energy back)')
    _finish(fig, ax, path, 'time [s]', 'E_in [uJ]', dropped, 'energies')


def plot_force_change(data: ReportData, path: Path) -> None:
    """|dF| of the force sent from one answered pose to the next (stamp order), against the
    goldens' targets: p99 at most 5 mN in steady contact, no one-frame reversal above 10 mN."""
    fig, ax = _figure()
    f = data.table('feel')
    t = f['stamp']
    vec = np.column_stack([f['fx'], f['fy'], f['fz']])
    ok = _TIMES.mask(t) & LIMITS['wrench_force'].mask(vec).all(axis=1)
    dropped = int(ok.size - np.count_nonzero(ok))
    t, vec = t[ok], vec[ok]
    near = feel.neighbour_frames(t, len(t), data.haptic_period)
    if near.any():
        d_mn = np.linalg.norm(np.diff(vec, axis=0), axis=1)[near] * 1e3
        tt = t[1:][near]
        sel = _thin(len(tt), d_mn)
        ax.plot(tt[sel], d_mn[sel], color='tab:blue', lw=0.6, label='|dF| per frame')
        ax.axhline(feel.TARGETS['dF_p99_mN'], color='tab:green', ls='--', lw=1.0,
                   label='target for the p99 in steady contact')
        ax.axhline(feel.REVERSAL * 1e3, color='tab:red', ls=':', lw=1.0,
                   label='a change this large that comes straight back is a click')
        ax.set_yscale('symlog', linthresh=1.0)
        ax.set_ylim(bottom=0.0)
        ax.legend(loc='upper right', fontsize=8)
        s = data.summary
        ax.set_title(f"Force sent, change per frame: p99 {_fmt(s.get('feel_dF_p99_mN'), 1, 2, 'mN')} "
                     f"in steady contact,\n{_fmt(s.get('feel_reversals'), 1, 0)} one-frame reversals "
                     f"above {feel.REVERSAL * 1e3:g} mN, E_in min {_fmt(s.get('feel_E_in_min_uJ'), 1, 2, 'uJ')} "
                     f"(targets: 5 mN, none, -1 uJ)", fontsize=10)
    else:
        _no_data(ax, 'answered poses')
        ax.set_title('Force sent, change per frame')
    _finish(fig, ax, path, 'pose stamp [s]', '|dF| [mN]', dropped, 'forces')


def _placeholder(path: Path, title: str, reason: str) -> None:
    """A plot that says why it could not be drawn (a plain grey PNG if not even text can be).

    Raises:
        OSError: the file cannot be written.
    """
    try:
        fig, ax = _figure()
        ax.axis('off')
        ax.set_title(title)
        ax.text(0.5, 0.5, 'plot could not be drawn:\n' + textwrap.fill(reason, 70), ha='center',
                va='center', transform=ax.transAxes, fontsize=10, color='tab:red',
                parse_math=False)
        _save(fig, path)
    except OSError:
        raise
    except Exception:  # noqa: BLE001 -- matplotlib itself failed: still leave a valid image
        _plain_png(path, 800, 450)


def _plain_png(path: Path, width: int, height: int, grey: int = 230) -> None:
    """A uniform grey PNG written without any imaging library."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack('>I', len(body)) + kind + body
                + struct.pack('>I', zlib.crc32(kind + body) & 0xFFFFFFFF))

    rows = b''.join(b'\x00' + bytes([grey]) * width for _ in range(height))
    header = struct.pack('>IIBBBBB', width, height, 8, 0, 0, 0, 0)   # 8-bit greyscale
    Path(path).write_bytes(b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', header)
                           + chunk(b'IDAT', zlib.compress(rows)) + chunk(b'IEND', b''))


def _plot_tissue(which: str):
    def plot(data: ReportData, path: Path) -> None:
        t = data.tissue
        snap = getattr(t, which, None) if t is not None else None
        if snap is None:
            fig, ax = _figure()
            ax.set_title('Tissue ' + ('at rest' if which == 'rest' else 'at the deepest press'))
            _no_data(ax, 'tissue/particles cloud')
            _save(fig, path)
            return
        title = ('at rest' if which == 'rest' else
                 f'at the deepest press: largest displacement {snap.peak * 1e3:.1f} mm')
        # rest and deepest share their scales, so they share one figure
        if 'tissue' not in data.shared:
            data.shared['tissue'] = SnapshotFigure([t.rest, t.deepest], reference=t.rest)
        try:
            data.shared['tissue'].save(snap, path,
                                       f'Tissue {title} ({len(snap.xyz)} particles drawn)')
        except Exception:
            del data.shared['tissue']       # half drawn: the next plot builds its own
            raise
    return plot


PLOTTERS = {
    'tissue_rest.png': _plot_tissue('rest'),
    'tissue_deepest.png': _plot_tissue('deepest'),
    'force_vs_time.png': plot_force_vs_time,
    'force_vs_displacement.png': plot_force_vs_displacement,
    'step_time_hist.png': plot_step_hist,
    'rates.png': plot_rates,
    'latency_hist.png': plot_latency_hist,
    'energy_in.png': plot_energy_in,
    'force_change.png': plot_force_change,
}


# -- summaries ------------------------------------------------------------------------------------
# Which table columns carry each input quantity of LIMITS (all columns of a row must be in range).
BAD_VALUE_COLUMNS = (
    ('metrics', 'step_wall_time', ('step_wall_time',)),
    ('metrics', 'contact_force', ('fx', 'fy', 'fz')),
    ('metrics', 'max_displacement', ('max_displacement',)),
    ('metrics', 'penetration', ('penetration',)),
    ('metrics', 'kinetic_energy', ('kinetic_energy',)),
    ('metrics', 'active_particles', ('n_active',)),
    ('metrics', 'substeps', ('substeps',)),
    ('metrics', 'contact_index', ('contact_index',)),
    ('metrics', 'haptic_mode', ('haptic_mode',)),
    ('metrics', 'solver_rate', ('solver_rate',)),
    ('metrics', 'model_age', ('model_age',)),
    ('metrics', 'coupling_stretch', ('coupling_stretch',)),
    ('metrics', 'energy_in', ('energy_in', 'energy_in_min')),
    ('metrics', 'added_damping', ('added_damping',)),
    ('force', 'wrench_force', ('fx', 'fy', 'fz')),
    ('force', 'pose_position', ('px', 'py', 'pz')),
    ('latency', 'latency', ('latency',)),
)


def bad_values_in_tables(data: ReportData) -> dict[str, int]:
    """Per LIMITS key, the table rows holding a value that is NaN/inf or out of range.

    Only columns the tables actually hold are judged, and a tool position that is NaN in all three
    columns means "no pose matched" rather than a bad value.
    """
    counts = {}
    for table, key, columns in BAD_VALUE_COLUMNS:
        got = data.tables.get(table) or {}
        if not all(c in got for c in columns):
            continue
        values = np.column_stack([np.asarray(got[c], dtype=float) for c in columns])
        if values.size and np.isnan(values).all():
            # Not one value: the empty cells a rebuilt report writes for a column its source
            # lacked (e.g. the haptic columns of an older report), so as good as absent.
            continue
        bad = ~LIMITS[key].mask(values).all(axis=1)
        if key == 'pose_position':
            bad &= ~np.isnan(values).all(axis=1)
        counts[key] = counts.get(key, 0) + int(np.count_nonzero(bad))
    return counts


def summary_from_tables(data: ReportData) -> dict:
    """A summary computed from the tables alone (when no summary.json came with them)."""
    m, f, lat, r = (data.table(n) for n in ('metrics', 'force', 'latency', 'rates'))
    steps = m['step_wall_time'][LIMITS['step_wall_time'].mask(m['step_wall_time'])]
    latency = lat['latency'][LIMITS['latency'].mask(lat['latency'])]
    forces = np.concatenate([f['force'], m['force']])
    forces = forces[LIMITS['wrench_force'].mask(forces)]
    times = np.concatenate([m['t'], f['t'], r['t']])
    times = times[np.isfinite(times)]
    disp = m['max_displacement'][LIMITS['max_displacement'].mask(m['max_displacement'])]

    def num(x):
        return None if x is None or not math.isfinite(x) else float(x)

    def mean_rate(t):
        t = t[np.isfinite(t)]
        return num((t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else math.nan)

    period = data.haptic_period if within(data.haptic_period, 0.0, MAX_SECONDS) else math.nan
    misses = int(np.count_nonzero(steps > period))
    return {
        'duration_s': num(times.max() - times.min() if times.size else math.nan),
        'haptic_period_s': num(period),
        'rates_hz': {'metrics': mean_rate(m['t']), 'force': mean_rate(f['t'])},
        'steps': int(steps.size),
        'forces': int(len(f['t'])),
        'step_p50_s': num(percentile(steps, 50)),
        'step_p99_s': num(percentile(steps, 99)),
        'step_max_s': num(float(steps.max()) if steps.size else math.nan),
        'deadline_misses': misses,
        'deadline_miss_pct': num(100.0 * misses / steps.size if steps.size else math.nan),
        'latency_p50_s': num(percentile(latency, 50)),
        'latency_p99_s': num(percentile(latency, 99)),
        'max_force_n': num(float(forces.max()) if forces.size else math.nan),
        'max_displacement_m': num(float(disp.max()) if disp.size else math.nan),
        'bad_values': bad_values_in_tables(data),
        **{key: num(value) for key, value in haptic_summary(m).items()},
        **{key: num(value) for key, value in feel_summary_of(data.table('feel'), period
                                                              if math.isfinite(period) else 1e-3).items()},
    }


def _fmt(value, scale: float = 1.0, digits: int = 3, unit: str = '') -> str:
    if value is None or isinstance(value, bool):
        return 'n/a' if value is None else str(value)
    if isinstance(value, (int, float, np.integer, np.floating)):
        try:
            x = float(value) * scale
        except OverflowError:          # an integer beyond any float
            return str(value)
        if not math.isfinite(x):
            return 'n/a'
        text = f'{x:.3g}' if abs(x) >= 1e12 else f'{x:.{digits}f}'
        return text + (f' {unit}' if unit else '')
    return str(value)


def summary_rows(summary: dict) -> list[tuple[str, str]]:
    """(label, formatted value) rows shared by summary.md and index.html."""
    rows = [('duration', _fmt(summary.get('duration_s'), 1, 1, 's'))]
    rates = summary.get('rates_hz')
    for topic, rate in (rates.items() if isinstance(rates, dict) else ()):
        rows.append((f'{topic} rate', _fmt(rate, 1, 1, 'Hz')))
    rows += [
        ('steps', _fmt(summary.get('steps'), 1, 0)),
        ('step wall time p50', _fmt(summary.get('step_p50_s'), 1e3, 3, 'ms')),
        ('step wall time p99', _fmt(summary.get('step_p99_s'), 1e3, 3, 'ms')),
        ('step wall time max', _fmt(summary.get('step_max_s'), 1e3, 3, 'ms')),
        ('deadline misses', f"{_fmt(summary.get('deadline_misses'), 1, 0)} "
                            f"({_fmt(summary.get('deadline_miss_pct'), 1, 2, '%')})"),
        ('poses', _fmt(summary.get('poses'), 1, 0)),
        ('pose to force latency p50', _fmt(summary.get('latency_p50_s'), 1e3, 3, 'ms')),
        ('pose to force latency p99', _fmt(summary.get('latency_p99_s'), 1e3, 3, 'ms')),
        ('poses without reply', _fmt(summary.get('replies_missed_pct'), 1, 2, '%')),
        ('max force', _fmt(summary.get('max_force_n'), 1, 3, 'N')),
        ('max displacement', _fmt(summary.get('max_displacement_m'), 1e3, 2, 'mm')),
        ('max active particles', _fmt(summary.get('max_active_particles'), 1, 0)),
        ('messages with NaN/inf or out-of-range values (ignored)',
         _fmt(summary.get('bad_messages'), 1, 0)),
    ]
    if 'energy_in_min_j' in summary:     # only a run with multirate haptic rendering has these
        rows += [
            ('E_in min (below zero: not passive)', _fmt(summary.get('energy_in_min_j'), 1e6, 3,
                                                         'uJ')),
            ('E_in final', _fmt(summary.get('energy_in_final_j'), 1e6, 3, 'uJ')),
            ('max added damping', _fmt(summary.get('max_added_damping_n_s_per_m'), 1, 3,
                                       'N s/m')),
            ('solver rate p50', _fmt(summary.get('solver_rate_p50_hz'), 1, 1, 'Hz')),
        ]
    instruments = summary.get('instruments')
    for name, s in (instruments.items() if isinstance(instruments, dict) else ()):
        s = _counts(s)                   # several instruments: each one's force, latency and E_in
        rows += [
            (f'{name}: max force', _fmt(s.get('max_force_n'), 1, 3, 'N')),
            (f'{name}: pose to force latency p50', _fmt(s.get('latency_p50_s'), 1e3, 3, 'ms')),
            (f'{name}: pose to force latency p99', _fmt(s.get('latency_p99_s'), 1e3, 3, 'ms')),
            (f'{name}: poses without reply', _fmt(s.get('replies_missed_pct'), 1, 2, '%')),
            (f'{name}: E_in min (below zero: not passive)', _fmt(s.get('energy_in_min_j'), 1e6, 3, 'uJ')),
        ]
    if 'feel_dF_p99_mN' in summary:      # what the hand got: the forces sent, frame to frame
        rows += [
            ('force change per frame in steady contact p99 (target <= 5 mN)',
             _fmt(summary.get('feel_dF_p99_mN'), 1, 2, 'mN')),
            ('force change per frame in steady contact max', _fmt(summary.get('feel_dF_max_mN'), 1, 1, 'mN')),
            ('one-frame force reversals above 10 mN (clicks; target 0)',
             _fmt(summary.get('feel_reversals'), 1, 0)),
            ('E_in min of the forces sent (target >= -1 uJ)', _fmt(summary.get('feel_E_in_min_uJ'), 1, 2, 'uJ')),
        ]
    return rows


def _counts(value) -> dict:
    return value if isinstance(value, dict) else {}


def problem_lines(summary: dict) -> list[str]:
    """Sentences on what the report could not show: bad values, plots replaced by a placeholder."""
    lines = []
    for key, count in _counts(summary.get('bad_values')).items():
        if isinstance(count, (int, np.integer)) and count > 0 and key in LIMITS:
            limit = LIMITS[key]
            lines.append(f'{limit.what}: {count} not finite or out of range (accepted '
                         f'{limit.describe()}), not plotted and not in the statistics')
    for png, reason in _counts(summary.get('plot_failures')).items():
        lines.append(f'{png} could not be drawn ({reason}); it shows a placeholder')
    return lines


def write_markdown(path: Path, data: ReportData, created: str) -> None:
    lines = [f'# {data.title}', '', f'Report written {created}.', '', '| quantity | value |',
             '|---|---|']
    lines += [f'| {k} | {v} |' for k, v in summary_rows(data.summary)]
    problems = problem_lines(data.summary)
    if problems:
        lines += ['', '## Not shown', ''] + [f'- {line}' for line in problems]
    lines += ['', 'Series: ' + ', '.join(f'[{n}.csv]({n}.csv)' for n in TABLES) +
              ', machine-readable summary: [summary.json](summary.json).', '']
    for png, caption in _figures(path.parent):
        lines += [f'## {caption}', '', f'![{caption}]({png})', '']
    path.write_text('\n'.join(lines))


def _figures(folder: Path) -> list[tuple[str, str]]:
    """The plots, and the animation where it was written."""
    return list(PLOTS) + ([ANIMATION] if (folder / ANIMATION[0]).is_file() else [])


def write_html(path: Path, data: ReportData, created: str) -> None:
    rows = '\n'.join(f'<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>'
                     for k, v in summary_rows(data.summary))
    problems = problem_lines(data.summary)
    not_shown = ('<h2>Not shown</h2><ul>' + ''.join(f'<li>{html.escape(p)}</li>' for p in problems)
                 + '</ul>') if problems else ''
    figures = '\n'.join(
        f'<figure><img src="{png}" alt="{html.escape(c)}"><figcaption>{html.escape(c)}'
        f'</figcaption></figure>' for png, c in _figures(path.parent))
    links = ', '.join(f'<a href="{n}.csv">{n}.csv</a>' for n in TABLES)
    path.write_text(f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(data.title)}</title>
<style>body{{font-family:sans-serif;max-width:900px;margin:2em auto}}
table{{border-collapse:collapse}}td{{border:1px solid #ccc;padding:2px 8px}}
img{{max-width:100%}}figure{{margin:1.5em 0}}</style></head>
<body><h1>{html.escape(data.title)}</h1><p>Report written {html.escape(created)}.</p>
<table>{rows}</table>
{not_shown}
<p>Series: {links}; summary: <a href="summary.json">summary.json</a>.</p>
{figures}
</body></html>
""")


def _json_safe(obj):
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    return str(obj)


def default_report_dir(base: str | Path = 'reports') -> Path:
    return Path(base) / _dt.datetime.now().strftime('%Y%m%d-%H%M%S')


def report_files() -> list[str]:
    """Every file of a report folder, summary.json (written last) at the end."""
    return ([f'{n}.csv' for n in TABLES] + [png for png, _ in PLOTS]
            + ['summary.md', 'index.html', 'summary.json'])


def prepare_report_dir(directory: str | Path) -> Path:
    """Create the report folder and check that its files can be written there; return it.

    Quick (no data involved), so a caller can refuse a report before starting to draw it.

    Raises:
        ReportError: naming the folder or file and the reason.
    """
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReportError(f'cannot create report folder {out}: {exc}') from exc
    try:
        probe = out / '.write_test'
        probe.write_bytes(b'')
        probe.unlink()
    except OSError as exc:
        raise ReportError(f'cannot write into report folder {out}: {exc}') from exc
    for name in report_files():
        target = out / name
        if target.exists() and not target.is_file():
            raise ReportError(f'cannot write {target}: it exists and is not a file')
    return out


def _reason(exc: BaseException) -> str:
    return f'{type(exc).__name__}: {exc}'


def _complete_summary(data: ReportData) -> dict:
    """The summary to write: the given one, else one from the tables; bad values counted from the
    tables when the summary does not carry them. Never raises (a failure is noted instead)."""
    try:
        summary = dict(data.summary) if data.summary else summary_from_tables(data)
        if 'bad_values' not in summary:
            summary['bad_values'] = bad_values_in_tables(data)
    except Exception as exc:  # noqa: BLE001 -- the plots and series are still worth writing
        summary = {'summary_error': _reason(exc)}
    return summary


def _draw(plotter, data: ReportData, path: Path, caption: str) -> str | None:
    """Draw one plot; if that fails for any reason draw a placeholder naming it instead.

    Returns:
        The reason the plot could not be drawn, None when it was.

    Raises:
        OSError: not even the placeholder could be written.
    """
    try:
        with np.errstate(all='ignore'):
            plotter(data, path)
        return None
    except Exception as exc:  # noqa: BLE001 -- one plot must never cost the whole report
        reason = _reason(exc)
    _placeholder(path, caption, reason)
    return reason


def write_report(directory: str | Path, data: ReportData, processes: int = 1) -> Path:
    """Write the report folder and return its path (created if needed).

    Whatever the tables hold, every file is written: values that are NaN/inf or out of range are
    left out of the plots and counted in the summary, and a plot that fails anyway is replaced by a
    placeholder naming the failure. Only a file that cannot be written at all (an unwritable
    folder, a full disk) is an error; the other files are still written first.

    ``processes`` > 1 draws in that many processes, the caller and forked children (see
    :mod:`tissue_viz.forked`: only where no other thread of the caller can hold a lock).

    Raises:
        ReportError: the folder cannot be used, or some files could not be written (named with
            their reasons; summary.json then lists them under ``failed_files``).
    """
    out = prepare_report_dir(directory)
    # A summary.json left from an earlier report would claim this one is finished.
    try:
        (out / 'summary.json').unlink(missing_ok=True)
    except OSError as exc:
        raise ReportError(f'cannot remove the old {out / "summary.json"}: {exc}') from exc
    created = _dt.datetime.now(_dt.timezone.utc).strftime('%Y-%m-%d %H:%M:%S UTC')
    data = dataclasses.replace(data, summary=_complete_summary(data))
    failed: dict[str, str] = {}

    def attempt(name: str, write) -> None:
        try:
            write()
        except Exception as exc:  # noqa: BLE001 -- named in the result, the rest still written
            failed[name] = _reason(exc)

    for stale in (ANIMATION[0], SNAPSHOTS):     # from an earlier report into this folder
        attempt(stale, lambda p=out / stale: p.unlink(missing_ok=True))
    outcomes = forked.run(_file_jobs(out, data), processes)
    plot_failures: dict[str, str] = {}
    for name in report_files() + [SNAPSHOTS, ANIMATION[0]]:
        outcome = outcomes.get(name, {})
        if 'failed' in outcome:
            failed[name] = outcome['failed']
        if 'plot_failure' in outcome:
            plot_failures[name] = outcome['plot_failure']
    data.summary['plot_failures'] = plot_failures
    attempt('summary.md', lambda: write_markdown(out / 'summary.md', data, created))
    attempt('index.html', lambda: write_html(out / 'index.html', data, created))
    attempt('summary.json', lambda: _write_summary_json(out, data, created, failed))
    if failed:
        total = len(report_files())
        raise ReportError(f'{len(failed)} of {total} report files not written into {out}: '
                          + '; '.join(f'{name} ({reason})' for name, reason in failed.items()))
    return out


def _file_jobs(out: Path, data: ReportData) -> list:
    """The files of a report but its summaries, as jobs of :func:`tissue_viz.forked.run`: each
    returns {file: {'failed': reason} or {'plot_failure': reason} or {}}.

    The data first (tissue_report redraws everything from it), then the drawings, the slowest first
    so that parallel processes finish together. The two tissue images share one figure, so they
    are one job.
    """
    def job(*files: tuple[str, object]):
        def run() -> dict:
            outcome = {}
            for name, write in files:
                try:
                    reason = write()
                except Exception as exc:  # noqa: BLE001 -- named in the result, the rest written
                    outcome[name] = {'failed': _reason(exc)}
                else:
                    outcome[name] = {'plot_failure': reason} if reason else {}
            return outcome
        return run

    def table(name: str, columns: tuple):
        return f'{name}.csv', lambda: write_csv(out / f'{name}.csv', columns, data.table(name),
                                                data.csv_heads.get(name))

    def plot(png: str):
        return png, lambda: _draw(PLOTTERS[png], data, out / png, dict(PLOTS)[png])

    jobs = [job(table(name, columns)) for name, columns in TABLES.items()]
    t = data.tissue
    if t is not None and t.rest is not None:
        jobs.append(job((SNAPSHOTS, lambda: t.save(out / SNAPSHOTS))))
    jobs.append(job(plot('tissue_rest.png'), plot('tissue_deepest.png')))
    if t is not None and len(t.frames) >= 2:
        def animate() -> str | None:
            try:
                draw_animation(t.frames, out / ANIMATION[0], 'Tissue', reference=t.rest)
            except Exception as exc:  # noqa: BLE001 -- noted like a failed plot; no placeholder
                (out / ANIMATION[0]).unlink(missing_ok=True)
                return _reason(exc)
            return None
        jobs.append(job((ANIMATION[0], animate)))
    charts = [png for png, _ in PLOTS if png not in ('tissue_rest.png', 'tissue_deepest.png')]
    charts.sort(key=lambda png: _SLOWEST_CHARTS.index(png) if png in _SLOWEST_CHARTS else 99)
    return jobs + [job(plot(png)) for png in charts]


# the charts that take longest to draw, slowest first (log axes have many ticks to lay out)
_SLOWEST_CHARTS = ('step_time_hist.png', 'force_change.png', 'force_vs_displacement.png',
                   'latency_hist.png', 'rates.png')


def _write_summary_json(out: Path, data: ReportData, created: str, failed: dict) -> None:
    """summary.json, last and atomically: its presence means the report is finished."""
    summary = dict(_json_safe(data.summary))
    if data.rate_targets:
        summary['rate_targets_hz'] = _json_safe(data.rate_targets)
    summary['created'] = created
    summary['files'] = sorted(n for n in report_files() + [ANIMATION[0], SNAPSHOTS]
                              if n not in failed and n != 'summary.json' and (out / n).is_file())
    summary['failed_files'] = dict(failed)
    tmp = out / '.summary.json.tmp'
    tmp.write_text(json.dumps(summary, indent=2, sort_keys=True) + '\n')
    tmp.replace(out / 'summary.json')


def load_report_data(directory: str | Path) -> ReportData:
    """Read the CSV tables (and summary.json, if present) of an existing report folder."""
    src = Path(directory)
    if not src.is_dir():
        raise ReportError(f'{src} is not a report folder')
    tables = {}
    for name in TABLES:
        path = src / f'{name}.csv'
        if path.is_file():
            tables[name] = read_csv(path)
    if not tables:
        raise ReportError(f'{src} holds none of ' + ', '.join(f'{n}.csv' for n in TABLES))
    summary = {}
    js = src / 'summary.json'
    if js.is_file():
        try:
            summary = json.loads(js.read_text())
        except json.JSONDecodeError as exc:
            raise ReportError(f'{js} is not valid JSON: {exc}') from exc
        if not isinstance(summary, dict):
            raise ReportError(f'{js} is not a JSON object')
    period = summary.get('haptic_period_s')
    period = float(period) if within(period, 1e-9, MAX_SECONDS) else 1e-3
    targets = summary.get('rate_targets_hz')
    targets = {k: tuple(v) for k, v in targets.items() if isinstance(v, (list, tuple))} \
        if isinstance(targets, dict) else {}
    summary = {k: v for k, v in summary.items()
               if k not in ('created', 'files', 'failed_files', 'rate_targets_hz', 'plot_failures')}
    tissue = None
    if (src / SNAPSHOTS).is_file():
        try:
            tissue = TissueSnapshots.load(src / SNAPSHOTS)
        except (OSError, ValueError, KeyError) as exc:
            raise ReportError(f'{src / SNAPSHOTS} is not a tissue snapshot file: {exc}') from exc
    return ReportData(tables=tables, summary=summary, haptic_period=period, rate_targets=targets,
                      tissue=tissue)


def main(argv: list[str] | None = None) -> int:
    """``tissue_report SRC [-o OUT]``: rebuild plots and summaries from a report's CSV files."""
    parser = argparse.ArgumentParser(prog='tissue_report', description=main.__doc__)
    parser.add_argument('source', help='report folder holding metrics.csv / force.csv / ...')
    parser.add_argument('-o', '--output', help='output folder (default: the source folder)')
    parser.add_argument('--recompute-summary', action='store_true',
                        help='ignore summary.json and recompute the summary from the CSV files')
    args = parser.parse_args(argv)
    try:
        data = load_report_data(args.source)
        if args.recompute_summary:
            data.summary = {}
        out = write_report(args.output or args.source, data)
    except ReportError as exc:
        print(f'tissue_report: error: {exc}', file=sys.stderr)
        return 2
    print(f'tissue_report: wrote {out / "index.html"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
