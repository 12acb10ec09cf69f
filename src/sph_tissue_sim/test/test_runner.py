"""sim_node's run loop without ROS (:mod:`sph_tissue_sim.runner`): the pose inbox of each mode,
the answers, the interrupt of a reset, run-time parameter changes."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from sim_probe import BLOCK, T0_NS, press_path
from sph_tissue_sim.params import SIM_PARAMS, build_config, build_material, build_model
from sph_tissue_sim.runner import Pose, Runner, make_solver, pose_history

LIMIT = 0.5
MS = 1_000_000


def make_runner(**over) -> tuple[Runner, list]:
    """A runner on the 256-particle block; what it sends lands in the returned list as
    ('force', stamp, frame, force), ('metrics', stamp, haptic status) or ('log', level, text)."""
    p = {name: spec[0] for name, spec in SIM_PARAMS.items()} | BLOCK | {'force_limit': LIMIT, **over}
    model = build_model(p)
    solver = make_solver(model, build_material(p), build_config(p), p['nominal_dt'])
    out = []
    runner = Runner(p, model, solver, lambda stamp, frame, f: out.append(('force', stamp, frame, np.array(f))),
                    lambda stamp, res, s, h: out.append(('metrics', stamp, h)),
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
    step = runner.solver.step
    runner.solver.step = lambda *a: (gate.acquire(), gate.release(), step(*a))[2]
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
