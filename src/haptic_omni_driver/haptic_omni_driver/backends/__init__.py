"""Backends of omni_driver: openhaptics (libHD via ctypes), replay (rosbag2 MCAP), scripted."""

BACKENDS = ('openhaptics', 'replay', 'scripted')
