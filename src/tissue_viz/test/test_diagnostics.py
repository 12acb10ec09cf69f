"""Diagnostic levels against targets, as diagnostic_updater's FrequencyStatus would give them."""

from __future__ import annotations

import math

import pytest

from tissue_viz.diagnostics import (ERROR, OK, STALE, WARN, RateTarget, Targets, evaluate,
                                    evaluate_instruments, haptic_status, input_status, latency_status, rate_status,
                                    step_status, tissue_status, worst_level)
from tissue_viz.errors import VizConfigError
from tissue_viz.stats import HAPTIC_MULTIRATE, Snapshot, VizStats

MS = 1_000_000


def _snap(rate: float | None, age: float | None, count: int = 100) -> Snapshot:
    snap = Snapshot(now=10.0, window=1.0)
    snap.rates['metrics'] = rate or 0.0
    snap.ages['metrics'] = age
    snap.counts['metrics'] = count if age is not None else 0
    return snap


@pytest.mark.parametrize('rate, age, level, text', [
    (None, None, ERROR, 'no data'),                     # never arrived
    (1000.0, 0.001, OK, 'rate ok'),
    (815.0, 0.001, OK, 'rate ok'),                      # 900 * (1 - 0.1) = 810 is the edge
    (805.0, 0.001, WARN, 'rate too low'),
    (1215.0, 0.001, WARN, 'rate too high'),             # 1100 * 1.1 = 1210
    (1000.0, 2.5, ERROR, 'no data for 2.5 s'),          # silent longer than stale_timeout
])
def test_rate_status_levels_follow_frequency_status_semantics(rate, age, level, text):
    status = rate_status('metrics', _snap(rate, age), Targets())
    assert status.level == level and status.message.startswith(text), status
    assert status.name == 'viz_node: tissue/metrics rate'
    assert dict(status.values)['min rate [Hz]'] == '900.0'


def test_a_topic_that_is_not_required_is_ok_without_data():
    targets = Targets()
    targets.rates['metrics'] = RateTarget(900.0, 1100.0, required=False)
    assert rate_status('metrics', _snap(None, None), targets).level == OK
    assert rate_status('metrics', _snap(1000.0, 30.0), targets).level == OK


def test_step_status_warns_and_errors_on_p99_and_deadline_misses():
    targets = Targets()
    snap = Snapshot(now=0.0, window=1.0)
    assert step_status(snap, targets).level == STALE
    snap.step_p50, snap.step_p99, snap.step_max, snap.deadline_miss_pct = 1e-4, 5e-4, 6e-4, 0.0
    assert step_status(snap, targets).level == OK
    snap.step_p99 = 0.9e-3                               # above 0.8 ms warn, below 1 ms error
    assert step_status(snap, targets).level == WARN
    snap.step_p99, snap.deadline_miss_pct = 5e-4, 6.0   # 6 % misses > 5 % error
    status = step_status(snap, targets)
    assert status.level == ERROR and 'too slow' in status.message


def test_latency_status_uses_design_targets_and_reply_loss():
    targets = Targets()
    snap = Snapshot(now=0.0, window=1.0)
    assert latency_status(snap, targets).level == STALE
    snap.latency_p50, snap.latency_p99, snap.latency_max = 0.5e-3, 2e-3, 3e-3
    snap.replies_missed_pct = 0.5
    assert latency_status(snap, targets).level == OK
    snap.latency_p50 = 1.5e-3                            # median above 1 ms
    assert latency_status(snap, targets).level == WARN
    snap.latency_p50, snap.replies_missed_pct = 0.5e-3, 20.0
    assert latency_status(snap, targets).level == ERROR


def test_tissue_status_warns_when_the_force_reaches_the_device_limit():
    stats = VizStats(window=1.0)
    assert tissue_status(stats.snapshot(0.0), Targets()).level == STALE
    stats.on_metrics(0.0, 0, 1e-4, (0.0, 0.0, 1.0), 0.002, n_interaction=50)
    status = tissue_status(stats.snapshot(0.01), Targets())
    assert status.level == OK and 'active 50' in status.message and 'disp 2.0 mm' in status.message
    stats.on_force(0.02, MS, (0.0, 0.0, 3.3))
    assert tissue_status(stats.snapshot(0.03), Targets()).level == WARN


