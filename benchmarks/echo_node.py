#!/usr/bin/env python3
"""The floor under sim_node's round trip: a node that answers every pose with a zero wrench at once.

Same transport as ``sim_node`` in multirate live mode (``omni/pose`` in, ``omni/force_feedback``
out, best effort, history depth 10, the ``EventsExecutor`` of :func:`tissue_common.node_start.
spin_until_stopped`, the same GIL switch interval) and no simulation: ``sim_latency.py --peer`` times
it with the same probe, so what sim_node adds to the round trip is the difference. Not a product
node; the benchmarks start it as a script.
"""

from __future__ import annotations

import sys

import rclpy
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sph_tissue_sim.runner import MULTIRATE_MIN_DEPTH
from sph_tissue_sim.sim_node import SWITCH_INTERVAL
from tissue_common.node_start import spin_until_stopped, stop_on_signals


class EchoNode(Node):
    """omni/pose -> a zero omni/force_feedback with the pose's header."""

    def __init__(self) -> None:
        super().__init__('echo_node')
        qos = QoSProfile(depth=MULTIRATE_MIN_DEPTH, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.BEST_EFFORT)
        self.answered = 0
        self._reply = WrenchStamped()
        self.pub = self.create_publisher(WrenchStamped, 'omni/force_feedback', qos)
        self.sub = self.create_subscription(PoseStamped, 'omni/pose', self._on_pose, qos)

    def _on_pose(self, msg: PoseStamped) -> None:
        self.answered += 1
        self._reply.header = msg.header
        self.pub.publish(self._reply)


def main() -> int:
    rclpy.init()
    sys.setswitchinterval(SWITCH_INTERVAL)
    node = EchoNode()
    stop = stop_on_signals()
    try:
        spin_until_stopped(node, stop, on_spinning=lambda: node.get_logger().info(
            'ready: echo (no simulation)'))
    except KeyboardInterrupt:
        pass
    finally:
        node.get_logger().info(f'totals: {node.answered} poses, {node.answered} answered')
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
