"""What every package of the simulator shares, defined once.

- :mod:`.force`: the device's force limits and the exact norm clamp (numpy only).
- :mod:`.stamps`: ROS time stamps as integer nanoseconds.
- :mod:`.rotation`: quaternion <-> rotation matrix (numpy only).
- :mod:`.throttle`: at most one log line per kind of event and period, every event counted.
- :mod:`.node_start`: a node's start-up and shutdown: an unparsable command line as one sentence,
  Ctrl-C / SIGTERM as a flag (these import rclpy, lazily).
"""
