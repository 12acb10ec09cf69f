"""A sphere: the tip of a probe (the simulator's default tool)."""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import SweptSphere


class Sphere(SweptSphere):
    """A sphere of ``radius`` [m] centred at the pose's position (orientation has no effect)."""

    name = 'sphere'
    oriented = False

    @classmethod
    def from_dimensions(cls, radius: float, length: float = 0.0) -> 'Sphere':
        """The sphere of ``radius`` (a sphere has no length)."""
        return cls(radius)

    def __init__(self, radius: float) -> None:
        if not radius > 0.0:
            raise ConfigError(f'tool_radius must be > 0 m, got {radius}')
        self.radius = float(radius)

    def segment(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        p = position.tolist()
        return np.array((p, p))
