"""Pure tests of the rosbag2 MCAP bag reader: message order, raw bytes, topics, clear errors."""

import pytest

from haptic_omni_driver.backends.replay import load_replay
from haptic_omni_driver.bag_reader import read_bag
from haptic_omni_driver.bag_types import POSE_TYPE, WRENCH_TYPE, typestore
from haptic_omni_driver.bag_writer import write_bag
from haptic_omni_driver.errors import BagError
from omni_test_utils import make_pose_bag, pose_msg, wrench_msg


def test_write_then_read_returns_messages_in_order(tmp_path):
    msgs = make_pose_bag(tmp_path / 'b', n=20)
    out = list(read_bag(tmp_path / 'b'))
    assert [o[0] for o in out] == ['/omni/pose'] * 20
    assert [o[2] for o in out] == sorted(o[2] for o in out)
    for (_, msgtype, _, msg), ref in zip(out, msgs):
        assert msgtype == POSE_TYPE
        assert msg.header.stamp.sec == ref.header.stamp.sec
        assert msg.header.stamp.nanosec == ref.header.stamp.nanosec
        assert msg.pose.position.x == ref.pose.position.x


def test_raw_read_returns_the_cdr_bytes_written(tmp_path):
    store = typestore()
    msg = pose_msg(5_000_000_123, (0.1, 0.2, 0.3))
    raw = bytes(store.serialize_cdr(msg, POSE_TYPE))
    write_bag(tmp_path / 'b', [('/omni/pose', POSE_TYPE, 7, raw)])
    [(_, _, stamp, data)] = list(read_bag(tmp_path / 'b', raw=True))
    assert stamp == 7 and data == raw


def test_read_bag_filters_topics_with_or_without_slash(tmp_path):
    write_bag(tmp_path / 'b', [
        ('/omni/pose', POSE_TYPE, 1, pose_msg(1, (0, 0, 0))),
        ('/omni/force_feedback', WRENCH_TYPE, 2, wrench_msg(1, (0.1, 0, 0)))])
    assert [t for t, *_ in read_bag(tmp_path / 'b', topics=['omni/force_feedback'])] == [
        '/omni/force_feedback']


def test_missing_bag_is_a_clear_error(tmp_path):
    with pytest.raises(BagError, match='bag not found'):
        list(read_bag(tmp_path / 'nope'))


def test_folder_without_metadata_is_not_a_bag(tmp_path):
    (tmp_path / 'b').mkdir()
    with pytest.raises(BagError, match='no metadata.yaml'):
        load_replay(tmp_path / 'b')


def test_corrupt_mcap_is_a_clear_error(tmp_path):
    make_pose_bag(tmp_path / 'b', n=200)
    mcap = tmp_path / 'b' / 'b.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])  # truncated: no summary, broken chunk
    with pytest.raises(BagError):
        load_replay(tmp_path / 'b')


def test_garbage_metadata_is_a_clear_error(tmp_path):
    make_pose_bag(tmp_path / 'b', n=2)
    (tmp_path / 'b' / 'metadata.yaml').write_text('::: not yaml [')
    with pytest.raises(BagError, match='corrupt or unreadable'):
        load_replay(tmp_path / 'b')
