#!/usr/bin/env python3
"""How deep the tissue holds: the straight press to 40 mm for each contact model, tool and resolution.

    python benchmarks/press_depth.py                                  # the full grid (~15 min)
    python benchmarks/press_depth.py --particles 3670 --contacts balls,samples --tools sphere

Presses the tool straight down into the liver's dome (where ``validate.py`` presses, level there)
at 10 mm/s from first touch, one 1 ms frame at a time (``cases.press_curve``), for every
combination of

* ``--particles``: the liver's resolution (3670 is the default model; 12k and 30k the finer ones);
* ``--contacts``: ``balls`` (particles as balls, the paper's contact: ``solver.BALL_CONTACT``) and
  ``backstop`` (the surface samples behind the balls: ``contact_samples: 3``, the default), each
  with the far field the model gets (the organ's own up to ``solver.ORGAN_MAX_FREE`` free
  particles, else the elastic half-space's);
* ``--tools``: ``sphere`` (the default 5 mm probe tip) and ``capsule`` (the same tip on a 60 mm
  shaft along +z: an instrument, whose shaft fills the pit above the tip).

For each it reports the largest force and its depth, where the force first gives way (falls below
its running maximum by more than 2 % of the largest force: ``cases.gives_way``, validate's
monotonic criterion), whether that happens only past the device's force limit
(``--limit``, the Omni's 3.3 N: the renderer never pushes harder, so the hand cannot press
further), the force at 10 / 20 / 30 / 40 mm, the most particle centres over the tool (inside
the radius of its axis, above the tip's centre) and the first-touched particle's sideways slip at
10 mm. A step that goes unstable (the solver raises ``SimError``) ends that press; the depth is
reported.

Writes ``--out`` (default ``benchmarks/results/press_depth``): ``press_depth.csv`` (one row per
press), ``press_depth_curves.csv`` (force against depth of every press), ``press_depth.md`` (the
table) and ``press_depth.png`` (one panel per resolution).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np

from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.solver import BALL_CONTACT, SolverConfig
from sph_tissue_sim.validation import cases

ROOT = Path(__file__).resolve().parents[1]
#: (x, y) [m] of the press: the top of the right lobe's dome (validate.py's LIVER_TOP)
LIVER_TOP = (-0.034, 0.0)
CONTACTS = {'balls': dict(BALL_CONTACT), 'backstop': {'contact_samples': 3}}
TOOLS = {'sphere': {}, 'capsule': {'tool_shape': 'capsule', 'tool_length': 0.06}}
REPORT_DEPTHS = (0.010, 0.020, 0.030, 0.040)
COLUMNS = ('particles', 'spacing_mm', 'contact', 'tool', 'status', 'peak_n', 'peak_mm', 'gives_way_mm',
           'holds_limit', 'fz10_n', 'fz20_n', 'fz30_n', 'fz40_n', 'over_max', 'slip10_mm', 'wall_s')


def press(n: int, contact: str, tool: str, depth: float, mode: str) -> tuple[dict, dict]:
    """One press; returns its curve (:func:`~sph_tissue_sim.validation.cases.press_curve`) and the
    start of its summary row."""
    model = make_model('liver', n_particles=n)
    config = SolverConfig(mode=mode, parallel_min_particles=0, **CONTACTS[contact], **TOOLS[tool])
    t0 = time.perf_counter()
    c = cases.press_curve(model, liver_default(), config, depth, xy=LIVER_TOP)
    wall = time.perf_counter() - t0
    return c, {'particles': model.n_particles, 'spacing_mm': model.spacing * 1e3, 'contact': contact,
               'tool': tool, 'wall_s': wall,
               'status': 'ok' if c['unstable_at'] is None else f'unstable at {c["unstable_at"] * 1e3:.1f} mm'}


def summarise(c: dict, row: dict, limit: float) -> dict:
    d, fz = c['depth'], c['normal']
    if len(d) == 0:                       # unstable at the first frame
        d, fz, c = np.zeros(1), np.zeros(1), {**c, 'over': np.zeros(1), 'slip': np.full(1, math.nan)}
    k = int(np.argmax(fz))
    way = cases.gives_way(d, fz)
    # held to the limit: the force reached it before (or without) giving way
    reach = np.flatnonzero(fz >= limit)
    row.update(peak_n=float(fz[k]), peak_mm=d[k] * 1e3, gives_way_mm=way * 1e3,
               holds_limit=bool(len(reach) and d[reach[0]] <= way), over_max=int(c['over'].max()))
    for dd in REPORT_DEPTHS:
        i = int(np.argmin(np.abs(d - dd)))
        row[f'fz{dd * 1e3:.0f}_n'] = float(fz[i]) if abs(d[i] - dd) < 1e-4 else math.nan
    i10 = int(np.argmin(np.abs(d - 0.010)))
    row['slip10_mm'] = float(c['slip'][i10]) * 1e3 if abs(d[i10] - 0.010) < 1e-4 else math.nan
    return row


def _fmt(v) -> str:
    if isinstance(v, bool):
        return 'yes' if v else 'no'
    if isinstance(v, float):
        return '-' if math.isnan(v) else ('never' if math.isinf(v) else f'{v:.3g}')
    return str(v)


def table(rows: list[dict]) -> str:
    head = ('particles', 'contact', 'tool', 'peak [N at mm]', 'gives way at [mm]', 'holds the limit',
            'Fz at 10 / 20 / 30 / 40 mm [N]', 'most particles over the tool', 'slip at 10 mm [mm]', 'status')
    out = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for r in rows:
        fz = ' / '.join(_fmt(r[f'fz{int(dd * 1e3)}_n']) for dd in REPORT_DEPTHS)
        out.append('| ' + ' | '.join([str(r['particles']), r['contact'], r['tool'],
                                      f'{r["peak_n"]:.2f} at {r["peak_mm"]:.1f}', _fmt(r['gives_way_mm']),
                                      _fmt(r['holds_limit']), fz, str(r['over_max']), _fmt(r['slip10_mm']),
                                      r['status']]) + ' |')
    return '\n'.join(out)


def plot(curves: dict, rows: list[dict], limit: float, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    sizes = sorted({r['particles'] for r in rows})
    fig, axes = plt.subplots(1, len(sizes), figsize=(5.0 * len(sizes), 3.8), sharey=True, squeeze=False)
    colours = {'balls': '#d62728', 'backstop': '#9467bd'}
    for ax, n in zip(axes[0], sizes):
        for r in rows:
            if r['particles'] != n:
                continue
            c = curves[(n, r['contact'], r['tool'])]
            ax.plot(c['depth'] * 1e3, c['normal'], color=colours[r['contact']],
                    ls='-' if r['tool'] == 'sphere' else '--', lw=1.1, label=f'{r["contact"]}, {r["tool"]}')
        ax.axhline(limit, color='0.5', lw=0.8, ls=':', label=f'force limit {limit} N')
        spacing = next(r['spacing_mm'] for r in rows if r['particles'] == n)
        ax.set_title(f'liver, {n} particles ({spacing:.1f} mm spacing)', fontsize=9)
        ax.set_xlabel('tool depth below first touch [mm]')
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel('force on the tool, Fz [N]')
    axes[0][-1].legend(fontsize=7, loc='upper left')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--particles', default='3670,12000,30000', help='liver sizes, comma-separated')
    ap.add_argument('--contacts', default=','.join(CONTACTS), help='of ' + ','.join(CONTACTS))
    ap.add_argument('--tools', default=','.join(TOOLS), help='of ' + ','.join(TOOLS))
    ap.add_argument('--depth', type=float, default=0.04, help='deepest press [m]')
    ap.add_argument('--mode', choices=('local', 'global'), default='local')
    ap.add_argument('--limit', type=float, default=SolverConfig().force_limit, help='device force limit [N]')
    ap.add_argument('--out', type=Path, default=ROOT / 'benchmarks' / 'results' / 'press_depth')
    args = ap.parse_args(argv)
    try:
        sizes = [int(s) for s in args.particles.split(',') if s.strip()]
    except ValueError:
        ap.error(f'--particles {args.particles!r}: expected integers')
    contacts = [c.strip() for c in args.contacts.split(',') if c.strip()]
    tools = [t.strip() for t in args.tools.split(',') if t.strip()]
    for name, chosen, known in (('--contacts', contacts, CONTACTS), ('--tools', tools, TOOLS)):
        bad = sorted(set(chosen) - set(known))
        if bad or not chosen:
            ap.error(f'{name}: unknown {bad}; choose from {",".join(known)}')
    if not (0.0 < args.depth <= 0.06):
        ap.error('--depth must be in (0, 0.06] m')
    args.out.mkdir(parents=True, exist_ok=True)
    rows, curves = [], {}
    grid = [(n, c, t) for n in sizes for c in contacts for t in tools]
    for i, (n, contact, tool) in enumerate(grid, start=1):
        print(f'[{i}/{len(grid)}] {n} particles, {contact}, {tool} ...', flush=True)
        c, row = press(n, contact, tool, args.depth, args.mode)
        row = summarise(c, row, args.limit)
        curves[(row['particles'], contact, tool)] = c
        rows.append(row)
        print(f'    peak {row["peak_n"]:.3f} N at {row["peak_mm"]:.1f} mm, gives way at '
              f'{_fmt(row["gives_way_mm"])} mm, holds the limit: {_fmt(row["holds_limit"])}, '
              f'{row["over_max"]} over the tool, {row["wall_s"]:.0f} s', flush=True)
    with open(args.out / 'press_depth.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    with open(args.out / 'press_depth_curves.csv', 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['particles', 'contact', 'tool', 'depth_mm', 'fz_n'])
        for (n, contact, tool), c in curves.items():
            for d, f in zip(c['depth'], c['normal']):
                w.writerow([n, contact, tool, f'{d * 1e3:.3f}', f'{f:.6g}'])
    md = table(rows)
    (args.out / 'press_depth.md').write_text(
        f'# Straight press to {args.depth * 1e3:.0f} mm ({args.mode}, '
        f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())})\n\n{md}\n\n![press_depth](press_depth.png)\n')
    plot(curves, rows, args.limit, args.out / 'press_depth.png')
    print(md)
    print(f'written to {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
