"""The tool protocol: what the solver needs to know of a tool, whatever its shape."""

from __future__ import annotations

from typing import Protocol

import numpy as np

#: identity orientation (no rotation) of a tool pose
NO_ROTATION = np.eye(3)


class Tool(Protocol):
    """A rigid tool, posed in the tissue frame by a position [m] and a 3x3 rotation matrix.

    The contact kernels see every tool as a segment swept by a sphere of ``radius``
    (:mod:`~sph_tissue_sim.core.contact`): a shape is defined by the segment it puts where, for a
    pose. The pose's position is the tool's tip, the point the device drives.
    """

    name: str
    radius: float            # [m] radius of the swept sphere
    oriented: bool           # whether the pose's orientation moves the shape
    cuts: bool               # whether its edge breaks the bonds it loads (:mod:`..cutting`)
    pierces: bool            # whether it enters the tissue past its puncture force (:mod:`..needle`)

    def segment(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """(2, 3) ends of the tool's core segment in the tissue frame [m]."""

    def bounding_radius(self) -> float:
        """[m] every point of the tool lies within this of its position."""

    @classmethod
    def from_dimensions(cls, radius: float, length: float = 0.0) -> 'Tool':
        """The tool with these dimensions [m] (those a shape has no use for are ignored)."""


class SweptSphere:
    """Signed distance and contact normal of any tool given by :meth:`Tool.segment` (numpy)."""

    name = 'swept sphere'
    radius = 0.0
    oriented = True
    cuts = False
    pierces = False

    def segment(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def bounding_radius(self) -> float:
        seg = self.segment(np.zeros(3), NO_ROTATION)
        return float(np.linalg.norm(seg, axis=1).max()) + self.radius

    def signed_distance(self, points, position, rotation=NO_ROTATION) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance [m] of ``points`` (M, 3) from the tool's surface (negative inside) and
        the unit outward normal of the surface there (M, 3), for the tool at this pose."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        a, b = self.segment(np.asarray(position, dtype=np.float64), np.asarray(rotation, dtype=np.float64))
        d = b - a
        dd = float(d @ d)
        t = np.clip((p - a) @ d / dd, 0.0, 1.0) if dd > 0.0 else np.zeros(len(p))
        e = p - (a + t[:, None] * d)
        r = np.linalg.norm(e, axis=1)
        n = np.divide(e, r[:, None], out=np.zeros_like(e), where=r[:, None] > 0.0)
        return r - self.radius, n
