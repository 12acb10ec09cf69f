"""sim_node's run loop without ROS (:mod:`sph_tissue_sim.runner`): the pose inbox of each mode,
the answers, the interrupt of a reset, run-time parameter changes."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from sim_probe import BLOCK, GRASP_AT, T0_NS, press_path, run_grasp_lift
from sph_tissue_sim.params import SIM_PARAMS, build_config, build_material, build_model, instrument_tools
from sph_tissue_sim.runner import Pose, Runner, make_solver, pose_history

LIMIT = 0.5
MS = 1_000_000


def make_runner(**over) -> tuple[Runner, list]:
    """A runner on the 256-particle block; what it sends lands in the returned list as
    ('force', stamp, frame, force, instrument), ('metrics', stamp, haptic status, instrument),
    ('cloud', stamp) or ('log', level, text). A live solver thread runs at the caller's priority
    here: a thread niced below a busy machine's other loads steps too rarely for these tests' waits
    (its priority is tested with the node, test_sim_node_errors.py)."""
    p = {name: spec[0] for name, spec in SIM_PARAMS.items()} | BLOCK | {'force_limit': LIMIT, 'solver_nice': 0,
                                                                          **over}
    model = build_model(p)
    solver = make_solver(model, build_material(p), build_config(p), p['nominal_dt'],
                         instruments=len(p['instruments']), tools=instrument_tools(p))
    out = []
    runner = Runner(p, model, solver, lambda stamp, frame, f, k=0: out.append(('force', stamp, frame, np.array(f), k)),
                    lambda stamp, res, s, h, k=0: out.append(('metrics', stamp, h, k)),
                    lambda stamp: out.append(('cloud', stamp)), lambda level, text: out.append(('log', level, text)))
    return runner, out


def pose(k: int, pos, frame: str = 'omni_base') -> Pose:
    return Pose(T0_NS + k * MS, T0_NS + k * MS, frame, tuple(pos), (0.0, 0.0, 0.0, 1.0))


def forces(out) -> list:
    return [o for o in out if o[0] == 'force']


def test_the_runner_imports_no_ros():
    code = 'import sys, sph_tissue_sim.runner; sys.exit(any(m.startswith("rclpy") for m in sys.modules))'
    assert subprocess.run([sys.executable, '-c', code], timeout=120).returncode == 0


@pytest.mark.parametrize('haptic_mode', ['direct', 'multirate'])
def test_lockstep_answers_every_pose_in_order_with_its_own_stamp_and_a_force_within_the_limit(haptic_mode):
    runner, out = make_runner(haptic_mode=haptic_mode, timing_mode='lockstep', step_thread=False)
    path = press_path(80, depth=0.01)
    for k, p in enumerate(path):
        runner.on_pose(pose(k, p))      # without a stepping thread: stepped here, in order
    sent = forces(out)
    assert [s[1] for s in sent] == [T0_NS + k * MS for k in range(len(path))]
    assert all(s[2] == 'omni_base' for s in sent)
    norms = [np.linalg.norm(s[3]) for s in sent]
    assert max(norms) <= LIMIT + 1e-12 and norms[-1] > 0.05
    assert runner.counts['poses'] == len(path) and runner.counts['steps'] == len(path)


def test_live_direct_with_a_stepping_thread_steps_the_newest_pose_and_counts_the_rest_dropped():
    runner, out = make_runner(haptic_mode='direct', timing_mode='live', step_thread=True)
    gate = threading.Lock()
    step = runner.solver.step_tools
    runner.solver.step_tools = lambda *a: (gate.acquire(), gate.release(), step(*a))[2]
    gate.acquire()                      # the thread's first step waits here
    runner.start()
    try:
        runner.on_pose(pose(0, (0.0, 0.01, 0.0)))
        deadline = time.monotonic() + 30.0
        while runner._inbox and time.monotonic() < deadline:
            time.sleep(0.01)
        for k in range(1, 6):           # five more while the first is stepping: only the newest stays
            runner.on_pose(pose(k, (0.0, 0.01, 0.0)))
        gate.release()
        while len(forces(out)) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        assert runner.shutdown()
    assert [s[1] for s in forces(out)] == [T0_NS, T0_NS + 5 * MS]
    assert runner.counts['dropped'] == 4 and runner.counts['steps'] == 2


def test_a_lockstep_inbox_over_its_limit_drops_the_oldest_and_says_so():
    runner, out = make_runner(haptic_mode='direct', timing_mode='lockstep', step_thread=True,
                              lockstep_queue_limit=3)
    for k in range(5):                  # no thread yet: the poses wait in the inbox
        runner.on_pose(pose(k, (0.0, 0.01, 0.0)))
    assert [q.stamp for q in runner._inbox] == [T0_NS + k * MS for k in (2, 3, 4)]
    assert runner.counts['overflow'] == 2
    assert any(o[0] == 'log' and o[1] == 'error' and 'lockstep queue full' in o[2] for o in out)


def test_a_reset_interrupts_a_step_and_the_tissue_and_the_clock_start_over():
    runner, out = make_runner(haptic_mode='direct', timing_mode='lockstep', step_thread=False)
    for k, p in enumerate(press_path(40, depth=0.006)):
        runner.on_pose(pose(k, p))
    assert runner.solver.sim_time > 0.0
    ok, message, sim_time, n = runner.reset(keep_material=True)
    assert ok and 'kept' in message and sim_time == pytest.approx(0.040) and n == 256
    assert runner.solver.sim_time == 0.0
    assert np.array_equal(runner.solver.positions, runner.model.positions)
    runner.on_pose(pose(100, (0.0, 0.01, 0.0)))   # the clock restarted: a first pose steps nominal_dt
    assert runner.solver.sim_time == pytest.approx(runner.p['nominal_dt'])


def test_a_parameter_change_is_validated_whole_and_a_solver_setting_rebuilds_the_solver():
    runner, out = make_runner(haptic_mode='multirate', timing_mode='lockstep')
    solver = runner.solver
    refused = runner.apply({'k1_min': 7.0})              # above k1_max: the whole change refused
    assert not refused.successful and 'k1_min' in refused.reason and runner.p['k1_min'] != 7.0
    assert runner.apply({'not_ours': 1}).changed == frozenset()
    change = runner.apply({'force_limit': 0.2})          # a next-step setting: same solver
    assert change.successful and change.changed == {'force_limit'} and runner.solver is solver
    assert runner.solver.config.force_limit == 0.2 and runner.haptic.renderer.config.force_limit == 0.2
    change = runner.apply({'mode': 'global'})            # a solver setting: a new one, at rest
    assert change.successful and change.what == 'solver rebuilt, tissue at rest' and change.remapped
    assert runner.solver is not solver and runner.solver.config.mode == 'global'


def test_a_material_the_solver_cannot_model_is_refused_at_run_time_and_nothing_changes(tmp_path):
    """A relaxing spring on the paper scheme: the change is refused with the reason (it used to
    escape apply() and the node's parameter callback); a Prony series that sums to 1 the same."""
    path = tmp_path / 'materials.yaml'
    path.write_text('materials:\n  relaxing:\n    G: 1800.0\n    nu: 0.45\n    rho: 1060.0\n    eta_shear: 3.0\n'
                    '    prony: [[0.4, 0.05]]\n  fluid:\n    G: 1800.0\n    nu: 0.45\n    rho: 1060.0\n'
                    '    eta_shear: 3.0\n    prony: [[0.6, 0.05], [0.4, 1.0]]\n')
    runner, _ = make_runner(scheme='paper')
    material = runner.solver.material
    for name, reason in (('relaxing', 'needs scheme tlsph'), ('fluid', 'sum below 1')):
        change = runner.apply({'materials_file': str(path), 'material': name})
        assert not change.successful and reason in change.reason
        assert runner.solver.material is material and runner.p['material'] != name
    runner, _ = make_runner()
    change = runner.apply({'materials_file': str(path), 'material': 'relaxing'})
    assert change.successful and change.what == 'material swapped' and runner.solver.material.prony


def test_the_pose_history_keeps_every_lockstep_pose_and_one_live_pose_stepped_in_the_callback():
    runner, _ = make_runner(timing_mode='lockstep')
    assert pose_history(runner.p, runner) == (1000, True, '')
    runner, _ = make_runner(haptic_mode='direct', timing_mode='live', step_thread=False, qos_depth=5)
    depth, reliable, note = pose_history(runner.p, runner)
    assert depth == 1 and 'depth 5 -> 1' in note
    runner, _ = make_runner(haptic_mode='multirate', timing_mode='live', qos_depth=1)
    assert pose_history(runner.p, runner)[0] == 10


TWO = {'instruments': ['left', 'right'], 'instrument_offsets': [-0.015, 0.0, 0.0, 0.015, 0.0, 0.0],
       'mode': 'global'}


def test_two_instruments_in_lockstep_are_answered_in_rounds_and_step_the_tissue_once_per_round():
    runner, out = make_runner(**TWO, timing_mode='lockstep')
    path = press_path(60, depth=0.006)
    runner.on_pose(pose(0, path[0]), 0)
    assert forces(out) == []                            # the left waits for the right's pose
    runner.on_pose(pose(0, path[0]), 1)
    for k, p in enumerate(path[1:], start=1):
        runner.on_pose(pose(k, p), 0)
        runner.on_pose(pose(k, p), 1)
    sent = forces(out)
    assert [(s[1], s[4]) for s in sent] == [(T0_NS + k * MS, i) for k in range(len(path)) for i in (0, 1)]
    assert runner.counts['steps'] == len(path)
    left, right = np.array([s[3] for s in sent if s[4] == 0]), np.array([s[3] for s in sent if s[4] == 1])
    # two presses 30 mm apart on the block's top: each pushes its own stylus up (device +y)
    assert left[-1][1] > 0.05 and right[-1][1] > 0.05
    origins = [ch.mapping.origin for ch in runner.channels]
    np.testing.assert_allclose(origins[1] - origins[0], [0.03, 0.0, 0.0], rtol=0, atol=1e-12)
    tips = [hand.tip for hand in runner.solver.instruments]
    assert tips[1][0] - tips[0][0] == pytest.approx(0.03, abs=1e-4)     # the tools follow (proxies)
    metrics = [o for o in out if o[0] == 'metrics']
    assert {o[3] for o in metrics} == {0, 1}


def test_two_instruments_in_lockstep_repeat_bit_for_bit_whatever_order_their_poses_arrive_in():
    path = press_path(50, depth=0.006)
    runs = []
    for order in ('alternating', 'left_first'):
        runner, out = make_runner(**TWO, timing_mode='lockstep')
        if order == 'alternating':
            for k, p in enumerate(path):
                runner.on_pose(pose(k, p), 0)
                runner.on_pose(pose(k, p * [1.0, 1.0, 1.0]), 1)
        else:
            for k, p in enumerate(path):
                runner.on_pose(pose(k, p), 0)
            for k, p in enumerate(path):
                runner.on_pose(pose(k, p), 1)
        runs.append(sorted(((s[4], s[1], tuple(s[3])) for s in forces(out))))
    assert runs[0] == runs[1]


def test_a_pose_in_a_foreign_frame_is_answered_at_once_and_takes_no_place_in_a_round():
    runner, out = make_runner(**TWO, timing_mode='lockstep')
    path = press_path(3, depth=0.006)
    runner.on_pose(pose(0, path[0]), 0)                      # waits in its round for the right's
    probe = Pose(T0_NS - MS, T0_NS - MS, 'system_monitor_probe', (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    runner.on_pose(probe, 0)
    assert [(s[1], s[2], s[4]) for s in forces(out)] == [(T0_NS - MS, 'system_monitor_probe', 0)]
    assert runner.counts['rejected'] == 1 and runner.counts['steps'] == 0
    runner.on_pose(pose(0, path[0]), 1)
    for k, p in enumerate(path[1:], start=1):
        runner.on_pose(pose(k, p), 0)
        runner.on_pose(pose(k, p), 1)
    # the rounds pair the instruments' poses as sent: each round's two answers carry one stamp
    assert [(s[1], s[4]) for s in forces(out)[1:]] == [(T0_NS + k * MS, i) for k in range(3) for i in (0, 1)]
    assert runner.counts['steps'] == len(path)


def test_a_bad_position_of_one_instrument_keeps_its_place_in_the_round():
    runner, out = make_runner(**TWO, timing_mode='lockstep')
    path = press_path(4, depth=0.006)
    for k, p in enumerate(path):
        runner.on_pose(pose(k, p * np.nan if k == 1 else p), 0)
        runner.on_pose(pose(k, p), 1)
    assert runner.counts['rejected'] == 1
    assert [(s[1], s[4]) for s in forces(out)] == [(T0_NS + k * MS, i) for k in range(4) for i in (0, 1)]
    assert not np.any(forces(out)[2][3])                     # the bad pose: zero force


def test_a_named_instruments_device_may_name_its_frame_in_its_namespace_but_not_in_anothers():
    runner, out = make_runner(**TWO, timing_mode='lockstep')
    path = press_path(2, depth=0.006)
    runner.on_pose(pose(0, path[0], 'right/omni_base'), 0)          # the left's pose in the right's frame
    assert runner.counts['rejected'] == 1
    assert any("frame 'right/omni_base' is not 'left/omni_base'" in o[2] for o in out if o[0] == 'log')
    for k, p in enumerate(path):
        runner.on_pose(pose(k, p, 'left/omni_base'), 0)
        runner.on_pose(pose(k, p), 1)
    assert runner.counts['rejected'] == 1 and runner.counts['steps'] == len(path)


def test_each_instruments_tool_is_its_own_and_its_metrics_say_so():
    from sph_tissue_sim.params import check_value, parse_tool

    assert parse_tool('') is None
    assert parse_tool('capsule 0.003 0.04') == {'tool_shape': 'capsule', 'tool_radius': 0.003, 'tool_length': 0.04}
    assert parse_tool('needle 0.0005 0.06') == {'tool_shape': 'needle', 'tool_radius': 0.0005, 'tool_length': 0.06}
    for bad in ('cube 0.01', 'sphere', 'capsule 0.003', 'sphere x', 'needle 0.0005'):
        assert 'instrument_tools' in check_value('instrument_tools', [bad], SIM_PARAMS)
    runner, out = make_runner(**TWO, instrument_tools=['', 'sphere 0.003'], timing_mode='lockstep')
    path = press_path(30, depth=0.004)
    for k, p in enumerate(path):
        runner.on_pose(pose(k, p), 0)
        runner.on_pose(pose(k, p), 1)
    radii = [runner.solver.instruments[k].tool.radius for k in range(2)]
    assert radii == [SIM_PARAMS['tool_radius'][0], 0.003]
    from sph_tissue_sim.runner import metrics_values
    res = runner.solver.last_result
    assert [metrics_values(res, runner.solver, None, k)['tool_radius'] for k in range(2)] == radii


def _touch_and_close(runner) -> list:
    """Touch the block 1 mm deep and close the first instrument's jaw; returns the poses sent."""
    path = list(press_path(40, depth=0.001))
    for k, p in enumerate(path):
        runner.on_pose(pose(k, p))
    runner.on_grasp(0, True)
    return path


def test_a_closed_button_grasps_lifting_pulls_and_opening_lets_go():
    runner, out = make_runner(timing_mode='lockstep', step_thread=False)
    path = _touch_and_close(runner)
    up = [path[-1] + [0.0, 0.001 * (j + 1) / 10, 0.0] for j in range(40)]   # lifted 4 mm, device +y
    for j, p in enumerate(up):
        runner.on_pose(pose(len(path) + j, p))
    logs = [o[2] for o in out if o[0] == 'log']
    assert any('grasped' in text for text in logs), logs
    assert runner.solver.instruments[0].holding > 0
    pull = forces(out)[-1][3]
    assert pull[1] < -0.02                             # the tissue pulls the stylus down (device -y)
    runner.on_grasp(0, False)
    runner.on_pose(pose(len(path) + len(up), up[-1]))
    assert runner.solver.instruments[0].holding == 0
    assert any('let go of' in o[2] for o in out if o[0] == 'log')


def test_the_cloud_marks_the_particles_an_instrument_holds_until_it_lets_go():
    runner, out = make_runner(timing_mode='lockstep', step_thread=False)
    path = _touch_and_close(runner)
    runner.on_pose(pose(len(path), path[-1]))
    runner.send_cloud_once()
    hand = runner.solver.instruments[0]
    held = np.flatnonzero(runner.cloud.points['held'])
    assert hand.holding > 0 and np.array_equal(held, np.sort(hand.grip_idx[hand.grip_held]))
    assert set(runner.cloud.points['held'][held].tolist()) == {1}          # instrument 0 holds: 1
    runner.on_grasp(0, False)
    runner.on_pose(pose(len(path) + 1, path[-1]))
    runner.send_cloud_once()
    assert not runner.cloud.points['held'].any()


def test_a_button_closed_over_nothing_grasps_nothing_and_says_so():
    runner, out = make_runner(timing_mode='lockstep', step_thread=False)
    runner.on_grasp(0, True)
    for k in range(5):
        runner.on_pose(pose(k, (0.0, 0.03, 0.0)))         # 30 mm above the tissue
    assert runner.solver.instruments[0].holding == 0
    assert any('closed on nothing' in o[2] for o in out if o[0] == 'log')


def test_two_instruments_live_are_answered_at_once_and_the_solver_thread_steps_both():
    runner, out = make_runner(**TWO, timing_mode='live')
    runner.start()
    t0 = time.monotonic()
    path = press_path(200, depth=0.005)
    sent_poses = 0
    try:
        # until the solver thread has stepped a while (its first step may compile for a minute) and
        # the right one is pushed back (a busy machine's solver refreshes its contact model late)
        deadline = time.monotonic() + 240.0

        def pushed() -> bool:
            return any(o[0] == 'force' and o[4] == 1 and o[3][1] > 0.01 for o in out[-50:])

        while ((runner.counts['steps'] < 20 or sent_poses < len(path) or not pushed())
               and time.monotonic() < deadline):
            p = path[min(sent_poses, len(path) - 1)]
            runner.on_pose(pose(sent_poses, p), 0)
            runner.on_pose(pose(sent_poses, p), 1)
            sent_poses += 1
            time.sleep(1e-3)
    finally:
        assert runner.shutdown()
    print(f'{runner.counts["steps"]} steps, {sent_poses} poses in {time.monotonic() - t0:.1f} s')
    sent = forces(out)
    assert len(sent) == 2 * sent_poses                  # every pose answered, none waits for a round
    assert runner.counts['steps'] >= 20
    assert all(np.linalg.norm(s[3]) <= LIMIT + 1e-12 for s in sent)
    assert max(s[3][1] for s in sent if s[4] == 1) > 0.01


@pytest.mark.parametrize('names, error', [(['left', 'left'], 'named twice'), (['1st'], 'not a valid namespace'),
                                          (['a/b'], 'not a valid namespace'), ([], 'list of names'),
                                          (['left', ''], 'not a valid namespace')])
def test_instrument_names_that_are_not_distinct_namespaces_are_refused(names, error):
    from sph_tissue_sim.params import check_value

    assert error in check_value('instruments', names)


def test_several_instruments_run_in_either_mode_and_need_the_multirate_renderer():
    from sph_tissue_sim.core.errors import ConfigError

    p = {name: spec[0] for name, spec in SIM_PARAMS.items()} | BLOCK | TWO
    assert build_config(p).mode == 'global'
    assert build_config(p | {'mode': 'local'}).mode == 'local'
    with pytest.raises(ConfigError, match='multirate'):
        build_config(p | {'haptic_mode': 'direct'})


def test_two_live_instruments_half_a_period_apart_simulate_the_pose_time_once():
    """Each device's poses 1 ms apart, the second's half a period after the first's: the solver's
    steps add up to the pose time that passed, not to each device's own time counted again."""
    runner, out = make_runner(**TWO, timing_mode='live')
    runner.start()
    n = 400
    try:
        for k in range(n):
            p = (0.0, 0.01, 0.0)                     # above the tissue: cheap steps
            runner.on_pose(pose(k, p), 0)
            time.sleep(5e-4)
            runner.on_pose(Pose(T0_NS + k * MS + MS // 2, T0_NS + k * MS + MS // 2, 'omni_base', p,
                                (0.0, 0.0, 0.0, 1.0)), 1)
            time.sleep(5e-4)
    finally:
        assert runner.shutdown()
    span = (n - 1) * 1e-3 + 5e-4
    print(f'{runner.counts["steps"]} steps simulated {runner.solver.sim_time:.4f} s of {span:.4f} s of poses')
    assert runner.counts['steps'] > 10
    assert runner.solver.sim_time <= span + runner.p['max_dt']


def test_a_lockstep_grasp_applies_from_the_pose_after_its_stamp_whichever_arrives_first():
    """The driver sends a button change before the pose it came with; DDS may still deliver the pose
    first. Either way the grasp applies from the next pose on: the forces repeat bit for bit."""
    runs = []
    for button_first in (True, False):
        runner, out = make_runner(timing_mode='lockstep', step_thread=False)
        run_grasp_lift(lambda k, p: runner.on_pose(pose(k, p)),
                       lambda: runner.on_grasp(0, True, T0_NS + GRASP_AT * MS), button_first)
        runs.append(np.array([f[3] for f in forces(out)]))
        assert runner.solver.instruments[0].holding > 0
    assert runs[0].tobytes() == runs[1].tobytes()
    assert runs[0][-1][1] < -0.02                        # and it pulls


def test_a_periodic_state_stamped_by_the_wall_clock_neither_blocks_nor_repeats_a_lockstep_grasp():
    """The driver also sends its state at 100 Hz, stamped by the wall clock (far from a replayed
    bag's stamps): such a state only repeats the button, and must not hold back the change stamped
    with its sample, whichever arrives first."""
    runner, _ = make_runner(timing_mode='lockstep', step_thread=False)
    ch = runner.channels[0]
    wall = T0_NS + 10 ** 15
    runner.on_grasp(0, True, wall)                     # a periodic state after the change, first
    runner.on_grasp(0, True, T0_NS + 5 * MS)           # the change
    for k in range(200):
        runner.on_grasp(0, True, wall + k * 10 * MS)   # more periodic ones: nothing queued
    assert ch.grasps == [(T0_NS + 5 * MS, True)]
    runner.on_pose(pose(5, (0.0, 0.01, 0.0)))
    assert not ch.closed
    runner.on_pose(pose(6, (0.0, 0.01, 0.0)))
    assert ch.closed and ch.grasps == []
    runner.on_grasp(0, False, T0_NS + 9 * MS)
    runner.on_pose(pose(10, (0.0, 0.01, 0.0)))
    assert not ch.closed
