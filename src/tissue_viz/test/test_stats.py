"""Rolling statistics against series whose answers are computed by hand (no rclpy)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tissue_viz.errors import VizConfigError
from tissue_viz.markers import ToolShape, force_arrow
from tissue_viz.stats import (HAPTIC_MULTIRATE, INSTRUMENT_SUMMARY_KEYS, LIMITS, DecimatingRecorder,
                              LatencyMatcher, Limit,
                              RateMeter, StampOrder, VizStats, percentile, press_displacement,
                              summary_line)

MS = 1_000_000  # ns per ms


def test_percentile_interpolates_linearly_and_is_nan_when_empty():
    values = [float(v) for v in range(1, 11)]   # 1..10
    assert percentile(values, 50) == pytest.approx(5.5)
    # rank 0.99 * 9 = 8.91 -> 9 + 0.91 * (10 - 9)
    assert percentile(values, 99) == pytest.approx(9.91)
    assert math.isnan(percentile([], 50))


def test_rate_meter_reports_100_hz_then_falls_when_the_stream_stops():
    meter = RateMeter(window=1.0)
    for i in range(100):                      # 100 Hz for one second: t = 0.00 .. 0.99
        meter.tick(i / 100)
    # Start-up (seen for less than a window): (n - 1) / span over t = 0 .. 0.99.
    assert meter.rate(0.99) == pytest.approx(99 / 0.99)
    # A whole window seen: messages in (0.0, 1.0] = 99 of them.
    assert meter.rate(1.0) == pytest.approx(99.0)
    # Stopped: only t = 0.51 .. 0.99 are inside (0.5, 1.5].
    assert meter.rate(1.5) == pytest.approx(49.0)
    assert meter.rate(2.0) == 0.0
    assert meter.age(2.0) == pytest.approx(1.01)
    assert meter.mean_rate() == pytest.approx(100.0)
    assert RateMeter(1.0).age(5.0) is None


def test_rate_meter_rejects_a_non_positive_window():
    with pytest.raises(VizConfigError, match='window'):
        RateMeter(0.0)


def test_step_time_percentiles_and_deadline_misses_against_the_haptic_period():
    stats = VizStats(window=10.0, haptic_rate=1000.0)
    steps_ms = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 2.0, 3.0]
    for i, ms in enumerate(steps_ms):
        assert stats.on_metrics(i * 1e-3, i * MS, ms * 1e-3, (0.0, 0.0, 0.0), 0.0)
    snap = stats.snapshot(0.02)
    assert snap.step_p50 == pytest.approx(0.65e-3)       # (0.6 + 0.7) / 2
    assert snap.step_max == pytest.approx(3.0e-3)
    # exactly one period (1.0 ms) is on time; 2 and 3 ms miss
    assert snap.deadline_misses == 2
    assert snap.deadline_miss_pct == pytest.approx(100 * 2 / 12)
    # p99: rank 0.99 * 11 = 10.89 between 2.0 and 3.0 ms
    assert snap.step_p99 == pytest.approx(2.89e-3)


def test_step_statistics_forget_steps_older_than_the_window():
    stats = VizStats(window=1.0)
    stats.on_metrics(0.0, 0, 5e-3, (0, 0, 0), 0.0)      # slow, but long ago
    stats.on_metrics(1.5, MS, 1e-4, (0, 0, 0), 0.0)
    snap = stats.snapshot(1.6)
    assert snap.step_max == pytest.approx(1e-4) and snap.deadline_misses == 0
    assert stats.summary(1.6)['deadline_misses'] == 1   # the whole-run count keeps it


def test_latency_is_matched_by_stamp_and_unanswered_poses_count_as_missed():
    stats = VizStats(window=10.0, latency_timeout=0.1)
    for k in range(5):                                   # poses with stamps 1..5 ms, 1 ms apart
        stats.on_pose(k * 1e-3, (k + 1) * MS, (0.0, 0.0, 0.0))
    stats.on_force(0.0005, 1 * MS, (0, 0, 1.0))          # 0.5 ms after pose 1
    stats.on_force(0.0030, 2 * MS, (0, 0, 1.0))          # 2.0 ms after pose 2
    stats.on_force(0.0042, 4 * MS, (0, 0, 1.0))          # 1.2 ms after pose 4
    stats.on_force(0.0050, 99 * MS, (0, 0, 1.0))         # no such pose
    snap = stats.snapshot(0.5)                           # poses 3 and 5 have timed out
    assert snap.latency_p50 == pytest.approx(1.2e-3)
    assert snap.latency_max == pytest.approx(2.0e-3)
    assert snap.replies_missed_pct == pytest.approx(100 * 2 / 5)
    assert stats.matcher.unmatched_forces == 1 and stats.matcher.pending == 0


def test_reply_loss_in_the_diagnostics_covers_the_window_only():
    stats = VizStats(window=1.0, latency_timeout=0.1)
    for k in range(4):                                   # 4 poses at t = 0, none answered
        stats.on_pose(0.0, (k + 1) * MS, (0, 0, 0))
    assert stats.snapshot(0.5).replies_missed_pct == pytest.approx(100.0)
    for k in range(10):                                  # later, 10 poses all answered
        stats.on_pose(2.0 + k * 0.01, (10 + k) * MS, (0, 0, 0))
        stats.on_force(2.0 + k * 0.01 + 0.001, (10 + k) * MS, (0, 0, 1.0))
    assert stats.snapshot(2.2).replies_missed_pct == 0.0
    assert stats.summary(2.2)['replies_missed_pct'] == pytest.approx(100 * 4 / 14)


def test_latency_matcher_keeps_the_first_of_repeated_stamps_and_bounds_its_memory():
    matcher = LatencyMatcher(timeout=1.0, max_pending=3)
    matcher.on_pose(1, 0.0, (0, 0, 0))
    matcher.on_pose(1, 0.5, (0, 0, 0))                   # repeated stamp: first arrival counts
    assert matcher.on_force(1, 0.75)[0] == pytest.approx(0.75)
    for stamp in range(10, 15):                          # 5 pending, only 3 kept
        matcher.on_pose(stamp, 1.0, (0, 0, 0))
    assert matcher.pending == 3 and matcher.missed == 2
    with pytest.raises(VizConfigError):
        LatencyMatcher(timeout=0.0)


def test_nan_metrics_are_counted_and_left_out_of_the_statistics():
    stats = VizStats(window=5.0)
    assert stats.on_metrics(0.0, 0, 1e-4, (0, 0, 0.5), 0.001)
    assert not stats.on_metrics(0.001, MS, math.nan, (0, 0, 0.5), 0.001)
    assert not stats.on_metrics(0.002, 2 * MS, 1e-4, (0, math.inf, 0.5), 0.001)
    assert not stats.on_pose(0.003, 3 * MS, (math.nan, 0, 0))
    snap = stats.snapshot(0.01)
    assert snap.bad_in_window == 3 and snap.bad_total == 3
    assert snap.step_max == pytest.approx(1e-4)
    assert snap.counts['metrics'] == 3                   # received, even if rejected
    assert stats.steps_total == 1 and len(stats.metrics_table) == 1
    assert stats.last_pose is None
    assert stats.snapshot(10.0).bad_in_window == 0       # out of the window again
    assert stats.summary(10.0)['bad_messages'] == 3


ABSURD = (math.nan, math.inf, -math.inf, 1e308, -1e308, -1.0)


@pytest.mark.parametrize('field, value, key', [
    *[('step_wall_time', v, 'step_wall_time') for v in ABSURD],
    *[('max_displacement', v, 'max_displacement') for v in ABSURD],
    *[('penetration', v, 'penetration') for v in ABSURD],
    *[('kinetic_energy', v, 'kinetic_energy') for v in ABSURD],
    ('force', (1e308, 0.0, 0.0), 'contact_force'),
    ('force', (0.0, -math.inf, 0.0), 'contact_force'),
    ('n_interaction', 4_294_967_295, 'active_particles'),
    ('n_layer', [4_294_967_295] * 2, 'active_particles'),
    ('n_relaxing', 10 ** 400, 'active_particles'),          # beyond any float: still just bad
    ('substeps', 4_294_967_295, 'substeps'), ('contact_index', -2_147_483_648, 'contact_index'),
], ids=lambda x: repr(x)[:12])
def test_an_absurd_value_in_any_metrics_field_is_counted_and_its_message_left_out(field, value,
                                                                                  key):
    stats = VizStats(window=5.0)
    for i in range(10):
        assert stats.on_metrics(i * 1e-3, i * MS, 1e-4 * (1 + i % 2), (0, 0, 0.5), 0.001,
                                n_interaction=100, n_layer=[20, 10])
    normal = dict(step_wall_time=1e-4, force=(0, 0, 0.5), max_displacement=0.001)
    assert not stats.on_metrics(0.02, 20 * MS, **dict(normal, **{field: value}))
    snap = stats.snapshot(0.03)
    assert snap.bad_in_window == 1 and snap.bad_values[key] == 1
    assert sum(snap.bad_values.values()) == 1
    # The statistics are those of the ten normal messages.
    assert snap.step_max == pytest.approx(2e-4) and snap.active == 130
    assert snap.force == pytest.approx(0.5) and snap.displacement == pytest.approx(0.001)
    summary = stats.summary(0.03)
    assert summary['steps'] == 10 and summary['step_max_s'] == pytest.approx(2e-4)
    assert summary['max_active_particles'] == 130 and summary['bad_values'][key] == 1
    assert len(stats.metrics_table) == 10


@pytest.mark.parametrize('value', ABSURD[:-1])
def test_absurd_poses_and_forces_are_counted_and_do_not_move_the_tool(value):
    stats = VizStats(window=5.0)
    stats.on_pose(0.0, MS, (0.01, 0.02, 0.03))
    stats.on_force(0.001, MS, (0.0, 0.0, 1.0))
    assert not stats.on_pose(0.002, 2 * MS, (0.0, value, 0.0))
    assert stats.on_force(0.003, 2 * MS, (value, 0.0, 0.0)) is None
    assert stats.last_pose == (0.01, 0.02, 0.03) and stats.last_force_vec == (0.0, 0.0, 1.0)
    snap = stats.snapshot(0.004)
    assert snap.bad_values['pose_position'] == 1 and snap.bad_values['wrench_force'] == 1
    assert snap.force_max == pytest.approx(1.0) and snap.latency_max == pytest.approx(0.001)


# A multirate rendering mid-press: values as the simulator's haptic renderer reports them.
HAPTIC = dict(haptic_mode=HAPTIC_MULTIRATE, solver_rate=400.0, model_age=2.5e-3,
              coupling_stretch=1e-4, energy_in=3e-6, energy_in_min=-2e-7, added_damping=0.5)


def test_the_multirate_constant_is_the_one_of_the_message():
    from tissue_msgs.msg import SimMetrics

    assert HAPTIC_MULTIRATE == SimMetrics.HAPTIC_MULTIRATE != SimMetrics.HAPTIC_DIRECT


def test_multirate_haptic_values_are_recorded_in_the_table_the_snapshot_and_the_summary():
    stats = VizStats(window=1.0)
    assert stats.on_metrics(0.0, 0, 1e-4, (0, 0, 0.5), 0.001,
                            **dict(HAPTIC, energy_in=-4e-7, added_damping=2.0, solver_rate=300.0))
    assert stats.on_metrics(0.5, 500 * MS, 1e-4, (0, 0, 0.5), 0.001, **HAPTIC)
    table = stats.metrics_table.as_dict()
    assert {c: table[c][-1] for c in HAPTIC} == pytest.approx(HAPTIC)
    snap = stats.snapshot(0.6)
    assert snap.haptic_mode == HAPTIC_MULTIRATE
    assert (snap.solver_rate, snap.model_age, snap.coupling_stretch, snap.added_damping) == \
        pytest.approx((400.0, 2.5e-3, 1e-4, 0.5))
    assert snap.energy_in == pytest.approx(3e-6) and snap.energy_in_min == pytest.approx(-2e-7)
    assert snap.energy_in_low == pytest.approx(-4e-7)           # the dip at t = 0, in the window
    assert stats.snapshot(1.2).energy_in_low == pytest.approx(3e-6)   # the dip left the window
    summary = stats.summary(1.2)
    assert summary['energy_in_min_j'] == pytest.approx(-4e-7)
    assert summary['energy_in_final_j'] == pytest.approx(3e-6)
    assert summary['max_added_damping_n_s_per_m'] == pytest.approx(2.0)
    assert summary['solver_rate_p50_hz'] == pytest.approx(350.0)


def test_direct_mode_zeros_are_recorded_but_are_no_haptic_measurements():
    stats = VizStats(window=1.0)
    assert stats.on_metrics(0.0, 0, 1e-4, (0, 0, 0.5), 0.001, **HAPTIC)
    assert stats.on_metrics(0.001, MS, 1e-4, (0, 0, 0.5), 0.001)      # direct: all zero
    assert stats.metrics_table.as_dict()['haptic_mode'].tolist() == [HAPTIC_MULTIRATE, 0.0]
    snap = stats.snapshot(0.002)
    assert snap.haptic_mode == 0
    assert math.isnan(snap.energy_in) and math.isnan(snap.solver_rate)
    assert 'energy_in_min_j' not in VizStats().summary(0.0)           # no multirate row at all
    assert VizStats().snapshot(0.0).haptic_mode is None                 # no metrics yet


def test_a_negative_energy_in_is_a_valid_value_since_it_is_what_is_watched_for():
    stats = VizStats(window=1.0)
    assert stats.on_metrics(0.0, 0, 1e-4, (0, 0, 0.5), 0.001,
                            **dict(HAPTIC, energy_in=-5e-3, energy_in_min=-5e-3))
    assert stats.snapshot(0.001).energy_in_low == pytest.approx(-5e-3)


@pytest.mark.parametrize('field, value, key', [
    *[(f, v, f) for f in ('solver_rate', 'model_age', 'coupling_stretch', 'added_damping')
      for v in ABSURD],
    *[(f, v, 'energy_in') for f in ('energy_in', 'energy_in_min') for v in ABSURD[:-1]],
    ('haptic_mode', 256, 'haptic_mode'), ('haptic_mode', math.nan, 'haptic_mode'),
], ids=lambda x: repr(x)[:16])
def test_an_absurd_haptic_value_is_counted_and_its_message_left_out(field, value, key):
    stats = VizStats(window=5.0)
    assert stats.on_metrics(0.0, 0, 1e-4, (0, 0, 0.5), 0.001, **HAPTIC)
    assert not stats.on_metrics(0.001, MS, 1e-4, (0, 0, 0.5), 0.001,
                                **dict(HAPTIC, **{field: value}))
    snap = stats.snapshot(0.002)
    assert snap.bad_values[key] == 1 and sum(snap.bad_values.values()) == 1
    assert len(stats.metrics_table) == 1
    assert (snap.energy_in, snap.solver_rate) == pytest.approx((3e-6, 400.0))


def test_zero_and_the_limits_themselves_are_valid_values():
    stats = VizStats(window=5.0)
    assert stats.on_metrics(0.0, 0, 0.0, (0, 0, 0), 0.0)
    assert stats.on_metrics(0.001, MS, LIMITS['step_wall_time'].hi, (0, 0, 0), 0.0)
    assert stats.snapshot(0.002).step_max == LIMITS['step_wall_time'].hi
    limit = Limit(0.0, 1.0, 'things')
    assert limit.ok(0.0, 1.0) and not limit.ok(0.5, 1.5) and not limit.ok(math.nan)
    assert limit.mask([-1.0, 0.5, math.inf, math.nan, 1.0]).tolist() == [False, True, False,
                                                                         False, True]


def test_backwards_stamps_are_counted_per_topic_but_equal_stamps_are_not():
    order = StampOrder()
    assert [order.check(s) for s in (1, 2, 2, 1, 3, 2)] == [True, True, True, False, True, False]
    assert order.backwards == 2
    stats = VizStats(window=5.0)
    for now, stamp in ((0.0, 5 * MS), (0.001, 4 * MS), (0.002, 6 * MS)):
        stats.on_metrics(now, stamp, 1e-4, (0, 0, 0), 0.0)
    stats.on_pose(0.003, 1 * MS, (0, 0, 0))              # another topic: its own order
    snap = stats.snapshot(0.01)
    assert snap.backwards_in_window == 1 and snap.backwards_total == 1
    assert stats.summary(0.01)['backwards_stamps'] == {'metrics': 1, 'particles': 0, 'pose': 0,
                                                        'force': 0}


def test_a_clock_that_restarts_earlier_counts_as_one_backwards_stamp_not_one_per_message():
    # the sim's clouds before a lockstep replay's first pose, then the bag's (older) stamps
    order = StampOrder()
    wall = [1_800_000_000 * 10**9 + k * MS for k in range(5)]
    bag = [1_700_000_000 * 10**9 + k * MS for k in range(1000)]
    checks = [order.check(s) for s in wall + bag]
    assert order.backwards == 1
    assert checks.count(False) == 1 and checks[len(wall)] is False


def test_active_particles_force_and_displacement_come_from_the_latest_metrics():
    stats = VizStats(window=5.0)
    stats.on_metrics(0.0, 0, 1e-4, (3.0, 4.0, 0.0), 0.002, n_interaction=100, n_layer=[40, 20],
                     n_relaxing=5)
    stats.on_metrics(0.001, MS, 1e-4, (0.0, 0.6, 0.8), 0.001, n_interaction=10, n_layer=[4],
                     n_relaxing=0)
    snap = stats.snapshot(0.002)
    assert snap.active == 14 and snap.n_interaction == 10
    assert snap.force == pytest.approx(1.0)              # |(0, 0.6, 0.8)|
    assert snap.force_max == pytest.approx(5.0)          # |(3, 4, 0)| earlier in the window
    assert snap.displacement == pytest.approx(0.001)
    summary = stats.summary(0.002)
    assert summary['max_active_particles'] == 165
    assert summary['max_force_n'] == pytest.approx(5.0)
    assert summary['max_displacement_m'] == pytest.approx(0.002)


def test_force_commands_take_over_the_force_figure_once_they_arrive():
    stats = VizStats(window=5.0)
    stats.on_metrics(0.0, 0, 1e-4, (0, 0, 2.0), 0.0)
    stats.on_force(0.001, 0, (0, 0, 0.5))                # e.g. clamped by the device chain
    assert stats.snapshot(0.002).force == pytest.approx(0.5)


def test_decimating_recorder_keeps_an_evenly_thinned_whole_run():
    rec = DecimatingRecorder(('t',), max_rows=4)
    for i in range(10):
        rec.append((i,))
    # full at 4 rows -> keep every 2nd (0, 2) then every 2nd new; full again -> every 4th
    assert rec.array()[:, 0].tolist() == [0.0, 4.0, 8.0]
    with pytest.raises(ValueError):
        rec.append((1.0, 2.0))
    with pytest.raises(VizConfigError):
        DecimatingRecorder(('t',), max_rows=1)


def test_decimating_recorder_writes_each_full_block_as_csv_lines_until_it_thins_them():
    from tissue_viz.stats import csv_rows

    block = DecimatingRecorder.BLOCK
    rec = DecimatingRecorder(('t', 'v'), max_rows=3 * block, csv_text=True)
    for i in range(2 * block + 5):
        rec.append((i * 1e-3, math.nan if i % 7 == 0 else i / 3))
    rows, text = rec.csv_head()
    assert rows == 2 * block and text == csv_rows(rec.array()[:rows])
    assert text.splitlines()[:2] == ['0,', '0.001,0.333333333333']      # NaN: an empty cell
    for i in range(block):             # full at 3 blocks: every other row goes, and the lines
        rec.append((i * 1e-3, 1.0))
    assert rec.stride == 2 and rec.csv_head() == (0, '')
    assert DecimatingRecorder(('t',), max_rows=10).csv_head() == (0, '')


def test_press_displacement_is_measured_from_first_contact_against_the_reaction():
    # Tool goes down in z from +1 mm to -4 mm; contact at z = 0 with a 500 N/m tissue.
    z = np.linspace(0.001, -0.004, 11)                   # 0.5 mm steps
    position = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    force = np.column_stack([np.zeros_like(z), np.zeros_like(z), 500.0 * np.maximum(0.0, -z)])
    disp = press_displacement(force, position, contact_threshold=0.01)
    # first force > 0.01 N is at z = -0.5 mm (0.25 N), index 3
    assert np.isnan(disp[:3]).all()
    assert disp[3:] == pytest.approx(np.arange(8) * 0.0005)
    assert np.isnan(press_displacement(np.zeros((3, 3)), np.zeros((3, 3)))).all()


def test_summary_line_is_one_compact_line_with_units():
    stats = VizStats(window=1.0)
    for i in range(11):
        stats.on_metrics(i * 0.1, i * 100 * MS, 2e-4, (0, 0, 1.25), 0.0031, n_interaction=7)
    line = summary_line(stats.snapshot(1.0))
    assert '\n' not in line
    assert 'step p50 0.20 ms' in line and 'F 1.25 N' in line and 'disp 3.1 mm' in line
    assert 'active 7' in line and 'lat p50 -' in line


def test_a_shaft_is_drawn_as_a_cylinder_along_its_axis_and_the_arrow_starts_at_the_tip():
    from tissue_msgs.msg import SimMetrics

    msg = SimMetrics()
    msg.tool_position.x, msg.tool_position.y, msg.tool_position.z = 0.1, 0.0, 0.05
    s = math.sqrt(0.5)
    msg.tool_axis.x, msg.tool_axis.z = s, s
    msg.tool_length, msg.tool_radius = 0.08, 0.004
    tool = ToolShape.from_metrics(msg)
    centre, q = tool.shaft_pose()
    assert centre == pytest.approx([0.1 + 0.04 * s, 0.0, 0.05 + 0.04 * s])
    x, y, z, w = q                      # the quaternion takes the cylinder's z onto the axis
    rz = [2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)]
    assert rz == pytest.approx([s, 0.0, s])
    msg.tool_length = 0.0                               # a sphere: no shaft
    assert ToolShape.from_metrics(msg).shaft_pose() is None
    msg.tool_radius = math.nan                          # nothing usable: nothing drawn
    assert ToolShape.from_metrics(msg) is None
    start, end = force_arrow((0.0, 0.0, 0.01), (0.0, 0.0, 2.0), scale=0.02)
    assert end == pytest.approx([0.0, 0.0, 0.05]) and start == pytest.approx([0.0, 0.0, 0.01])


def test_the_summary_says_what_the_hand_felt_frame_to_frame_in_stamp_order():
    """A held 0.16 N press with one 50 mN click that comes straight back; the replies arrive out
    of order. The summary counts the one reversal, and E_in of a still hand stays zero."""
    stats = VizStats(window=1.0)
    forces = np.full(100, 0.16)
    forces[60] = 0.11
    order = list(range(100))
    order[10], order[11] = order[11], order[10]
    for k in range(100):
        stats.on_pose(k * 1e-3, k * MS, (0.0, 0.0, -0.002))
    for k in order:
        stats.on_force(0.1 + k * 1e-3, k * MS, (0.0, 0.0, forces[k]))
    s = stats.summary(0.3)
    assert s['feel_reversals'] == 1.0 and s['feel_E_in_min_uJ'] == 0.0
    assert s['feel_dF_max_mN'] == pytest.approx(50.0) and s['feel_steady_frames'] == 100 - 1 - 20


def test_an_instrument_summary_gives_its_force_latency_and_lowest_e_in():
    stats = VizStats(window=1.0)
    for k in range(10):
        stats.on_pose(k * 1e-3, k * MS, (0.0, 0.0, 0.0))
        stats.on_force(k * 1e-3 + 2e-4, k * MS, (0.0, 0.0, 0.1 * k))
        stats.on_metrics(k * 1e-3, k * MS, 1e-4, (0.0, 0.0, 0.1 * k), 0.0, haptic_mode=HAPTIC_MULTIRATE,
                         energy_in=-2e-6 if k == 5 else 0.0, energy_in_min=-2e-6 if k >= 5 else 0.0)
    got = stats.instrument_summary(0.02)
    assert tuple(got) == INSTRUMENT_SUMMARY_KEYS
    assert got['max_force_n'] == pytest.approx(0.9)
    assert got['latency_p50_s'] == pytest.approx(2e-4) and got['latency_p99_s'] == pytest.approx(2e-4)
    assert got['replies_missed_pct'] == 0.0 and got['energy_in_min_j'] == pytest.approx(-2e-6)


def test_the_summary_line_of_several_instruments_gives_each_ones_latency_and_force():
    stats = {name: VizStats(window=1.0) for name in ('left', 'right')}
    for k, s in enumerate(stats.values()):
        s.on_pose(0.0, MS, (0.0, 0.0, 0.0))
        s.on_force(1e-3 * (k + 1), MS, (0.0, 0.0, 1.0 + k))
    snaps = {name: s.snapshot(0.01) for name, s in stats.items()}
    line = summary_line(snaps['left'], snaps)
    assert 'left lat p50 1.00 ms p99 1.00 ms F 1.00 N' in line
    assert 'right lat p50 2.00 ms p99 2.00 ms F 2.00 N' in line
    assert ' | F ' not in line                      # no force without its instrument
    assert ' | lat p50' in summary_line(snaps['left'])   # one instrument: as before
