"""Test-side helpers for sim_node: a probe that sends poses and collects the node's replies."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from tissue_testing import harness

PKG = 'sph_tissue_sim'
# 8 x 8 x 4 cm block at 1 cm spacing: exactly 8 * 8 * 4 = 256 particles, bottom layer (64) fixed
BLOCK = {'model': 'block', 'block_size': [0.08, 0.08, 0.04], 'n_particles': 256,
         'particles_rate': 20.0, 'log_throttle': 0.0}
N_BLOCK = 256
START_TIMEOUT = 240.0  # numba recompiles every kernel after a core edit (tens of seconds on 2 cores)
T0_NS = 1_700_000_000_000_000_000
#: frame of the probe's handshake poses: sim_node rejects them (zero force in this frame, tissue not
#: stepped, clock not advanced), see :meth:`SimProbe.wait_matched`
HANDSHAKE_FRAME = 'sim_probe_handshake'


def sim(params: dict | None = None, **kw) -> harness.NodeProcess:
    return harness.NodeProcess(PKG, 'sim_node', params={**BLOCK, **(params or {})}, **kw)


def qos(reliable: bool, depth: int = 1000):
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT)


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def press_path(n: int, depth: float, start_height: float = 0.01) -> np.ndarray:
    """(n, 3) device positions from ``start_height`` above the surface point down to ``depth`` below
    it along device -y (the scripted driver's press)."""
    y = np.linspace(start_height, -depth, n)
    return np.stack([np.full(n, 1e-3), y, np.full(n, -5e-4)], axis=1)


#: the pose of :func:`grasp_lift_path` the jaw closes with (the press's last)
GRASP_AT = 40


def grasp_lift_path() -> list[np.ndarray]:
    """Device positions: a 1 mm press (40 poses), then a 4 mm lift (40) with the jaw closed."""
    path = list(press_path(GRASP_AT, depth=0.001))
    return path + [path[-1] + [0.0, 0.0001 * (j + 1), 0.0] for j in range(40)]


def run_grasp_lift(on_pose: Callable[[int, np.ndarray], None], close_jaw: Callable[[], None],
                   close_first: bool) -> None:
    """Feed :func:`grasp_lift_path` pose by pose (``on_pose(k, position)``); the jaw closes
    (``close_jaw()``, stamped with pose GRASP_AT) just before or just after that pose arrives: the
    driver sends it first, but DDS may deliver either first."""
    for k, position in enumerate(grasp_lift_path()):
        if k == GRASP_AT and close_first:
            close_jaw()
        on_pose(k, position)
        if k == GRASP_AT and not close_first:
            close_jaw()


class SimProbe:
    """Publishes omni/pose and collects omni/force_feedback, tissue/metrics and tissue/particles."""

    def __init__(self, node, reliable: bool = False, ns: str = '') -> None:
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from sensor_msgs.msg import PointCloud2
        from tissue_msgs.msg import SimMetrics

        self.node = node
        self.ns = ns
        self.orientation = (0.0, 0.0, 0.0, 1.0)   # of every pose published (x, y, z, w)
        self.pose_pub = node.create_publisher(PoseStamped, ns + 'omni/pose', qos(True))
        self.forces: dict[int, object] = {}
        self.force_order: list[int] = []
        self.metrics: list = []
        self.clouds: list = []
        self.handshakes_sent = 0      # handshake poses published (each counts as a rejected pose)
        self._handshake_replies = 0
        self.force_sub = node.create_subscription(WrenchStamped, ns + 'omni/force_feedback',
                                                  self._on_force, qos(reliable, 10000))
        self.metrics_sub = node.create_subscription(SimMetrics, ns + 'tissue/metrics',
                                                    self.metrics.append, qos(True, 10000))
        self.cloud_sub = node.create_subscription(PointCloud2, ns + 'tissue/particles',
                                                  self.clouds.append, qos(False, 5))
        self._msg = PoseStamped()

    def _on_force(self, msg) -> None:
        if msg.header.frame_id == HANDSHAKE_FRAME:
            self._handshake_replies += 1
            return
        ns = stamp_ns(msg.header)
        self.forces[ns] = msg
        self.force_order.append(ns)

    def wait_matched(self, proc, timeout: float = 60.0) -> None:
        """Wait until the node is ready and no reply to this probe can be lost to discovery.

        The subscriptions seeing the node's writers does not tell whether the node's force writer
        knows this probe's reader yet (a volatile writer drops what it sends before, more likely on a
        busy machine). So a pose in a foreign frame is sent until its answer arrives; the node
        rejects it without stepping or advancing its clock, and replies in that frame are not
        recorded.
        """
        proc.wait_for_output(r'ready:', START_TIMEOUT)
        for endpoint in (self.pose_pub, self.force_sub, self.metrics_sub, self.cloud_sub):
            harness.wait_for_matching(self.node, endpoint)
        n0 = self._handshake_replies
        deadline = time.monotonic() + timeout
        while self._handshake_replies == n0:
            assert time.monotonic() < deadline, f'no answer to a handshake pose within {timeout} s'
            self.publish((0.0, 0.0, 0.0), 1, frame=HANDSHAKE_FRAME)
            self.handshakes_sent += 1
            self.node.spin_until(lambda: self._handshake_replies > n0, 0.5)
        # a resent one still on its way would meet the test's first poses: let it be answered (a
        # best-effort answer may be lost, hence the bound)
        self.node.spin_until(lambda: self._handshake_replies >= self.handshakes_sent, 2.0)

    def publish(self, pos, ns: int, frame: str = 'omni_base') -> None:
        msg = self._msg
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(ns), 1_000_000_000)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pos)
        q = msg.pose.orientation
        q.x, q.y, q.z, q.w = (float(v) for v in self.orientation)
        self.pose_pub.publish(msg)

    def exchange(self, pos, ns: int, frame: str = 'omni_base', timeout: float = 10.0,
                 resend: float = 1.0):
        """Send one pose and wait for the wrench with its stamp (resent if a best-effort reply is
        lost: a repeated stamp is answered again without stepping)."""
        deadline = time.monotonic() + timeout
        self.forces.pop(ns, None)
        while True:
            self.publish(pos, ns, frame)
            if self.node.spin_until(lambda: ns in self.forces, min(resend, timeout)):
                return self.forces[ns]
            if time.monotonic() > deadline:
                raise AssertionError(f'no wrench for the pose stamped {ns}')

    def run_path(self, path: np.ndarray, t0_ns: int, period_ns: int = 1_000_000) -> list:
        """Exchange every pose of ``path`` in turn; returns the device-frame forces (n, 3)."""
        out = []
        for k, p in enumerate(path):
            w = self.exchange(p, t0_ns + k * period_ns)
            f = w.wrench.force
            out.append((f.x, f.y, f.z))
        return np.array(out)


