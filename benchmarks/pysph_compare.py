#!/usr/bin/env python3
"""Time per particle-step against PySPH's elastic solid, side by side in one run.

    python benchmarks/pysph_compare.py --pysph-python /path/to/pysph-env/bin/python [--steps 2000]

PySPH is not a dependency of this project (it builds C++ extensions with Cython against its own
numpy). It installs from PyPI into an environment of its own, for example::

    python3 -m venv /tmp/pysph-env
    /tmp/pysph-env/bin/pip install "numpy<2.3" cython setuptools wheel mako compyle cyarray
    /tmp/pysph-env/bin/pip install --no-build-isolation pysph==1.0b2

**PySPH**: its example ``solid_mech/oscillating_plate`` as shipped (a 2D plate clamped between wall
particles, 1386 plate + 207 wall particles, dx 2 mm, E 2 MPa, nu 0.3975, rho 1000 kg/m^3, dt 1e-5 s;
Gray-Monaghan elastic dynamics with artificial stress, artificial viscosity and XSPH), serial (no
OpenMP), no output. Its set-up (and the compilation of its equations on first use) is taken out by
timing a run of ``--steps`` + 10 steps against one of 10 steps in the same process.

**Ours**: the same plate extruded to 3D, ``--layers`` particle layers wide (default 11: a square
section, 11 x 11 like the plate's 11 rows), clamped by fixed layers over the plate's first 50 mm as
PySPH's walls hold it, E, nu and rho the same, Kelvin-Voigt with a small viscosity (retardation
1e-5 s), ``tlsph`` global, serial; sub-steps of exactly 1e-5 s (``cfl`` set so), frames of 1 ms,
after one warm-up frame. Both codes start from rest here (the swing does not change the cost).

Rounds alternate (PySPH, ours, PySPH, ...). Prints a table of microseconds per particle-step (over all
particles, and over the moving ones) and writes ``pysph_compare.csv`` to ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_beam
from sph_tissue_sim.core.solver import Solver, SolverConfig

HERE = Path(__file__).resolve().parent
DX = 0.002             # [m] PySPH's dx_plate
LENGTH = 0.2           # [m] free length
CLAMPED = 0.05         # [m] length held by PySPH's walls (its plate_inside_wall_length)
ROWS = 11              # PySPH's plate: 11 rows across its 20 mm
E, NU, RHO = 2.0e6, 0.3975, 1000.0
DT = 1e-5              # [s] PySPH's time step, and our sub-step

PYSPH_RUN = r'''
import json, sys, tempfile, time
from pysph.examples.solid_mech.oscillating_plate import OscillatingPlate
steps = int(sys.argv[1])
out = tempfile.mkdtemp()
def run(n):
    app = OscillatingPlate(fname='oscillating_plate')
    t0 = time.perf_counter()
    app.run(['--max-steps', str(n), '--disable-output', '-q', '-d', out, '--no-openmp'])
    counts = {pa.name: pa.get_number_of_particles() for pa in app.particles}
    return time.perf_counter() - t0, counts, app.solver.count
short, counts, n_short = run(10)
long, _, n_long = run(10 + steps)
print(json.dumps({'seconds': long - short, 'steps': n_long - n_short, 'counts': counts}))
'''


def run_pysph(python: str, steps: int) -> dict:
    """Seconds for ``steps`` steps of PySPH's oscillating plate (set-up excluded) and its counts."""
    out = subprocess.run([python, '-c', PYSPH_RUN, str(steps)], capture_output=True, text=True,
                         timeout=3600, check=False)
    if out.returncode != 0:
        raise SystemExit(f'pysph_compare: PySPH run failed ({python}):\n{out.stderr[-2000:]}')
    res = json.loads(out.stdout.strip().splitlines()[-1])
    n = sum(res['counts'].values())
    moving = res['counts']['plate']
    return {'code': 'PySPH 1.0b2, 2D', 'particles': n, 'moving': moving, 'steps': res['steps'],
            'seconds': res['seconds']}


def our_solver(layers: int) -> Solver:
    clamp = int(round(CLAMPED / DX))
    model = make_beam(LENGTH, layers * DX, ROWS * DX, DX, fixed_layers=clamp)
    G = E / (2.0 * (1.0 + NU))
    material = Material.from_shear(G, NU, G * 1e-5, None, rho=RHO)
    probe = Solver(model, material, SolverConfig(mode='global'))
    # the sub-step bound scales with cfl: choose cfl so that a 1 ms frame takes 1e-5 s sub-steps
    cfl = probe.config.cfl * DT / probe.dt_max * (1.0 + 1e-9)
    return Solver(model, material, SolverConfig(mode='global', cfl=min(cfl, 0.99), max_substeps=100000))


def run_ours(layers: int, steps: int) -> dict:
    s = our_solver(layers)
    s.step(None, 1e-3)                     # compile and warm up
    frames = max(1, steps // 100)
    t0 = time.perf_counter()
    for _ in range(frames):
        res = s.step(None, 1e-3)
    seconds = time.perf_counter() - t0
    if abs(res.substep_dt - DT) > 1e-12:
        raise SystemExit(f'pysph_compare: our sub-step is {res.substep_dt:g} s, not {DT:g} s')
    return {'code': f'ours, tlsph global, 3D ({layers} layers)', 'particles': s.n,
            'moving': int(np.count_nonzero(~s.model.fixed)), 'steps': frames * res.substeps,
            'seconds': seconds}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--pysph-python', required=True, help='a Python interpreter that imports pysph')
    ap.add_argument('--steps', type=int, default=2000, help='time steps per run (each code)')
    ap.add_argument('--layers', type=int, default=ROWS, help='our plate: particle layers wide')
    ap.add_argument('--rounds', type=int, default=2)
    ap.add_argument('--out', type=Path, default=HERE / 'results')
    args = ap.parse_args(argv)
    rows: dict[str, list[dict]] = {}
    for r in range(args.rounds):
        for name, fn in (('pysph', lambda: run_pysph(args.pysph_python, args.steps)),
                         ('ours', lambda: run_ours(args.layers, args.steps))):
            print(f'round {r + 1}/{args.rounds}: {name} ...', flush=True)
            rows.setdefault(name, []).append(fn())
    table = []
    for runs in rows.values():
        per = [1e6 * x['seconds'] / (x['steps'] * x['particles']) for x in runs]
        per_moving = [1e6 * x['seconds'] / (x['steps'] * x['moving']) for x in runs]
        first = runs[0]
        table.append({'code': first['code'], 'particles': first['particles'], 'moving': first['moving'],
                      'steps': first['steps'], 'us_per_particle_step': statistics.median(per),
                      'us_per_moving_particle_step': statistics.median(per_moving),
                      'runs': ' '.join(f'{p:.3f}' for p in per)})
    print(f'\nper particle-step, {args.rounds} alternating rounds (median; every run listed)')
    print(f'{"code":38s} {"particles":>9s} {"moving":>7s} {"steps":>6s} {"us/particle-step":>17s} '
          f'{"us/moving":>10s}  runs')
    for t in table:
        print(f'{t["code"]:38s} {t["particles"]:9d} {t["moving"]:7d} {t["steps"]:6d} '
              f'{t["us_per_particle_step"]:17.3f} {t["us_per_moving_particle_step"]:10.3f}  {t["runs"]}')
    if len(table) == 2:
        print(f'ours / PySPH per particle-step: {table[1]["us_per_particle_step"] / table[0]["us_per_particle_step"]:.3f}')
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / 'pysph_compare.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(table)
    return 0


if __name__ == '__main__':
    sys.exit(main())
