"""The user's guide, checked: two instruments side by side in namespaces, two devices on one tissue,
and CRTK names by remapping.

Two complete loops (omni_driver with its scripted stylus + sim_node on a small block) run at once on
one ROS domain, one under /left and one under /right, each with its own frame names; each loop's
forces answer its own poses only, both press their tissue, and the left driver's CRTK pose, remapped
as a CRTK client expects it (``omni/measured_cp:=measured_cp``), is at /left/measured_cp.
"""

from __future__ import annotations

import pytest

from tissue_testing import harness
from tissue_testing import system_graph as graph

pytestmark = pytest.mark.ros

BLOCK = {'model': 'block', 'block_size': [0.08, 0.08, 0.04], 'n_particles': 256,
         'particles_rate': 0.0, 'timing_mode': 'live'}
SCRIPT = {'approach_time': 0.3, 'press_time': 0.3, 'hold_time': 0.3, 'pull_time': 0.3,
          'release_time': 0.3, 'sweep_time': 0.3, 'return_time': 0.3, 'tremor_amplitude': 0.0,
          'loop': True}


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_two_instruments_in_namespaces_keep_their_loops_apart(rclpy_node):
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import qos_profile_sensor_data

    seen = {ns: {'pose': {}, 'force': []} for ns in ('left', 'right')}
    cps = []
    for ns in seen:
        rclpy_node.create_subscription(
            PoseStamped, f'/{ns}/omni/pose',
            lambda m, ns=ns: seen[ns]['pose'].__setitem__(stamp_ns(m.header), m), qos_profile_sensor_data)
        rclpy_node.create_subscription(
            WrenchStamped, f'/{ns}/omni/force_feedback',
            lambda m, ns=ns: seen[ns]['force'].append(m), qos_profile_sensor_data)
    rclpy_node.create_subscription(PoseStamped, '/left/measured_cp', cps.append,
                                   qos_profile_sensor_data)
    procs = []
    try:
        for ns, z0 in (('left', 0.0), ('right', 0.001)):
            frames = {'device_frame': f'{ns}/omni_base', 'tissue_frame': f'{ns}/tissue'}
            sim = graph.sim('live', golden=False, params={**BLOCK, **frames}, name=f'sim_{ns}',
                            ros_args=['-r', f'__ns:=/{ns}'])
            remap = ['-r', 'omni/measured_cp:=measured_cp'] if ns == 'left' else []
            drv = harness.NodeProcess('haptic_omni_driver', 'omni_driver', name=f'driver_{ns}',
                                      ros_args=['-r', f'__ns:=/{ns}', *remap],
                                      params={'backend': 'scripted', 'frame_id': f'{ns}/omni_base',
                                              'target': [0.0, z0, 0.0], **SCRIPT})
            procs += [sim.start(), drv]
        for p in procs[::2]:
            p.wait_for_output(graph.SIM_READY, timeout=240)
        for p in procs[1::2]:
            p.start()

        def pressed(ns):
            return sum(1 for m in seen[ns]['force'] if m.wrench.force.y > 0.05) >= 50

        assert rclpy_node.spin_until(lambda: pressed('left') and pressed('right') and len(cps) > 50,
                                     60), [p.output()[-1500:] for p in procs]
        # remapped: the CRTK name is where the client looks, and not under omni/ any more (the
        # graph learns of each publisher on its own: wait until both drivers' are known)
        assert rclpy_node.spin_until(lambda: rclpy_node.get_publishers_info_by_topic('/left/measured_cp')
                                     and rclpy_node.get_publishers_info_by_topic('/right/omni/measured_cp'), 30)
        assert rclpy_node.get_publishers_info_by_topic('/left/omni/measured_cp') == []
    finally:
        graph.stop_all(procs, timeout=30)
    for ns in seen:
        # a force answers a pose of its own instrument: the sim replies in the pose's frame
        assert seen[ns]['force'] and all(m.header.frame_id == f'{ns}/omni_base'
                                         for m in seen[ns]['force'])
        assert all(m.header.frame_id == f'{ns}/omni_base' for m in seen[ns]['pose'].values())
    assert all(c.header.frame_id == 'left/omni_base' for c in cps)


def test_two_devices_on_one_tissue_are_each_answered_for_their_own_press(rclpy_node):
    """The guide's two devices on one tissue: one sim_node with instruments [left, right] (local
    mode, the default) and a scripted driver in each namespace: each is answered, both press the
    same block 30 mm apart, and each namespace's metrics follow its own device."""
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from tissue_msgs.msg import SimMetrics

    deep = QoSProfile(depth=10000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
    seen = {ns: {'pressed': 0, 'metrics': []} for ns in ('left', 'right')}

    def on_force(m, ns: str) -> None:
        # counted as they come: re-counting every answer at each spin fell a minute behind the node
        seen[ns]['pressed'] += m.wrench.force.y > 0.05

    for ns in seen:
        rclpy_node.create_subscription(
            WrenchStamped, f'/{ns}/omni/force_feedback', lambda m, ns=ns: on_force(m, ns), deep)
        rclpy_node.create_subscription(SimMetrics, f'/{ns}/tissue/metrics',
                                       lambda m, ns=ns: seen[ns]['metrics'].append(m), 100)
    sim = graph.sim('live', golden=False, params={
        **BLOCK, 'instruments': ['left', 'right'],
        'instrument_offsets': [-0.015, 0.0, 0.0, 0.015, 0.0, 0.0]}, name='sim_hands').start()
    procs = [sim]
    try:
        sim.wait_for_output(graph.SIM_READY, timeout=240)
        for ns, z0 in (('left', 0.0), ('right', 0.001)):
            procs.append(harness.NodeProcess('haptic_omni_driver', 'omni_driver', name=f'driver_{ns}',
                                             ros_args=['-r', f'__ns:=/{ns}'],
                                             params={'backend': 'scripted', 'target': [0.0, z0, 0.0], **SCRIPT,
                                                     'pull_distance': 0.0, 'sweep_length': 0.0}).start())

        assert rclpy_node.spin_until(lambda: seen['left']['pressed'] >= 50 and seen['right']['pressed'] >= 50,
                                     60), [p.output()[-1500:] for p in procs]
    finally:
        codes = graph.stop_all(procs, timeout=30)
    assert codes['sim_hands'] == 0, sim.output()[-2000:]
    # each namespace's metrics follow its own device: pressing straight down (no pull, no sweep),
    # the tools 30 mm apart along x
    x = {}
    for ns in seen:
        touching = [m for m in seen[ns]['metrics'] if m.contact_force.z > 0.05]
        assert touching, ns
        x[ns] = touching[-1].tool_position.x
    assert abs(x['right'] - x['left'] - 0.03) < 0.003, x
    assert 'instruments left (device origin' in sim.output()
