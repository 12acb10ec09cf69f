"""benchmarks/press_depth.py presses the liver with each contact model and tool and says where the
tissue gives way; ``cases.gives_way`` is the criterion it shares with validate.py's press check."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from sph_tissue_sim.validation.cases import gives_way

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / 'benchmarks' / 'press_depth.py'


def test_a_force_that_keeps_rising_never_gives_way():
    d = np.linspace(0.0, 0.04, 401)
    assert math.isinf(gives_way(d, 3.0 * d ** 1.5))
    # a dip of 1 % of the peak is within the tolerance
    f = 3.0 * d ** 1.5
    f[200] -= 0.01 * f.max()
    assert math.isinf(gives_way(d, f))


def test_the_force_gives_way_where_it_first_falls_below_its_running_maximum():
    d = np.linspace(0.0, 0.04, 401)
    f = np.where(d <= 0.01, d / 0.01, np.maximum(0.0, 1.0 - (d - 0.01) / 0.001))
    # the peak (1 N) is at 10 mm; the next sample, 0.1 mm deeper, has fallen by 0.1 N
    assert abs(gives_way(d, f) - 0.0101) < 1e-9


def test_a_small_grid_writes_its_table_curves_and_plot(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), '--particles', '743', '--depth', '0.008',
                           '--contacts', 'balls,backstop', '--tools', 'sphere', '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert '| particles | contact | tool |' in proc.stdout
    with open(tmp_path / 'press_depth.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert [(r['contact'], r['tool']) for r in rows] == [('balls', 'sphere'), ('backstop', 'sphere')]
    for r in rows:
        assert float(r['peak_n']) > 0.0 and 0.0 < float(r['peak_mm']) <= 8.0 + 1e-6
    with open(tmp_path / 'press_depth_curves.csv', newline='') as fh:
        curve = [r for r in csv.DictReader(fh) if r['contact'] == 'balls']
    assert len(curve) == 800 and abs(float(curve[-1]['depth_mm']) - 8.0) < 1e-6
    assert (tmp_path / 'press_depth.png').stat().st_size > 0


def test_bad_arguments_are_refused_with_a_reason(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), '--contacts', 'springs', '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2 and 'springs' in proc.stderr
