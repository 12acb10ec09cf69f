"""The report folder: files, CSV series, summaries, and PNGs that are real, non-blank plots."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from tissue_viz.errors import ReportError
from tissue_viz.report import (PLOTS, TABLES, ReportData, load_report_data, main, read_csv,
                               summary_rows, write_csv, write_report)
from tissue_viz.stats import HAPTIC_MULTIRATE, VizStats
from tissue_viz.tissue_images import TissueSnapshots, draw_snapshot

MS = 1_000_000
PNGS = [png for png, _ in PLOTS]
TISSUE_PNGS = ['tissue_rest.png', 'tissue_deepest.png']
CHARTS = [png for png in PNGS if png not in TISSUE_PNGS]       # the 800 x 450 plots


def _press_run(seconds: float = 2.0, rate: float = 500.0, multirate: bool = True) -> VizStats:
    """A press into 400 N/m tissue and back, poses/forces/metrics at ``rate``, 1 in 50 steps slow.

    Multirate: E_in is the spring's stored energy plus a steady 10 uJ/s lost to damping, so it
    never goes below zero and ends at about 20 uJ; solver at 400 Hz, 0.3 N s/m added in contact.
    Direct: the haptic values are zero, as the simulator sends them.
    """
    stats = VizStats(window=0.5, haptic_rate=1000.0)
    n = int(seconds * rate)
    for i in range(n):
        t = i / rate
        z = 0.002 - 0.006 * math.sin(math.pi * t / seconds) ** 2
        f = 400.0 * max(0.0, -z)
        step = 2e-3 if i % 50 == 0 else 1e-4 + 1e-4 * (i % 7) / 7
        haptic = dict(haptic_mode=HAPTIC_MULTIRATE, solver_rate=400.0, model_age=2.5e-3,
                      coupling_stretch=f / 2000.0, energy_in=0.5 * f * max(0.0, -z) + 1e-5 * t,
                      energy_in_min=0.0, added_damping=0.3 if f else 0.0) if multirate else {}
        stats.on_pose(t, i * MS, (0.0, 0.0, z))
        stats.on_metrics(t + step, i * MS, step, (0.0, 0.0, f), 0.5 * max(0.0, -z),
                         n_interaction=80 if f else 0, n_layer=[30, 10] if f else [], **haptic)
        stats.on_force(t + 3e-4, i * MS, (0.0, 0.0, f))
        if i % 50 == 0:
            stats.sample_rates(t)
    return stats


def _press_clouds(n_clouds: int = 40) -> TissueSnapshots:
    """A 10 x 10 x 5 block pressed at its top centre and released: displacement a bowl under the
    tool, deepest (4 mm) half-way, von Mises 1 kPa per mm of it."""
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(5), indexing='ij'), -1)
    rest = g.reshape(-1, 3) * 0.005 + np.array([-0.0225, -0.0225, 0.0])
    top = np.array([0.0, 0.0, 0.02])
    snaps = TissueSnapshots()
    for k in range(n_clouds):
        depth = 0.004 * math.sin(math.pi * k / (n_clouds - 1))
        r2 = np.sum((rest - top) ** 2, axis=1)
        disp = depth * np.exp(-r2 / 0.01 ** 2)
        xyz = rest - np.outer(disp, [0.0, 0.0, 1.0])
        columns = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2], 'displacement': disp,
                   'von_mises': 1e6 * disp}
        tool = (top + np.array([0.0, 0.0, 0.005 - depth]), np.zeros(3), 0.0, 0.005)
        snaps.add(columns, k * 33 * MS, (tool,))
    return snaps


def _ink(path) -> tuple[tuple[int, int], float, int]:
    """(size, share of non-white pixels, number of distinct colours) of a PNG."""
    with Image.open(path) as img:
        assert img.format == 'PNG'
        rgb = np.asarray(img.convert('RGB'), dtype=int)
        size = img.size
    ink = float(np.mean(rgb.sum(axis=2) < 3 * 250))
    colours = len(np.unique((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]))
    return size, ink, colours


@pytest.fixture(scope='module')
def report(tmp_path_factory):
    stats = _press_run()
    out = tmp_path_factory.mktemp('report') / 'run'
    targets = {'metrics': (450.0, 550.0), 'particles': (25.0, 35.0), 'pose': (450.0, 550.0),
               'force': (450.0, 550.0)}
    write_report(out, ReportData.from_stats(stats, 2.0, title='Press test', rate_targets=targets,
                                            tissue=_press_clouds()))
    return out, stats


def test_report_folder_holds_plots_series_and_summaries(report):
    out, _ = report
    expected = set(PNGS) | {f'{n}.csv' for n in TABLES} | {'summary.md', 'index.html',
                                                            'summary.json', 'tissue_press.gif',
                                                            'tissue_snapshots.npz'}
    assert expected <= {p.name for p in out.iterdir()}
    summary = json.loads((out / 'summary.json').read_text())
    assert set(summary['files']) == expected - {'summary.json'}
    md = (out / 'summary.md').read_text()
    assert md.startswith('# Press test') and all(f'({png})' in md for png in PNGS)
    html = (out / 'index.html').read_text()
    assert all(f'src="{png}"' in html for png in PNGS) and '<table>' in html


def test_report_pngs_are_non_blank_plots_with_colour(report):
    out, _ = report
    for png in CHARTS:
        size, ink, colours = _ink(out / png)
        assert size == (800, 450), png
        # Axes, labels, title and data: several per cent of the pixels, many colours (antialiasing,
        # coloured series), but not a filled or black image.
        assert 0.02 < ink < 0.8, (png, ink)
        assert colours > 50, (png, colours)


def test_plots_with_data_carry_more_ink_than_the_empty_placeholders(report, tmp_path):
    out, _ = report
    empty = write_report(tmp_path / 'empty', ReportData())
    for png in ('force_vs_time.png', 'step_time_hist.png', 'force_vs_displacement.png'):
        _, ink_data, _ = _ink(out / png)
        _, ink_empty, _ = _ink(empty / png)
        assert ink_data > 1.5 * ink_empty, (png, ink_data, ink_empty)
    assert json.loads((empty / 'summary.json').read_text())['steps'] == 0


def test_summary_numbers_match_the_run(report):
    out, stats = report
    summary = json.loads((out / 'summary.json').read_text())
    n = 1000
    assert summary['steps'] == n and summary['poses'] == n and summary['forces'] == n
    assert summary['deadline_misses'] == n // 50
    assert summary['deadline_miss_pct'] == pytest.approx(2.0)
    assert summary['latency_p50_s'] == pytest.approx(3e-4)
    assert summary['max_force_n'] == pytest.approx(400.0 * 0.004, rel=1e-3)
    assert summary['max_active_particles'] == 120
    assert summary['rates_hz']['pose'] == pytest.approx(500.0)
    md = (out / 'summary.md').read_text()
    assert '| deadline misses | 20 (2.00 %) |' in md
    assert '| pose to force latency p50 | 0.300 ms |' in md


def test_a_multirate_run_gets_the_e_in_plot_and_the_haptic_summary_rows(report, tmp_path,
                                                                        monkeypatch):
    out, _ = report
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['energy_in_min_j'] == 0.0
    assert summary['energy_in_final_j'] == pytest.approx(1e-5 * 999 / 500)
    assert summary['max_added_damping_n_s_per_m'] == pytest.approx(0.3)
    assert summary['solver_rate_p50_hz'] == pytest.approx(400.0)
    md = (out / 'summary.md').read_text()
    assert '| E_in min (below zero: not passive) | 0.000 uJ |' in md
    assert '| E_in final | 19.980 uJ |' in md and '| solver rate p50 | 400.0 Hz |' in md
    assert '| max added damping | 0.300 N s/m |' in md
    # The same figures when the summary is recomputed from the CSV files, and E_in is drawn.
    said = _spy_no_data(monkeypatch)
    assert main([str(out), '-o', str(tmp_path / 'again'), '--recompute-summary']) == 0
    assert 'multirate haptic rendering' not in said
    again = json.loads((tmp_path / 'again' / 'summary.json').read_text())
    for key in ('energy_in_min_j', 'energy_in_final_j', 'max_added_damping_n_s_per_m',
                'solver_rate_p50_hz'):
        assert again[key] == pytest.approx(summary[key]), key


def _spy_no_data(monkeypatch) -> list[str]:
    """Record what each plot said it had no data of (the placeholder is still drawn)."""
    import tissue_viz.report as report

    said = []
    real = report._no_data

    def no_data(ax, what):
        said.append(what)
        real(ax, what)

    monkeypatch.setattr(report, '_no_data', no_data)
    return said


def test_a_direct_run_gets_an_e_in_placeholder_and_no_haptic_summary_rows(tmp_path, monkeypatch):
    said = _spy_no_data(monkeypatch)
    out = write_report(tmp_path / 'run',
                       ReportData.from_stats(_press_run(0.5, multirate=False), 0.5))
    summary = _assert_complete_with_drawn_plots(out)
    # every other plot has its data (no clouds in this run: the tissue images say so too)
    assert sorted(said) == ['multirate haptic rendering'] + ['tissue/particles cloud'] * 2
    md = (out / 'summary.md').read_text()
    assert 'energy_in_min_j' not in summary and 'E_in final' not in md
    # what the hand got is measured from the forces sent, whatever rendered them
    assert 'E_in min of the forces sent' in md and summary['feel_reversals'] >= 0


def test_an_old_report_without_the_haptic_columns_still_loads_and_renders(tmp_path, monkeypatch):
    old = write_report(tmp_path / 'old', ReportData.from_stats(_press_run(0.5), 0.5))
    haptic = ('haptic_mode',) + VizStats.HAPTIC_COLUMNS
    old_columns = tuple(c for c in TABLES['metrics'] if c not in haptic)
    write_csv(old / 'metrics.csv', old_columns, read_csv(old / 'metrics.csv'))
    summary = json.loads((old / 'summary.json').read_text())
    (old / 'summary.json').write_text(json.dumps(
        {k: v for k, v in summary.items() if k not in ('energy_in_min_j', 'energy_in_final_j',
                                                        'max_added_damping_n_s_per_m',
                                                        'solver_rate_p50_hz')}))
    data = load_report_data(old)
    assert tuple(data.tables['metrics']) == old_columns
    assert np.isnan(data.table('metrics')['energy_in']).all()
    said = _spy_no_data(monkeypatch)
    # Rebuilt with its summary, recomputed, and rebuilt again from the rebuilt (empty haptic cells).
    runs = ((old, 'kept', []), (old, 'recomputed', ['--recompute-summary']),
            (tmp_path / 'recomputed', 'twice', ['--recompute-summary']))
    for src, name, flags in runs:
        assert main([str(src), '-o', str(tmp_path / name), *flags]) == 0
        summary = _assert_complete_with_drawn_plots(tmp_path / name)
        assert summary['steps'] == 250 and 'energy_in_min_j' not in summary, name
        assert not any(summary['bad_values'].get(c) for c in haptic), (name, summary['bad_values'])
        md = (tmp_path / name / 'summary.md').read_text()
        assert 'E_in final' not in md and '## Not shown' not in md, name
    assert sorted(said) == sorted((['multirate haptic rendering'] + ['tissue/particles cloud'] * 2)
                                  * len(runs))


def test_csv_series_round_trip_with_the_recorded_values(report):
    out, stats = report
    metrics = read_csv(out / 'metrics.csv')
    assert list(metrics) == list(TABLES['metrics'])
    assert np.allclose(metrics['step_wall_time'], stats.metrics_table.as_dict()['step_wall_time'])
    force = read_csv(out / 'force.csv')
    assert len(force['t']) == 1000 and np.nanmax(force['force']) == pytest.approx(1.6, rel=1e-3)
    # The pose matched to each force is recorded, so force against displacement can be drawn.
    assert np.isfinite(force['pz']).all()


def test_tissue_report_rebuilds_a_report_from_its_csv_files(report, tmp_path, capsys):
    out, _ = report
    assert load_report_data(out).rate_targets['metrics'] == (450.0, 550.0)
    again = tmp_path / 'again'
    assert main([str(out), '-o', str(again), '--recompute-summary']) == 0
    assert 'wrote' in capsys.readouterr().out
    summary = json.loads((again / 'summary.json').read_text())
    assert summary['steps'] == 1000 and summary['deadline_misses'] == 20
    for png in PNGS:
        assert _ink(again / png)[1] > 0.02


def test_tissue_report_rejects_missing_and_corrupt_input(tmp_path, capsys):
    assert main([str(tmp_path / 'nowhere')]) == 2
    assert 'not a report folder' in capsys.readouterr().err
    (tmp_path / 'metrics.csv').write_text('t,step_wall_time\n0.0,abc\n')
    with pytest.raises(ReportError, match='not a numeric CSV'):
        load_report_data(tmp_path)
    assert main([str(tmp_path)]) == 2


def test_report_into_an_unwritable_place_raises_a_report_error(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    with pytest.raises(ReportError, match='cannot create report folder'):
        write_report(blocker / 'report', ReportData())


def test_plot_thinning_keeps_every_peak_of_a_long_run():
    from tissue_viz.report import MAX_PLOT_POINTS, _thin

    force = np.zeros(100_000)
    force[[12_345, 77_777]] = 3.3                        # two 1-sample force spikes
    force[50_000] = -1.0
    idx = _thin(len(force), force)
    assert len(idx) <= MAX_PLOT_POINTS
    assert {12_345, 77_777, 50_000} <= set(idx.tolist())
    assert np.all(np.diff(idx) > 0)
    assert _thin(10, force[:10]).tolist() == list(range(10))
    assert idx[0] == 0 and idx[-1] == len(force) - 1              # the whole time span drawn


def test_a_pause_in_a_long_stream_still_breaks_the_line_after_thinning():
    from tissue_viz.report import _break_gaps, _thin

    t = np.arange(100_000) * 1e-3
    t[60_000:] += 0.3                                     # the stream paused for 0.3 s
    force = np.sin(t)
    out_t, out_f = _break_gaps(t, force, sel=_thin(len(t), force))
    (gap,) = np.flatnonzero(np.isnan(out_t))
    assert np.isnan(out_f[gap]) and out_t[gap - 1] < 60.0 < 60.3 <= out_t[gap + 1]
    # hiccups of a few periods stay joined
    hiccup = np.arange(1000) * 1e-3
    hiccup[500:] += 5e-3
    assert not np.isnan(_break_gaps(hiccup, np.sin(hiccup))[0]).any()


def test_csv_lines_written_during_the_run_are_the_ones_written_at_the_end(tmp_path):
    data = ReportData.from_stats(_press_run(seconds=9.0, rate=1000.0), 9.0)
    assert data.csv_heads['metrics'][0] == data.csv_heads['force'][0] == 8192    # 2 full blocks
    for name, columns in TABLES.items():
        write_csv(tmp_path / 'during.csv', columns, data.table(name), data.csv_heads.get(name))
        write_csv(tmp_path / 'end.csv', columns, data.table(name))
        assert (tmp_path / 'during.csv').read_bytes() == (tmp_path / 'end.csv').read_bytes(), name


def test_csv_marks_missing_values_as_empty_cells(tmp_path):
    from tissue_viz.report import write_csv

    write_csv(tmp_path / 'x.csv', ('t', 'v'), {'t': np.array([0.0, 0.5]), 'v': np.array([np.nan, 2.5])})
    assert (tmp_path / 'x.csv').read_text() == 't,v\n0,\n0.5,2.5\n'
    back = read_csv(tmp_path / 'x.csv')
    assert np.isnan(back['v'][0]) and back['v'][1] == 2.5


# -- bad values ---------------------------------------------------------------------------------
ALL_FILES = set(PNGS) | {f'{n}.csv' for n in TABLES} | {'summary.md', 'index.html', 'summary.json'}
HUGE_OR_NOT_FINITE = (math.nan, math.inf, -math.inf, 1e308, -1e308)
ABSURD = HUGE_OR_NOT_FINITE + (-1e-3,)    # a negative time, length or energy


def _assert_complete_with_drawn_plots(out) -> dict:
    """Every file is there, every PNG decodes and is drawn on; returns summary.json."""
    assert ALL_FILES <= {p.name for p in out.iterdir()}
    for png in PNGS:
        size, ink, _ = _ink(out / png)
        assert size == (800, 450) and ink > 0.02, (png, ink)
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['failed_files'] == {} and summary['plot_failures'] == {}
    return summary


def _normal_then_absurd_run() -> tuple[VizStats, dict]:
    """A normal press run with, in between, messages carrying each absurd value in each field.

    Returns the statistics and the number of bad values sent per quantity.
    """
    stats = _press_run(seconds=1.0)
    sent = dict.fromkeys(('step_wall_time', 'contact_force', 'max_displacement', 'penetration',
                          'kinetic_energy', 'active_particles', 'substeps', 'contact_index',
                          'pose_position', 'wrench_force'), 0)
    t, stamp = 1.0, 10_000
    huge = 4_294_967_295                                  # uint32 max
    for bad in ABSURD:
        good = dict(step_wall_time=1e-4, force=(0.0, 0.0, 1.0), max_displacement=0.002,
                    penetration=0.001, kinetic_energy=1e-4)
        for field, value in (('step_wall_time', bad), ('max_displacement', bad),
                             ('penetration', bad), ('kinetic_energy', bad)):
            t, stamp = t + 1e-3, stamp + 1
            assert not stats.on_metrics(t, stamp * MS, **dict(good, **{field: value}))
            sent[field] += 1
        if bad not in HUGE_OR_NOT_FINITE:
            continue                                      # negative forces and positions are fine
        t, stamp = t + 1e-3, stamp + 1
        assert not stats.on_metrics(t, stamp * MS, **dict(good, force=(0.0, bad, 1.0)))
        assert not stats.on_pose(t, stamp * MS, (0.0, 0.0, bad))
        assert stats.on_force(t, stamp * MS, (bad, 0.0, 0.0)) is None
        for key in ('contact_force', 'pose_position', 'wrench_force'):
            sent[key] += 1
    for field in ('n_interaction', 'n_relaxing', 'substeps'):
        t, stamp = t + 1e-3, stamp + 1
        assert not stats.on_metrics(t, stamp * MS, 1e-4, (0, 0, 1.0), 0.002, **{field: huge})
        sent['substeps' if field == 'substeps' else 'active_particles'] += 1
    t, stamp = t + 1e-3, stamp + 1
    assert not stats.on_metrics(t, stamp * MS, 1e-4, (0, 0, 1.0), 0.002, n_layer=[huge] * 3)
    assert not stats.on_metrics(t, (stamp + 1) * MS, 1e-4, (0, 0, 1.0), 0.002,
                                contact_index=-2_147_483_648)
    sent['active_particles'] += 1
    sent['contact_index'] += 1
    stats.sample_rates(t)
    return stats, sent


def test_report_of_a_run_with_absurd_values_is_complete_and_counts_them_in_the_summary(tmp_path):
    stats, sent = _normal_then_absurd_run()
    out = write_report(tmp_path / 'run', ReportData.from_stats(stats, 1.2))
    summary = _assert_complete_with_drawn_plots(out)
    assert {k: v for k, v in summary['bad_values'].items() if v} == sent
    assert summary['bad_messages'] == sum(sent.values())
    assert summary['steps'] == 500                       # only the normal messages
    assert summary['step_max_s'] == pytest.approx(2e-3)  # no absurd value in the statistics
    md = (out / 'summary.md').read_text()
    assert f'- step times: {len(ABSURD)} not finite or out of range' in md
    assert f'- tool positions: {len(HUGE_OR_NOT_FINITE)} not finite or out of range' in md
    assert '- active particle counts: 3 not finite or out of range' in md
    assert (f'| messages with NaN/inf or out-of-range values (ignored) | {sum(sent.values())} |'
            in md)
    assert 'nan' not in md.lower().replace('nan/inf', '')
    html = (out / 'index.html').read_text()
    assert 'step times: 6 not finite or out of range' in html


@pytest.mark.parametrize('bad', ABSURD + (0.0, 5e-324), ids=repr)
def test_report_tables_holding_a_bad_value_in_every_column_still_give_every_file(tmp_path, bad):
    """Tables as another tool or an edited CSV could hold them: each column of each table has
    normal values and ``bad`` (zero and the smallest float are odd but valid everywhere)."""
    n = 50
    normal = {'t': np.arange(n) * 1e-3, 'step_wall_time': np.full(n, 1e-4),
              'latency': np.full(n, 5e-4), 'px': np.zeros(n), 'py': np.zeros(n),
              'pz': -np.arange(n) * 1e-4, 'fx': np.zeros(n), 'fy': np.zeros(n),
              'fz': np.arange(n) * 0.04, 'penetration': np.arange(n) * 1e-4}
    tables = {}
    for name, columns in TABLES.items():
        tables[name] = {c: normal.get(c, np.full(n, 1.0)).copy() for c in columns}
        for c in columns:
            tables[name][c][7 + columns.index(c)] = bad
    valid = bad in (0.0, 5e-324)
    out = write_report(tmp_path / 'run', ReportData(tables=tables, rate_targets={
        'metrics': (900.0, 1100.0), 'particles': (25.0, 35.0)}))
    summary = _assert_complete_with_drawn_plots(out)
    md = (out / 'summary.md').read_text()
    if valid:
        assert summary['bad_values']['step_wall_time'] == 0 and '## Not shown' not in md
    else:
        bad_values = summary['bad_values']
        assert bad_values['step_wall_time'] == 1 and bad_values['latency'] == 1
        # one row per force column; a negative force component is fine
        assert bad_values['contact_force'] == (3 if bad in HUGE_OR_NOT_FINITE else 0)
        assert '- step times: 1 not finite or out of range' in md
        assert '- latencies: 1 not finite or out of range' in md


def test_one_huge_step_time_among_fast_ones_is_drawn_on_a_log_axis(tmp_path):
    stats = VizStats(window=1.0)
    for i in range(200):
        stats.on_metrics(i * 1e-3, i * MS, 0.0 if i % 10 == 0 else 1e-4, (0, 0, 0.5), 0.001)
    stats.on_metrics(0.2, 200 * MS, 3600.0, (0, 0, 0.5), 0.001)          # one hour: valid
    stats.on_metrics(0.201, 201 * MS, 5e-324, (0, 0, 0.5), 0.001)        # the smallest float
    out = write_report(tmp_path / 'run', ReportData.from_stats(stats, 0.3))
    summary = _assert_complete_with_drawn_plots(out)
    assert summary['steps'] == 202 and summary['step_max_s'] == 3600.0


def test_a_plot_that_fails_is_replaced_by_a_placeholder_named_in_the_summary(tmp_path,
                                                                             monkeypatch):
    import tissue_viz.report as report

    def broken(data, path):
        raise RuntimeError('cannot draw $this$')

    monkeypatch.setitem(report.PLOTTERS, 'rates.png', broken)
    out = write_report(tmp_path / 'run', ReportData.from_stats(_press_run(0.5), 0.5))
    size, ink, _ = _ink(out / 'rates.png')
    assert size == (800, 450) and ink > 0.005                 # the placeholder says why
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['plot_failures'] == {'rates.png': 'RuntimeError: cannot draw $this$'}
    assert summary['failed_files'] == {}
    assert ('- rates.png could not be drawn (RuntimeError: cannot draw $this$); it shows a '
            'placeholder') in (out / 'summary.md').read_text()
    for png in set(PNGS) - {'rates.png'}:
        assert _ink(out / png)[1] > 0.02, png


def test_without_a_working_matplotlib_every_plot_is_still_a_valid_png(tmp_path, monkeypatch):
    import tissue_viz.figures as figures

    def no_matplotlib():
        raise ImportError('matplotlib is broken')

    monkeypatch.setattr(figures, '_matplotlib', no_matplotlib)
    out = write_report(tmp_path / 'run', ReportData.from_stats(_press_run(0.5), 0.5))
    summary = json.loads((out / 'summary.json').read_text())
    assert set(summary['plot_failures']) == set(PNGS) and summary['failed_files'] == {}
    for png in PNGS:
        size, _, _ = _ink(out / png)                         # decodes as a PNG
        assert size == (800, 450)


def test_a_file_that_cannot_be_written_is_named_and_the_others_are_written(tmp_path,
                                                                           monkeypatch):
    import tissue_viz.report as report

    real = report.write_csv

    def full_disk(path, columns, table, head=None):
        if path.name == 'force.csv':
            raise OSError(28, 'No space left on device')
        real(path, columns, table, head)

    monkeypatch.setattr(report, 'write_csv', full_disk)
    with pytest.raises(ReportError, match=rf'1 of {len(ALL_FILES)} report files not written .*force\.csv '
                                          r'\(OSError: .*No space left on device\)'):
        write_report(tmp_path / 'run', ReportData.from_stats(_press_run(0.5), 0.5))
    written = {p.name for p in (tmp_path / 'run').iterdir()}
    assert written == ALL_FILES - {'force.csv'}
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    assert list(summary['failed_files']) == ['force.csv'] and 'force.csv' not in summary['files']


def test_a_report_folder_whose_file_names_are_taken_by_folders_is_refused_before_writing(tmp_path):
    from tissue_viz.report import prepare_report_dir

    (tmp_path / 'run' / 'summary.md').mkdir(parents=True)
    with pytest.raises(ReportError, match='summary.md: it exists and is not a file'):
        prepare_report_dir(tmp_path / 'run')
    with pytest.raises(ReportError, match='summary.md: it exists and is not a file'):
        write_report(tmp_path / 'run', ReportData())
    assert prepare_report_dir(tmp_path / 'new') == tmp_path / 'new'
    assert list((tmp_path / 'new').iterdir()) == []          # the check leaves nothing behind


def test_a_new_report_into_the_same_folder_removes_the_old_summary_json_first(tmp_path,
                                                                              monkeypatch):
    import tissue_viz.report as report

    out = write_report(tmp_path / 'run', ReportData())
    assert (out / 'summary.json').is_file()

    def fails(*_):
        raise OSError(5, 'Input/output error')

    monkeypatch.setattr(report, '_write_summary_json', fails)
    with pytest.raises(ReportError, match='summary.json'):
        write_report(out, ReportData())
    assert not (out / 'summary.json').exists()   # no stale file claims the report is finished


def test_tissue_report_rebuilds_a_report_from_csv_files_holding_inf_and_huge_values(tmp_path):
    (tmp_path / 'src').mkdir()
    (tmp_path / 'src' / 'metrics.csv').write_text(
        't,step_wall_time,fx,fy,fz,force,max_displacement\n'
        '0,1e-4,0,0,0.5,0.5,0.001\n0.001,inf,0,0,0.5,0.5,0.001\n0.002,1e308,0,-inf,0.5,inf,1e308\n'
        '0.003,-1,0,0,0.5,0.5,\n0.004,2e-4,0,0,0.6,0.6,0.002\n')
    (tmp_path / 'src' / 'summary.json').write_text('{"haptic_period_s": "soon"}')
    assert main([str(tmp_path / 'src'), '-o', str(tmp_path / 'out'), '--recompute-summary']) == 0
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['steps'] == 2 and summary['bad_values']['step_wall_time'] == 3
    assert summary['max_displacement_m'] == pytest.approx(0.002)
    assert ALL_FILES <= {p.name for p in (tmp_path / 'out').iterdir()}


# -- the organ in the report ------------------------------------------------------------------------
def test_the_tissue_images_show_the_pressed_cloud_coloured_and_the_animation_its_frames(report):
    out, _ = report
    for png in TISSUE_PNGS:
        size, ink, colours = _ink(out / png)
        assert size == (1200, 900) and 0.02 < ink < 0.8 and colours > 100, (png, ink, colours)
    # the deepest press carries more colour than the rest (all dots one colour at rest)
    assert _ink(out / 'tissue_deepest.png')[2] > _ink(out / 'tissue_rest.png')[2]
    with Image.open(out / 'tissue_press.gif') as gif:
        assert gif.format == 'GIF' and gif.n_frames == 25          # 12 before, the deepest, 12 after
    html = (out / 'index.html').read_text()
    assert 'src="tissue_press.gif"' in html and 'src="tissue_deepest.png"' in html


def test_snapshots_keep_rest_deepest_and_the_clouds_around_it():
    snaps = _press_clouds(40)
    assert snaps.rest.peak == 0.0 and snaps.deepest.stamp_ns == 19 * 33 * MS   # half-way
    assert snaps.deepest.peak == pytest.approx(0.004 * math.exp(-0.125) * math.sin(math.pi * 19 / 39))
    stamps = [s.stamp_ns for s in snaps.frames]
    deepest = stamps.index(snaps.deepest.stamp_ns)
    assert deepest == 12 and len(stamps) == 25 and np.all(np.diff(stamps) > 0)
    assert snaps.deepest.tools[0][3] == 0.005


def test_a_large_cloud_is_kept_as_a_fixed_subset():
    snaps = TissueSnapshots(max_points=1000)
    n = 100_000
    x = np.arange(n, dtype=float)
    for k in range(3):
        snaps.add({'x': x, 'y': x, 'z': x, 'displacement': x * k, 'von_mises': x}, k, ())
    assert len(snaps.rest.xyz) == 1000 and np.array_equal(snaps.rest.xyz[:, 0], snaps.deepest.xyz[:, 0])
    assert snaps.rest.xyz[0, 0] == 0.0 and snaps.rest.xyz[-1, 0] == n - 1


def test_tissue_report_draws_the_tissue_again_from_the_saved_snapshots(report, tmp_path):
    out, _ = report
    again = tmp_path / 'again'
    assert main([str(out), '-o', str(again)]) == 0
    assert _ink(again / 'tissue_deepest.png')[2] > 100
    with Image.open(again / 'tissue_press.gif') as gif:
        assert gif.n_frames == 25


def test_without_clouds_the_tissue_images_say_so_and_no_animation_is_written(tmp_path):
    empty = write_report(tmp_path / 'empty', ReportData())
    assert (empty / 'tissue_rest.png').is_file() and not (empty / 'tissue_press.gif').exists()
    assert 'tissue_press.gif' not in json.loads((empty / 'summary.json').read_text())['files']


def test_a_point_cloud_message_layout_is_read_by_its_fields():
    from tissue_viz.tissue_images import cloud_arrays

    dtype = np.dtype({'names': ['x', 'y', 'z', 'displacement', 'von_mises', 'region'],
                      'formats': ['<f4'] * 5 + ['u1'], 'offsets': [0, 4, 8, 12, 16, 20],
                      'itemsize': 24})
    rec = np.zeros(3, dtype)
    rec['x'], rec['displacement'], rec['von_mises'] = [1, 2, 3], [0.1, 0.2, 0.3], [5, 6, 7]
    fields = [('x', 0, 7), ('y', 4, 7), ('z', 8, 7), ('displacement', 12, 7), ('von_mises', 16, 7),
              ('region', 20, 2)]
    cols = cloud_arrays(fields, rec.tobytes(), 3, 24)
    assert cols['x'].tolist() == [1, 2, 3] and cols['von_mises'].tolist() == [5, 6, 7]
    assert cols['displacement'] == pytest.approx([0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match='x, y and z'):
        cloud_arrays(fields[3:], rec.tobytes(), 3, 24)
    with pytest.raises(ValueError, match='3 points need 72'):
        cloud_arrays(fields, rec.tobytes()[:50], 3, 24)


# -- drawn by two processes ------------------------------------------------------------------------
def test_forked_jobs_each_run_once_shared_between_the_processes():
    import os
    import time

    from tissue_viz import forked

    def job(k):
        def run():
            time.sleep(0.1)
            return {str(k): os.getpid()}
        return run

    # alone the caller would take 1.6 s: the child surely gets some, however busy the machine
    done = forked.run([job(k) for k in range(16)], processes=2)
    assert sorted(done, key=int) == [str(k) for k in range(16)]
    assert os.getpid() in done.values() and len(set(done.values())) == 2
    assert forked.run([job(k) for k in range(3)], processes=1) == {str(k): os.getpid()
                                                                    for k in range(3)}


def test_a_job_whose_process_dies_runs_again_in_the_caller():
    import os
    import time

    from tissue_viz import forked

    parent = os.getpid()

    def job(k):
        def run():
            time.sleep(0.05)
            if k == 5 and os.getpid() != parent:
                os._exit(3)                  # the child dies without a word
            return {str(k): os.getpid()}
        return run

    done = forked.run([job(k) for k in range(12)], processes=2)
    assert sorted(done, key=int) == [str(k) for k in range(12)]
    assert done['5'] == parent


def test_a_report_drawn_by_two_processes_is_the_one_drawn_by_one(tmp_path):
    data = ReportData.from_stats(_press_run(), 2.0, title='Press test', tissue=_press_clouds())
    one = write_report(tmp_path / 'one', data, processes=1)
    two = write_report(tmp_path / 'two', data, processes=2)
    summaries = [json.loads((out / 'summary.json').read_text()) for out in (one, two)]
    for summary in summaries:
        summary.pop('created')
    assert summaries[0] == summaries[1] and summaries[1]['plot_failures'] == {}
    md = [(out / 'summary.md').read_text().splitlines() for out in (one, two)]
    assert [line for line in md[0] if 'written' not in line] == \
        [line for line in md[1] if 'written' not in line]
    for name in summaries[1]['files']:
        if name.endswith(('.csv', '.npz')):
            assert (one / name).read_bytes() == (two / name).read_bytes(), name
        elif name.endswith('.png'):
            assert _ink(one / name) == _ink(two / name), name


def test_the_summary_table_gives_each_instruments_force_latency_and_e_in():
    stats = {name: VizStats(window=1.0) for name in ('left', 'right')}
    for k, s in enumerate(stats.values()):
        s.on_pose(0.0, MS, (0.0, 0.0, 0.0))
        s.on_force(1e-3 * (k + 1), MS, (0.0, 0.0, 1.0 + k))
        s.on_metrics(0.0, MS, 1e-4, (0.0, 0.0, 1.0 + k), 0.0, haptic_mode=HAPTIC_MULTIRATE,
                     energy_in=1e-6 * (1 - 2 * k), energy_in_min=1e-6 * (1 - 2 * k))
    data = ReportData.from_stats(stats['left'], 0.01, instruments=stats)
    rows = dict(summary_rows(data.summary))
    assert rows['left: max force'] == '1.000 N' and rows['right: max force'] == '2.000 N'
    assert rows['left: pose to force latency p50'] == '1.000 ms'
    assert rows['right: pose to force latency p99'] == '2.000 ms'
    assert rows['left: E_in min (below zero: not passive)'] == '1.000 uJ'
    assert rows['right: E_in min (below zero: not passive)'] == '-1.000 uJ'
    # one instrument: no rows of its own, as before there were several
    assert not any(label.startswith(('left:', 'right:')) for label in dict(summary_rows(
        ReportData.from_stats(stats['left'], 0.01).summary)))


def test_the_tissue_images_keep_both_tools_and_the_held_particles(tmp_path):
    snaps = TissueSnapshots()
    g = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(3), indexing='ij'), -1)
    xyz = g.reshape(-1, 3) * 0.005
    held = np.zeros(len(xyz))
    held[[3, 4]], held[[30]] = 1, 2                       # left holds 3 and 4, right 30
    tools = ((np.array([0.0, 0.0, 0.015]), np.array([0.0, 0.0, 1.0]), 0.02, 0.003),
             (np.array([0.02, 0.0, 0.015]), np.zeros(3), 0.0, 0.003))
    for k, depth in enumerate((0.0, 0.002)):
        disp = np.full(len(xyz), depth)
        snaps.add({'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2] - disp, 'displacement': disp,
                   'von_mises': 1e6 * disp, 'held': held}, k * MS, tools if k else (None, None))
    snaps.save(tmp_path / 'snaps.npz')
    back = TissueSnapshots.load(tmp_path / 'snaps.npz')
    assert back.rest.tools == (None, None)               # both lifted at rest
    assert [t[0][0] for t in back.deepest.tools] == [0.0, 0.02]
    assert np.flatnonzero(back.deepest.held).tolist() == [3, 4, 30] and back.deepest.held[30] == 2
    draw_snapshot(back.deepest, tmp_path / 'deepest.png', 'two tools', [back.rest, back.deepest],
                  back.rest)
    size, ink, colours = _ink(tmp_path / 'deepest.png')
    assert ink > 0.05 and colours > 50


def test_a_snapshot_file_from_before_several_instruments_loads_its_one_tool(tmp_path):
    np.savez(tmp_path / 'old.npz', rest_xyz=np.zeros((2, 3)), rest_disp=np.zeros(2), rest_vm=np.zeros(2),
             rest_stamp=np.array(0), rest_tool=np.r_[1.0, 2.0, 3.0, 0.0, 0.0, 1.0, 0.0, 0.004])
    rest = TissueSnapshots.load(tmp_path / 'old.npz').rest
    assert len(rest.tools) == 1 and rest.tools[0][3] == 0.004 and rest.held is None


def test_a_cut_cloud_draws_its_faces_and_leaves_its_removed_particles_out(tmp_path):
    """A block cut through its middle: the particles beside the cut marked (black crosses: more
    dark ink than the whole cloud), a removed particle (NaN) neither drawn nor stretching the axes;
    the severed byte is saved and loaded with the snapshots."""
    snaps = _press_clouds(3)
    whole = snaps.deepest
    severed = (np.abs(whole.xyz[:, 0]) < 0.003).astype(np.uint8) * 2
    xyz = whole.xyz.copy()
    xyz[0] = np.nan
    cut = TissueSnapshots()
    columns = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2], 'displacement': whole.displacement,
               'von_mises': whole.von_mises, 'severed': severed}
    cut.add(columns, 0, whole.tools)
    assert cut.deepest.severed is not None and np.array_equal(cut.deepest.severed, severed)
    draw_snapshot(cut.deepest, tmp_path / 'cut.png', 'cut', reference=snaps.rest)
    draw_snapshot(whole, tmp_path / 'whole.png', 'whole', reference=snaps.rest)

    def dark(path):
        with Image.open(path) as im:
            return int(np.count_nonzero(np.asarray(im.convert('L')) < 40))
    assert dark(tmp_path / 'cut.png') > dark(tmp_path / 'whole.png')
    cut.save(tmp_path / 'snaps.npz')
    assert np.array_equal(TissueSnapshots.load(tmp_path / 'snaps.npz').deepest.severed, severed)
