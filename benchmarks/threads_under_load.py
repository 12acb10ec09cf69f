#!/usr/bin/env python3
"""Serial vs numba-threaded tlsph steps on an idle machine and beside busy processes.

    python benchmarks/threads_under_load.py                 # 3670 liver, 0/1/2 busy processes
    python benchmarks/threads_under_load.py --busy 0 --local-frames 200 --global-frames 10

For each number of busy processes (pure-Python spin loops started by this script, so the machine's
cores are contended as they are when the driver and the visualiser share them with the simulator),
the liver is pressed 10 mm and palpated like in ``bench_core.py``, once with
``parallel_min_particles=0`` (serial, the default) and once with ``1`` (every sub-step threaded).
Prints the median, p99 and max frame time of the second half of the frames (after the press) and
writes ``threads_under_load.csv`` to ``--out``. It also checks that both runs end in bit-identical
positions (they must: the threaded pass keeps each particle's summation order).
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_core import PressScript  # noqa: E402  (benchmarks/ is not a package)

from sph_tissue_sim.core.material import liver_default  # noqa: E402
from sph_tissue_sim.core.factory import make_model  # noqa: E402
from sph_tissue_sim.core.solver import Solver, SolverConfig, warmup  # noqa: E402


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def run(model, mode: str, par: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame times [s] of the second half and the final positions."""
    solver = Solver(model, liver_default(), SolverConfig(mode=mode, parallel_min_particles=par))
    script = PressScript(model, solver.contact_reach, 0.010, frames // 2, 0.001, 2.0)
    times = []
    for k in range(frames):
        t0 = time.perf_counter()
        solver.step(script.at(k), 1e-3)
        times.append(time.perf_counter() - t0)
    return np.array(times[frames // 2:]), solver.positions.copy()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--particles', type=int, default=3670)
    ap.add_argument('--busy', default='0,1,2', help='comma-separated counts of busy processes')
    ap.add_argument('--local-frames', type=int, default=2000)
    ap.add_argument('--global-frames', type=int, default=40)
    ap.add_argument('--out', type=Path, default=Path(__file__).resolve().parent / 'results')
    a = ap.parse_args(argv)
    import numba
    warmup('tlsph')
    model = make_model('liver', n_particles=a.particles)
    print(f'{model.n_particles}-particle liver, numba {numba.__version__}, {numba.get_num_threads()} threads '
          f'({os.environ.get("NUMBA_THREADING_LAYER", "default")} threading layer), {os.cpu_count()} CPUs, '
          f'load {os.getloadavg()[0]:.2f}')
    rows = []
    ctx = mp.get_context('spawn')
    for busy in (int(b) for b in a.busy.split(',')):
        stop = ctx.Event()
        hogs = [ctx.Process(target=_spin, args=(stop,), daemon=True) for _ in range(busy)]
        for h in hogs:
            h.start()
        try:
            for mode, frames in (('local', a.local_frames), ('global', a.global_frames)):
                serial, x_s = run(model, mode, 0, frames)
                threaded, x_t = run(model, mode, 1, frames)
                for name, t in (('serial', serial), ('threads', threaded)):
                    rows.append(dict(busy=busy, mode=mode, run=name, frames=len(t),
                                     median_ms=float(np.median(t)) * 1e3,
                                     p99_ms=float(np.percentile(t, 99)) * 1e3, max_ms=float(t.max()) * 1e3,
                                     identical=bool(np.array_equal(x_s, x_t))))
        finally:
            stop.set()
            for h in hogs:
                h.join(5.0)
    print(f'{"busy":>4} {"mode":7} {"run":8} {"median ms":>10} {"p99 ms":>8} {"max ms":>8}  bit-identical')
    for r in rows:
        print(f'{r["busy"]:4d} {r["mode"]:7} {r["run"]:8} {r["median_ms"]:10.3f} {r["p99_ms"]:8.3f} '
              f'{r["max_ms"]:8.3f}  {r["identical"]}')
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / 'threads_under_load.csv'
    with path.open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f'wrote {path}')
    return 0 if all(r['identical'] for r in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
