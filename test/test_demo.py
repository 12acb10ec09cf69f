"""scripts/demo_run.py with the bring-up's choices: backend, model, tool and one YAML per node."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from tissue_testing import harness

pytestmark = pytest.mark.ros


def test_demo_runs_the_scripted_stylus_on_a_block_with_a_capsule_from_params_files(tmp_path,
                                                                                     ros_domain):
    driver_yaml = tmp_path / 'driver.yaml'
    driver_yaml.write_text('omni_driver:\n  ros__parameters:\n' + ''.join(
        f'    {k}: 0.2\n' for k in ('approach_time', 'press_time', 'hold_time', 'pull_time',
                                    'release_time', 'sweep_time', 'return_time')))
    sim_yaml = tmp_path / 'sim.yaml'
    sim_yaml.write_text('sim_node:\n  ros__parameters:\n    n_particles: 256\n'
                        '    block_size: [0.08, 0.08, 0.04]\n')
    report = tmp_path / 'report'
    out = subprocess.run(
        [sys.executable, str(harness.REPO_ROOT / 'scripts' / 'demo_run.py'), '--backend', 'scripted',
         '--model', 'block', '--tool', 'capsule', '--driver-params', str(driver_yaml),
         '--sim-params', str(sim_yaml), '--report-dir', str(report), '--domain', str(ros_domain)],
        capture_output=True, text=True, timeout=600, env=harness.ros_env(ros_domain))
    text = out.stdout + out.stderr
    assert out.returncode == 0, text
    assert 'demo: backend scripted' in text
    # the options reached sim_node over its YAML: a 256-particle block with a capsule
    assert 'demo: sim_node model block (256 particles' in text and 'tool capsule' in text
    # the driver read its YAML: the script with 0.2 s segments, one pass at 1 kHz
    from haptic_omni_driver.backends.scripted import ScriptConfig, build_script, script_duration

    times = {k: 0.2 for k in ('approach_time', 'press_time', 'hold_time', 'pull_time',
                              'release_time', 'sweep_time', 'return_time')}
    duration = script_duration(build_script(ScriptConfig(**times)))
    assert f'script finished: {round(duration * 1000) + 1} poses, one pass of {duration:.2f} s' in text
    # the closing lines say what the hand got, as the report does
    # (a machine too busy for steady contact says so instead of printing nan)
    assert re.search(r'demo: force sent: (\|dF\| per frame in steady contact p99 [\d.]+ mN, max '
                     r'[\d.]+ mN|no frames in steady contact); \d+ one-frame reversals above 10 '
                     r'mN; E_in min -?[\d.]+ uJ; '
                     r'(targets met|missed: )', text), text[-3000:]
    summary = json.loads((report / 'summary.json').read_text())
    assert 'feel_reversals' in summary and 'feel_E_in_min_uJ' in summary
    assert {'force_vs_time.png', 'tissue_deepest.png', 'tissue_press.gif'} <= set(summary['files'])
    assert summary['failed_files'] == {}, summary


def test_demo_refuses_lockstep_without_a_bag_and_a_missing_params_file(tmp_path):
    demo = str(harness.REPO_ROOT / 'scripts' / 'demo_run.py')
    for extra, why in ((['--backend', 'scripted', '--timing', 'lockstep'], 'needs --backend replay'),
                       (['--sim-params', str(tmp_path / 'none.yaml')], 'no params file')):
        out = subprocess.run([sys.executable, demo, *extra], capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 2 and why in out.stderr, out.stderr


def test_demo_closing_lines_read_a_report_without_latency_figures(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location('demo_run', harness.REPO_ROOT / 'scripts' / 'demo_run.py')
    demo_run = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo_run)
    summary = tmp_path / 'summary.json'
    summary.write_text(json.dumps({'poses': 12, 'forces': 0, 'replies_missed': 12, 'replies_missed_pct': 100.0,
                                   'latency_p50_s': None, 'latency_p99_s': None, 'feel_dF_p99_mN': None,
                                   'feel_dF_max_mN': None, 'feel_reversals': 0.0, 'feel_E_in_min_uJ': 0.0}))
    lines = demo_run.closing_lines(summary)
    assert lines[0] == ('12 poses, 0 forces, 12 poses without a reply (100.00 %); pose->force latency '
                        'median n/a, p99 n/a')
    assert 'no frames in steady contact' in lines[1] and 'nan' not in lines[1]


def test_demo_feel_line_says_no_steady_contact_instead_of_nan():
    import importlib.util

    spec = importlib.util.spec_from_file_location('demo_run', harness.REPO_ROOT / 'scripts' / 'demo_run.py')
    demo_run = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo_run)
    line = demo_run.feel_line({'dF_p99_mN': float('nan'), 'dF_max_mN': float('nan'), 'reversals': 0,
                               'E_in_min_uJ': -3.0})
    assert 'nan' not in line and 'no frames in steady contact' in line
    assert line.endswith('missed: E_in min -3.0 uJ < -1')
    line = demo_run.feel_line({'dF_p99_mN': 4.0, 'dF_max_mN': 8.0, 'reversals': 0, 'E_in_min_uJ': 0.0})
    assert 'steady contact p99 4.00 mN, max 8.0 mN' in line and line.endswith('targets met')
