"""benchmarks/contact_cost.py times each contact model's local step in one interleaved run."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / 'benchmarks' / 'contact_cost.py'


def test_a_small_run_writes_one_row_per_model_and_depth(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), '--particles', '743', '--contacts', 'balls,backstop',
                           '--depths', '0.002,0.004', '--frames', '20', '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert '| particles | depth [mm] | contact |' in proc.stdout
    with open(tmp_path / 'contact_cost.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert [(r['depth_mm'], r['contact']) for r in rows] == [('2.0', 'balls'), ('2.0', 'backstop'),
                                                             ('4.0', 'balls'), ('4.0', 'backstop')]
    for r in rows:
        assert float(r['step_ms']) > 0.0 and float(r['active']) > 0.0 and float(r['substeps']) >= 1.0
    # the first model is the reference of the ratios
    assert all(float(r['ratio']) == 1.0 for r in rows if r['contact'] == 'balls')
    assert (tmp_path / 'contact_cost.md').read_text().count(f"| {rows[0]['particles']} |") == 4


def test_bad_arguments_are_refused_with_a_reason(tmp_path):
    for args, word in ((['--contacts', 'springs'], 'springs'), (['--depths', '0.1'], '--depths'),
                       (['--frames', '3'], '--frames')):
        proc = subprocess.run([sys.executable, str(SCRIPT), *args, '--out', str(tmp_path)],
                              capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert proc.returncode == 2 and word in proc.stderr, args
