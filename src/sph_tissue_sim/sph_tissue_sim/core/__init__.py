"""Numerical core of the simulator: numpy + numba only, never rclpy."""