def _multirate(stats: VizStats, now: float, energy_in: float, model_age: float = 2.5e-3,
               substeps: int = 0) -> None:
    stats.on_metrics(now, int(now * 1e9), 1e-4, (0.0, 0.0, 1.0), 0.002, substeps=substeps,
                     haptic_mode=HAPTIC_MULTIRATE, solver_rate=400.0, model_age=model_age,
                     coupling_stretch=1e-4, energy_in=energy_in,
                     energy_in_min=min(energy_in, 0.0), added_damping=0.75)


def test_haptic_status_is_ok_while_e_in_stays_above_the_target_and_carries_the_rendering_values():
    stats = VizStats(window=1.0)
    _multirate(stats, 0.0, 5e-6)
    _multirate(stats, 0.1, -0.5e-6)               # round-off above the -1 uJ target
    status = haptic_status(stats.snapshot(0.2), Targets())
    assert status.level == OK and status.name == 'viz_node: haptic rendering'
    assert 'E_in -0.500 uJ' in status.message and 'solver 400 Hz' in status.message
    values = dict(status.values)
    assert values['solver rate [Hz]'] == '400.0' and values['model age [ms]'] == '2.500'
    assert values['coupling stretch [mm]'] == '0.100' and values['E_in [uJ]'] == '-0.500'
    assert values['added damping [N s/m]'] == '0.750'
    assert values['E_in warn below [uJ]'] == '-1.000'


def test_haptic_status_warns_when_e_in_goes_below_the_target_until_the_dip_leaves_the_window():
    stats = VizStats(window=1.0)
    _multirate(stats, 0.0, 5e-6)
    _multirate(stats, 0.1, -2e-6)                 # the rendering gave 2 uJ back
    _multirate(stats, 0.2, 1e-6)                  # the hand pushes again: E_in above zero
    status = haptic_status(stats.snapshot(0.3), Targets())
    assert status.level == WARN and status.message.startswith('gave energy back')
    assert dict(status.values)['lowest E_in in window [uJ]'] == '-2.000'
    # A looser target accepts the dip; once it is out of the window the default one does too.
    assert haptic_status(stats.snapshot(0.3), Targets(energy_in_min=-1e-5)).level == OK
    _multirate(stats, 1.5, 1e-6)
    assert haptic_status(stats.snapshot(1.6), Targets()).level == OK


def test_haptic_status_warns_when_the_contact_model_is_older_than_the_limit():
    stats = VizStats(window=1.0)
    _multirate(stats, 0.0, 5e-6, model_age=0.019)
    assert haptic_status(stats.snapshot(0.1), Targets()).level == OK
    _multirate(stats, 0.2, 5e-6, model_age=0.029)           # the solver fell behind the hand
    status = haptic_status(stats.snapshot(0.3), Targets())
    assert status.level == WARN and status.message.startswith('contact model 29.000 ms old')
    assert dict(status.values)['model age warn [ms]'] == '20.000'
    assert haptic_status(stats.snapshot(0.3), Targets(model_age_warn=0.05)).level == OK


def test_step_status_carries_the_sub_steps_per_step():
    stats = VizStats(window=1.0)
    for k, n in enumerate((2, 8, 8, 31)):
        _multirate(stats, 0.01 * k, 5e-6, substeps=n)
    values = dict(step_status(stats.snapshot(0.1), Targets()).values)
    assert values['sub-steps per step p50'] == '8.0' and values['sub-steps per step max'] == '31'


def test_haptic_status_says_direct_mode_or_no_metrics_at_ok_level():
    stats = VizStats(window=1.0)
    status = haptic_status(stats.snapshot(0.0), Targets())
    assert status.level == OK and status.message == 'no metrics yet'
    stats.on_metrics(0.0, 0, 1e-4, (0.0, 0.0, 1.0), 0.002)        # direct: haptic fields zero
    status = haptic_status(stats.snapshot(0.01), Targets())
    assert status.level == OK and status.message.startswith('direct')
    assert dict(status.values)['E_in [uJ]'] == 'n/a'


