"""A steady force-command stream in its own process (no GIL shared with the test), for driver tests.

    python force_sender.py OUT_FILE FX FY FZ [PERIOD]

Publishes omni/force_feedback (best effort, depth 1, stamped with the system clock) every PERIOD
seconds (default 0.001) until SIGINT or SIGTERM, then writes the monotonic send times, one per
line, to OUT_FILE (CLOCK_MONOTONIC is shared by all processes of the machine).
"""

from __future__ import annotations

import signal
import sys
import threading
import time


def main(argv: list[str]) -> int:
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    out, force = argv[0], [float(v) for v in argv[1:4]]
    period = float(argv[4]) if len(argv) > 4 else 0.001
    stop = threading.Event()
    rclpy.init()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = rclpy.create_node('force_sender')
    pub = node.create_publisher(WrenchStamped, 'omni/force_feedback',
                                QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    msg = WrenchStamped()
    msg.header.frame_id = 'omni_base'
    msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = force
    times = []
    print('sending', flush=True)
    while not stop.is_set():
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
        pub.publish(msg)
        times.append(time.monotonic())
        stop.wait(period)
    with open(out, 'w') as f:
        f.write('\n'.join(f'{t:.9f}' for t in times))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
