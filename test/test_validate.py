"""The validation command runs every check end to end (``--quick``) and reports what it measured.

The quick run's numbers are small-model smoke values; the checks themselves are asserted by the
core's tests (``test_core_validation.py``). Here: every check produced finite measurements, a
verdict where it has a target, a plot, and a report that says how many targets were met; the
creep rows match Kelvin-Voigt, so the report carries real numbers.
"""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VALIDATE = ROOT / 'benchmarks' / 'validate.py'


@pytest.fixture(scope='module')
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('validate')
    proc = subprocess.run([sys.executable, str(VALIDATE), '--quick', '--out', str(out)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open(out / 'validate.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    return out, proc, rows


def test_the_quick_validation_measures_every_check_and_writes_a_plot_for_each(quick_run):
    out, _, rows = quick_run
    checks = {'creep', 'uniaxial', 'relaxation', 'cantilever', 'hertz', 'local_global', 'drag', 'press', 'press_set',
              'grasp', 'cut', 'needle'}
    assert {r['check'] for r in rows} == checks
    for r in rows:
        assert math.isfinite(float(r['measured'])), r
        assert r['met'] in ('yes', 'no', '')
        assert (r['met'] == '') == (r['target'] == 'reported'), r
    for name in checks - {'uniaxial'}:
        assert (out / f'validate_{name}.png').stat().st_size > 10_000


def test_the_report_tables_every_measure_and_counts_the_targets_met(quick_run):
    out, proc, rows = quick_run
    text = (out / 'validate.md').read_text()
    scored = [r for r in rows if r['met']]
    met = sum(r['met'] == 'yes' for r in scored)
    assert f'targets met: {met} of {len(scored)}' in text
    assert f'targets met: {met} of {len(scored)}' in proc.stdout
    assert text.count('\n| ') == len(rows) + 1          # header + one line per measure
    assert '![validate_press.png](validate_press.png)' in text


def test_the_creep_rows_follow_kelvin_voigt_within_two_percent(quick_run):
    creep = [r for r in quick_run[2] if r['check'] == 'creep']
    assert len(creep) == 3
    for r in creep:
        assert abs(float(r['measured']) / float(r['reference']) - 1.0) < 0.02
        assert r['met'] == 'yes'


def test_an_unknown_check_is_refused_with_the_list_of_checks():
    proc = subprocess.run([sys.executable, str(VALIDATE), '--checks', 'creep,hertzz'],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert "unknown checks ['hertzz']" in proc.stderr and 'local_global' in proc.stderr


@pytest.mark.parametrize('setting, message', [
    ('nope=1', "'nope=1': expected FIELD=VALUE with FIELD a SolverConfig field"),
    ('contact_samples=three', "'three' is not a int"),
    ('contact_samples=9', 'contact_samples must be in [0, 5], got 9'),
    ('far_field=near', "'near' is not a float"),
])
def test_a_bad_solver_setting_is_refused_before_any_check_runs(setting, message):
    proc = subprocess.run([sys.executable, str(VALIDATE), '--set', setting, '--checks', 'creep'],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert '[1/1]' not in proc.stdout


def test_the_report_names_the_solver_settings_it_ran_with(tmp_path):
    proc = subprocess.run([sys.executable, str(VALIDATE), '--quick', '--checks', 'creep', '--set',
                           'contact_samples=3', '--set', 'far_field=0.5', '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "tool checks' solver settings: contact_samples=3, far_field=0.5;" in (tmp_path / 'validate.md').read_text()


def test_the_quick_needle_insertion_shows_the_three_phases_and_gains_no_energy(quick_run):
    needle = [r for r in quick_run[2] if r['check'] == 'needle']
    scored = [r for r in needle if r['met']]
    assert len(scored) >= 9 and all(r['met'] == 'yes' for r in scored), scored
