#!/usr/bin/env python3
"""Force-displacement experiment on the liver (the paper's Figs. 9 and 11).

The tool tip (a small sphere) starts touching the top of the right lobe and is driven, one 1 kHz
haptic frame at a time, through four phases:

1. press:   straight down to ``depth`` at constant speed;
2. hold:    still at full depth (viscoelastic settling);
3. pull:    dragged tangentially (+x, towards the left lobe) at full depth, dragging the
            dented tissue with it;
4. release: straight up until it has left the surface.

Every configuration (scheme x mode) runs the same tool path on the same liver. The force is the
reaction of the tissue on the tool before the device clamp (``StepResult.force_raw``). Writes

* ``force_displacement.csv``: one row per frame and configuration;
* ``summary.csv`` and a printed table: peak force, normal force at full depth, local-vs-global
  difference, quadratic fit of the loading curve (the paper fits its curves with quadratics);
* ``force_displacement.png``: normal force vs depth (press/release), drag force vs tangential
  displacement (pull) and force vs time.

Usage: ``python benchmarks/force_displacement.py [--out DIR] [--quick] [--particles N]``
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

try:
    from sph_tissue_sim.core.errors import ConfigError, SimError
except ImportError:                                  # run from a source checkout without env.sh
    for pkg in ('sph_tissue_sim', 'tissue_common'):
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / pkg))
    from sph_tissue_sim.core.errors import ConfigError, SimError
from sph_tissue_sim.core.liver import REFERENCE_LENGTH, make_liver
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.solver import Solver, SolverConfig

DEFAULT_OUT = Path(__file__).resolve().parent / 'results' / 'force_displacement'
CONFIGS = (('tlsph', 'global'), ('tlsph', 'local'), ('mass_spring', 'global'),
           ('paper', 'global'), ('paper', 'local'))
COLOURS = {'tlsph global': '#1f77b4', 'tlsph local': '#ff7f0e', 'mass_spring global': '#2ca02c',
           'paper global': '#d62728', 'paper local': '#9467bd'}
PHASES = ('press', 'hold', 'pull', 'release')
CSV_COLUMNS = ('config', 'scheme', 'mode', 'phase', 'frame', 'time', 'tool_dx', 'tool_dy', 'tool_dz',
               'depth', 'tangential', 'node_dx', 'node_dy', 'node_dz', 'fx', 'fy', 'fz', 'f_norm',
               'f_drag', 'clamped', 'substeps', 'n_active', 'wall_ms')
SUMMARY_COLUMNS = ('config', 'status', 'frames', 'peak_force_N', 'fz_max_depth_N', 'fz_end_hold_N',
                   'peak_drag_N', 'fit_a_N_per_mm', 'fit_b_N_per_mm2', 'local_vs_global_pct',
                   'mean_ms_per_frame', 'max_ms_per_frame')


@dataclass
class Protocol:
    """Tool path (SI units); ``frame_dt`` is the haptic frame."""

    particles: int = 3670
    depth: float = 0.010          # [m] indentation below first touch
    speed: float = 0.02           # [m/s] press, pull and release speed
    hold: float = 0.2             # [s]
    pull: float = 0.008           # [m] tangential drag distance
    lift_extra: float = 0.004     # [m] released this far above the first-touch height
    frame_dt: float = 1e-3        # [s]
    tool_radius: float = SolverConfig.tool_radius   # [m] tool-tip sphere

    @classmethod
    def quick(cls) -> 'Protocol':
        return cls(particles=572, depth=0.005, speed=0.04, hold=0.03, pull=0.004, lift_extra=0.002)


def tool_path(p: Protocol) -> tuple[np.ndarray, list[str]]:
    """Tool offsets from the first-touch point, one per frame, and the phase of each frame."""
    def ramp(a, b, dist):
        n = max(1, int(math.ceil(dist / (p.speed * p.frame_dt))))
        t = np.arange(1, n + 1)[:, None] / n
        return a + t * (b - a)

    e_z = np.array([0.0, 0.0, 1.0])
    e_t = np.array([1.0, 0.0, 0.0])
    bottom = -p.depth * e_z
    pulled = bottom + p.pull * e_t
    segs = [('press', ramp(np.zeros(3), bottom, p.depth)),
            ('hold', np.repeat(bottom[None], max(1, int(round(p.hold / p.frame_dt))), axis=0)),
            ('pull', ramp(bottom, pulled, p.pull)),
            ('release', ramp(pulled, pulled + (p.depth + p.lift_extra) * e_z, p.depth + p.lift_extra))]
    offsets = np.concatenate([s for _, s in segs])
    phases = [name for name, s in segs for _ in range(len(s))]
    return offsets, phases


def contact_node(model) -> int:
    """The pressed node: top particle of a column on a locally level patch of the right lobe's top.

    Among the top particles whose 8 neighbouring columns end at the same height (a flat patch of
    the lattice surface, so a vertical push has no lateral component from the staircase), the
    one nearest the apex of the right lobe; without such a patch, the top of the nearest column.
    """
    pos, s = model.positions, model.spacing
    apex_xy = np.array([-0.035, 0.0]) * (model.info.get('length', REFERENCE_LENGTH) / REFERENCE_LENGTH)
    ijk = np.rint((pos - pos.min(axis=0)) / s).astype(np.int64)
    top: dict[tuple[int, int], int] = {}
    for n, (i, j, k) in enumerate(ijk):
        if (i, j) not in top or k > ijk[top[(i, j)], 2]:
            top[(i, j)] = n
    best, best_key = None, None
    for (i, j), n in top.items():
        k = ijk[n, 2]
        level = all((i + a, j + b) in top and ijk[top[(i + a, j + b)], 2] == k
                    for a in (-1, 0, 1) for b in (-1, 0, 1))
        key = (not level, float(np.linalg.norm(pos[n, :2] - apex_xy)))
        if best_key is None or key < best_key:
            best, best_key = n, key
    return int(best)


def run_config(model, material, scheme: str, mode: str, p: Protocol, offsets, phases, progress=True):
    """Run one configuration; returns (rows, status)."""
    from tqdm import tqdm

    name = f'{scheme} {mode}'
    try:
        solver = Solver(model, material, SolverConfig(scheme=scheme, mode=mode, tool_radius=p.tool_radius))
    except ConfigError as exc:
        return [], f'skipped: {exc}'
    node = contact_node(model)
    X0 = model.positions[node]
    touch = X0 + np.array([0.0, 0.0, solver.contact_reach])
    rows = []
    status = 'ok'
    bar = tqdm(total=len(offsets), desc=f'{name:>18}', unit='frame', disable=not progress,
               leave=True, dynamic_ncols=True, mininterval=0.5)
    try:
        for k, (off, phase) in enumerate(zip(offsets, phases)):
            try:
                res = solver.step(touch + off, p.frame_dt)
            except ConfigError as exc:
                status = f'skipped: {exc}'
                rows = []
                break
            except SimError as exc:
                status = f'unstable at frame {k} ({phase}): {exc}'
                break
            f = res.force_raw
            nd = solver.positions[node] - X0
            rows.append({
                'config': name, 'scheme': scheme, 'mode': mode, 'phase': phase, 'frame': k,
                'time': (k + 1) * p.frame_dt, 'tool_dx': off[0], 'tool_dy': off[1], 'tool_dz': off[2],
                'depth': -off[2], 'tangential': off[0], 'node_dx': nd[0], 'node_dy': nd[1],
                'node_dz': nd[2], 'fx': f[0], 'fy': f[1], 'fz': f[2], 'f_norm': float(np.linalg.norm(f)),
                'f_drag': -f[0], 'clamped': int(res.clamped), 'substeps': res.substeps,
                'n_active': res.n_active, 'wall_ms': res.wall_time * 1e3})
            bar.update(1)
    finally:
        bar.close()
    return rows, status


def summarise(name: str, rows: list[dict], status: str) -> dict:
    out = {c: '' for c in SUMMARY_COLUMNS}
    out.update(config=name, status=status, frames=len(rows))
    if not rows:
        return out
    ph = np.array([r['phase'] for r in rows])
    col = {k: np.array([r[k] for r in rows], dtype=float) for k in ('depth', 'fz', 'f_norm', 'f_drag', 'wall_ms')}
    press = ph == 'press'
    out['peak_force_N'] = col['f_norm'].max()
    if press.any():
        last_press = np.flatnonzero(press)[-1]
        out['fz_max_depth_N'] = col['fz'][last_press]
        d = col['depth'][press] * 1e3
        if press.sum() >= 5:
            # F = a d + b d^2 through the origin (least squares), d in mm
            A = np.stack([d, d * d], axis=1)
            (a, b), *_ = np.linalg.lstsq(A, col['fz'][press], rcond=None)
            out['fit_a_N_per_mm'] = a
            out['fit_b_N_per_mm2'] = b
    if (ph == 'hold').any():
        out['fz_end_hold_N'] = col['fz'][np.flatnonzero(ph == 'hold')[-1]]
    if (ph == 'pull').any():
        out['peak_drag_N'] = col['f_drag'][ph == 'pull'].max()
    out['mean_ms_per_frame'] = col['wall_ms'].mean()
    out['max_ms_per_frame'] = col['wall_ms'].max()
    return out


def write_csv(path: Path, rows: list[dict], columns) -> None:
    with open(path, 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction='ignore')
        w.writeheader()
        for r in rows:
            w.writerow({k: (f'{v:.6g}' if isinstance(v, float) else v) for k, v in r.items()})


def _robust_top(values: list[np.ndarray]) -> float:
    """Upper y limit that shows every curve but not brief spikes (97th percentile per curve)."""
    tops = [np.percentile(v, 97.0) for v in values if len(v)]
    return 1.2 * max(max(tops, default=0.0), 1e-3)


def plot(path: Path, results: dict, p: Protocol, model, material, statuses: dict | None = None) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5.4), constrained_layout=True)
    ax_press, ax_pull, ax_time = axes
    series = {}
    for name, rows in results.items():
        if rows:
            ph = np.array([r['phase'] for r in rows])
            series[name] = (ph, {k: np.array([r[k] for r in rows], dtype=float) for k in
                                 ('depth', 'tangential', 'fz', 'f_drag', 'f_norm', 'time')})
    for name, (ph, get) in series.items():
        c = COLOURS.get(name, None)
        load = (ph == 'press') | (ph == 'hold')
        rel = ph == 'release'
        label = name
        if statuses and statuses.get(name, 'ok') != 'ok':
            # mark where the run stopped (a blow-up) on every panel
            label = f'{name} (unstable at {get["time"][-1]:.2f} s)'
            ax_press.plot(get['depth'][-1] * 1e3, get['fz'][-1], 'x', color=c, ms=10, mew=2.5)
            ax_time.plot(get['time'][-1], get['f_norm'][-1], 'x', color=c, ms=10, mew=2.5)
        ax_press.plot(get['depth'][load] * 1e3, get['fz'][load], '-', color=c, lw=2, label=label)
        if rel.any():
            ax_press.plot(get['depth'][rel] * 1e3, get['fz'][rel], ':', color=c, lw=1.5)
        pull = ph == 'pull'
        if pull.any():
            ax_pull.plot(get['tangential'][pull] * 1e3, get['f_drag'][pull], '-', color=c, lw=2, label=name)
            ax_pull.plot(get['tangential'][pull] * 1e3, get['fz'][pull], '--', color=c, lw=1, alpha=0.6)
        ax_time.plot(get['time'], get['f_norm'], '-', color=c, lw=1.5, label=name)

    # y ranges that keep the curves readable; single-frame spikes are named, not hidden silently
    def limit(ax, key, mask_fn, bottom=None):
        vals = {n: g[key][mask_fn(ph)] for n, (ph, g) in series.items()}
        top = _robust_top(list(vals.values()))
        low = min([v.min() for v in vals.values() if len(v)], default=0.0)
        lo = bottom if bottom is not None else min(0.0, 1.2 * max(low, -top))
        ax.set_ylim(lo, top)
        off = [f'{n} (max {v.max():.2f} N)' for n, v in vals.items() if len(v) and v.max() > top]
        if off:
            ax.text(0.99, 0.02, 'off scale: ' + ', '.join(off), transform=ax.transAxes, ha='right',
                    va='bottom', fontsize=8, color='0.25',
                    bbox=dict(boxstyle='round', fc='white', ec='0.7', alpha=0.9))

    if series:
        limit(ax_press, 'fz', lambda ph: ph != 'pull', bottom=-0.05 * _robust_top(
            [g['fz'] for _, g in series.values()]))
        vals = [np.concatenate([g['f_drag'][ph == 'pull'], g['fz'][ph == 'pull']]) for ph, g in series.values()]
        top = _robust_top(vals)
        low = min(v.min() for v in vals if len(v)) if any(len(v) for v in vals) else 0.0
        ax_pull.set_ylim(min(0.0, 1.2 * max(low, -top)), top)
        limit(ax_time, 'f_norm', lambda ph: np.ones(len(ph), bool), bottom=0.0)
        # phase bands on the time axis (same path for every configuration)
        ph, g = next(iter(series.values()))
        shades = {'press': '#f2f2f2', 'hold': '#e0e0e0', 'pull': '#f2f2f2', 'release': '#e0e0e0'}
        for name in PHASES:
            ts = g['time'][ph == name]
            if len(ts):
                ax_time.axvspan(ts[0] - p.frame_dt, ts[-1], color=shades[name], zorder=0)
                ax_time.text(0.5 * (ts[0] + ts[-1]), 0.98, name, transform=ax_time.get_xaxis_transform(),
                             ha='center', va='top', fontsize=9, color='0.3')
    ax_press.set(xlabel='indentation depth of the tool below first touch [mm]',
                 ylabel='normal force $F_z$ on the tool [N]',
                 title='Press + hold (solid), release (dotted)')
    ax_pull.set(xlabel=f'tangential tool displacement (+x) at {p.depth * 1e3:.0f} mm depth [mm]',
                ylabel='force on the tool [N]',
                title='Pull: drag $-F_x$ (solid), normal $F_z$ (dashed)')
    ax_time.set(xlabel='time [s]', ylabel='|F| on the tool [N]', title='Force magnitude over the run')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.axhline(0.0, color='0.5', lw=0.8)
    ax_press.legend(loc='upper left', fontsize=9)
    fig.suptitle(f'Liver force-displacement: {model.n_particles} particles (spacing '
                 f'{model.spacing * 1e3:.1f} mm, {model.info.get("n_fixed", 0)} fixed), '
                 f'G = {material.G / 1e3:.2f} kPa, nu = {material.nu:.2f}, '
                 f'tool radius {p.tool_radius * 1e3:.1f} mm, '
                 f'speed {p.speed * 1e3:.0f} mm/s, 1 kHz frames', fontsize=12)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(summary: list[dict]) -> None:
    head = ('config', 'peak |F| N', 'Fz@max N', 'Fz hold N', 'drag N', 'a N/mm', 'b N/mm2',
            'loc-glob %', 'ms/frame', 'status')
    keys = ('config', 'peak_force_N', 'fz_max_depth_N', 'fz_end_hold_N', 'peak_drag_N',
            'fit_a_N_per_mm', 'fit_b_N_per_mm2', 'local_vs_global_pct', 'mean_ms_per_frame', 'status')
    fmt = '{:<19}' + '{:>11}' * 8 + '  {}'
    print(fmt.format(*head))
    for s in summary:
        vals = []
        for k in keys:
            v = s.get(k, '')
            vals.append(f'{v:.4g}' if isinstance(v, float) else str(v))
        print(fmt.format(*vals))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', type=Path, default=DEFAULT_OUT, help='output directory')
    ap.add_argument('--quick', action='store_true', help='small liver, short path (smoke run)')
    ap.add_argument('--particles', type=int, default=None, help='liver particle count')
    ap.add_argument('--tool-radius', type=float, default=None, help='tool-tip radius [m]')
    ap.add_argument('--configs', default=None,
                    help='comma-separated subset, e.g. "tlsph global,tlsph local" (default: all)')
    ap.add_argument('--no-progress', action='store_true', help='no progress bars')
    args = ap.parse_args(argv)

    p = Protocol.quick() if args.quick else Protocol()
    if args.particles is not None:
        p.particles = args.particles
    if args.tool_radius is not None:
        p.tool_radius = args.tool_radius
    configs = CONFIGS
    if args.configs:
        wanted = [c.strip() for c in args.configs.split(',') if c.strip()]
        known = {f'{a} {b}' for a, b in CONFIGS}
        bad = [c for c in wanted if c not in known]
        if bad:
            ap.error(f'unknown configuration(s) {bad}; choose from {sorted(known)}')
        configs = [tuple(c.split()) for c in wanted]
    args.out.mkdir(parents=True, exist_ok=True)
    model = make_liver(p.particles)
    material = liver_default()
    offsets, phases = tool_path(p)
    print(f'liver: {model.n_particles} particles, spacing {model.spacing * 1e3:.2f} mm, '
          f'{model.info["n_fixed"]} fixed; tool path {len(offsets)} frames '
          f'({len(offsets) * p.frame_dt:.2f} s): press {p.depth * 1e3:.0f} mm, hold {p.hold:.2f} s, '
          f'pull {p.pull * 1e3:.0f} mm, release', flush=True)

    results: dict[str, list[dict]] = {}
    summary = []
    all_rows = []
    t0 = time.perf_counter()
    for scheme, mode in configs:
        name = f'{scheme} {mode}'
        rows, status = run_config(model, material, scheme, mode, p, offsets, phases,
                                  progress=not args.no_progress)
        if status.startswith('skipped'):
            print(f'note: {name}: {status}', flush=True)
            continue
        if status != 'ok':
            print(f'warning: {name}: {status}', flush=True)
        results[name] = rows
        all_rows.extend(rows)
        summary.append(summarise(name, rows, status))
    by_name = {s['config']: s for s in summary}
    for s in summary:
        scheme, mode = s['config'].split()
        g = by_name.get(f'{scheme} global')
        if mode == 'local' and g and isinstance(g['fz_max_depth_N'], float) \
                and isinstance(s['fz_max_depth_N'], float) and abs(g['fz_max_depth_N']) > 1e-12:
            s['local_vs_global_pct'] = 100.0 * (s['fz_max_depth_N'] - g['fz_max_depth_N']) / g['fz_max_depth_N']

    write_csv(args.out / 'force_displacement.csv', all_rows, CSV_COLUMNS)
    write_csv(args.out / 'summary.csv', summary, SUMMARY_COLUMNS)
    plot(args.out / 'force_displacement.png', results, p, model, material,
         {s['config']: s['status'] for s in summary})
    print()
    print_table(summary)
    print(f'\nwrote {args.out}/force_displacement.csv, summary.csv, force_displacement.png '
          f'({time.perf_counter() - t0:.1f} s)')
    return 0 if all(s['status'] == 'ok' for s in summary) and summary else 1


if __name__ == '__main__':
    sys.exit(main())
