"""The core benchmark runs end to end in --quick mode and writes sane CSV/PNG/TXT/JSON outputs.

Timing values are never asserted (speed is reported by the benchmark, not tested); only that every
measured configuration produced finite, positive numbers and consistent bookkeeping.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / 'benchmarks' / 'bench_core.py'


def _load_bench():
    spec = importlib.util.spec_from_file_location('bench_core', BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules['bench_core'] = mod         # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope='module')
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench')
    proc = subprocess.run([sys.executable, str(BENCH), '--quick', '--out', str(out)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open(out / 'bench_core_quick.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    return out, proc, rows


def _num(row, key):
    return float(row[key]) if row.get(key) not in (None, '') else math.nan


def test_quick_benchmark_writes_csv_png_txt_and_json(quick_run):
    out, proc, rows = quick_run
    png = (out / 'bench_core_quick.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 20_000
    text = (out / 'bench_core_quick.txt').read_text()
    for title in ('Table 1', 'Table 2', 'Table 3', 'Table 4', 'Table 5', 'Scaling', 'Memory', 'Targets'):
        assert title in text and title in proc.stdout
    meta = json.loads((out / 'bench_core_quick.json').read_text())
    assert meta['meta']['numba_warmup_s'] >= 0.0 and meta['targets']
    assert {r['table'] for r in rows} >= {'1', '2', '3', '4', '5', 'scaling', 'area', 'memory', 'targets'}


def test_every_tlsph_case_is_measured_with_finite_positive_numbers(quick_run):
    _, _, rows = quick_run
    timed = [r for r in rows if r['table'] not in ('memory', 'cut')]
    assert all(r['status'] == 'ok' for r in timed if r['scheme'] in ('tlsph', 'mass_spring'))
    for r in timed:
        if r['status'] != 'ok':
            assert r['scheme'] == 'paper'       # only the paper scheme may be n/a or unstable
            continue
        for key in ('step_ms', 'step_p90_ms', 'substep_us', 'ns_per_particle_substep', 'first_frame_ms'):
            assert math.isfinite(_num(r, key)) and _num(r, key) > 0.0, (r['label'], key)
        assert _num(r, 'step_p90_ms') >= _num(r, 'step_ms')
        assert _num(r, 'substeps') >= 1 and int(r['frames']) >= 3
        assert 1 <= _num(r, 'n_active') <= int(r['n_particles'])
        if r['mode'] == 'global':
            assert _num(r, 'n_stress') == int(r['n_particles'])


def test_the_cut_table_times_a_blade_and_a_needle_against_a_capsule_on_the_same_path(quick_run):
    out, _, rows = quick_run
    cut = {r['label']: r for r in rows if r['table'] == 'cut'}
    assert set(cut) == {f'{name} {mode} {shape}' for mode in ('local', 'global')
                        for name, tool in (('cut', 'blade'), ('needle', 'needle')) for shape in ('capsule', tool)}
    for r in cut.values():
        assert r['status'] == 'ok' and int(r['frames']) > 0
        assert 0.0 < _num(r, 'step_ms') <= _num(r, 'step_p90_ms') <= _num(r, 'step_p99_ms')
    assert all(int(cut[f'cut {mode} capsule']['bonds_cut']) == 0 for mode in ('local', 'global'))
    assert 'Cutting: a blade' in (out / 'bench_core_quick.txt').read_text()


def test_local_cases_integrate_fewer_particles_than_global_ones(quick_run):
    _, _, rows = quick_run
    glob = {(r['n_target'], r['h_paper']): _num(r, 'n_active') for r in rows
            if r['table'] == '2' and r['scheme'] == 'tlsph'}
    loc = {(r['n_target'], r['h_paper']): _num(r, 'n_active') for r in rows
           if r['table'] == '3' and r['scheme'] == 'tlsph'}
    assert glob and glob.keys() == loc.keys()
    assert all(loc[k] < glob[k] for k in glob)


def test_wider_interaction_area_and_more_layers_activate_more_particles(quick_run):
    _, _, rows = quick_run
    area = sorted((_num(r, 'k1'), _num(r, 'n_active')) for r in rows if r['table'] == 'area')
    assert [a[0] for a in area] == [1.0, 2.0, 3.0, 4.0]
    assert all(b[1] > a[1] for a, b in zip(area, area[1:]))
    layers = sorted((int(r['n_layers']), _num(r, 'n_active')) for r in rows
                    if r['table'] == '5' and r['scheme'] == 'tlsph')
    assert all(b[1] >= a[1] for a, b in zip(layers, layers[1:])) and layers[-1][1] > layers[0][1]


def test_memory_phases_report_resident_set_size(quick_run):
    _, _, rows = quick_run
    mem = [r for r in rows if r['table'] == 'memory']
    assert len(mem) >= 4 and all(r['status'] == 'ok' for r in mem)
    assert all(_num(r, 'peak_rss_mb') >= _num(r, 'rss_mb') > 10.0 for r in mem)


def test_paper_smoothing_lengths_map_to_one_physical_length_anchored_at_3670():
    bench = _load_bench()
    from sph_tissue_sim.core.solver import SolverConfig

    models = bench.Models('liver')
    anchor = bench.h_ratio_for(models, 3670, 0.3)
    assert anchor == pytest.approx(SolverConfig().h_ratio)
    # one paper length unit is one physical length: h/s scales with h and inversely with spacing
    for n in (289, 1289):
        for h in (0.3, 0.8):
            hr = bench.h_ratio_for(models, n, h)
            assert hr * models.get(n).spacing == pytest.approx(h / 0.3 * anchor * models.get(3670).spacing)
            assert hr > 0.5                     # 2h > spacing: every particle keeps neighbours


def test_threads_under_load_benchmark_writes_rows_and_finds_threaded_steps_bit_identical(tmp_path):
    script = ROOT / 'benchmarks' / 'threads_under_load.py'
    proc = subprocess.run([sys.executable, str(script), '--particles', '289', '--busy', '0,1',
                           '--local-frames', '20', '--global-frames', '6', '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    with open(tmp_path / 'threads_under_load.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert {(r['busy'], r['mode'], r['run']) for r in rows} == {
        (b, m, r) for b in ('0', '1') for m in ('local', 'global') for r in ('serial', 'threads')}
    for r in rows:
        assert r['identical'] == 'True' and int(r['frames']) > 0
        assert 0.0 < float(r['median_ms']) <= float(r['p99_ms']) <= float(r['max_ms'])


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / 'benchmarks' / f'{name}.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_pysph_comparison_runs_our_plate_at_pysphs_time_step():
    """Our half of ``pysph_compare.py`` (PySPH itself is not installed here): the plate extruded to
    3D takes sub-steps of exactly PySPH's 1e-5 s, and the run counts its steps and particles."""
    mod = _load('pysph_compare')
    res = mod.run_ours(3, 200)
    assert res['steps'] == 200
    assert res['particles'] == (100 + 25) * 11 * 3 and res['moving'] == 100 * 11 * 3
    assert res['seconds'] > 0.0 and math.isfinite(res['seconds'])


