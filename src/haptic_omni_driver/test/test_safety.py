"""Pure tests of the force safety chain (clamp, ramp, watchdog, input rejection)."""

import math

import numpy as np
import pytest

from haptic_omni_driver.errors import ConfigError
from haptic_omni_driver.safety import HARD_FORCE_LIMIT, ForceSafety, SafetyConfig


def make(**kw) -> ForceSafety:
    """A safety chain; the force-rate limit is off unless asked for (tested in test_safety_battery)."""
    kw.setdefault('max_force_rate', 0.0)
    kw.setdefault('max_command_lag', 0.0)   # commands here answer no pose (window: test_safety_battery)
    return ForceSafety(SafetyConfig(**kw))


def test_output_is_zero_and_disabled_before_first_command():
    s = make(ramp_time=0.0)
    assert np.array_equal(s.output(0.0), np.zeros(3))
    st = s.status(0.0)
    assert not st.force_enabled and not st.watchdog_tripped and st.command_age == -1.0


def test_force_norm_is_clamped_keeping_direction():
    s = make(force_limit=0.88, ramp_time=0.0)
    res = s.command([3.0, 4.0, 0.0], 'omni_base', now=1.0)
    assert res.accepted and res.clamped
    out = s.output(1.001)
    assert np.linalg.norm(out) == pytest.approx(0.88, abs=1e-12)
    assert out == pytest.approx([0.88 * 0.6, 0.88 * 0.8, 0.0])
    assert s.status(1.001).force_clamped


def test_force_below_limit_passes_unchanged():
    s = make(force_limit=0.88, ramp_time=0.0)
    assert not s.command([0.1, -0.2, 0.3], 'omni_base', now=0.0).clamped
    assert s.output(0.0) == pytest.approx([0.1, -0.2, 0.3])


@pytest.mark.parametrize('bad', [[math.nan, 0, 0], [0, math.inf, 0], [0, 0, -math.inf]])
def test_non_finite_commands_are_rejected_and_counted(bad):
    s = make(ramp_time=0.0)
    s.command([0.2, 0, 0], 'omni_base', now=0.0)
    res = s.command(bad, 'omni_base', now=0.001)
    assert not res.accepted and res.reason == 'nan'
    assert s.output(0.002) == pytest.approx([0.2, 0, 0])  # previous valid command kept
    assert s.status(0.002).rejected_commands == 1


def test_wrong_frame_is_rejected_empty_frame_configurable():
    s = make(ramp_time=0.0)
    assert s.command([0.1, 0, 0], 'tissue', now=0.0).reason == 'frame'
    assert s.command([0.1, 0, 0], '', now=0.0).accepted
    strict = make(ramp_time=0.0, accept_empty_frame=False)
    assert strict.command([0.1, 0, 0], '', now=0.0).reason == 'frame'


def test_ramp_is_linear_over_ramp_time_after_enabling():
    s = make(ramp_time=0.5)
    s.command([0.4, 0, 0], 'omni_base', now=10.0)
    for t, frac in ((10.0, 0.0), (10.125, 0.25), (10.25, 0.5), (10.5, 1.0), (10.7, 1.0)):
        s.command([0.4, 0, 0], 'omni_base', now=t)  # keep the watchdog fed
        assert s.output(t)[0] == pytest.approx(0.4 * frac)


def test_watchdog_zeroes_force_after_timeout_and_rearms_with_ramp():
    s = make(ramp_time=0.1, watchdog_timeout=0.02)
    s.command([0.5, 0, 0], 'omni_base', now=0.0)
    s.command([0.5, 0, 0], 'omni_base', now=0.2)
    assert s.output(0.219)[0] == pytest.approx(0.5)
    assert not s.status(0.219).watchdog_tripped
    assert np.array_equal(s.output(0.2201), np.zeros(3))
    st = s.status(0.2201)
    assert st.watchdog_tripped and not st.force_enabled and s.trip_count == 1
    # commands resume: the force ramps up again from zero
    s.command([0.5, 0, 0], 'omni_base', now=1.0)
    assert s.output(1.0)[0] == pytest.approx(0.0)
    assert s.output(1.01)[0] == pytest.approx(0.05)
    assert not s.status(1.01).watchdog_tripped


def test_rejected_commands_do_not_feed_the_watchdog():
    s = make(ramp_time=0.0, watchdog_timeout=0.02)
    s.command([0.5, 0, 0], 'omni_base', now=0.0)
    for k in range(1, 30):
        s.command([math.nan, 0, 0], 'omni_base', now=k * 0.001)
    assert np.array_equal(s.output(0.03), np.zeros(3))
    assert s.status(0.03).watchdog_tripped


def test_stale_replies_are_rejected_when_lag_check_enabled():
    s = make(ramp_time=0.0, max_command_lag=0.05)
    s.note_pose(10.0)
    assert s.command([0.1, 0, 0], 'omni_base', now=0.0, stamp=9.96).accepted
    assert s.command([0.1, 0, 0], 'omni_base', now=0.0, stamp=9.9).reason == 'stale'


@pytest.mark.parametrize('kw', [dict(force_limit=HARD_FORCE_LIMIT + 0.1), dict(force_limit=-1.0),
                                dict(watchdog_timeout=0.2), dict(watchdog_timeout=0.001),
                                dict(ramp_time=math.nan), dict(frame_id='')])
def test_invalid_config_is_rejected(kw):
    with pytest.raises(ConfigError):
        SafetyConfig(**kw).validate()
