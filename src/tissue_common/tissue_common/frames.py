"""The graph's coordinate frames as transforms, and /tf where the install has it.

Three frames put the stylus, the tool and the tissue in one scene (RViz2's fixed frame ``tissue``;
the names are the nodes' parameters, defaults shown)::

    tissue  --(static, sim_node: the device map)-->  omni_base  --(omni_driver: the pose)-->  omni_stylus

A :class:`Transform` maps a point of its ``child`` frame into its ``parent`` frame, ``p_parent =
R p_child + t``, as ``geometry_msgs/TransformStamped`` and tf2 state it. The simulator's device map
``p_tissue = R (s p_device) + origin`` is such a transform only for the workspace scale ``s = 1``;
with another scale the static transform carries its rotation and origin, and a stylus drawn through
tf sits at its unscaled offset (the simulated tool, drawn in ``tissue`` by viz_node, is exact).

tf2_msgs is part of every ROS 2 install but not of the PyPI wheels this workspace can use, so
:class:`TfBroadcaster` publishes ``tf2_msgs/TFMessage`` on ``/tf`` or ``/tf_static`` when it can
be imported and otherwise nothing (saying so once); the transforms' values also travel in plain
``TransformStamped`` messages the nodes publish (``tissue/device_frame``), which is where the tests
here read them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rotation import matrix_quaternion, quaternion_matrix

@dataclass(frozen=True)
class Transform:
    """``child`` -> ``parent``: ``p_parent = R p_child + translation``, R from ``rotation`` (x, y, z, w)."""

    parent: str
    child: str
    translation: np.ndarray
    rotation: np.ndarray

    @classmethod
    def from_matrix(cls, parent: str, child: str, rotation: np.ndarray,
                    translation) -> 'Transform':
        return cls(parent, child, np.asarray(translation, dtype=np.float64).reshape(3),
                   matrix_quaternion(np.asarray(rotation, dtype=np.float64)))

    def apply(self, p_child) -> np.ndarray:
        """The parent-frame point [m] of a child-frame point."""
        return quaternion_matrix(self.rotation) @ np.asarray(p_child, dtype=np.float64) + self.translation

    def to_msg(self, stamp_msg):
        """``geometry_msgs/TransformStamped`` at ``stamp_msg`` (a builtin_interfaces/Time)."""
        from geometry_msgs.msg import TransformStamped

        msg = TransformStamped()
        # copied, not shared: a caller's stamp message is often reused for the next sample
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_msg.sec, stamp_msg.nanosec
        msg.header.frame_id = self.parent
        msg.child_frame_id = self.child
        t, q = msg.transform.translation, msg.transform.rotation
        t.x, t.y, t.z = (float(v) for v in self.translation)
        q.x, q.y, q.z, q.w = (float(v) for v in self.rotation)
        return msg


def from_msg(msg) -> Transform:
    """The :class:`Transform` of a ``geometry_msgs/TransformStamped``."""
    t, q = msg.transform.translation, msg.transform.rotation
    return Transform(msg.header.frame_id, msg.child_frame_id, np.array([t.x, t.y, t.z]),
                     np.array([q.x, q.y, q.z, q.w]))


class TfBroadcaster:
    """Sends transforms on ``/tf_static`` (``static``: latched, once per change) or ``/tf``.

    Without tf2_msgs (not on PyPI) it sends nothing; :attr:`available` says which, and the node
    logs it once.
    """

    def __init__(self, node, static: bool) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.topic = '/tf_static' if static else '/tf'
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.available, self._pub, self._type = False, None, None
            node.get_logger().info(f'tf2_msgs is not installed here: nothing on {self.topic} '
                                   '(every ROS 2 install has it)')
            return
        qos = (QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL) if static
               else QoSProfile(depth=100))
        self.available, self._type = True, TFMessage
        self._pub = node.create_publisher(TFMessage, self.topic, qos)

    def send(self, transforms: list) -> None:
        """Publish ``geometry_msgs/TransformStamped`` messages in one TFMessage."""
        if self._pub is not None:
            self._pub.publish(self._type(transforms=list(transforms)))