def force_of(msg) -> np.ndarray:
    f = msg.wrench.force
    return np.array([f.x, f.y, f.z])


def finite_and_bounded(forces, limit: float) -> bool:
    forces = np.asarray(forces, dtype=float).reshape(-1, 3)
    return bool(np.all(np.isfinite(forces)) and np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-9))


def set_parameters(node, names_values: dict, node_name: str = '/sim_node', timeout: float = 20.0):
    """Call the node's set_parameters service; returns the list of SetParametersResult."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    client = node.create_client(SetParameters, f'{node_name}/set_parameters')
    try:
        assert node.spin_until(client.service_is_ready, timeout), 'set_parameters not available'
        req = SetParameters.Request()
        req.parameters = [Parameter(n, value=v).to_parameter_msg() for n, v in names_values.items()]
        fut = client.call_async(req)
        assert node.spin_until(fut.done, timeout), 'set_parameters did not answer'
        return fut.result().results
    finally:
        node.destroy_client(client)


def call_reset(node, keep_material: bool = True, timeout: float = 20.0, ns: str = ''):
    from tissue_msgs.srv import ResetTissue

    client = node.create_client(ResetTissue, ns + 'tissue/reset')
    try:
        assert node.spin_until(client.service_is_ready, timeout), 'tissue/reset not available'
        fut = client.call_async(ResetTissue.Request(keep_material=keep_material))
        assert node.spin_until(fut.done, timeout), 'tissue/reset did not answer'
        return fut.result()
    finally:
        node.destroy_client(client)


def norm(v) -> float:
    return math.sqrt(sum(float(x) ** 2 for x in v))
