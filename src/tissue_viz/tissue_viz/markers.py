"""Tool and force marker geometry (pure Python + numpy, no rclpy).

In the device frame the markers show the stylus tip (``omni/pose``) and the force sent to the
device. In the tissue frame they show the simulator's own tool (shape and pose, as it reports them
in ``tissue/metrics``) and the reaction of the tissue on it: no second copy of the device map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from tissue_common.rotation import matrix_quaternion


@dataclass
class ToolShape:
    """The tool to draw: its tip [m], unit shaft axis, shaft length [m] and radius [m], all in one
    frame. The simulator reports its tool in the tissue frame (``SimMetrics``); a device-frame
    drawing has only the stylus tip (no shaft)."""

    tip: np.ndarray
    axis: np.ndarray
    length: float
    radius: float

    @classmethod
    def from_metrics(cls, msg) -> 'ToolShape | None':
        """The simulated tool of a ``tissue_msgs/SimMetrics`` (None if it carries no usable tool)."""
        p, a = msg.tool_position, msg.tool_axis
        tip, axis = np.array([p.x, p.y, p.z]), np.array([a.x, a.y, a.z])
        values = [*tip, *axis, msg.tool_length, msg.tool_radius]
        if not all(math.isfinite(v) for v in values) or not msg.tool_radius > 0.0:
            return None
        return cls(tip, axis, max(float(msg.tool_length), 0.0), float(msg.tool_radius))

    def shaft_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Centre [m] and orientation (quaternion x, y, z, w) of a cylinder marker for the shaft
        (a marker cylinder runs along its own z axis), or None for a tool without a shaft."""
        n = float(np.linalg.norm(self.axis))
        if self.length <= 0.0 or not n > 0.0:
            return None
        z = self.axis / n
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        rot = np.column_stack([x, np.cross(z, x), z])
        return self.tip + 0.5 * self.length * z, matrix_quaternion(rot)


def force_arrow(tip, force, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Arrow start and end for the force on the tool: from the tool tip along F, |F|·scale long."""
    tip = np.asarray(tip, dtype=float)
    return tip, tip + scale * np.asarray(force, dtype=float)
