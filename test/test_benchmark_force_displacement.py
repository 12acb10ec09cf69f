"""The force-displacement experiment script (paper Figs. 9 and 11) in its --quick form."""

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / 'benchmarks' / 'force_displacement.py'
REQUIRED = {'tlsph global', 'tlsph local', 'mass_spring global'}


def test_force_displacement_quick_run_writes_csv_summary_and_a_real_png(tmp_path):
    out = tmp_path / 'fd'
    proc = subprocess.run([sys.executable, str(SCRIPT), '--quick', '--no-progress', '--out', str(out)],
                          capture_output=True, text=True, timeout=240, cwd=str(tmp_path))
    assert proc.returncode in (0, 1), proc.stderr
    assert 'peak |F| N' in proc.stdout                  # the summary table was printed

    with open(out / 'force_displacement.csv', newline='') as fh:
        reader = csv.DictReader(fh)
        assert set(reader.fieldnames) >= {'config', 'phase', 'time', 'tool_dx', 'tool_dy', 'tool_dz',
                                          'depth', 'fx', 'fy', 'fz', 'f_norm'}
        rows = list(reader)
    configs = {r['config'] for r in rows}
    assert REQUIRED <= configs
    for name in REQUIRED:
        mine = [r for r in rows if r['config'] == name]
        assert {r['phase'] for r in mine} == {'press', 'hold', 'pull', 'release'}
        f = np.array([[float(r['fx']), float(r['fy']), float(r['fz']), float(r['f_norm'])] for r in mine])
        assert np.all(np.isfinite(f))
        assert np.allclose(np.linalg.norm(f[:, :3], axis=1), f[:, 3], rtol=1e-4, atol=1e-6)
        depth = np.array([float(r['depth']) for r in mine])
        at_depth = [r for r in mine if r['phase'] == 'hold']
        assert depth.max() > 0.0
        # pressing the liver pushes the tool back up, and the tool is free after the release
        assert all(float(r['fz']) > 0.0 for r in at_depth)
        assert float(mine[-1]['f_norm']) < 0.1 * max(float(r['f_norm']) for r in at_depth)
    # a skipped configuration is announced, never silently missing
    for scheme_mode in ('paper global', 'paper local'):
        assert scheme_mode in configs or f'note: {scheme_mode}' in proc.stdout

    with open(out / 'summary.csv', newline='') as fh:
        summary = {r['config']: r for r in csv.DictReader(fh)}
    assert REQUIRED <= set(summary)
    assert summary['tlsph local']['local_vs_global_pct'] != ''

    png = out / 'force_displacement.png'
    assert png.stat().st_size > 20_000
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    img = plt.imread(str(png))
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 900
    assert img[..., :3].std() > 0.05                    # not a blank canvas
