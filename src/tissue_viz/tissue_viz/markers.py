"""Tool and force marker geometry (pure Python + numpy, no rclpy).

The device publishes the stylus tip in ``omni_base``. If the node is given the device→tissue map
used by the simulator, the markers are drawn in the ``tissue`` frame instead:
``p_tissue = R (scale * p_device) + t`` for positions and ``R f`` for forces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from tissue_common.rotation import quaternion_matrix

from tissue_viz.errors import VizConfigError


@dataclass
class ToolFrame:
    """Where to draw the tool: the device frame as is, or mapped into the tissue frame."""

    frame_id: str = 'omni_base'
    to_tissue: bool = False
    translation: tuple = (0.0, 0.0, 0.0)       # [m]
    rotation: tuple = (0.0, 0.0, 0.0, 1.0)     # quaternion x, y, z, w
    scale: float = 1.0                         # device workspace → tissue scale

    def __post_init__(self) -> None:
        if len(self.translation) != 3 or not all(math.isfinite(v) for v in self.translation):
            raise VizConfigError(f'translation must be 3 finite numbers, got {self.translation}')
        if len(self.rotation) != 4:
            raise VizConfigError(f'rotation must be a quaternion x, y, z, w, got {self.rotation}')
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise VizConfigError(f'workspace scale must be > 0, got {self.scale}')
        try:
            self._r = quaternion_matrix(self.rotation)
        except ValueError as exc:
            raise VizConfigError(str(exc)) from exc
        self._t = np.asarray(self.translation, dtype=float)

    def point(self, p) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        return self._r @ (self.scale * p) + self._t if self.to_tissue else p

    def vector(self, v) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        return self._r @ v if self.to_tissue else v


def force_arrow(tip, force, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Arrow start and end for the force on the tool: from the tool tip along F, |F|·scale long."""
    tip = np.asarray(tip, dtype=float)
    return tip, tip + scale * np.asarray(force, dtype=float)
