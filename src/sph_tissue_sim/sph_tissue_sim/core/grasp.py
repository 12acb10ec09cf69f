"""Grasp: an instrument that closes on the tissue holds the particles inside its jaws.

When an instrument closes (:meth:`~.solver.Solver.grasp`) the free particles whose centres lie
within ``GRASP_REGION`` times the tool's contact reach of its segment are attached to it: each
keeps an anchor ``a``, where it sat relative to the tool's tip in the tool's own frame, and is
pulled towards the anchor's place ``p = b + R a`` by a spring and a dashpot of the contact's
stiffness ``k_c`` and damping ``c_c``, where ``b`` follows the tip through a first-order lag
(:data:`GRIP_LAG_CUTOFF`, :func:`trail_after`):

    f = k_c (p - x) - c_c ((v - v_p) . n) n,        n = (p - x) / |p - x|.

The reaction on the tool is ``-sum f``: the hand feels the pull as it feels a press, through the
same renderer. The spring is integrated backward with the pushing contacts
(:mod:`.implicit_contact`: a grasp is recorded as a ball touch whose friction sticks, so its whole
stiffness ``k_c I`` is implicit, the dashpot along ``n``). A particle pulled harder than
``grasp_limit`` lets go (the grasp slips, one particle at a time) instead of tearing the tissue.
Within a frame the anchors follow the tool's tip linearly and turn from the start's to the end's
orientation (a few particles: their offsets are rotated in Python, per frame).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import record_touch
from .state import TOUCH_BALL, Grip

#: particles whose centres lie within this times the tool's contact reach of its segment are grasped
#: (a region a little larger than the tool, as grasping in iMSTK advises)
GRASP_REGION = 1.2
#: [Hz] the anchors' base follows the tool's tip through a first-order lag of this cut-off. An
#: encoder tick moves the tip in one frame, and the grip springs, far stiffer than the tissue,
#: answered that jump at once: the grasping hand felt it (docs/decisions/grasp-retract-smoothness.md).
#: At 60 Hz and 1 kHz the base trails a 26 mm/s retract by 0.057 mm.
GRIP_LAG_CUTOFF = 60.0


def trail_after(trail: np.ndarray, tip0: np.ndarray, tip1: np.ndarray, dt: float) -> np.ndarray:
    """Where the anchors' base ``b`` is from the tip [m] at the end of a frame of ``dt`` [s] in
    which the tip moved from ``tip0`` to ``tip1``, ``b`` having been at ``tip0 + trail``:
    ``b1 = b0 + alpha (tip1 - b0)``, ``alpha = 1 - exp(-2 pi f_c dt)``."""
    alpha = 1.0 - math.exp(-2.0 * math.pi * GRIP_LAG_CUTOFF * dt)
    return (1.0 - alpha) * (tip0 + trail - tip1)


def no_grip() -> Grip:
    """A tool that holds nothing."""
    return Grip(np.zeros(0, dtype=np.int32), 0, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.bool_),
                0.0)


def grasp_region(x: np.ndarray, fixed: np.ndarray, seg: np.ndarray, reach: float) -> np.ndarray:
    """The free particles (indices, int32) whose centres lie within ``reach`` [m] of the segment
    ``seg`` (2, 3)."""
    a, b = seg
    d = b - a
    dd = float(d @ d)
    t = np.clip((x - a) @ d / dd, 0.0, 1.0) if dd > 0.0 else np.zeros(len(x))
    r = np.linalg.norm(x - (a + t[:, None] * d), axis=1)
    return np.flatnonzero((r < reach) & ~fixed).astype(np.int32)


@njit(cache=True, fastmath=True)
def grip_forces(body, motion, tool, seg, frac, frame_dt, seg_vel, react):
    """The springs of the particles ``tool.grip`` holds (module docstring) at the sub-step ``frac``
    (0..1] of the frame: added to ``motion.acc``, their reaction to ``react``, each recorded in
    ``tool.touches``. A particle pulled harder than ``grip.limit`` [N] is let go (``grip.held``)."""
    x, v, acc, fixed, inv_mass = motion.x, motion.v, motion.acc, body.fixed, body.inv_mass
    g = tool.grip
    k_c, c_c = tool.stiffness, tool.damping
    for t in range(g.n):
        if not g.held[t]:
            continue
        i = g.idx[t]
        o0 = g.off0[t, 0] + frac * (g.off1[t, 0] - g.off0[t, 0])
        o1 = g.off0[t, 1] + frac * (g.off1[t, 1] - g.off0[t, 1])
        o2 = g.off0[t, 2] + frac * (g.off1[t, 2] - g.off0[t, 2])
        d0 = seg[0, 0] + o0 - x[i, 0]; d1 = seg[0, 1] + o1 - x[i, 1]; d2 = seg[0, 2] + o2 - x[i, 2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if r < 1e-12:
            n0 = 0.0; n1 = 0.0; n2 = 1.0
        else:
            n0 = d0 / r; n1 = d1 / r; n2 = d2 / r
        pv0 = seg_vel[0, 0] + (g.off1[t, 0] - g.off0[t, 0]) / frame_dt
        pv1 = seg_vel[0, 1] + (g.off1[t, 1] - g.off0[t, 1]) / frame_dt
        pv2 = seg_vel[0, 2] + (g.off1[t, 2] - g.off0[t, 2]) / frame_dt
        vn = (v[i, 0] - pv0) * n0 + (v[i, 1] - pv1) * n1 + (v[i, 2] - pv2) * n2
        fmag = k_c * r - c_c * vn
        if abs(fmag) > g.limit:
            g.held[t] = False
            continue
        react[0] -= fmag * n0; react[1] -= fmag * n1; react[2] -= fmag * n2
        if tool.touches.on:
            record_touch(tool.touches, TOUCH_BALL, i, n0, n1, n2, True, seg, 0.0, tool.slot)
        if not fixed[i]:
            acc[i, 0] += fmag * n0 * inv_mass
            acc[i, 1] += fmag * n1 * inv_mass
            acc[i, 2] += fmag * n2 * inv_mass
