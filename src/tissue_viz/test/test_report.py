"""The report folder: files, CSV series, summaries, and PNGs that are real, non-blank plots."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from tissue_viz.errors import ReportError
from tissue_viz.report import (PLOTS, TABLES, ReportData, load_report_data, main, read_csv,
                               write_report)
from tissue_viz.stats import VizStats

MS = 1_000_000
PNGS = [png for png, _ in PLOTS]


def _press_run(seconds: float = 2.0, rate: float = 500.0) -> VizStats:
    """A press into 400 N/m tissue and back, poses/forces/metrics at ``rate``, 1 in 50 steps slow."""
    stats = VizStats(window=0.5, haptic_rate=1000.0)
    n = int(seconds * rate)
    for i in range(n):
        t = i / rate
        z = 0.002 - 0.006 * math.sin(math.pi * t / seconds) ** 2
        f = 400.0 * max(0.0, -z)
        step = 2e-3 if i % 50 == 0 else 1e-4 + 1e-4 * (i % 7) / 7
        stats.on_pose(t, i * MS, (0.0, 0.0, z))
        stats.on_metrics(t + step, i * MS, step, (0.0, 0.0, f), 0.5 * max(0.0, -z),
                         n_interaction=80 if f else 0, n_layer=[30, 10] if f else [])
        stats.on_force(t + 3e-4, i * MS, (0.0, 0.0, f))
        if i % 50 == 0:
            stats.sample_rates(t)
    return stats


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
    write_report(out, ReportData.from_stats(stats, 2.0, title='Press test', rate_targets=targets))
    return out, stats


def test_report_folder_holds_plots_series_and_summaries(report):
    out, _ = report
    expected = set(PNGS) | {f'{n}.csv' for n in TABLES} | {'summary.md', 'index.html',
                                                            'summary.json'}
    assert expected <= {p.name for p in out.iterdir()}
    summary = json.loads((out / 'summary.json').read_text())
    assert set(summary['files']) == expected - {'summary.json'}
    md = (out / 'summary.md').read_text()
    assert md.startswith('# Press test') and all(f'({png})' in md for png in PNGS)
    html = (out / 'index.html').read_text()
    assert all(f'src="{png}"' in html for png in PNGS) and '<table>' in html


def test_report_pngs_are_non_blank_plots_with_colour(report):
    out, _ = report
    for png in PNGS:
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


def test_csv_marks_missing_values_as_empty_cells(tmp_path):
    from tissue_viz.report import write_csv

    write_csv(tmp_path / 'x.csv', ('t', 'v'), {'t': np.array([0.0, 0.5]), 'v': np.array([np.nan, 2.5])})
    assert (tmp_path / 'x.csv').read_text() == 't,v\n0,\n0.5,2.5\n'
    back = read_csv(tmp_path / 'x.csv')
    assert np.isnan(back['v'][0]) and back['v'][1] == 2.5
