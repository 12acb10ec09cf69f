"""Re-export the shared ROS fixtures of test/conftest.py (a conftest only covers its own folder)."""

import importlib.util

from tissue_testing import harness

_spec = importlib.util.spec_from_file_location(
    'haptic_omni_driver_shared_conftest', harness.REPO_ROOT / 'test' / 'conftest.py')
_shared = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_shared)

ros_domain = _shared.ros_domain
rclpy_node = _shared.rclpy_node
