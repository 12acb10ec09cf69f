"""Frames as transforms, their messages, and /tf where tf2_msgs exists (a stand-in type here)."""

import math
import sys
import types

import numpy as np
import pytest

from tissue_common.frames import TfBroadcaster, Transform, from_msg
from tissue_common.rotation import quaternion_matrix

QUARTER_X = (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))     # +90 degrees about x


def test_a_transform_maps_child_points_into_the_parent_frame():
    tr = Transform('tissue', 'omni_base', np.array([0.01, -0.02, 0.03]), np.array(QUARTER_X))
    # +90 degrees about x: child y (the device's up) is parent z (the tissue's up)
    assert tr.apply([0.0, 1.0, 0.0]) == pytest.approx([0.01, -0.02, 1.03])
    assert tr.apply([0.0, 0.0, 1.0]) == pytest.approx([0.01, -1.02, 0.03])
    back = Transform.from_matrix('tissue', 'omni_base', quaternion_matrix(QUARTER_X), [0.01, -0.02, 0.03])
    assert back.rotation == pytest.approx(np.array(QUARTER_X)) and back.apply([1, 2, 3]) == \
        pytest.approx(tr.apply([1, 2, 3]))


def test_the_message_carries_the_frames_and_values_exactly():
    from builtin_interfaces.msg import Time

    tr = Transform('tissue', 'omni_base', np.array([0.1, 0.2, 0.3]), np.array(QUARTER_X))
    msg = tr.to_msg(Time(sec=12, nanosec=34))
    assert (msg.header.frame_id, msg.child_frame_id, msg.header.stamp.sec) == ('tissue', 'omni_base', 12)
    again = from_msg(msg)
    assert (again.parent, again.child) == ('tissue', 'omni_base')
    assert np.array_equal(again.translation, tr.translation) and np.array_equal(again.rotation, tr.rotation)


class FakeNode:
    def __init__(self):
        self.logs, self.publishers = [], []

    def get_logger(self):
        return self

    def info(self, text):
        self.logs.append(text)

    def create_publisher(self, kind, topic, qos):
        pub = types.SimpleNamespace(kind=kind, topic=topic, qos=qos, sent=[])
        pub.publish = pub.sent.append
        self.publishers.append(pub)
        return pub


def test_without_tf2_msgs_nothing_is_sent_and_the_node_says_so_once(monkeypatch):
    monkeypatch.setitem(sys.modules, 'tf2_msgs', None)           # as on this PyPI-only install
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)
    node = FakeNode()
    tf = TfBroadcaster(node, static=True)
    tf.send(['anything'])
    assert not tf.available and node.publishers == []
    assert node.logs == ['tf2_msgs is not installed here: nothing on /tf_static (every ROS 2 install '
                         'has it)']


@pytest.mark.parametrize('static, topic', [(True, '/tf_static'), (False, '/tf')])
def test_with_tf2_msgs_the_transforms_go_out_in_one_tfmessage(monkeypatch, static, topic):
    from rclpy.qos import DurabilityPolicy

    class TFMessage:
        def __init__(self, transforms):
            self.transforms = transforms

    msg_mod = types.ModuleType('tf2_msgs.msg')
    msg_mod.TFMessage = TFMessage
    monkeypatch.setitem(sys.modules, 'tf2_msgs', types.ModuleType('tf2_msgs'))
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', msg_mod)
    node = FakeNode()
    tf = TfBroadcaster(node, static=static)
    tf.send(['a', 'b'])
    (pub,) = node.publishers
    assert tf.available and pub.topic == topic and pub.kind is TFMessage
    assert [m.transforms for m in pub.sent] == [['a', 'b']]
    # /tf_static is latched: a viewer started later still gets the device's place
    assert (pub.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL) == static
