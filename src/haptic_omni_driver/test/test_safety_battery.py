"""The safety chain's promises, with injected times: stamp window, clamped outputs, watchdog age, rate limit."""

import math

import numpy as np
import pytest

from haptic_omni_driver.errors import ConfigError
from haptic_omni_driver.safety import (DEFAULT_COMMAND_LAG, HARD_FORCE_LIMIT, MAX_TICK_CREDIT,
                                       STAMP_TOLERANCE, ForceSafety, SafetyConfig)

POSE = 1_700_000_000.123  # [s] a wall-clock pose stamp, as the live backends publish


def make(**kw) -> ForceSafety:
    """A safety chain; commands answer no pose unless a test notes one, so the stale-reply window
    is off unless asked for (its default is tested on its own)."""
    kw.setdefault('max_command_lag', 0.0)
    return ForceSafety(SafetyConfig(**kw))


def norms(vec) -> tuple[float, float]:
    """The two float64 norms a reader of the force may compute."""
    return float(np.linalg.norm(vec)), math.hypot(*vec)


def run(s: ForceSafety, force, t0: float, t1: float, dt: float = 0.001) -> list:
    """Command ``force`` and take the output every ``dt`` from t0 to t1: [(t, output), ...]."""
    out = []
    for k in range(int(round((t1 - t0) / dt)) + 1):
        t = t0 + k * dt
        s.command(force, 'omni_base', now=t)
        out.append((t, s.output(t)))
    return out


# -- stale-reply window (max_command_lag) ---------------------------------------------------------
@pytest.mark.parametrize('stamp, reason', [
    (0.0, 'stale'),                        # an unset stamp
    (-5.0, 'stale'),                       # a negative seconds field
    (POSE - 0.0501, 'stale'),              # answers a pose older than the lag
    (POSE + 0.5, 'future'),                # answers a pose not published yet
    (POSE + 10 * STAMP_TOLERANCE, 'future'),
    (math.nan, 'stale'),
    (None, 'stale'),                       # no stamp to check
])
def test_command_whose_stamp_is_outside_the_pose_window_is_rejected_and_counted(stamp, reason):
    s = make(ramp_time=0.0, max_command_lag=0.05, max_force_rate=0.0)
    s.note_pose(POSE)
    res = s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=stamp)
    assert not res.accepted and res.reason == reason
    st = s.status(1.0)
    assert st.rejected_commands == 1 and st.rejected_by_reason == {reason: 1}
    assert not st.force_enabled                     # a rejected command does not enable the output
    assert np.array_equal(s.output(1.0), np.zeros(3))


@pytest.mark.parametrize('stamp', [POSE, POSE - 0.05, POSE - 0.001, POSE + STAMP_TOLERANCE / 2])
def test_reply_to_a_recent_pose_is_accepted(stamp):
    s = make(ramp_time=0.0, max_command_lag=0.05, max_force_rate=0.0)
    s.note_pose(POSE - 0.2)
    s.note_pose(POSE)
    assert s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=stamp).accepted


def test_command_before_any_pose_is_rejected_when_the_lag_check_is_on():
    s = make(ramp_time=0.0, max_command_lag=0.05)
    res = s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=POSE)
    assert not res.accepted and res.reason == 'no_pose'
    assert s.status(1.0).rejected_by_reason == {'no_pose': 1}
    s.note_pose(POSE)
    assert s.command([0.5, 0, 0], 'omni_base', now=1.001, stamp=POSE).accepted


def test_by_default_replies_stamped_zero_negative_future_or_too_old_are_rejected():
    s = ForceSafety(SafetyConfig(ramp_time=0.0))
    assert s.config.max_command_lag == DEFAULT_COMMAND_LAG > 0.0
    assert s.command([0.5, 0, 0], 'omni_base', now=0.5, stamp=POSE).reason == 'no_pose'
    s.note_pose(POSE)
    expected = {0.0: 'stale', -5.0: 'stale', None: 'stale', math.nan: 'stale',
                POSE - 2 * DEFAULT_COMMAND_LAG: 'stale', POSE + 0.001: 'future', POSE + 100.0: 'future'}
    for stamp, reason in expected.items():
        result = s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=stamp)
        assert (result.accepted, result.reason) == (False, reason), stamp
    assert s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=POSE - 0.5 * DEFAULT_COMMAND_LAG).accepted
    assert s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=POSE).accepted


