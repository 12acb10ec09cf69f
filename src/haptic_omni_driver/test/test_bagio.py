"""Pure tests of rosbag2 MCAP bag reading/writing and replay bag validation."""

import json
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from haptic_omni_driver import bagio
from haptic_omni_driver.backends.replay import ReplayBackend, load_replay
from haptic_omni_driver.errors import BagError
from omni_test_utils import make_pose_bag, pose_msg, wrench_msg


def test_write_then_read_returns_messages_in_order(tmp_path):
    msgs = make_pose_bag(tmp_path / 'b', n=20)
    out = list(bagio.read_bag(tmp_path / 'b'))
    assert [o[0] for o in out] == ['/omni/pose'] * 20
    assert [o[2] for o in out] == sorted(o[2] for o in out)
    for (_, msgtype, _, msg), ref in zip(out, msgs):
        assert msgtype == bagio.POSE_TYPE
        assert msg.header.stamp.sec == ref.header.stamp.sec
        assert msg.header.stamp.nanosec == ref.header.stamp.nanosec
        assert msg.pose.position.x == ref.pose.position.x


def test_raw_read_returns_the_cdr_bytes_written(tmp_path):
    store = bagio.typestore()
    msg = pose_msg(5_000_000_123, (0.1, 0.2, 0.3))
    raw = bytes(store.serialize_cdr(msg, bagio.POSE_TYPE))
    bagio.write_bag(tmp_path / 'b', [('/omni/pose', bagio.POSE_TYPE, 7, raw)])
    [(_, _, stamp, data)] = list(bagio.read_bag(tmp_path / 'b', raw=True))
    assert stamp == 7 and data == raw


def test_rclpy_messages_are_stored_as_rclpy_cdr_and_decode_equal(tmp_path):
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message

    m = PoseStamped()
    m.header.frame_id = 'omni_base'
    m.header.stamp.sec, m.header.stamp.nanosec = 12, 345
    m.pose.position.x = 0.25
    m.pose.orientation.w = 1.0
    bagio.write_bag(tmp_path / 'b', [('/omni/pose', bagio.POSE_TYPE, 1, m)])
    [(_, _, _, data)] = list(bagio.read_bag(tmp_path / 'b', raw=True))
    # CDR alignment padding is unspecified (Fast CDR leaves it uninitialised), so bytes are only
    # comparable when passed through untouched; the decoded values must agree both ways.
    assert deserialize_message(data, PoseStamped) == m
    [(_, _, _, msg)] = list(bagio.read_bag(tmp_path / 'b'))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345)
    assert msg.header.frame_id == 'omni_base' and msg.pose.position.x == 0.25


def test_metadata_is_rosbag2_v9_mcap_with_ros_type_hashes(tmp_path):
    from tissue_msgs.msg import DeviceState

    state = DeviceState(backend='replay', button1=True)  # an rclpy message is accepted too
    bagio.write_bag(tmp_path / 'b', [
        ('/omni/pose', bagio.POSE_TYPE, 1, pose_msg(1, (0, 0, 0))),
        ('/omni/state', bagio.STATE_TYPE, 2, state),
        ('/omni/force_feedback', bagio.WRENCH_TYPE, 3, wrench_msg(1, (0.1, 0, 0)))])
    meta = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    assert meta['message_count'] == 3
    topics = {t['topic_metadata']['name']: t['topic_metadata'] for t in meta['topics_with_message_count']}
    assert set(topics) == {'/omni/pose', '/omni/state', '/omni/force_feedback'}
    # The hash of our custom message equals the one rosidl generated when tissue_msgs was built.
    share = Path(bagio._find_msg_file('DeviceState.msg')).with_suffix('.json')
    if share.is_file():
        ref = json.loads(share.read_text())['type_hashes'][0]['hash_string']
        assert topics['/omni/state']['type_description_hash'] == ref
    assert topics['/omni/pose']['type_description_hash'].startswith('RIHS01_')
    assert topics['/omni/pose']['offered_qos_profiles'][0]['reliability'] == 'reliable'
    assert (tmp_path / 'b' / 'b.mcap').is_file()
    decoded = [m for t, _, _, m in bagio.read_bag(tmp_path / 'b') if t == '/omni/state'][0]
    assert decoded.backend == 'replay' and decoded.button1


def test_version_8_metadata_on_request(tmp_path):
    bagio.write_bag(tmp_path / 'b', [('/omni/pose', bagio.POSE_TYPE, 1, pose_msg(1, (0, 0, 0)))],
                    version=8)
    meta = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())
    assert meta['rosbag2_bagfile_information']['version'] == 8


def test_writer_refuses_to_overwrite(tmp_path):
    make_pose_bag(tmp_path / 'b', n=2)
    with pytest.raises(BagError, match='already exists'):
        make_pose_bag(tmp_path / 'b', n=2)


