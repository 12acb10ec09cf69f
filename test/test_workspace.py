"""Plumbing of the built workspace: interfaces import, executables where ros2 run looks, DDS works."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tissue_testing import harness

PACKAGES = ('sph_tissue_sim', 'haptic_omni_driver', 'tissue_viz')


def _console_scripts(pkg: str) -> list[str]:
    """Executable names declared in a package's setup.py entry points."""
    tree = ast.parse((harness.REPO_ROOT / 'src' / pkg / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    return [ast.literal_eval(v).split('=')[0].strip() for v in value.elts]
    return []


def test_interfaces_import_in_built_workspace():
    from tissue_msgs.msg import DeviceState, SimMetrics
    from tissue_msgs.srv import ResetTissue

    metrics = SimMetrics()
    assert metrics.contact_index == 0 and len(metrics.n_layer) == 0
    assert (SimMetrics.SCHEME_PAPER, SimMetrics.SCHEME_TLSPH, SimMetrics.SCHEME_MASS_SPRING) == (0, 1, 2)
    assert (SimMetrics.MODE_GLOBAL, SimMetrics.MODE_LOCAL) == (0, 1)
    assert hasattr(DeviceState(), 'watchdog_tripped')
    assert hasattr(ResetTissue.Request(), 'keep_material')


@pytest.mark.parametrize('pkg', PACKAGES)
def test_every_console_script_is_installed_where_ros2_run_looks(pkg):
    scripts = _console_scripts(pkg)
    assert scripts, f'{pkg} declares no console_scripts'
    for exe in scripts:
        harness.executable(pkg, exe)


@pytest.mark.parametrize('pkg', PACKAGES + ('tissue_msgs', 'crtk_msgs'))
def test_package_is_registered_in_the_ament_index(pkg):
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory(pkg))
    assert (share / 'package.xml').is_file()


@pytest.mark.ros
def test_sim_metrics_cross_process_over_dds(rclpy_node):
    from tissue_msgs.msg import SimMetrics

    received = []
    sub = rclpy_node.create_subscription(SimMetrics, 'tissue/metrics', received.append, 10)
    proc = subprocess.Popen([sys.executable, str(harness.REPO_ROOT / 'test/tools/publish_metrics.py'),
                             '100', '0'], env=harness.ros_env(rclpy_node_domain(rclpy_node)),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        harness.wait_for_matching(rclpy_node, sub, timeout=30)
        assert rclpy_node.spin_until(lambda: len(received) >= 5, timeout=20), 'no SimMetrics arrived'
    finally:
        proc.terminate()
        proc.wait(10)
    msg = received[-1]
    assert msg.n_particles == 3670 and list(msg.n_layer) == [40, 60]
    assert msg.scheme == SimMetrics.SCHEME_TLSPH and msg.header.frame_id == 'tissue'
    # Messages come in publication order.
    seqs = [m.n_interaction for m in received]
    assert seqs == sorted(seqs)


def rclpy_node_domain(node) -> int:
    return node.context.get_domain_id()