def test_stamps_are_not_checked_when_the_lag_check_is_off():
    s = make(ramp_time=0.0)
    for stamp in (0.0, -5.0, POSE + 100.0, None):
        assert s.command([0.5, 0, 0], 'omni_base', now=1.0, stamp=stamp).accepted


def test_rejected_stale_commands_do_not_feed_the_watchdog():
    s = make(ramp_time=0.0, max_command_lag=0.05, watchdog_timeout=0.02, max_force_rate=0.0)
    s.note_pose(POSE)
    s.command([0.5, 0, 0], 'omni_base', now=0.0, stamp=POSE)
    for k in range(1, 31):
        s.command([0.5, 0, 0], 'omni_base', now=k * 0.001, stamp=0.0)
        s.output(k * 0.001)
    assert s.status(0.03).watchdog_tripped
    assert s.status(0.03).rejected_commands == 30


# -- exact norm clamp (the clamp itself: tissue_common/test/test_force_clamp.py) -----------------
def random_vectors(n: int, seed: int = 8) -> np.ndarray:
    """Random directions with norms from 1e-3 to 1e6 N (fixed seed)."""
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-3, 6, size=(n, 1))


def test_published_outputs_never_exceed_the_force_limit():
    """Every output of the chain, at the hard limit, for commands far above it (the old 3.3000000000000003 N)."""
    s = make(force_limit=HARD_FORCE_LIMIT, ramp_time=0.0, max_force_rate=0.0)
    for k, vec in enumerate(random_vectors(5000, seed=11)):
        s.command(vec, 'omni_base', now=k * 0.001)
        assert max(norms(s.output(k * 0.001))) <= HARD_FORCE_LIMIT


# -- watchdog: the command's true age -------------------------------------------------------------
def test_command_counts_from_its_reception_not_from_when_it_is_handed_over():
    """A command received at 0.000 but processed late still trips the watchdog on time."""
    s = make(ramp_time=0.0, watchdog_timeout=0.02, max_force_rate=0.0)
    s.output(0.0)
    s.command([0.3, 0, 0], 'omni_base', now=0.000)   # reception time
    for k in range(1, 21):
        s.output(k * 0.001)
    assert not s.status(0.020).watchdog_tripped
    s.output(0.0205)
    assert s.status(0.0205).watchdog_tripped and s.trip_count == 1


def test_late_servo_tick_after_a_process_stall_does_not_trip_a_clean_stream():
    """The servo ran 1 ms ticks, then the process stalled 45 ms; the stream never stopped."""
    s = make(ramp_time=0.0, watchdog_timeout=0.02, max_force_rate=0.0)
    for k in range(11):                                  # commands and ticks every ms to 10 ms
        s.command([0.3, 0, 0], 'omni_base', now=k * 0.001)
        s.output(k * 0.001)
    # no tick and no command received from 10 ms to 55 ms (the process did not run)
    assert s.output(0.055)[0] == 0.3                     # the first tick after the stall renders on
    assert not s.status(0.055).watchdog_tripped
    s.command([0.3, 0, 0], 'omni_base', now=0.0555)      # DDS delivers what arrived meanwhile
    for k in range(56, 80):
        s.command([0.3, 0, 0], 'omni_base', now=k * 0.001)
        s.output(k * 0.001)
    assert s.trip_count == 0


def test_silent_simulator_trips_after_the_timeout_of_running_time_even_after_a_stall():
    s = make(ramp_time=0.0, watchdog_timeout=0.02, max_force_rate=0.0)
    s.command([0.3, 0, 0], 'omni_base', now=0.0)
    s.output(0.001)
    s.output(0.050)          # stalled 49 ms: counts MAX_TICK_CREDIT
    observed = 0.001 + MAX_TICK_CREDIT
    assert not s.status(0.050).watchdog_tripped
    t, k = 0.050, 0
    while not s.status(t).watchdog_tripped:
        k += 1
        t = 0.050 + k * 0.001
        s.output(t)
    # tripped on the first tick where the silence the driver saw exceeded the timeout
    assert observed + (k - 1) * 0.001 <= 0.02 < observed + k * 0.001 + 1e-12
    assert np.array_equal(s.output(t), np.zeros(3))


def test_silent_simulator_trips_even_when_every_servo_tick_is_late():
    s = make(ramp_time=0.0, watchdog_timeout=0.02, max_force_rate=0.0)
    s.command([0.3, 0, 0], 'omni_base', now=0.0)
    s.output(0.0)
    ticks = [k * 0.1 for k in range(1, 5)]             # a starved servo: 100 ms apart
    tripped = []
    for t in ticks:
        s.output(t)
        tripped.append(s.status(t).watchdog_tripped)
    assert tripped == [False, False, True, True]       # 10 + 10 ms, then 30 ms of running time