def test_read_bag_filters_topics_with_or_without_slash(tmp_path):
    bagio.write_bag(tmp_path / 'b', [
        ('/omni/pose', bagio.POSE_TYPE, 1, pose_msg(1, (0, 0, 0))),
        ('/omni/force_feedback', bagio.WRENCH_TYPE, 2, wrench_msg(1, (0.1, 0, 0)))])
    assert [t for t, *_ in bagio.read_bag(tmp_path / 'b', topics=['omni/force_feedback'])] == [
        '/omni/force_feedback']


def test_missing_bag_is_a_clear_error(tmp_path):
    with pytest.raises(BagError, match='bag not found'):
        list(bagio.read_bag(tmp_path / 'nope'))


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


def test_bag_without_pose_topic_is_rejected(tmp_path):
    bagio.write_bag(tmp_path / 'b', [('/other', bagio.WRENCH_TYPE, 1, wrench_msg(1, (0, 0, 0)))])
    with pytest.raises(BagError, match="no pose topic '/omni/pose'"):
        load_replay(tmp_path / 'b')


def test_pose_topic_of_wrong_type_is_rejected(tmp_path):
    bagio.write_bag(tmp_path / 'b', [('/omni/pose', bagio.WRENCH_TYPE, 1, wrench_msg(1, (0, 0, 0)))])
    with pytest.raises(BagError, match='expected geometry_msgs/msg/PoseStamped'):
        load_replay(tmp_path / 'b')


def test_empty_bag_is_rejected(tmp_path):
    with bagio.BagWriter(tmp_path / 'b') as w:
        w.add_topic('/omni/pose', bagio.POSE_TYPE)
    with pytest.raises(BagError, match='empty'):
        load_replay(tmp_path / 'b')


def test_pose_topic_in_bag_is_remappable(tmp_path):
    make_pose_bag(tmp_path / 'b', n=3, topic='/left/omni/pose')
    events = load_replay(tmp_path / 'b', pose_topic='left/omni/pose')
    assert [e.sample.position[0] for e in events] == pytest.approx([0.0, 0.001, 0.002])


class _Sink:
    def __init__(self):
        self.samples, self.times, self.finished = [], [], None

    def on_sample(self, s):
        self.samples.append(s)
        self.times.append(time.monotonic())

    def wait_for_subscribers(self):
        return True

    def wait_for_reply(self, stamp_ns, timeout):
        return False

    def on_finished(self, summary, code):
        self.finished = (summary, code)

    def log(self, level, text):
        pass


class _Clock:
    """A monotonic clock that only the replay's own waits advance (and its stop event's wait)."""

    def __init__(self):
        self.now = 1000.0

    def monotonic(self):
        return self.now

    def wait(self, delay):
        self.now += delay
        return False


def test_timed_replay_keeps_recorded_spacing_divided_by_rate(tmp_path, monkeypatch):
    from haptic_omni_driver.backends import replay

    make_pose_bag(tmp_path / 'b', n=41, period_ns=10_000_000)  # 0.4 s of poses
    backend = ReplayBackend(tmp_path / 'b', rate=2.0)
    # on the wall clock a busy machine would stretch the span: time here is what the replay waits
    clock = _Clock()
    monkeypatch.setattr(replay, 'time', clock)
    monkeypatch.setattr(backend._stop, 'wait', clock.wait)
    sink = _Sink()
    sink.on_sample = lambda s: (sink.samples.append(s), sink.times.append(clock.now))
    backend.run(sink)
    span = sink.times[-1] - sink.times[0]
    assert span == pytest.approx(0.2, abs=1e-9)
    assert np.diff(sink.times) == pytest.approx(0.005, abs=1e-9)
    assert sink.finished[1] == 0 and sink.finished[0].startswith('replay finished: 41 poses')
    assert [s.stamp_ns for s in sink.samples] == [1_700_000_000_123_000_000 + k * 10_000_000
                                                  for k in range(41)]


def test_lockstep_abort_returns_exit_code_3(tmp_path):
    make_pose_bag(tmp_path / 'b', n=5)
    backend = ReplayBackend(tmp_path / 'b', mode='lockstep', lockstep_timeout=0.01,
                            timeout_action='abort')
    sink = _Sink()
    backend.run(sink)
    assert len(sink.samples) == 1 and sink.finished[1] == 3


def test_lockstep_resend_repeats_the_pose_then_continues(tmp_path):
    make_pose_bag(tmp_path / 'b', n=2)
    backend = ReplayBackend(tmp_path / 'b', mode='lockstep', lockstep_timeout=0.005,
                            timeout_action='resend', max_resends=2)
    sink = _Sink()
    backend.run(sink)
    stamps = [s.stamp_ns for s in sink.samples]
    assert len(stamps) == 6 and len(set(stamps[:3])) == 1 and backend.timeouts == 6
