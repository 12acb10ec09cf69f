"""Rotations as quaternions ``(x, y, z, w)`` (the ROS order) and 3x3 matrices (numpy only)."""

from __future__ import annotations

import math

import numpy as np


def quaternion_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (x, y, z, w); normalised first.

    Raises:
        ValueError: not 4 finite numbers, or a (near) zero norm.
    """
    try:
        x, y, z, w = (float(v) for v in np.asarray(q, dtype=np.float64).reshape(4))
    except (TypeError, ValueError) as exc:
        raise ValueError(f'rotation must be a quaternion [x, y, z, w], got {q!r}') from exc
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(n) and n >= 1e-6):
        raise ValueError(f'rotation quaternion must be finite with a non-zero norm, got {[x, y, z, w]}')
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method, numerically safe)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2.0
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2.0
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2.0
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)
