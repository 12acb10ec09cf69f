"""Suite-wide pytest hooks (the ROS fixtures are the plugin tissue_testing.fixtures, see pytest.ini)."""

import pytest

# pytest.ini's timeout (300 s) catches a hung test; a test marked slow does minutes of numerical
# work that a loaded 2-core machine can stretch several times over, so it gets a longer leash.
SLOW_TIMEOUT = 1800


def pytest_collection_modifyitems(items):
    for item in items:
        if item.get_closest_marker('slow') and not item.get_closest_marker('timeout'):
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT))
