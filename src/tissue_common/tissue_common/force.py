"""The device's force limits and the one clamp every stage uses (numpy only).

The clamp keeps its promise exactly: the clamped norm, as ``np.linalg.norm`` or ``math.hypot``
computes it, never exceeds the limit, not even by rounding (plain ``f * (limit / |f|)`` rounds above
it for about a third of all vectors).
"""

from __future__ import annotations

import math

import numpy as np

#: [N] PHANTOM Omni nominal peak force: nothing may send the device more.
HARD_FORCE_LIMIT = 3.3
#: [N] PHANTOM Omni nominal continuous force.
CONTINUOUS_FORCE_LIMIT = 0.88

#: a vector whose math.hypot norm is below limit * this is within the limit for np.linalg.norm too
#: (both are within a few ulps of the exact norm; 2**-40 leaves ample room)
_SURELY_BELOW = 1.0 - 2.0 ** -40
#: above this norm np.linalg.norm (a sum of squares) may overflow: no fast path there
_NO_OVERFLOW = 1e150


def _norm(vec: np.ndarray) -> float:
    """The larger of the float64 norms a reader may compute (``np.linalg.norm``, ``math.hypot``)."""
    with np.errstate(over='ignore'):
        return max(float(np.linalg.norm(vec)), math.hypot(vec[0], vec[1], vec[2]))


def clamp_norm(vec, limit: float) -> tuple[np.ndarray, bool]:
    """``vec`` (3 numbers) scaled down to norm ``limit`` if longer; returns (vector, clamped).

    Non-finite input becomes zero (clamped). Huge finite components are scaled, not lost to an
    overflowing norm. Scalar maths, and ``np.linalg.norm`` only near or above the limit: this runs
    on every 1 kHz frame, where numpy's per-call overhead on a 3-vector matters.

    Raises:
        ValueError: ``limit`` is negative or NaN.
    """
    f0, f1, f2 = float(vec[0]), float(vec[1]), float(vec[2])
    if not (math.isfinite(f0) and math.isfinite(f1) and math.isfinite(f2)):
        return np.zeros(3), True
    if not limit >= 0.0:
        raise ValueError(f'force limit must be >= 0 N, got {limit}')
    out = np.array((f0, f1, f2))
    h = math.hypot(f0, f1, f2)
    if h < limit * _SURELY_BELOW and h < _NO_OVERFLOW:
        return out, False
    if h * _SURELY_BELOW <= limit and _norm(out) <= limit:   # at the limit: ask both norms
        return out, False
    return _scaled_within(f0, f1, f2, limit), True


def _scaled_within(f0: float, f1: float, f2: float, limit: float) -> np.ndarray:
    """The vector (f0, f1, f2) (finite, non-zero) scaled to the largest norm not above ``limit``."""
    big = max(abs(f0), abs(f1), abs(f2))
    u0, u1, u2 = f0 / big, f1 / big, f2 / big           # components <= 1: no overflow below
    scale = limit / math.hypot(u0, u1, u2)
    shrink = 0
    while True:
        out = np.array((u0 * scale, u1 * scale, u2 * scale))
        if _norm(out) <= limit:
            return out
        # rounded above the limit: next float towards zero, faster if that is not enough
        # (always ends: a zero scale fits any limit >= 0)
        scale = max(0.0, scale - math.ulp(scale) * 2.0 ** shrink)
        shrink += 1
