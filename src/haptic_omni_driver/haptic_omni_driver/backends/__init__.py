"""Device backends: openhaptics (libHD via ctypes), replay (rosbag2 MCAP), scripted."""
