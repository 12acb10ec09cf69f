#!/usr/bin/env python3
"""What a touch on new ground costs the frame that makes it: the organ's far field waiting for its
responses, against solving them on a worker thread (``Solver(..., background=True)``).

Local mode with the organ's far field (the default on the bundled liver) solves a particle's
response the first time it carries the tool; each takes tens of milliseconds. Here the tool
presses straight down into the 3670 liver at the validation's four places, one 1 ms frame per
millisecond of wall clock (as the running loop paces it), once waiting for the responses in the
frame and once with the worker, interleaved. Per place and way: the longest frame, how many
frames took more than 2 ms, their total, and the force: Fz at 2 / 4 / 10 mm and the largest
difference between the two ways over the press (the worker's frames share the load among the
responses that are ready).

Writes ``first_touch.csv`` and ``first_touch.png`` (frame time and Fz against depth) to ``--out``.

Usage: ``python benchmarks/first_touch.py [--speed M_PER_S] [--depth M] [--particles N] [--out DIR]``
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np

from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.response_store import CACHE_ENV
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.sim_node import SWITCH_INTERVAL, one_blas_thread
from sph_tissue_sim.validation.cases import NUDGE, first_touch

ROOT = Path(__file__).resolve().parents[1]
PLACES = ((0.0, 0.0), (0.03, 0.0), (-0.04, 0.01), (0.0, -0.03))
SLOW_FRAME = 2e-3   # [s]
REPORT_DEPTHS = (0.002, 0.004, 0.010)


def press(model, background: bool, xy, depth: float, speed: float, dt: float = 1e-3) -> dict:
    """One paced press from first touch; per frame: depth [m], wall time [s], Fz [N]."""
    solver = Solver(model, liver_default(), SolverConfig(mode='local', parallel_min_particles=0),
                    background=background)
    start = first_touch(model, solver.contact_reach, xy, NUDGE)
    frames = int(np.ceil(depth / (speed * dt)))
    out = {k: np.zeros(frames) for k in ('depth', 'wall', 'fz')}
    due = time.perf_counter()
    for k in range(frames):
        d = min(depth, (k + 1) * speed * dt)
        t0 = time.perf_counter()
        res = solver.step(start - np.array([0.0, 0.0, d]), dt)
        t1 = time.perf_counter()
        out['depth'][k], out['wall'][k], out['fz'][k] = d, t1 - t0, res.force_raw[2]
        due = max(due + dt, t1)   # the running loop's pace: the next pose a millisecond later
        while time.perf_counter() < due:
            pass
    solver.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--speed', type=float, default=0.02, help='pressing speed [m/s]')
    ap.add_argument('--depth', type=float, default=0.010, help='deepest press [m]')
    ap.add_argument('--particles', type=int, default=3670, help='liver size')
    ap.add_argument('--out', type=Path, default=ROOT / 'benchmarks' / 'results' / 'first_touch')
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    os.environ[CACHE_ENV] = ''   # new ground every press: no response from disk
    # as sim_node (which also keeps BLAS to one thread): a thread that wants the interpreter gets it within 0.2 ms, not Python's 5 ms
    sys.setswitchinterval(SWITCH_INTERVAL)
    one_blas_thread()
    model = make_model('liver', n_particles=args.particles)
    for way in (False, True):   # compile the kernels and factor the organ outside the timing
        press(model, way, PLACES[0], 0.002, args.speed)
    rows, curves = [], {}
    for xy in PLACES:
        runs = {way: press(model, way == 'background', xy, args.depth, args.speed) for way in ('wait', 'background')}
        curves[xy] = runs
        diff = float(np.max(np.abs(runs['background']['fz'] - runs['wait']['fz'])))
        for way, r in runs.items():
            slow = r['wall'] > SLOW_FRAME
            row = {'place_mm': f'({xy[0] * 1e3:.0f}, {xy[1] * 1e3:.0f})', 'way': way,
                   'longest_frame_ms': r['wall'].max() * 1e3, 'frames_over_2ms': int(slow.sum()),
                   'time_over_2ms_ms': r['wall'][slow].sum() * 1e3,
                   'median_frame_ms': float(np.median(r['wall'])) * 1e3, 'largest_fz_difference_N': diff}
            for dd in REPORT_DEPTHS:   # nan below the deepest press
                row[f'fz_{dd * 1e3:.0f}mm_N'] = (float(r['fz'][int(np.argmin(np.abs(r['depth'] - dd)))])
                                                 if dd <= args.depth + 1e-12 else float('nan'))
            rows.append(row)
            print(' | '.join(f'{k}={v:.4g}' if isinstance(v, float) else f'{k}={v}' for k, v in row.items()),
                  flush=True)
    with open(args.out / 'first_touch.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    cols = list(rows[0])
    print('\n| ' + ' | '.join(cols) + ' |\n|' + '---|' * len(cols))
    for r in rows:
        print('| ' + ' | '.join(f'{r[c]:.3g}' if isinstance(r[c], float) else str(r[c]) for c in cols) + ' |')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    for i, (xy, runs) in enumerate(curves.items()):
        colour = f'C{i}'
        for way, ls in (('wait', '-'), ('background', '--')):
            r = runs[way]
            label = f'({xy[0] * 1e3:.0f}, {xy[1] * 1e3:.0f}) mm, {way}'
            a0.plot(r['depth'] * 1e3, r['wall'] * 1e3, color=colour, ls=ls, lw=1, label=label)
            a1.plot(r['depth'] * 1e3, r['fz'], color=colour, ls=ls, lw=1, label=label)
    a0.set_yscale('log')
    a0.set_ylabel('frame wall time [ms]')
    a1.set_ylabel('Fz [N]')
    a1.set_xlabel('tool depth below first touch [mm]')
    a0.set_title(f'pressing the {len(model.positions)}-particle liver at {args.speed * 1e3:.0f} mm/s: waiting for the far field\'s '
                 'responses or not', fontsize=9)
    a1.legend(fontsize=7, ncol=2)
    for a in (a0, a1):
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / 'first_touch.png', dpi=110)
    print(f'wrote {args.out}/first_touch.csv, first_touch.png')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
