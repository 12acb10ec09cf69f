"""Fixtures for real-process ROS 2 tests: a pytest plugin every package's tests get through
``pytest.ini`` (``-p tissue_testing.fixtures``), so no test folder needs a conftest of its own."""

from __future__ import annotations

import os

import pytest

from . import harness


@pytest.fixture(scope='session', autouse=True)
def response_store(tmp_path_factory):
    """The organ's responses on disk (sph_tissue_sim's response_store) in a folder of this run,
    shared by its tests, its pytest-xdist workers and the node processes they start, never the
    user's cache (the store writes each response whole and renames it, so sharing is safe)."""
    saved = os.environ.get('SPH_TISSUE_CACHE')
    if os.environ.get('PYTEST_XDIST_WORKER'):
        folder = tmp_path_factory.getbasetemp().parent / 'responses'
        folder.mkdir(exist_ok=True)
    else:
        folder = tmp_path_factory.mktemp('responses')
    os.environ['SPH_TISSUE_CACHE'] = str(folder)
    yield folder
    if saved is None:
        os.environ.pop('SPH_TISSUE_CACHE', None)
    else:
        os.environ['SPH_TISSUE_CACHE'] = saved


@pytest.fixture(scope='module')
def ros_domain():
    """Isolate this test module on its own ROS_DOMAIN_ID with localhost-only discovery."""
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    domain = harness.new_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    yield domain
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture
def rclpy_node(ros_domain):
    """An initialised rclpy context and a probe node; ``node.spin_until(pred, timeout)`` spins it."""
    import rclpy

    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('test_probe', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.spin_until = lambda predicate, timeout=10.0: harness.spin_until(
        node, predicate, timeout, executor=executor)
    node.executor_for_test = executor
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
