#!/usr/bin/env python3
"""Before/after comparison of the core at two git revisions, back to back on the same machine.

    python benchmarks/ab_core.py --before 0956b18 [--after WORKTREE] [--rounds 2] [--tables targets]

The ``sph_tissue_sim`` package of each revision is exported (``git archive``) to a temporary
directory and put first on ``PYTHONPATH``; ``bench_core.py`` (always the current one) then runs the
chosen tables against it. Revisions alternate for ``--rounds`` rounds (before, after, before,
after, ...) so that slow drifts of the machine's load hit both; the table reports, per
configuration, the median over rounds of each run's median frame time.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PKG = 'src/sph_tissue_sim/sph_tissue_sim'


def export(rev: str, dest: Path) -> Path | None:
    """Export the package at ``rev`` under ``dest``; None means the working tree."""
    if rev.upper() == 'WORKTREE':
        return None
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(['git', 'archive', rev, PKG], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(['tar', '-x', '-C', str(dest)], input=archive, check=True)
    return dest / 'src' / 'sph_tissue_sim'


def run(pythonpath: Path | None, tables: str, out: Path) -> list[dict]:
    env = dict(os.environ)
    if pythonpath is not None:
        env['PYTHONPATH'] = f'{pythonpath}{os.pathsep}{env.get("PYTHONPATH", "")}'
    subprocess.run([sys.executable, str(HERE / 'bench_core.py'), '--tables', tables, '--out', str(out)],
                   env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with open(out / 'bench_core.csv', newline='') as fh:
        return list(csv.DictReader(fh))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--before', required=True, help='git revision (or WORKTREE)')
    ap.add_argument('--after', default='WORKTREE', help='git revision or WORKTREE (default)')
    ap.add_argument('--rounds', type=int, default=2)
    ap.add_argument('--tables', default='targets')
    args = ap.parse_args()
    results: dict[str, dict[str, list]] = {'before': {}, 'after': {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths = {'before': export(args.before, tmp / 'before'), 'after': export(args.after, tmp / 'after')}
        for k in range(args.rounds):
            for side in ('before', 'after'):
                print(f'round {k + 1}/{args.rounds}: {side} ({getattr(args, side)})', file=sys.stderr)
                rows = run(paths[side], args.tables, tmp / f'{side}{k}')
                for r in rows:
                    if r.get('status') == 'ok' and r.get('step_ms'):
                        results[side].setdefault(r['label'], []).append(
                            (float(r['step_ms']), float(r['substep_us']), r['n_particles'], r['substeps']))
    print(f'Before/after, back to back on {os.uname().nodename} ({os.cpu_count()} CPUs), {args.rounds} '
          f'alternating rounds; median over rounds of the per-run median frame time')
    print(f"{'config':<22} {'N':>7} {'sub':>3} | {'before ' + args.before:>16} {'after ' + args.after:>16} | "
          f"{'speed-up':>8} | {'us/sub before':>13} {'after':>8}")
    for label, after in results['after'].items():
        before = results['before'].get(label)
        a = statistics.median(x[0] for x in after)
        au = statistics.median(x[1] for x in after)
        if before:
            b = statistics.median(x[0] for x in before)
            bu = statistics.median(x[1] for x in before)
            print(f'{label:<22} {after[0][2]:>7} {after[0][3]:>3} | {b:>14.4f}ms {a:>14.4f}ms | {b / a:>7.2f}x | '
                  f'{bu:>13.1f} {au:>8.1f}')
        else:
            print(f'{label:<22} {after[0][2]:>7} {after[0][3]:>3} | {"n/a":>16} {a:>14.4f}ms |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
