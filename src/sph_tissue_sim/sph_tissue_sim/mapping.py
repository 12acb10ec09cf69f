"""Device space <-> tissue space (pure numpy, no rclpy).

The haptic device reports the stylus tip in its base frame ``omni_base`` (OpenHaptics: x right,
y up, z towards the user, metres). The tissue lives in the ``tissue`` frame (z up). A point maps as

    p_tissue = R (s * p_device) + anchor + translation

with ``R`` the rotation given as a unit quaternion (x, y, z, w), ``s`` the workspace scale, ``anchor``
a point of the model (e.g. where the tool first touches the top surface above the model centre)
and ``translation`` an extra offset [m]. Forces go the other way: ``f_device = k R^T f_tissue`` with
``k`` the force scale (``k = s`` keeps the energy exchanged equal on both sides of a scaled
workspace; the default 1 renders the tissue force unscaled).

The default quaternion (sin 45deg, 0, 0, cos 45deg) is +90deg about x: device y (up) -> tissue z
(up), device z (towards the user) -> tissue -y, device x -> tissue x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tissue_common.rotation import quaternion_matrix

from .core.errors import ConfigError

DEFAULT_ROTATION = (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))
ANCHORS = ('top_contact', 'top_surface', 'centre', 'origin')


def anchor_point(positions: np.ndarray, spacing: float, contact_reach: float, kind: str) -> np.ndarray:
    """Tissue point the device origin maps to (before ``translation``).

    Args:
        positions: (N, 3) reference particle positions [m].
        spacing: particle spacing [m].
        contact_reach: tool-centre to particle-centre distance at which contact starts [m].
        kind: ``top_contact`` -- the tool centre just touching the top particle above the centre
            of the model's x-y bounding box (a press of d metres below the device origin indents
            the tissue by d); ``top_surface`` -- the geometric top surface there (top particle
            centre + spacing/2); ``centre`` -- the bounding-box centre; ``origin`` -- (0, 0, 0).
    """
    if kind not in ANCHORS:
        raise ConfigError(f'anchor must be one of {", ".join(ANCHORS)}, got {kind!r}')
    if kind == 'origin':
        return np.zeros(3)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    centre = 0.5 * (lo + hi)
    if kind == 'centre':
        return centre
    # the highest particle in a column around the centre (a liver's top is not flat)
    r_xy = np.hypot(positions[:, 0] - centre[0], positions[:, 1] - centre[1])
    col = r_xy <= max(1.5 * spacing, float(r_xy.min()) + 1e-12)
    top = float(positions[col, 2].max())
    lift = contact_reach if kind == 'top_contact' else 0.5 * spacing
    return np.array([centre[0], centre[1], top + lift])


@dataclass
class DeviceMapping:
    """Rigid + scale map between the device frame and the tissue frame.

    Attributes:
        rotation: (3, 3) device -> tissue rotation.
        origin: (3,) tissue point of the device origin (anchor + translation) [m].
        scale: workspace scale s (tissue displacement per device displacement).
        force_scale: k in f_device = k R^T f_tissue.
    """

    rotation: np.ndarray
    origin: np.ndarray
    scale: float = 1.0
    force_scale: float = 1.0

    @classmethod
    def build(cls, quaternion, translation, scale: float, force_scale: float,
              anchor: np.ndarray) -> 'DeviceMapping':
        """Validate the parameters and build the map (raises ConfigError)."""
        try:
            rot = quaternion_matrix(quaternion)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        try:
            t = np.asarray(translation, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f'translation must be [x, y, z] metres, got {translation!r}') from exc
        if not np.all(np.isfinite(t)):
            raise ConfigError(f'translation must be finite, got {t.tolist()}')
        for name, v in (('workspace_scale', scale), ('force_scale', force_scale)):
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f'{name} must be > 0, got {v}')
        return cls(rot, np.asarray(anchor, dtype=np.float64) + t, float(scale), float(force_scale))

    def to_tissue(self, p_device) -> np.ndarray:
        """Tissue-frame point [m] of a device-frame point [m]."""
        return self.rotation @ (self.scale * np.asarray(p_device, dtype=np.float64)) + self.origin

    def rotation_to_tissue(self, q_device) -> np.ndarray:
        """Tissue-frame orientation (3x3) of a device-frame orientation quaternion (x, y, z, w).

        Raises:
            ValueError: not a finite, non-zero quaternion.
        """
        return self.rotation @ quaternion_matrix(q_device)

    def to_device(self, p_tissue) -> np.ndarray:
        """Inverse of :meth:`to_tissue`."""
        return (self.rotation.T @ (np.asarray(p_tissue, dtype=np.float64) - self.origin)) / self.scale

    def force_to_device(self, f_tissue) -> np.ndarray:
        """Device-frame force [N] of the tissue-frame reaction force on the tool."""
        return self.force_scale * (self.rotation.T @ np.asarray(f_tissue, dtype=np.float64))


def check_position(p, max_norm: float) -> str | None:
    """Why a device position is unusable (non-finite, or farther than ``max_norm`` from the origin)."""
    p = np.asarray(p, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        return 'non-finite position'
    n = float(np.linalg.norm(p))
    if n > max_norm:
        return f'position {n:.3g} m from the device origin (max_device_distance {max_norm:g} m)'
    return None
