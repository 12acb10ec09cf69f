"""The bundled bags (no ROS processes): readable by rosbags and the replay backend, complete goldens,
device-clock timing, and poses that are exactly the documented session scripts.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from tissue_testing import system_graph as graph
from haptic_omni_driver.backends.replay import load_replay
from haptic_omni_driver.bag_reader import read_bag
from haptic_omni_driver.bag_types import POSE_TYPE, STATE_TYPE, WRENCH_TYPE, typestore

sys.path.insert(0, str(graph.BAGS))
import make_bags  # noqa: E402
from sessions import Geometry, session_trajectory, topic  # noqa: E402

ALL_BAGS = (*graph.SHORT_BAGS, 'long')


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


@pytest.mark.parametrize('name', ALL_BAGS)
def test_bundled_bag_is_a_complete_golden_on_the_device_clock(name):
    from rosbags.highlevel import AnyReader

    bag = graph.BAGS / name
    instruments = graph.bag_instruments(name)
    with AnyReader([bag], default_typestore=typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert {c.msgtype for c in reader.connections} == {POSE_TYPE, WRENCH_TYPE, STATE_TYPE}
    assert set(counts) == set(make_bags.topics(name))
    for instrument in instruments:
        pose_topic, force_topic = topic(instrument, 'omni/pose'), topic(instrument, 'omni/force_feedback')
        assert counts[pose_topic] == counts[force_topic] > 1000
        assert counts[topic(instrument, 'omni/state')] > 0

        poses, forces = [], []
        for name_, _, log_ns, msg in read_bag(bag, [pose_topic, force_topic]):
            (poses if name_ == pose_topic else forces).append((log_ns, _stamp(msg), msg))
        # every pose answered exactly once, by a force carrying its stamp in the device frame
        assert sorted(s for _, s, _ in forces) == [s for _, s, _ in poses]
        assert all(m.header.frame_id == 'omni_base' for _, _, m in forces)
        # log time = device time, 1 kHz: timed replay plays the session at its real rate
        assert all(log == s for log, s, _ in poses)
        assert np.all(np.diff([s for _, s, _ in poses]) == 1_000_000)
        norms = np.array([np.linalg.norm([m.wrench.force.x, m.wrench.force.y, m.wrench.force.z])
                          for _, _, m in forces])
        assert np.all(np.isfinite(norms)) and norms.max() <= 3.3 + 1e-12
        assert norms.max() > 0.05 and (norms == 0).any()  # contact and free motion both present
        duration = (poses[-1][1] - poses[0][1]) * 1e-9
        if name == 'long':
            assert duration >= 60.0
        # the replay backend reads it: every pose, in order, with the bag's own CDR bytes
        events = load_replay(bag, pose_topic)
        samples = [e.sample for e in events if e.sample is not None]
        assert [s.stamp_ns for s in samples] == [s for _, s, _ in poses]
        raw = [r for *_, r in read_bag(bag, [pose_topic], raw=True)]
        assert [s.raw for s in samples] == raw


@pytest.mark.parametrize('name', ALL_BAGS)
def test_bundled_bag_poses_are_exactly_the_session_script(name):
    rate, seed, t0 = make_bags.PLAN[name]
    for instrument in graph.bag_instruments(name):
        _, positions, buttons, _ = session_trajectory(name, rate, Geometry(), seed, instrument=instrument)
        pose_topic = topic(instrument, 'omni/pose')
        got = np.array([(m.pose.position.x, m.pose.position.y, m.pose.position.z)
                        for *_, m in read_bag(graph.BAGS / name, [pose_topic])])
        assert got.shape == positions.shape
        assert np.array_equal(got, positions)  # bit for bit: the bag is the documented script
        first = next(m for *_, m in read_bag(graph.BAGS / name, [pose_topic]))
        assert _stamp(first) == t0


def test_session_of_two_instruments_gives_each_its_own_script_and_tremor():
    rate, seed, _ = make_bags.PLAN['bimanual']
    left = session_trajectory('bimanual', rate, Geometry(), seed, instrument='left')
    right = session_trajectory('bimanual', rate, Geometry(), seed, instrument='right')
    assert left[0].shape == right[0].shape           # one round of poses each, in lockstep
    assert left[2].any() and not right[2].any()      # only the left hand closes its jaw
    assert not np.array_equal(left[1], right[1])


def test_bundled_bags_stay_small():
    total = sum(f.stat().st_size for f in graph.BAGS.rglob('*') if f.is_file())
    assert total < 8e6, f'bags/ is {total / 1e6:.1f} MB'


def test_make_bags_retries_a_recording_whose_driver_gave_up(monkeypatch, tmp_path):
    calls = []

    def record(name, input_bag, raw, timeout):
        calls.append(raw.name)
        if len(calls) == 1:   # the driver's lockstep wait ran out (a loaded machine)
            raise make_bags.IncompleteRecording('omni_driver exited with 3')

    def finalise(raw, out, expected, names):
        out.mkdir(parents=True)
        (out / 'metadata.yaml').write_text(raw.name)
        return {'poses': expected}

    monkeypatch.setattr(make_bags, 'record', record)
    monkeypatch.setattr(make_bags, 'finalise', finalise)
    counts = make_bags.make('press', tmp_path, Geometry())
    assert calls == ['press_raw1', 'press_raw2']
    assert (tmp_path / 'press' / 'metadata.yaml').read_text() == 'press_raw2'
    assert counts['poses'] > 1000


def test_make_bags_stops_after_three_failed_recordings(monkeypatch, tmp_path):
    def record(name, input_bag, raw, timeout):
        raise make_bags.IncompleteRecording('omni_driver exited with 3')

    monkeypatch.setattr(make_bags, 'record', record)
    with pytest.raises(SystemExit, match='no complete recording in 3 attempts'):
        make_bags.make('press', tmp_path, Geometry())