def test_pysph_comparison_says_clearly_when_pysph_is_missing():
    proc = subprocess.run([sys.executable, str(ROOT / 'benchmarks' / 'pysph_compare.py'),
                           '--pysph-python', sys.executable, '--steps', '10', '--rounds', '1'],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode != 0
    assert 'PySPH run failed' in proc.stderr and 'pysph' in proc.stderr


def test_the_latency_probe_times_the_echo_peer_that_answers_every_pose():
    """``sim_latency.py --peer`` (the floor printed beside sim_node's round trip): the echo node
    starts from the package's own constants and answers the probe's poses (a moved constant once
    broke it unnoticed)."""
    proc = subprocess.run([sys.executable, str(ROOT / 'benchmarks' / 'sim_latency.py'), '--peer',
                           '--duration', '2', '--skip', '0.5', '--csv', ''],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    sent, replies = (int(v) for v in
                     proc.stdout.split('poses sent / replies')[1].split('\n')[0].split('/'))
    assert sent == 1500 and replies > 0


def test_the_latency_probe_drives_two_instruments_and_reports_each():
    """``sim_latency.py --instruments left,right``: one pose stream per namespace, each answered on
    its own topic and reported on its own lines; ``--metrics`` reads the step times from the first
    instrument's metrics (there is no root ``tissue/metrics`` then: the probe once waited for it)."""
    proc = subprocess.run([sys.executable, str(ROOT / 'benchmarks' / 'sim_latency.py'), '--instruments', 'left,right',
                           '--model', 'block', '--n-particles', '256', '--duration', '2', '--skip', '0.5',
                           '--metrics', '--csv', ''], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    for name in ('left', 'right'):
        sent, replies = (int(v) for v in
                         proc.stdout.split(f'{name}: poses sent / replies')[1].split('\n')[0].split('/'))
        assert sent == 1500 and replies > 0
    steps = proc.stdout.split('step wall time median / p99')[1].split('\n')[0]
    assert 'ms' in steps and 'nan' not in steps


def test_the_latency_probe_takes_the_stylus_orientation_as_a_unit_quaternion():
    """``--orientation``: an upright needle or blade enters point first (a shaft along the stylus
    +z lies flat under the identity); four numbers, normalised, anything else refused."""
    mod = _load('sim_latency')
    args = mod.parser().parse_args(['--orientation=-1,0,0,1'])
    assert args.orientation == pytest.approx((-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)))
    assert mod.parser().parse_args([]).orientation == (0.0, 0.0, 0.0, 1.0)
    for bad in ('1,2', '0,0,0,0', 'nan,0,0,1'):
        with pytest.raises(SystemExit):
            mod.parser().parse_args(['--orientation', bad])
