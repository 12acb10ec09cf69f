"""benchmarks/first_touch.py presses the liver waiting for the far field's responses and not."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / 'benchmarks' / 'first_touch.py'


def test_a_small_run_writes_both_ways_at_every_place(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), '--particles', '743', '--depth', '0.004',
                           '--out', str(tmp_path)], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert 'Exception ignored' not in proc.stderr   # the worker was joined before the interpreter went
    with open(tmp_path / 'first_touch.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert [r['way'] for r in rows] == ['wait', 'background'] * 4
    for r in rows:
        assert float(r['longest_frame_ms']) >= float(r['median_frame_ms']) > 0.0
        assert int(r['frames_over_2ms']) >= 0
    for wait, background in zip(rows[::2], rows[1::2]):
        assert wait['place_mm'] == background['place_mm']
        assert wait['largest_fz_difference_N'] == background['largest_fz_difference_N']
        forces = [float(r[k]) for r in (wait, background) for k in ('fz_2mm_N', 'fz_4mm_N')]
        assert all(f >= 0.0 for f in forces)   # the tissue pushes the tool up, or not yet at all
    assert (tmp_path / 'first_touch.png').stat().st_size > 0
