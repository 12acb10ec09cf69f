#!/usr/bin/env python3
"""Live-rate system benchmark: a bag replayed at real time (1 kHz poses) through the whole loop.

Starts ``sim_node`` (live timing) and ``omni_driver`` (replay, timed, at the bag's recorded 1 kHz
timing) as real processes on a private ROS_DOMAIN_ID, plus an in-process monitor subscribed
(best effort) to ``omni/pose`` and ``omni/force_feedback``. Reports per run:

* achieved haptic rate: force replies per second over the replay;
* pose->force latency (median, p99, max): receive time of the force carrying a pose's stamp minus
  the receive time of that pose, both at the monitor;
* dropped poses: poses seen by the monitor without a force reply carrying their stamp;
* the driver's watchdog trips (omni/state) and the sim's step wall time (tissue/metrics).

Prints a table and writes a CSV (default ``benchmarks/results/system_live.csv``).

Usage (after ``source scripts/env.sh``)::

    python benchmarks/system_live.py [--bag bags/long] [--repeat 1] [--sim-param n_particles=3670]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import re
import statistics
import sys
import time
from pathlib import Path

from tissue_testing import harness
from tissue_testing import system_graph as graph

ROOT = Path(__file__).resolve().parent.parent


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {'true': True, 'false': False}.get(text.lower(), text)


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float('nan')
    s = sorted(values)
    return s[min(len(s) - 1, max(0, int(math.ceil(q / 100.0 * len(s))) - 1))]


def run_once(bag: Path, sim_params: dict, golden: bool, rate: float) -> dict:
    env = harness.ros_env()
    load_before = os.getloadavg()[0]
    sim = graph.sim('live', env=env, golden=golden, params=sim_params)
    drv = graph.driver_replay(bag, 'timed', env=env, rate=rate, subscribers=2)
    try:
        sim.start()
        sim.wait_for_output(graph.SIM_READY, timeout=240)
        with graph.Monitor(env, keep=True) as mon:
            mon.probe_sim()
            drv.start()
            t0 = time.monotonic()
            code = drv.wait(timeout=600)
            wall = time.monotonic() - t0
            time.sleep(0.3)  # replies in flight
            with mon.lock:
                forces = list(mon.forces)
                lat = list(mon.latencies)
                n_poses = mon.n_poses
                states = list(mon.states)
                steps = list(mon.step_times)
            unanswered = mon.unanswered()
    finally:
        graph.stop_all([drv, sim])
    if code != 0:
        raise SystemExit(f'omni_driver exited with {code}:\n{drv.output()[-3000:]}')
    m = re.search(r'replay finished: (\d+) poses in ([\d.]+) s', drv.output())
    sent = int(m.group(1)) if m else n_poses
    replay_s = float(m.group(2)) if m else wall
    # haptic rate: replies per second between the first and the last reply
    if len(forces) > 1:
        span = forces[-1][1] - forces[0][1]
        rate_hz = (len(forces) - 1) / span if span > 0 else float('nan')
    else:
        rate_hz = float('nan')
    norms = [math.sqrt(sum(v * v for v in f)) for _, _, f in forces]
    trips = sum(1 for i in range(1, len(states))
                if states[i][1].watchdog_tripped and not states[i - 1][1].watchdog_tripped)
    return {
        'bag': bag.name, 'load_1min': f'{load_before:.1f}/{os.getloadavg()[0]:.1f}',
        'poses_sent': sent, 'poses_seen': n_poses, 'replies': len(forces),
        'replay_s': round(replay_s, 3), 'haptic_rate_hz': round(rate_hz, 1),
        'latency_median_ms': round(statistics.median(lat) * 1e3, 4) if lat else float('nan'),
        'latency_p99_ms': round(percentile(lat, 99) * 1e3, 4),
        'latency_max_ms': round(max(lat) * 1e3, 4) if lat else float('nan'),
        'dropped_poses': unanswered,
        'dropped_pct': round(100.0 * unanswered / max(n_poses, 1), 3),
        'max_force_n': round(max(norms), 4) if norms else 0.0,
        'watchdog_trips': trips,
        'step_median_ms': round(statistics.median(steps) * 1e3, 4) if steps else float('nan'),
        'step_p99_ms': round(percentile(steps, 99) * 1e3, 4),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bag', type=Path, default=ROOT / 'bags' / 'long')
    ap.add_argument('--repeat', type=int, default=1)
    ap.add_argument('--rate', type=float, default=1.0, help='replay speed factor (1.0 = real time)')
    ap.add_argument('--golden', action='store_true',
                    help='sim with bags/golden_sim_params.yaml (else its defaults)')
    ap.add_argument('--sim-param', action='append', default=[], metavar='NAME=VALUE',
                    help='sim_node parameter override (repeatable)')
    ap.add_argument('--csv', type=Path, default=ROOT / 'benchmarks' / 'results' / 'system_live.csv')
    args = ap.parse_args(argv)
    sim_params = {}
    for item in args.sim_param:
        name, _, value = item.partition('=')
        sim_params[name] = _value(value)
    rows = []
    for k in range(args.repeat):
        row = run_once(args.bag.resolve(), sim_params, args.golden, args.rate)
        row['run'] = k + 1
        row['sim_params'] = ' '.join(f'{n}={v}' for n, v in sim_params.items()) or (
            'golden' if args.golden else 'defaults')
        rows.append(row)
    cols = ['run', 'bag', 'poses_sent', 'replies', 'haptic_rate_hz', 'latency_median_ms',
            'latency_p99_ms', 'latency_max_ms', 'dropped_poses', 'dropped_pct', 'max_force_n',
            'watchdog_trips', 'step_median_ms', 'step_p99_ms', 'replay_s', 'load_1min',
            'sim_params']
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    print('  '.join(c.rjust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print('  '.join(str(r[c]).rjust(w) for c, w in zip(cols, widths)))
    print('targets (DESIGN.md section 6): latency median <= 1 ms, p99 <= 3 ms, < 1 % poses '
          'without a reply')
    print(f'load_1min: 1-minute load average before/after the run on {os.cpu_count()} CPUs '
          '(other processes compete for the cores; the numbers are only as good as the machine)')
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=cols + ['poses_seen'])
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in w.fieldnames})
    print(f'wrote {args.csv}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
