"""Pure tests of the replay backend: bag validation, timed replay and lockstep."""

import time

import numpy as np
import pytest

from haptic_omni_driver.backends.replay import ReplayBackend, load_replay
from haptic_omni_driver.bag_types import POSE_TYPE, WRENCH_TYPE
from haptic_omni_driver.bag_writer import BagWriter, write_bag
from haptic_omni_driver.errors import BagError
from omni_test_utils import make_pose_bag, wrench_msg


def test_bag_without_pose_topic_is_rejected(tmp_path):
    write_bag(tmp_path / 'b', [('/other', WRENCH_TYPE, 1, wrench_msg(1, (0, 0, 0)))])
    with pytest.raises(BagError, match="no pose topic '/omni/pose'"):
        load_replay(tmp_path / 'b')


def test_pose_topic_of_wrong_type_is_rejected(tmp_path):
    write_bag(tmp_path / 'b', [('/omni/pose', WRENCH_TYPE, 1, wrench_msg(1, (0, 0, 0)))])
    with pytest.raises(BagError, match='expected geometry_msgs/msg/PoseStamped'):
        load_replay(tmp_path / 'b')


def test_empty_bag_is_rejected(tmp_path):
    with BagWriter(tmp_path / 'b') as w:
        w.add_topic('/omni/pose', POSE_TYPE)
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
