"""When a node warns that Fast DDS's shared-memory transport can stall it."""

import pytest

from tissue_common.transport import SAFE_TRANSPORTS, shared_memory_warning


@pytest.mark.parametrize('environ', [
    {},                                                       # Jazzy's default RMW and transports
    {'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'},
    {'RMW_IMPLEMENTATION': 'rmw_fastrtps_dynamic_cpp', 'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'},
    {'FASTDDS_BUILTIN_TRANSPORTS': 'DEFAULT'},
    {'FASTDDS_BUILTIN_TRANSPORTS': ''},                       # Fast DDS reads an empty value as DEFAULT
    {'FASTDDS_BUILTIN_TRANSPORTS': 'large_data?max_msg_size=1MB'},
    # the RMW adds shared memory for a localhost-only range, whatever the builtin transports say
    {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
])
def test_fast_dds_with_shared_memory_is_warned_about_with_the_setting_that_avoids_it(environ):
    text = shared_memory_warning(environ)
    assert text is not None
    assert f'FASTDDS_BUILTIN_TRANSPORTS={SAFE_TRANSPORTS}' in text


@pytest.mark.parametrize('environ', [
    {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'},
    {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'},
    {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv6'},
    {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'},
    {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp', 'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'},
    {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/lab/fastdds.xml'},  # the profile chooses
    {'FASTDDS_DEFAULT_PROFILES_FILE': '/etc/lab/fastdds.xml'},
])
def test_transports_without_shared_memory_or_chosen_by_a_profile_get_no_warning(environ):
    assert shared_memory_warning(environ) is None


def test_a_profile_file_does_not_hide_an_explicit_shared_memory_choice():
    environ = {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/lab/fastdds.xml',
               'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'}
    assert shared_memory_warning(environ) is not None
