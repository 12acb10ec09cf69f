"""The CRTK operating state machine and its gate on the safety chain (no ROS)."""

import numpy as np
import pytest

from haptic_omni_driver.crtk import OperatingStateMachine
from haptic_omni_driver.safety import ForceSafety, SafetyConfig


def test_enable_pause_resume_disable_follow_the_crtk_meta_states():
    m = OperatingStateMachine('DISABLED')
    assert m.current.state == 'DISABLED' and not m.current.renders_force
    steps = [('enable', 'ENABLED'), ('pause', 'PAUSED'), ('resume', 'ENABLED'),
             ('disable', 'DISABLED'), ('ENABLE', 'ENABLED')]          # case does not matter
    for cmd, state in steps:
        new, why = m.command(cmd)
        assert (new.state, why) == (state, ''), cmd
    assert m.current.renders_force


@pytest.mark.parametrize('start, cmd', [('DISABLED', 'pause'), ('DISABLED', 'resume')])
def test_a_command_that_does_not_apply_changes_nothing_and_says_why(start, cmd):
    m = OperatingStateMachine(start)
    new, why = m.command(cmd)
    assert new.state == start and f'does not apply in state {start}' in why


def test_enable_does_not_leave_pause_resume_does():
    m = OperatingStateMachine()
    m.command('pause')
    new, why = m.command('enable')
    assert new.state == 'PAUSED' and 'does not apply in state PAUSED' in why
    assert m.command('resume')[0].state == 'ENABLED'


def test_an_unknown_command_is_refused_by_name():
    new, why = OperatingStateMachine().command('fly')
    assert new.state == 'ENABLED' and "unknown command 'fly'" in why


def test_a_fault_holds_until_disable_and_then_the_device_can_be_enabled_again():
    m = OperatingStateMachine()
    assert m.fault('device failed: HD error').state == 'FAULT'
    for cmd in ('enable', 'resume', 'pause', 'home'):
        assert m.command(cmd)[0].state == 'FAULT'
    assert m.command('disable') == (m.current, '') and m.current.state == 'DISABLED'
    assert m.fault_reason == '' and m.command('enable')[0].state == 'ENABLED'


def test_home_reports_what_the_device_found_and_unhome_clears_it():
    m = OperatingStateMachine()
    assert m.current.is_homed
    assert not m.command('unhome')[0].is_homed
    new, why = m.command('home', homed_now=False)
    assert not new.is_homed and 'not calibrated' in why
    assert m.command('home', homed_now=True) == (m.current, '') and m.current.is_homed


def test_home_applies_where_cisst_accepts_it_and_unhome_everywhere():
    m = OperatingStateMachine()
    m.command('pause')
    assert 'does not apply in state PAUSED' in m.command('home')[1]
    m.fault('device failed')
    new, why = m.command('unhome')
    assert (new.state, new.is_homed, why) == ('FAULT', False, '')


def test_a_start_state_other_than_enabled_or_disabled_is_refused():
    with pytest.raises(ValueError, match='PAUSED'):
        OperatingStateMachine('PAUSED')


def test_output_held_at_zero_while_not_allowed_then_ramps_up_from_zero():
    s = ForceSafety(SafetyConfig(ramp_time=0.1, max_force_rate=0.0, max_command_lag=0.0))
    for k in range(10):
        s.command([0.5, 0.0, 0.0], 'omni_base', k * 0.001)
        s.output(k * 0.001)
    s.allow_output(False, 0.010)
    s.command([0.5, 0.0, 0.0], 'omni_base', 0.010)
    assert not np.any(s.output(0.010)) and not s.status(0.010).force_enabled
    s.allow_output(True, 0.020)
    s.command([0.5, 0.0, 0.0], 'omni_base', 0.020)
    s.command([0.5, 0.0, 0.0], 'omni_base', 0.070)
    assert s.output(0.070)[0] == pytest.approx(0.25)              # half-way up its 0.1 s ramp
    assert s.status(0.070).force_enabled
