"""Tool, force, held-particle and cut-face marker geometry and colours (pure Python + numpy, no rclpy).

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


#: (r, g, b) of instrument k's tool, force and held particles when there are several, and of the
#: particles one instrument holds (matplotlib's tab10: distinct on the report's white and RViz's grey)
INSTRUMENT_COLOURS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
                      (0.58, 0.40, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.74, 0.74, 0.13))


def instrument_colour(k: int) -> tuple[float, float, float]:
    """The colour of instrument ``k`` (the ``instruments`` order; the held byte's k + 1)."""
    return INSTRUMENT_COLOURS[k % len(INSTRUMENT_COLOURS)]


#: (r, g, b) of the cut faces' dots (the particles that lost bonds to a blade)
CUT_COLOUR = (0.1, 0.1, 0.1)


def cut_faces(xyz: np.ndarray, severed: np.ndarray) -> np.ndarray:
    """The positions (m, 3) of the particles that lost bonds to a cut (the cloud's ``severed``
    byte above 0), leaving out those the cut removed (NaN)."""
    return xyz[(severed > 0) & np.isfinite(xyz).all(axis=1)]


def held_positions(xyz: np.ndarray, held: np.ndarray, instruments: int) -> list[np.ndarray]:
    """Per instrument k the positions (m, 3) of the particles it holds: where the cloud's ``held``
    byte is k + 1 (:mod:`sph_tissue_sim.cloud`)."""
    return [xyz[held == k + 1] for k in range(instruments)]


def force_arrow(tip, force, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Arrow start and end for the force on the tool: from the tool tip along F, |F|·scale long."""
    tip = np.asarray(tip, dtype=float)
    return tip, tip + scale * np.asarray(force, dtype=float)
