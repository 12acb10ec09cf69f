"""Tool-tissue contact: a small rigid sphere (the tool tip) against the particles.

Penalty contact with a dashpot (for passivity): a particle at ``x_i`` overlapping the tool sphere
(centre ``c``, radius ``r_t``; particle radius ``r_p`` = spacing / 2) by

    d_i = r_t + r_p - |x_i - c| > 0

receives ``f_i = max(0, k_c d_i - c_c (v_i - v_tool) . n_i) n_i`` with ``n_i = (x_i - c)/|x_i - c|``
(push only, never pull). The reaction of the tissue on the tool is ``-sum_i f_i``: equal and
opposite, so the force rendered to the device is exactly what the tissue feels (not the paper's
eq. 23, which adds a stress to a force). ``k_c`` is kept below the Omni's displayable stiffness
(~1 N/mm) and the haptic loop sees the tissue in series with it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, fastmath=True)
def contact_forces(x, v, fixed, acc, inv_mass, cand, n_cand, tool, tool_vel, reach, k_c, c_c, react):
    """Add contact accelerations to ``acc`` for ``cand[:n_cand]``; accumulate the reaction in ``react``.

    Returns the largest overlap [m] (0 without contact).
    """
    best = 0.0
    r2max = reach * reach
    for t in range(n_cand):
        i = cand[t]
        d0 = x[i, 0] - tool[0]
        d1 = x[i, 1] - tool[1]
        d2 = x[i, 2] - tool[2]
        r2 = d0 * d0 + d1 * d1 + d2 * d2
        if r2 >= r2max:
            continue
        r = math.sqrt(r2)
        if r < 1e-12:
            # tool centre exactly on a particle: push along +z (any direction is as good)
            n0 = 0.0; n1 = 0.0; n2 = 1.0
        else:
            n0 = d0 / r; n1 = d1 / r; n2 = d2 / r
        overlap = reach - r
        if overlap > best:
            best = overlap
        vn = (v[i, 0] - tool_vel[0]) * n0 + (v[i, 1] - tool_vel[1]) * n1 + (v[i, 2] - tool_vel[2]) * n2
        fmag = k_c * overlap - c_c * vn
        if fmag <= 0.0:
            continue
        react[0] -= fmag * n0
        react[1] -= fmag * n1
        react[2] -= fmag * n2
        if not fixed[i]:
            acc[i, 0] += fmag * n0 * inv_mass
            acc[i, 1] += fmag * n1 * inv_mass
            acc[i, 2] += fmag * n2 * inv_mass
    return best


@njit(cache=True)
def deepest_contact(x, cand, n_cand, tool, reach):
    """Collision detection (paper sec. 4.4): the candidate with the largest overlap, or -1."""
    best = -1
    best_d = 0.0
    for t in range(n_cand):
        i = cand[t]
        d0 = x[i, 0] - tool[0]
        d1 = x[i, 1] - tool[1]
        d2 = x[i, 2] - tool[2]
        overlap = reach - math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if overlap > best_d:
            best_d = overlap
            best = i
    return best


def clamp_force(force: np.ndarray, limit: float) -> tuple[np.ndarray, bool]:
    """Scale ``force`` to norm ``limit`` if larger; non-finite input becomes zero. Returns (force, clamped)."""
    # scalar maths: this runs once per 1 kHz frame, where numpy's per-call overhead on a
    # 3-vector (~10 us) is a tenth of a local step
    f0, f1, f2 = float(force[0]), float(force[1]), float(force[2])
    if not (math.isfinite(f0) and math.isfinite(f1) and math.isfinite(f2)):
        return np.zeros(3), True
    norm = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    if norm > limit:
        k = limit / norm
        return np.array((f0 * k, f1 * k, f2 * k)), True
    return np.array((f0, f1, f2)), False
