"""System run at the live rate: a bag replayed at its recorded 1 kHz timing, sim in live mode.

No timing is asserted here (a loaded 2-core test machine decides the achieved rate; the numbers are
measured by benchmarks/system_live.py). The test checks that the graph keeps running through the
whole session and that every force is finite and within the limits: the sim's force_limit on
omni/force_feedback and the driver's clamp on what reaches the device (omni/state).
"""

from __future__ import annotations

import math
import re

import pytest
import yaml

from tissue_testing import harness
from tissue_testing import system_graph as graph
from haptic_omni_driver.bag_reader import read_bag

pytestmark = pytest.mark.ros


def _golden_param(name: str, default):
    doc = yaml.safe_load(graph.GOLDEN_SIM_PARAMS.read_text())
    for section in doc.values():
        params = section.get('ros__parameters', {})
        if name in params:
            return params[name]
    return default


def test_timed_replay_at_1khz_keeps_the_graph_running_with_finite_clamped_forces():
    bag = graph.BAGS / 'sweep'
    driver_limit = 0.88
    sim_limit = float(_golden_param('force_limit', 3.3))
    env = harness.ros_env()
    viz = graph.viz(None, env=env, params={'diagnostics_rate': 2.0})
    sim = graph.sim('live', env=env)
    drv = graph.driver_replay(bag, 'timed', env=env, subscribers=3,
                              params={'force_limit': driver_limit})
    procs = [drv, sim, viz]
    try:
        viz.start()
        sim.start()
        viz.wait_for_output(graph.VIZ_READY, timeout=60)
        sim.wait_for_output(graph.SIM_READY, timeout=180)
        with graph.Monitor(env) as mon:
            mon.probe_sim()
            drv.start()
            assert drv.wait(120) == 0, drv.output()
            # the graph is still up after the session: sim and viz alive, metrics still flowing
            assert sim.alive() and viz.alive(), (sim.output()[-2000:], viz.output()[-2000:])
            with mon.lock:
                forces = [f for _, _, f in mon.forces]
                states = [s for _, s in mon.states]
                n_poses, n_metrics = mon.n_poses, mon.metrics_count
                n_diag = len(mon.diagnostics)
    finally:
        codes = graph.stop_all(procs, timeout=30)

    # the driver played the whole session (its own count: best-effort readers here miss some)
    bag_poses = sum(1 for _ in read_bag(bag, ['/omni/pose'], raw=True))
    assert re.search(rf'replay finished: {bag_poses} poses', drv.output()), drv.output()[-2000:]
    # how many of them reached this monitor and were answered depends on the machine's load
    assert n_poses > 0 and forces, f'{len(forces)} force replies to {n_poses} poses'
    assert n_metrics > 0 and n_diag > 0
    norms = [math.sqrt(sum(v * v for v in f)) for f in forces]
    assert all(math.isfinite(n) for n in norms)
    assert max(norms) <= sim_limit + 1e-9
    assert max(norms) > 0.05, 'the sweep never touched the tissue'
    assert states, 'no omni/state received'
    device = [math.sqrt(s.commanded_force.x ** 2 + s.commanded_force.y ** 2
                        + s.commanded_force.z ** 2) for s in states]
    assert all(math.isfinite(d) and d <= driver_limit + 1e-9 for d in device)
    assert any(s.force_enabled for s in states)
    if max(norms) > driver_limit:
        assert any(s.force_clamped for s in states), 'forces above the limit were not flagged'
    assert codes == {'omni_driver': 0, 'sim_node': 0, 'viz_node': 0}, codes
    for p in procs:
        assert not graph.group_alive(p), f'{p.name} left processes behind'
