"""System regression: the bundled bags replayed in lockstep through driver, sim and viz processes.

Each short bag in bags/ carries the force the simulation returned when it was recorded (see
bags/README.md). Replaying its poses in lockstep through a freshly started sim_node with the same
parameters (bags/golden_sim_params.yaml) must return the same forces: the loop is deterministic
(lockstep, stamps from the bag, fixed parameters), so we require bit-identical wrenches on the kind
of CPU that made them (bags/golden_host.json), and everywhere the stated tolerance of 1e-9 N, with
the largest difference reported when they are not bit-identical.
"""

from __future__ import annotations

import json
import math
import struct
import time
import warnings

import pytest

from tissue_testing import harness
from tissue_testing import system_graph as graph
from haptic_omni_driver.bag_reader import read_bag

pytestmark = pytest.mark.ros

#: [N] stated tolerance on each force component against the golden
FORCE_TOLERANCE = 1e-9


def golden(bag) -> tuple[list[int], dict[int, tuple]]:
    """Pose stamps in order and stamp -> golden force (fx, fy, fz, tx, ty, tz) of a bundled bag."""
    poses, forces = [], {}
    for topic, _, _, msg in read_bag(bag, ['/omni/pose', '/omni/force_feedback']):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if topic == '/omni/pose':
            poses.append(stamp)
        else:
            f, t = msg.wrench.force, msg.wrench.torque
            forces[stamp] = (f.x, f.y, f.z, t.x, t.y, t.z)
    return poses, forces


def _bits(values) -> bytes:
    return struct.pack(f'<{len(values)}d', *values)


@pytest.mark.parametrize('name', graph.SHORT_BAGS)
def test_lockstep_replay_returns_the_golden_forces_and_the_graph_shuts_down_clean(name, tmp_path):
    bag = graph.BAGS / name
    pose_stamps, gold = golden(bag)
    assert len(gold) == len(pose_stamps) > 1000
    env = harness.ros_env()
    report = tmp_path / 'report' if name == 'press' else None
    viz = graph.viz(report, env=env, params={'diagnostics_rate': 5.0, 'window': 1.0})
    # histories deeper than the session on the sim's force writer and the monitor's readers: the
    # driver paces the loop, and a monitor that falls behind on a busy machine must not lose replies
    depth = 2 * len(pose_stamps)
    sim = graph.sim('lockstep', env=env, params={'qos_depth': depth, **graph.BAG_SIM_PARAMS.get(name, {})})
    drv = graph.driver_replay(bag, 'lockstep', env=env, subscribers=3,
                              params={'diagnostics_rate': 5.0})
    procs = [drv, sim, viz]
    try:
        viz.start()
        sim.start()
        viz.wait_for_output(graph.VIZ_READY, timeout=60)
        sim.wait_for_output(graph.SIM_READY, timeout=180)
        with graph.Monitor(env, reliable=True, depth=depth) as mon:
            mon.probe_sim()
            t0 = time.monotonic()
            drv.start()
            assert drv.wait(240) == 0, drv.output()
            replay_s = time.monotonic() - t0
            mon.wait_for(lambda: mon.n_forces >= len(pose_stamps), 60,
                         f'all {len(pose_stamps)} replies seen')
            # diagnostics come at 5 Hz from driver and viz; wait for both once the loop ran
            mon.wait_for(lambda: {'driver', 'viz'} <= mon.diagnostic_sources(), 30,
                         'diagnostics from omni_driver and viz_node')
            with mon.lock:
                got = {s: f for s, _, f in mon.wrenches}
                n_forces = mon.n_forces
                metrics, n_metrics = mon.last_metrics, mon.metrics_count
                cloud, n_clouds = mon.last_particles, mon.particles_count
    finally:
        codes = graph.stop_all(procs, timeout=30)

    # -- the golden forces, bit for bit --------------------------------------------------------
    assert n_forces == len(pose_stamps), f'{n_forces} replies for {len(pose_stamps)} poses'
    assert sorted(got) == pose_stamps
    worst = max(max(abs(a - b) for a, b in zip(got[s], gold[s])) for s in pose_stamps)
    assert worst <= FORCE_TOLERANCE, (
        f'{name}: forces differ from the golden by up to {worst:.3e} N (tolerance '
        f'{FORCE_TOLERANCE} N): an intended physics change needs regenerated goldens, see '
        f'bags/README.md')
    differing = [s for s in pose_stamps if _bits(got[s]) != _bits(gold[s])]
    made_on = json.loads(graph.GOLDEN_HOST.read_text())
    if graph.host_kind() == made_on:
        assert not differing, f'{len(differing)} forces not bit-identical (max diff {worst:.3e} N)'
    elif differing:
        warnings.warn(f'{name}: {len(differing)} forces differ in their last bits (up to {worst:.3e} N) '
                      f'on this CPU ({graph.host_kind()}), within the tolerance; the goldens were made '
                      f'on {made_on}')
    peak = max(math.sqrt(sum(v * v for v in gold[s][:3])) for s in pose_stamps)
    assert peak > 0.05, f'{name}: the session never pressed the tissue (peak {peak:.3f} N)'

    # -- particles, metrics and diagnostics arrived --------------------------------------------
    assert n_metrics > 0 and metrics is not None
    assert metrics.n_particles > 0
    assert all(math.isfinite(v) for v in (metrics.sim_time, metrics.max_displacement,
                                          metrics.kinetic_energy, metrics.step_wall_time))
    assert n_clouds > 0 and cloud is not None
    assert cloud.width * cloud.height == metrics.n_particles
    assert {'x', 'y', 'z'} <= {f.name for f in cloud.fields}

    # -- clean shutdown, no orphans, the viz report --------------------------------------------
    assert codes == {'omni_driver': 0, 'sim_node': 0, 'viz_node': 0}, (
        codes, sim.output()[-2000:], viz.output()[-2000:])
    for p in procs:
        assert not graph.group_alive(p), f'{p.name} left processes behind'
    if report is not None:
        assert (report / 'index.html').is_file(), viz.output()[-2000:]
        assert list(report.glob('*.png'))
        # every stream of a lockstep replay runs on the bag's clock from its first message
        summary = json.loads((report / 'summary.json').read_text())
        assert summary['backwards_stamps'] == {'metrics': 0, 'particles': 0, 'pose': 0, 'force': 0}
        # the organ itself, from the clouds viz_node received: pressed, with the tool drawn
        from tissue_viz.tissue_images import TissueSnapshots

        shots = TissueSnapshots.load(report / 'tissue_snapshots.npz')
        assert shots.rest.peak < 1e-4 < shots.deepest.peak and shots.deepest.tool is not None
        assert {'tissue_rest.png', 'tissue_deepest.png', 'tissue_press.gif'} <= set(summary['files'])
    print(f'{name}: {len(pose_stamps)} poses replayed in lockstep in {replay_s:.2f} s, peak golden '
          f'force {peak:.3f} N, max diff {worst:.1e} N')