# -- force-rate (impulse) limit -------------------------------------------------------------------
@pytest.mark.parametrize('rate', [100.0, 330.0, 20.0])
def test_force_step_to_the_peak_takes_at_least_peak_over_rate_to_render(rate):
    s = make(force_limit=HARD_FORCE_LIMIT, ramp_time=0.0, max_force_rate=rate)
    s.output(0.0)
    out = run(s, [0.0, HARD_FORCE_LIMIT, 0.0], 0.001, 1.0)
    t_full = next(t for t, f in out if f[1] == pytest.approx(HARD_FORCE_LIMIT, abs=1e-9))
    assert t_full >= HARD_FORCE_LIMIT / rate - 1e-9
    assert t_full <= HARD_FORCE_LIMIT / rate + 0.002           # and not slower than it must be


def test_output_changes_by_at_most_rate_times_dt_between_outputs():
    rate = 100.0
    s = make(force_limit=HARD_FORCE_LIMIT, ramp_time=0.0, max_force_rate=rate)
    rng = np.random.default_rng(5)
    t, prev = 0.0, s.output(0.0)
    for _ in range(3000):
        dt = float(rng.choice([0.0005, 0.001, 0.002, 0.004]))
        t += dt
        s.command(rng.normal(size=3) * 2.0, 'omni_base', now=t)
        out = s.output(t)
        if np.any(out):
            assert np.linalg.norm(out - prev) <= rate * dt * (1 + 1e-9) + 1e-15
        prev = out


def test_late_output_earns_no_larger_step_than_a_tick_credit():
    s = make(force_limit=HARD_FORCE_LIMIT, ramp_time=0.0, max_force_rate=100.0)
    s.output(0.0)
    s.command([HARD_FORCE_LIMIT, 0, 0], 'omni_base', now=0.2)
    out = s.output(0.2)                                   # 200 ms after the previous output
    assert out[0] == pytest.approx(100.0 * MAX_TICK_CREDIT)


def test_zeroing_is_immediate_on_trip_and_on_a_zero_command():
    s = make(force_limit=HARD_FORCE_LIMIT, ramp_time=0.0, max_force_rate=100.0,
             watchdog_timeout=0.02)
    run(s, [0, 0, 2.0], 0.0, 0.1)
    assert s.output(0.1)[2] == pytest.approx(2.0)
    s.command([0, 0, 0], 'omni_base', now=0.101)         # contact lost: zero at once
    assert np.array_equal(s.output(0.101), np.zeros(3))
    run(s, [0, 0, 2.0], 0.102, 0.2)
    outputs = [s.output(0.2 + k * 0.001) for k in range(30)]   # commands stop
    first_zero = next(k for k, f in enumerate(outputs) if not np.any(f))
    assert outputs[first_zero - 1][2] == pytest.approx(2.0)     # the watchdog: 2 N to 0 at once
    assert s.status(0.2 + first_zero * 0.001).watchdog_tripped


def test_rate_limit_is_reported_and_zero_rate_turns_it_off():
    s = make(force_limit=1.0, ramp_time=0.0, max_force_rate=100.0)
    s.output(0.0)
    s.command([1.0, 0, 0], 'omni_base', now=0.001)
    assert s.output(0.001)[0] == pytest.approx(0.1)
    assert s.status(0.001).rate_limited and s.rate_limited_count == 1
    off = make(force_limit=1.0, ramp_time=0.0, max_force_rate=0.0)
    off.output(0.0)
    off.command([1.0, 0, 0], 'omni_base', now=0.001)
    assert off.output(0.001)[0] == 1.0 and not off.status(0.001).rate_limited


def test_lowered_force_limit_applies_to_the_output_at_once():
    s = make(force_limit=1.0, ramp_time=0.0, max_force_rate=100.0)
    run(s, [1.0, 0, 0], 0.0, 0.05)
    s.set_config(SafetyConfig(force_limit=0.3, ramp_time=0.0, max_force_rate=100.0))
    out = s.output(0.0505)
    assert max(norms(out)) <= 0.3


@pytest.mark.parametrize('rate', [-1.0, 10001.0, math.nan, math.inf])
def test_out_of_range_force_rate_is_refused(rate):
    with pytest.raises(ConfigError, match='max_force_rate'):
        SafetyConfig(max_force_rate=rate).validate()