def test_input_status_names_nan_and_backwards_stamps():
    stats = VizStats(window=1.0)
    assert input_status(stats.snapshot(0.0)).level == OK
    stats.on_metrics(0.0, 2 * MS, math.nan, (0, 0, 0), 0.0)
    stats.on_metrics(0.001, 1 * MS, 1e-4, (0, 0, 0), 0.0)
    status = input_status(stats.snapshot(0.01))
    assert status.level == WARN
    assert '1 messages with NaN/inf' in status.message and '1 stamps went backwards' in status.message


def test_evaluate_reports_every_topic_and_the_worst_level():
    stats = VizStats(window=1.0)
    statuses = evaluate(stats.snapshot(0.0), Targets())
    assert [s.name.split(': ', 1)[1] for s in statuses] == [
        'tissue/metrics rate', 'tissue/particles rate', 'omni/pose rate',
        'omni/force_feedback rate', 'step time', 'pose to force latency', 'tissue',
        'haptic rendering', 'input']
    assert worst_level(statuses) == STALE
    assert worst_level([]) == OK


@pytest.mark.parametrize('change, message', [
    ({'rate_tolerance': 1.5}, 'rate_tolerance'),
    ({'stale_timeout': 0.0}, 'stale_timeout'),
    ({'step_p99_warn': 2e-3, 'step_p99_error': 1e-3}, 'step_p99_warn <= step_p99_error'),
    ({'force_limit': -1.0}, 'force_limit'),
    ({'energy_in_min': 1e-6}, 'energy_in_min'),
])
def test_inconsistent_targets_are_rejected_with_the_parameter_named(change, message):
    targets = Targets(**change)
    with pytest.raises(VizConfigError, match=message):
        targets.validate()


def test_rate_targets_need_min_below_max():
    targets = Targets()
    targets.rates['pose'] = RateTarget(500.0, 100.0)
    with pytest.raises(VizConfigError, match='min_rate <= max_rate'):
        targets.validate()


def test_statuses_without_data_are_ok_when_their_topics_are_not_required():
    targets = Targets()
    for topic in ('pose', 'force'):
        targets.rates[topic] = RateTarget(900.0, 1100.0, required=False)
    snap = VizStats(window=1.0).snapshot(0.0)
    assert latency_status(snap, targets).level == OK
    assert step_status(snap, targets).level == STALE        # metrics still required
    assert tissue_status(snap, targets).level == STALE
    targets.rates['metrics'] = RateTarget(900.0, 1100.0, required=False)
    assert step_status(snap, targets).level == OK and tissue_status(snap, targets).level == OK


def _all_values(statuses) -> list[str]:
    return [v for s in statuses for _, v in s.values] + [s.message for s in statuses]


def test_diagnostics_say_n_a_rather_than_nan_where_there_is_no_number():
    statuses = evaluate(VizStats(window=1.0).snapshot(0.0), Targets())
    values = _all_values(statuses)
    assert not [v for v in values if 'nan' in v.lower().replace('nan/inf', '')], values
    step = next(s for s in statuses if s.name.endswith('step time'))
    assert dict(step.values)['p99 [ms]'] == 'n/a'


def test_absurd_input_is_counted_per_kind_in_the_input_status_and_kept_out_of_the_others():
    stats = VizStats(window=1.0)
    for i in range(20):
        stats.on_metrics(i * 1e-3, i * MS, 1e-4, (0, 0, 0.5), 0.001)
    for i, bad in enumerate((math.nan, math.inf, 1e308, -1.0)):
        stats.on_metrics(0.02 + i * 1e-3, (20 + i) * MS, bad, (0, 0, 0.5), 0.001)
    stats.on_metrics(0.03, 30 * MS, 1e-4, (0, 0, 0.5), 0.001, n_interaction=4_294_967_295)
    stats.on_pose(0.031, 31 * MS, (math.inf, 0.0, 0.0))
    statuses = evaluate(stats.snapshot(0.04), Targets())
    assert not [v for v in _all_values(statuses) if 'nan' in v.lower().replace('nan/inf', '')]
    status = next(s for s in statuses if s.name.endswith('input'))
    values = dict(status.values)
    assert status.level == WARN
    assert '6 messages with NaN/inf or out-of-range values ignored' in status.message
    assert values['bad messages total'] == '6' and values['bad step times total'] == '4'
    assert values['bad active particle counts total'] == '1'
    assert values['bad tool positions total'] == '1'
    step = next(s for s in statuses if s.name.endswith('step time'))
    assert step.level == OK and dict(step.values)['max [ms]'] == '0.100'


