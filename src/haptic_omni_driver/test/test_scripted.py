"""Pure tests of the scripted motion generator (minimum jerk, script, tremor, quantisation)."""

import numpy as np
import pytest

from haptic_omni_driver.backends.scripted import (ScriptConfig, build_script, generate_trajectory,
                                                  min_jerk, min_jerk_derivatives, parse_script,
                                                  quantise, sample_script, script_duration,
                                                  script_segments, tremor)
from haptic_omni_driver.errors import ConfigError


def test_min_jerk_boundary_conditions():
    p0, p1, T = np.array([0.0, 0.05, 0.0]), np.array([0.01, -0.002, 0.003]), 0.8
    for t, pos_exp in ((0.0, p0), (T, p1)):
        pos, vel, acc = min_jerk_derivatives(p0, p1, T, t)
        assert pos == pytest.approx(p0 if t == 0 else p1, abs=1e-15)
        assert vel == pytest.approx(np.zeros(3), abs=1e-15)
        assert acc == pytest.approx(np.zeros(3), abs=1e-12)
    # midpoint: half way, peak speed 1.875 * distance / T (the known minimum-jerk value)
    pos, vel, acc = min_jerk_derivatives(p0, p1, T, T / 2)
    assert pos == pytest.approx((p0 + p1) / 2)
    assert np.linalg.norm(vel) == pytest.approx(1.875 * np.linalg.norm(p1 - p0) / T)
    assert acc == pytest.approx(np.zeros(3), abs=1e-12)


def test_min_jerk_derivatives_match_finite_differences():
    p0, p1, T = np.zeros(3), np.array([0.02, 0.0, -0.01]), 1.3
    t = np.linspace(0.05, 1.25, 25)
    h = 1e-6
    pos_p = min_jerk_derivatives(p0, p1, T, t + h)[0]
    pos_m = min_jerk_derivatives(p0, p1, T, t - h)[0]
    _, vel, acc = min_jerk_derivatives(p0, p1, T, t)
    assert vel == pytest.approx((pos_p - pos_m) / (2 * h), rel=1e-6, abs=1e-9)
    vel_p = min_jerk_derivatives(p0, p1, T, t + h)[1]
    vel_m = min_jerk_derivatives(p0, p1, T, t - h)[1]
    assert acc == pytest.approx((vel_p - vel_m) / (2 * h), rel=1e-5, abs=1e-7)
    assert min_jerk(0.0) == 0.0 and min_jerk(1.0) == 1.0 and min_jerk(0.5) == pytest.approx(0.5)


def test_script_reaches_press_depth_and_returns_home_continuously():
    cfg = ScriptConfig(tremor_amplitude=0.0, press_depth=0.008, target=[0.01, 0.0, 0.02])
    segs = build_script(cfg)
    assert [s.name for s in segs][:5] == ['approach', 'press', 'hold', 'pull', 'release']
    # segments chain: each starts where the previous ended
    for a, b in zip(segs, segs[1:]):
        assert np.allclose(a.end, b.start)
    t, pos, buttons, phases = generate_trajectory(cfg, rate=1000.0)
    assert t[-1] == pytest.approx(script_duration(segs))
    assert pos[0] == pytest.approx(cfg.home) and pos[-1] == pytest.approx(cfg.home)
    assert pos[:, 1].min() == pytest.approx(-0.008, abs=1e-9)  # deepest point: press depth
    hold = [i for i, ph in enumerate(phases) if ph == 'hold']
    assert np.allclose(pos[hold], [0.01, -0.008, 0.02])
    assert not buttons.any()        # the built-in script presses; only a script's close grasps
    # no jumps: the speed never exceeds the minimum-jerk peak 1.875 d/T of the fastest segment
    peak = max(1.875 * np.linalg.norm(s.end - s.start) / s.duration for s in segs)
    assert np.max(np.linalg.norm(np.diff(pos, axis=0), axis=1)) <= peak * 1e-3 * (1 + 1e-9)


