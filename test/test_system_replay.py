"""System regression: the bundled bags replayed in lockstep through driver, sim and viz processes.

Each short bag in bags/ carries the force the simulation returned when it was recorded (see
bags/README.md). Replaying its poses in lockstep through a freshly started sim_node with the same
parameters (bags/golden_sim_params.yaml) must return the same forces: the loop is deterministic
(lockstep, stamps from the bag, fixed parameters), so we require bit-identical wrenches on the kind
of CPU that made them (bags/golden_host.json), and everywhere the stated tolerance of 1e-9 N, with
the largest difference reported when they are not bit-identical.
"""

from __future__ import annotations

import contextlib
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


def golden(bag, instrument: str = '') -> tuple[list[int], dict[int, tuple]]:
    """Pose stamps in order and stamp -> golden force (fx, fy, fz, tx, ty, tz) of one instrument of a
    bundled bag."""
    ns = f'/{instrument}' if instrument else ''
    poses, forces = [], {}
    for topic, _, _, msg in read_bag(bag, [f'{ns}/omni/pose', f'{ns}/omni/force_feedback']):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if topic.endswith('/omni/pose'):
            poses.append(stamp)
        else:
            f, t = msg.wrench.force, msg.wrench.torque
            forces[stamp] = (f.x, f.y, f.z, t.x, t.y, t.z)
    return poses, forces


def _bits(values) -> bytes:
    return struct.pack(f'<{len(values)}d', *values)


@pytest.mark.parametrize('name', graph.SHORT_BAGS)
def test_lockstep_replay_returns_the_golden_forces_and_the_graph_shuts_down_clean(name, tmp_path):
    """Every instrument of the bag (two for ``bimanual``, each replayed by its own driver in its
    namespace) gets its golden forces back."""
    bag = graph.BAGS / name
    instruments = graph.bag_instruments(name)
    goldens = [golden(bag, i) for i in instruments]
    for pose_stamps, gold in goldens:
        assert len(gold) == len(pose_stamps) > 1000
    env = harness.ros_env()
    report = tmp_path / 'report' if name == 'press' else None
    viz = graph.viz(report, env=env, params={'diagnostics_rate': 5.0, 'window': 1.0,
                                             'instruments': list(instruments)})
    # histories deeper than the session on the sim's force writer and the monitor's readers: the
    # driver paces the loop, and a monitor that falls behind on a busy machine must not lose replies
    depth = 2 * max(len(g[0]) for g in goldens)
    sim = graph.sim('lockstep', env=env, params={'qos_depth': depth, **graph.BAG_SIM_PARAMS.get(name, {})})
    drivers = [graph.driver_replay(bag, 'lockstep', env=env, subscribers=3, instrument=i,
                                   params={'diagnostics_rate': 5.0}) for i in instruments]
    procs = [*drivers, sim, viz]
    try:
        viz.start()
        sim.start()
        viz.wait_for_output(graph.VIZ_READY, timeout=60)
        sim.wait_for_output(graph.SIM_READY, timeout=180)
        with contextlib.ExitStack() as stack:
            mons = [stack.enter_context(graph.Monitor(env, reliable=True, depth=depth, namespace=i))
                    for i in instruments]
            for mon in mons:
                mon.probe_sim()
            t0 = time.monotonic()
            for drv in drivers:
                drv.start()
            for drv in drivers:
                assert drv.wait(240) == 0, drv.output()
            replay_s = time.monotonic() - t0
            for mon, (pose_stamps, _) in zip(mons, goldens):
                mon.wait_for(lambda: mon.n_forces >= len(pose_stamps), 60,
                             f'all {len(pose_stamps)} replies seen')
            # diagnostics come at 5 Hz from driver and viz; wait for both once the loop ran
            mon = mons[0]
            mon.wait_for(lambda: {'driver', 'viz'} <= mon.diagnostic_sources(), 30,
                         'diagnostics from omni_driver and viz_node')
            got, n_forces, all_metrics = [], [], []
            for m in mons:
                with m.lock:
                    got.append({s: f for s, _, f in m.wrenches})
                    n_forces.append(m.n_forces)
                    all_metrics.append(m.last_metrics)
            with mon.lock:
                metrics, n_metrics = mon.last_metrics, mon.metrics_count
                cloud, n_clouds = mon.last_particles, mon.particles_count
    finally:
        codes = graph.stop_all(procs, timeout=30)

    # -- the golden forces, bit for bit --------------------------------------------------------
    made_on = json.loads(graph.GOLDEN_HOST.read_text())
    for instrument, (pose_stamps, gold), mine, n in zip(instruments, goldens, got, n_forces):
        what = f'{name} {instrument}'.strip()
        assert n == len(pose_stamps), f'{what}: {n} replies for {len(pose_stamps)} poses'
        assert sorted(mine) == pose_stamps
        worst = max(max(abs(a - b) for a, b in zip(mine[s], gold[s])) for s in pose_stamps)
        assert worst <= FORCE_TOLERANCE, (
            f'{what}: forces differ from the golden by up to {worst:.3e} N (tolerance '
            f'{FORCE_TOLERANCE} N): an intended physics change needs regenerated goldens, see '
            f'bags/README.md')
        differing = [s for s in pose_stamps if _bits(mine[s]) != _bits(gold[s])]
        if graph.host_kind() == made_on:
            assert not differing, f'{what}: {len(differing)} forces not bit-identical (max diff {worst:.3e} N)'
        elif differing:
            warnings.warn(f'{what}: {len(differing)} forces differ in their last bits (up to {worst:.3e} N) '
                          f'on this CPU ({graph.host_kind()}), within the tolerance; the goldens were '
                          f'made on {made_on}')
        peak = max(math.sqrt(sum(v * v for v in gold[s][:3])) for s in pose_stamps)
        assert peak > 0.05, f'{what}: the session never pressed the tissue (peak {peak:.3f} N)'
        print(f'{what}: {len(pose_stamps)} poses replayed in lockstep in {replay_s:.2f} s, peak golden '
              f'force {peak:.3f} N, max diff {worst:.1e} N')
    if len(instruments) > 1:
        # each instrument's own metrics: its tool where its device's offset puts it (left 20 mm to -x,
        # right 20 mm to +x of the shared origin; the scripts' own x differ by 5 mm)
        assert all(m is not None for m in all_metrics), 'an instrument\'s tissue/metrics never came'
        tips = [m.tool_position.x for m in all_metrics]
        assert tips[1] - tips[0] == pytest.approx(0.045, abs=0.002), f'instruments {instruments} at x = {tips}'

    # -- particles, metrics and diagnostics arrived --------------------------------------------
    assert n_metrics > 0 and metrics is not None
    assert metrics.n_particles > 0
    assert all(math.isfinite(v) for v in (metrics.sim_time, metrics.max_displacement,
                                          metrics.kinetic_energy, metrics.step_wall_time))
    assert n_clouds > 0 and cloud is not None
    assert cloud.width * cloud.height == metrics.n_particles
    assert {'x', 'y', 'z'} <= {f.name for f in cloud.fields}

    # -- clean shutdown, no orphans, the viz report --------------------------------------------
    assert codes == {p.name: 0 for p in procs}, (
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
        assert shots.rest.peak < 1e-4 < shots.deepest.peak and shots.deepest.tools[0] is not None
        assert {'tissue_rest.png', 'tissue_deepest.png', 'tissue_press.gif'} <= set(summary['files'])
