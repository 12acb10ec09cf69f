"""Pure tests of the rosbag2 MCAP bag writer: metadata, message encodings, unwritable output."""

import errno
import json
from pathlib import Path

import pytest
import yaml

from haptic_omni_driver.bag_reader import read_bag
from haptic_omni_driver.bag_types import POSE_TYPE, STATE_TYPE, WRENCH_TYPE, _find_msg_file
from haptic_omni_driver.bag_writer import BagWriter, write_bag
from haptic_omni_driver.errors import BagError, OutputError
from omni_test_utils import make_pose_bag, pose_msg, wrench_msg


def test_rclpy_messages_are_stored_as_rclpy_cdr_and_decode_equal(tmp_path):
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message

    m = PoseStamped()
    m.header.frame_id = 'omni_base'
    m.header.stamp.sec, m.header.stamp.nanosec = 12, 345
    m.pose.position.x = 0.25
    m.pose.orientation.w = 1.0
    write_bag(tmp_path / 'b', [('/omni/pose', POSE_TYPE, 1, m)])
    [(_, _, _, data)] = list(read_bag(tmp_path / 'b', raw=True))
    # CDR alignment padding is unspecified (Fast CDR leaves it uninitialised), so bytes are only
    # comparable when passed through untouched; the decoded values must agree both ways.
    assert deserialize_message(data, PoseStamped) == m
    [(_, _, _, msg)] = list(read_bag(tmp_path / 'b'))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345)
    assert msg.header.frame_id == 'omni_base' and msg.pose.position.x == 0.25


def test_metadata_is_rosbag2_v9_mcap_with_ros_type_hashes(tmp_path):
    from tissue_msgs.msg import DeviceState

    state = DeviceState(backend='replay', button1=True)  # an rclpy message is accepted too
    write_bag(tmp_path / 'b', [
        ('/omni/pose', POSE_TYPE, 1, pose_msg(1, (0, 0, 0))),
        ('/omni/state', STATE_TYPE, 2, state),
        ('/omni/force_feedback', WRENCH_TYPE, 3, wrench_msg(1, (0.1, 0, 0)))])
    meta = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    assert meta['message_count'] == 3
    topics = {t['topic_metadata']['name']: t['topic_metadata'] for t in meta['topics_with_message_count']}
    assert set(topics) == {'/omni/pose', '/omni/state', '/omni/force_feedback'}
    # The hash of our custom message equals the one rosidl generated when tissue_msgs was built.
    share = Path(_find_msg_file('DeviceState.msg')).with_suffix('.json')
    if share.is_file():
        ref = json.loads(share.read_text())['type_hashes'][0]['hash_string']
        assert topics['/omni/state']['type_description_hash'] == ref
    assert topics['/omni/pose']['type_description_hash'].startswith('RIHS01_')
    assert topics['/omni/pose']['offered_qos_profiles'][0]['reliability'] == 'reliable'
    assert (tmp_path / 'b' / 'b.mcap').is_file()
    decoded = [m for t, _, _, m in read_bag(tmp_path / 'b') if t == '/omni/state'][0]
    assert decoded.backend == 'replay' and decoded.button1


def test_version_8_metadata_on_request(tmp_path):
    write_bag(tmp_path / 'b', [('/omni/pose', POSE_TYPE, 1, pose_msg(1, (0, 0, 0)))],
                    version=8)
    meta = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())
    assert meta['rosbag2_bagfile_information']['version'] == 8


def test_writer_refuses_to_overwrite(tmp_path):
    make_pose_bag(tmp_path / 'b', n=2)
    with pytest.raises(BagError, match='already exists'):
        make_pose_bag(tmp_path / 'b', n=2)


# -- unwritable output ----------------------------------------------------------------------------
def test_output_under_a_file_is_a_clear_error(tmp_path):
    (tmp_path / 'afile').write_text('x')
    with pytest.raises(OutputError, match=r'afile is a file, not a folder'):
        BagWriter(tmp_path / 'afile' / 'sub' / 'bag')


def test_read_only_file_system_is_a_clear_error_and_leaves_nothing(tmp_path, monkeypatch):
    def refuse(self, *a, **kw):
        raise OSError(errno.EROFS, 'Read-only file system', str(self))

    monkeypatch.setattr(Path, 'mkdir', refuse)
    with pytest.raises(OutputError, match='cannot create bag folder .*Read-only file system'):
        BagWriter(tmp_path / 'bag')
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def test_a_refused_mcap_file_removes_the_folder_it_created(tmp_path, monkeypatch):
    import builtins

    real_open = builtins.open

    def refuse(file, mode='r', *a, **kw):
        if str(file).endswith('.mcap') and 'x' in mode:
            raise OSError(errno.ENOSPC, 'No space left on device', str(file))
        return real_open(file, mode, *a, **kw)

    monkeypatch.setattr(builtins, 'open', refuse)
    with pytest.raises(OutputError, match='No space left on device'):
        BagWriter(tmp_path / 'bag')
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