def test_tremor_is_bounded_in_band_and_deterministic():
    t = np.arange(0, 4.0, 0.001)
    a = tremor(t, 1.5e-4, (8.0, 12.0), seed=3)
    assert np.abs(a).max() <= 1.5e-4 + 1e-15
    assert np.array_equal(a, tremor(t, 1.5e-4, (8.0, 12.0), seed=3))
    assert not np.array_equal(a, tremor(t, 1.5e-4, (8.0, 12.0), seed=4))
    spec = np.abs(np.fft.rfft(a[:, 0]))
    freqs = np.fft.rfftfreq(t.size, 0.001)
    assert 8.0 <= freqs[np.argmax(spec)] <= 12.0


def test_quantisation_rounds_to_resolution():
    q = quantise(np.array([[1.23e-4, -0.9e-4, 0.0]]), 5.5e-5)
    assert q / 5.5e-5 == pytest.approx(np.round(q / 5.5e-5))
    assert q[0] == pytest.approx([1.1e-4, -1.1e-4, 0.0])


def test_generated_trajectory_is_deterministic_with_seed():
    cfg = ScriptConfig(seed=11)
    a = generate_trajectory(cfg, 500.0)[1]
    b = generate_trajectory(ScriptConfig(seed=11), 500.0)[1]
    assert np.array_equal(a, b)


def test_sample_script_holds_last_point_after_end():
    segs = build_script(ScriptConfig(tremor_amplitude=0.0))
    pos, _, _ = sample_script(segs, [script_duration(segs) + 5.0])
    assert pos[0] == pytest.approx(segs[-1].end)


SHORT = dict(approach_time=0.02, press_time=0.02, hold_time=0.02, pull_time=0.02, release_time=0.02,
             sweep_time=0.02, return_time=0.02, tremor_amplitude=0.0)


class PlaySink:
    """Records what a backend sends; stops it ``after`` samples past the end of the script."""

    def __init__(self, after: int = 50) -> None:
        self.samples, self.finished, self.after = [], [], after
        self.backend = None

    def wait_for_subscribers(self) -> bool:
        return True

    def on_sample(self, sample) -> None:
        self.samples.append(sample)
        if self.finished and len(self.samples) >= self.finished[0][0] + self.after:
            self.backend.stop(timeout=0.0)

    def on_finished(self, summary: str, code: int) -> None:
        self.finished.append((len(self.samples), summary, code))


def play(backend, sink: PlaySink) -> PlaySink:
    from threading import Timer
    sink.backend = backend
    guard = Timer(30.0, backend.stop, kwargs={'timeout': 0.0})     # never hang the suite
    guard.start()
    try:
        backend.run(sink)
    finally:
        guard.cancel()
    return sink


def test_without_loop_the_stylus_rests_at_the_last_point_and_the_driver_says_so_once():
    from haptic_omni_driver.backends.scripted import ScriptedBackend

    cfg = ScriptConfig(**SHORT)
    sink = play(ScriptedBackend(cfg, rate=2000.0, loop=False), PlaySink(after=50))
    _, ref, _, _ = generate_trajectory(cfg, 2000.0)
    n, summary, code = sink.finished[0]
    assert len(sink.finished) == 1 and code == 0 and n == len(ref)
    # one pass, not two: the last sample of the script is at t == duration (regression)
    assert 'one pass' in summary and 'pass(es)' not in summary and 'rests at its last point' in summary
    got = np.array([smp.position for smp in sink.samples])
    assert np.abs(got[:n] - ref).max() < 1e-12
    assert len(got) >= n + 50 and np.all(got[n:] == ref[-1])        # still publishing, at rest
    assert {smp.phase for smp in sink.samples[n:]} == {'rest'}


def test_with_exit_on_end_the_script_ends_after_its_last_sample():
    from haptic_omni_driver.backends.scripted import ScriptedBackend

    cfg = ScriptConfig(**SHORT)
    sink = play(ScriptedBackend(cfg, rate=2000.0, loop=False, exit_on_end=True), PlaySink())
    _, ref, _, _ = generate_trajectory(cfg, 2000.0)
    assert len(sink.samples) == len(ref)
    assert sink.finished == [(len(ref), f'script finished: {len(ref)} poses, one pass of '
                                         f'{script_duration(build_script(cfg)):.2f} s', 0)]


@pytest.mark.parametrize('kw', [dict(press_depth=-0.001), dict(hold_time=0.0),
                                dict(press_axis=[0, 0, 0]), dict(target=[0, 0]),
                                dict(tremor_band=(12.0, 8.0))])
