#!/usr/bin/env python3
"""What each contact model costs the local step: a press and a palpation, the models interleaved.

    python benchmarks/contact_cost.py                          # balls and backstop at 3 / 6 / 12 mm
    python benchmarks/contact_cost.py --contacts balls,backstop --depths 0.003 --frames 2000

For each depth, one solver per contact model (``press_depth.CONTACTS``) on the same liver (local
mode) presses the default tool into the liver's dome (``press_depth.LIVER_TOP``) over 300 frames
of 1 ms, then palpates it +-1 mm at 2 Hz for ``--frames`` frames. The solvers take turns frame by
frame, so the machine's load drifts hit them alike; the table gives, per model, the median of
``Solver.step`` over the palpation [ms], its ratio to the first model's, the mean active
particles and the mean sub-steps per frame.

Writes ``--out`` (default ``benchmarks/results/contact_cost``): ``contact_cost.csv`` and
``contact_cost.md``.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from press_depth import CONTACTS, LIVER_TOP  # noqa: E402  (benchmarks/ is not a package)

from sph_tissue_sim.core.factory import make_model  # noqa: E402
from sph_tissue_sim.core.material import liver_default  # noqa: E402
from sph_tissue_sim.core.solver import Solver, SolverConfig  # noqa: E402
from sph_tissue_sim.validation.cases import NUDGE, first_touch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PRESS_FRAMES = 300
PALPATE_AMP = 0.001     # [m]
PALPATE_HZ = 2.0
DT = 1e-3
COLUMNS = ('particles', 'depth_mm', 'contact', 'step_ms', 'ratio', 'active', 'substeps')


def measure(model, depth: float, contacts: list[str], frames: int) -> list[dict]:
    """One row per contact model: the palpation's median step [ms], mean active particles and sub-steps."""
    material = liver_default()
    solvers = {c: Solver(model, material, SolverConfig(mode='local', **CONTACTS[c])) for c in contacts}
    start = first_touch(model, solvers[contacts[0]].contact_reach, LIVER_TOP, NUDGE)
    times = {c: [] for c in contacts}
    active = {c: [] for c in contacts}
    subs = {c: [] for c in contacts}
    for k in range(PRESS_FRAMES + frames):
        d = depth * min(1.0, (k + 1) / PRESS_FRAMES)
        if k >= PRESS_FRAMES:
            d += PALPATE_AMP * math.sin(2.0 * math.pi * PALPATE_HZ * (k - PRESS_FRAMES) * DT)
        tip = start - np.array([0.0, 0.0, d])
        for c, solver in solvers.items():
            t0 = time.perf_counter()
            res = solver.step(tip, DT)
            elapsed = time.perf_counter() - t0
            if k >= PRESS_FRAMES:
                times[c].append(elapsed * 1e3)
                active[c].append(res.n_active)
                subs[c].append(res.substeps)
    base = statistics.median(times[contacts[0]])
    rows = []
    for c in contacts:
        med = statistics.median(times[c])
        rows.append(dict(particles=model.n_particles, depth_mm=depth * 1e3, contact=c, step_ms=med,
                         ratio=med / base, active=statistics.mean(active[c]), substeps=statistics.mean(subs[c])))
    return rows


def table(rows: list[dict]) -> str:
    lines = ['| particles | depth [mm] | contact | step [ms] | against the first | active particles | sub-steps |',
             '|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['particles']} | {r['depth_mm']:.0f} | {r['contact']} | {r['step_ms']:.3f} | "
                     f"{r['ratio']:.2f}x | {r['active']:.0f} | {r['substeps']:.2f} |")
    return '\n'.join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--particles', type=int, default=3670, help='liver size')
    ap.add_argument('--contacts', default='balls,backstop',
                    help='of ' + ','.join(CONTACTS) + ' (ratios are against the first)')
    ap.add_argument('--depths', default='0.003,0.006,0.012', help='press depths [m], comma-separated')
    ap.add_argument('--frames', type=int, default=1000, help='palpation frames timed per depth')
    ap.add_argument('--out', type=Path, default=ROOT / 'benchmarks' / 'results' / 'contact_cost')
    args = ap.parse_args(argv)
    contacts = [c.strip() for c in args.contacts.split(',') if c.strip()]
    bad = sorted(set(contacts) - set(CONTACTS))
    if bad or not contacts:
        ap.error(f'--contacts: unknown {bad}; choose from {",".join(CONTACTS)}')
    try:
        depths = [float(d) for d in args.depths.split(',') if d.strip()]
    except ValueError:
        ap.error(f'--depths {args.depths!r}: expected numbers [m]')
    if not depths or not all(0.0 < d <= 0.03 for d in depths):
        ap.error('--depths must be in (0, 0.03] m')
    if args.frames < 10:
        ap.error('--frames must be at least 10')
    model = make_model('liver', n_particles=args.particles)
    rows = []
    for i, depth in enumerate(depths, start=1):
        print(f'[{i}/{len(depths)}] {depth * 1e3:.0f} mm, {len(contacts)} models interleaved ...', flush=True)
        rows += measure(model, depth, contacts, args.frames)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / 'contact_cost.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    md = table(rows)
    (args.out / 'contact_cost.md').write_text(
        f'# The local step of each contact model ({time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())})\n\n'
        f'Palpation +-{PALPATE_AMP * 1e3:.0f} mm at {PALPATE_HZ:g} Hz for {args.frames} frames around each '
        f'depth, the models interleaved frame by frame; medians.\n\n{md}\n')
    print(md)
    print(f'written to {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
