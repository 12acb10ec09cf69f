"""A capsule: an instrument shaft with a rounded tip, oriented by the stylus."""

from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError
from .base import SweptSphere


class Capsule(SweptSphere):
    """A cylinder of ``radius`` [m] and ``length`` [m] with hemispherical ends.

    The tip's centre is at the pose's position and the shaft runs from there along the tool
    frame's +z axis (``rotation[:, 2]`` in the tissue frame), so the shaft can press the surface
    as well as the tip.
    """

    name = 'capsule'
    oriented = True

    @classmethod
    def from_dimensions(cls, radius: float, length: float = 0.0) -> 'Capsule':
        return cls(radius, length)

    def __init__(self, radius: float, length: float) -> None:
        if not radius > 0.0:
            raise ConfigError(f'tool_radius must be > 0 m, got {radius}')
        if not (math.isfinite(length) and length >= 0.0):
            raise ConfigError(f'tool_length must be >= 0 m, got {length}')
        self.radius = float(radius)
        self.length = float(length)

    def segment(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        p0, p1, p2 = (float(c) for c in position)
        L = self.length
        return np.array([[p0, p1, p2],
                         [p0 + L * rotation[0, 2], p1 + L * rotation[1, 2], p2 + L * rotation[2, 2]]])