def test_invalid_script_config_is_rejected(kw):
    with pytest.raises(ConfigError):
        build_script(ScriptConfig(**kw))


def test_script_bag_replays_the_generated_trajectory_with_buttons(tmp_path):
    from haptic_omni_driver.backends.replay import load_replay
    from haptic_omni_driver.backends.scripted import write_script_bag

    cfg = ScriptConfig(seed=5, script=['move 0 0.01 0 0.1', 'close 0.1', 'lift 0 0.02 0 0.1',
                                        'open 0.1', 'move 0 0.06 0 0.1'])
    write_script_bag(tmp_path / 'b', cfg, rate=500.0, t0_ns=2_000_000_000)
    events = load_replay(tmp_path / 'b')
    poses = [e.sample for e in events if e.sample is not None]
    t, pos, buttons, _ = generate_trajectory(cfg, 500.0)
    assert len(poses) == t.size
    assert np.array([p.position for p in poses]) == pytest.approx(pos, abs=0)
    assert [p.stamp_ns for p in poses] == [2_000_000_000 + 2_000_000 * k for k in range(t.size)]
    pressed = [e.buttons[0] for e in events if e.buttons is not None]
    assert any(pressed) and not pressed[0]


@pytest.mark.parametrize('shut_down', [False, True])
def test_backend_failure_is_an_error_unless_ctrl_c_shut_the_context_down(shut_down):
    """A backend thread whose publish fails because Ctrl-C already shut the context down must not
    turn a clean stop into exit code 1; any other backend failure ends the node with 1."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from haptic_omni_driver.driver_node import OmniDriver

    ctx = Context()
    rclpy.init(context=ctx)
    node = OmniDriver(context=ctx, parameter_overrides=[Parameter('backend', value='scripted')])
    try:
        if shut_down:
            ctx.shutdown()
        node.on_finished("scripted backend failed: Failed to publish: publisher's context is invalid", 1)
        assert node.exit_code == (0 if shut_down else 1)
        assert node.finished.is_set() == (not shut_down)
    finally:
        node.destroy_node()
        ctx.try_shutdown()


# -- custom scripts (parameter ``script``) ---------------------------------------------------------
HOME = [0.0, 0.06, 0.0]
#: a grasp and lift: above the tissue, press in, close the jaw, lift, carry aside, let go, back up
GRASP = ['move 0.0 0.01 0.0 0.5', 'press 0.0 -0.004 0.0 0.4', 'close 0.3', 'lift 0.0 0.015 0.0 0.4',
         'move 0.01 0.015 0.0 0.3', 'hold 0.2', 'open 0.2', 'move 0.0 0.06 0.0 0.5']


def test_a_script_parses_each_step_kind_into_chained_segments_from_home():
    segs = parse_script(GRASP, HOME)
    assert [s.name for s in segs] == ['move', 'press', 'close', 'lift', 'move', 'hold', 'open', 'move']
    assert [s.duration for s in segs] == [0.5, 0.4, 0.3, 0.4, 0.3, 0.2, 0.2, 0.5]
    assert np.array_equal(segs[0].start, HOME)                     # the script starts at home
    for a, b in zip(segs, segs[1:]):                                 # each starts where the last ended
        assert np.array_equal(a.end, b.start)
    ends = [[0.0, 0.01, 0.0], [0.0, -0.004, 0.0], [0.0, -0.004, 0.0], [0.0, 0.015, 0.0],
            [0.01, 0.015, 0.0], [0.01, 0.015, 0.0], [0.01, 0.015, 0.0], [0.0, 0.06, 0.0]]
    assert np.array_equal([s.end for s in segs], ends)               # absolute device-frame points
    # hold/close/open stay put
    assert all(np.array_equal(s.start, s.end) for s in segs if s.name in ('hold', 'close', 'open'))


def test_the_jaw_carries_over_from_the_last_close_or_open_through_moves_and_holds():
    segs = parse_script(['hold 0.1', 'close 0.1', 'move 0 0.01 0 0.1', 'hold 0.1', 'open 0.1',
                         'lift 0 0.02 0 0.1', 'close 0.1', 'close 0.1', 'hold 0.1'], HOME)
    assert [s.button1 for s in segs] == [False, True, True, True, False, False, True, True, True]


def test_an_empty_script_is_the_built_in_one_and_a_given_one_replaces_it():
    cfg = ScriptConfig()
    assert [(s.name, s.duration) for s in script_segments(cfg)] == [
        (s.name, s.duration) for s in build_script(cfg)]
    assert [s.name for s in script_segments(ScriptConfig(script=['hold 1']))] == ['hold']


@pytest.mark.parametrize('entry, why', [
    ('fly 0 0 0 1', r"unknown step 'fly' \(one of move, press, lift, hold, close, open\)"),
    ('', r'empty step'),
    ('move 0 0.01 1', r'move takes 4 numbers \(move x y z T\), got 3'),
    ('close', r'close takes 1 number \(close T\), got 0'),
    ('hold 0.5 1', r'hold takes 1 number \(hold T\), got 2'),
    ('press 0 -4mm 0 1', r"not a number in '0 -4mm 0 1'"),
    ('hold nan', r'non-finite number'),
    ('move 0 inf 0 1', r'non-finite number'),
    ('open -0.2', r'duration -0.2 s outside \[0.01, 600\] s'),
    ('lift 0 0.01 0 0', r'duration 0 s outside'),
    ('move 0 15 0 1', r'point beyond the workspace'),          # millimetres for metres
])
def test_a_bad_step_is_a_config_error_that_names_the_entry(entry, why):
    with pytest.raises(ConfigError, match=rf"^script\[1\] '{entry}': {why}"):
        parse_script(['hold 0.1', entry, 'hold 0.1'], HOME)
    with pytest.raises(ConfigError, match=why):                      # also via the config
        script_segments(ScriptConfig(script=['hold 0.1', entry]))


def test_a_sampled_script_reaches_each_target_by_minimum_jerk_with_button1_down_while_closed():
    segs = parse_script(GRASP, HOME)
    starts = np.cumsum([0.0] + [s.duration for s in segs])
    # each step's end point is reached at its end time (the last one also after it)
    pos, _, _ = sample_script(segs, starts[1:])
    assert pos == pytest.approx(np.array([s.end for s in segs]), abs=1e-15)
    # between them, the minimum-jerk profile of that step: half way at half time
    mid_pos, mid_buttons, mid_phases = sample_script(segs, (starts[:-1] + starts[1:]) / 2)
    assert mid_pos == pytest.approx(np.array([(s.start + s.end) / 2 for s in segs]), abs=1e-15)
    assert mid_phases == [s.name for s in segs]
    t = np.arange(0.0005, starts[-1], 0.001)             # a 1 kHz grid off the step boundaries
    pos, buttons, _ = sample_script(segs, t)
    k = np.searchsorted(starts, t) - 1
    s = (t - starts[k]) / np.array([segs[i].duration for i in k])
    d = np.array([segs[i].end - segs[i].start for i in k])
    assert pos == pytest.approx(np.array([segs[i].start for i in k]) + d * min_jerk(s)[:, None],
                                abs=1e-15)
    # button 1 (the jaw) down exactly from the start of close to the start of open
    t_close, t_open = starts[2], starts[6]
    assert np.array_equal(buttons, (t >= t_close) & (t < t_open))
    assert pos[buttons][:, 1].min() == pytest.approx(-0.004)     # grasped at the press depth...
    assert pos[buttons][:, 1].max() == pytest.approx(0.015)      # ...and lifted


def test_the_backend_plays_a_custom_script_with_its_jaw():
    from haptic_omni_driver.backends.scripted import ScriptedBackend

    cfg = ScriptConfig(script=['move 0 0.01 0 0.02', 'close 0.02', 'lift 0 0.02 0 0.02', 'open 0.02'],
                       tremor_amplitude=0.0)
    backend = ScriptedBackend(cfg, rate=2000.0, loop=False, exit_on_end=True)
    assert backend.source == 'script(4 steps, seed=0, 0.08 s)'
    sink = play(backend, PlaySink())
    _, ref, ref_buttons, ref_phases = generate_trajectory(cfg, 2000.0)
    assert np.abs(np.array([smp.position for smp in sink.samples]) - ref).max() < 1e-12
    assert [smp.buttons[0] for smp in sink.samples] == ref_buttons.tolist()
    assert [smp.phase for smp in sink.samples] == ref_phases
    assert ref_buttons.any() and ref[-1] == pytest.approx([0.0, 0.02, 0.0])
