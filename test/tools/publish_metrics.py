"""Publish tissue_msgs/SimMetrics at a fixed rate until killed (a stand-in simulator for tests).

Usage: publish_metrics.py [rate_hz] [count]   (count 0 = forever)
"""

import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from tissue_msgs.msg import SimMetrics


def main() -> None:
    rate = float(sys.argv[1]) if len(sys.argv) > 1 else 50.0
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    rclpy.init()
    node = rclpy.create_node('metrics_publisher')
    pub = node.create_publisher(SimMetrics, 'tissue/metrics', 10)
    state = {'seq': 0}

    def tick() -> None:
        msg = SimMetrics()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = 'tissue'
        msg.n_particles = 3670
        msg.n_interaction = 120 + state['seq']
        msg.n_layer = [40, 60]
        msg.contact_index = 17
        msg.penetration = 0.002
        msg.contact_force.z = 0.5
        msg.step_wall_time = 1e-4
        msg.substeps = 2
        msg.scheme = SimMetrics.SCHEME_TLSPH
        msg.mode = SimMetrics.MODE_LOCAL
        pub.publish(msg)
        state['seq'] += 1
        if count and state['seq'] >= count:
            raise SystemExit(0)

    node.create_timer(1.0 / rate, tick)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException, SystemExit):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