def test_a_snapshot_with_absurd_numbers_gives_short_readable_values():
    snap = Snapshot(now=1.0, window=1.0, step_p50=1e308, step_p99=math.inf, step_max=1e308,
                    deadline_misses=3, deadline_miss_pct=100.0, latency_p50=1e300,
                    latency_p99=1e300, latency_max=math.nan, replies_missed_pct=math.nan,
                    active=4e18, n_interaction=-1e300, force=1e308, force_max=1e308,
                    displacement=-math.inf, haptic_mode=HAPTIC_MULTIRATE, solver_rate=1e308,
                    model_age=math.inf, coupling_stretch=1e308, energy_in=-1e308,
                    energy_in_min=math.nan, energy_in_low=-1e308, added_damping=1e308)
    snap.rates = {t: 1e308 for t in ('metrics', 'particles', 'pose', 'force')}
    snap.ages = {t: 0.0 for t in snap.rates}
    snap.counts = {t: 10 for t in snap.rates}
    statuses = evaluate(snap, Targets())
    values = _all_values(statuses)
    assert all(len(v) < 120 for v in values), max(values, key=len)
    assert not [v for v in values if 'nan' in v.lower().replace('nan/inf', '')]


def _instrument_snap(force: float, latency: float, energy_low: float) -> Snapshot:
    snap = Snapshot(now=10.0, window=1.0, haptic_mode=HAPTIC_MULTIRATE, energy_in=energy_low,
                    energy_in_low=energy_low, energy_in_min=energy_low, solver_rate=400.0, model_age=0.002)
    snap.active, snap.force, snap.force_max, snap.displacement = 100.0, force, force, 0.001
    snap.latency_p50 = snap.latency_p99 = snap.latency_max = latency
    snap.replies_missed_pct = 0.0
    for topic in ('metrics', 'particles', 'pose', 'force'):
        snap.rates[topic], snap.ages[topic], snap.counts[topic] = 1000.0, 0.001, 5000
    return snap


def test_one_unnamed_instrument_keeps_the_single_instrument_statuses():
    snap = _instrument_snap(1.0, 0.0005, 0.0)
    assert evaluate_instruments({'': snap}, Targets()) == evaluate(snap, Targets())


def test_several_instruments_get_their_own_rates_force_latency_and_e_in_statuses():
    snaps = {'left': _instrument_snap(0.5, 0.0005, 0.0), 'right': _instrument_snap(3.3, 0.02, -1e-5)}
    statuses = {s.name: s for s in evaluate_instruments(snaps, Targets(), prefix='viz_node')}
    # the cloud and the step time are the tissue's: once; the rest per instrument
    assert [n for n in statuses if 'particles' in n or 'step time' in n] == \
        ['viz_node: tissue/particles rate', 'viz_node: step time']
    for name in snaps:
        assert {f'viz_node: {name}/tissue/metrics rate', f'viz_node: {name}/omni/pose rate',
                f'viz_node: {name}/omni/force_feedback rate'} <= set(statuses)
    assert 'viz_node: tissue' not in statuses and 'viz_node: pose to force latency' not in statuses
    left, right = (statuses[f'viz_node: {k} ({n})'] for k in ('tissue',) for n in ('left', 'right'))
    assert left.level == OK and dict(left.values)['force [N]'] == '0.500'
    assert right.level == WARN and 'device limit' in right.message          # at 3.3 N
    assert statuses['viz_node: pose to force latency (left)'].level == OK
    assert statuses['viz_node: pose to force latency (right)'].level == ERROR   # p99 20 ms > 10 ms
    assert statuses['viz_node: haptic rendering (left)'].level == OK
    right_haptic = statuses['viz_node: haptic rendering (right)']
    assert right_haptic.level == WARN and dict(right_haptic.values)['lowest E_in in window [uJ]'] == '-10.000'
    assert statuses['viz_node: input (left)'].level == OK
