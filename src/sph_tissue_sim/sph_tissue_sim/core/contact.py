"""Tool-tissue contact: a rigid swept sphere (the tool, see :mod:`.tools`) against the particles.

The kernels see every tool as a segment ``seg = [a, b]`` (2, 3) swept by a sphere of radius ``r_t``:
a sphere is the segment of length 0 (``a == b``), a capsule (an instrument shaft with a rounded tip)
one of the shaft's length. ``c_i`` is the point of the segment closest to particle ``i``.
Penalty contact with a dashpot (for passivity): a particle at ``x_i`` overlapping the tool
(particle radius ``r_p``) by

    d_i = r_t + r_p - |x_i - c_i| > 0

receives ``f_i = max(0, k_c d_i - c_c (v_i - v_tool(c_i)) . n_i) n_i`` with
``n_i = (x_i - c_i)/|x_i - c_i|`` (push only, never pull; ``v_tool(c_i)`` interpolates the
velocities of the segment's ends). A ball's radial normal pushes an off-centre particle sideways,
so the tool can slip between surface particles; the surface samples of :mod:`.surface_contact`
hold it out of those gaps (surface discs lost: docs/decisions/retired-contact_disc.md). The
reaction of the tissue on the tool is ``-sum_i f_i``: equal and opposite, so the force rendered to the device is exactly what the tissue feels (not the paper's
eq. 23, which adds a stress to a force). ``k_c`` is kept below the Omni's displayable stiffness
(~1 N/mm) and the haptic loop sees the tissue in series with it.

Friction (``friction`` = mu > 0): stick-slip, as in discrete-element contact, for the balls and
the surface samples alike. A contact point (a particle, or a sample of :mod:`.surface_contact`) that
starts to push keeps an anchor ``a``, where it sat relative to the tool's closest point ``c`` when it
touched; while it pushes it feels the tangential spring

    f_t = -k_c ((x - c) - a)_t,    |f_t| <= mu |f_n|,

(``_t``: the part normal to ``n``); at the cap the anchor slides so that the spring holds exactly
``mu |f_n|`` (sliding friction). The tool carries the tissue it presses instead of letting it slide
round it; the spring stores what it takes and sliding only dissipates, so the coupling stays passive.
A sticking point's tangential spring is integrated backward with its normal one
(:mod:`.implicit_contact`): a stuck point is held by ``k_c`` in every direction but, on a shaft,
along the tool's axis (there the closest point ``c`` slides with it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .state import TOUCH_BALL


@njit(cache=True, fastmath=True, inline='always')
def closest_on_segment(p0, p1, p2, seg):
    """``(c0, c1, c2, t)``: the point of segment ``seg[0]``-``seg[1]`` closest to ``p``, at
    ``seg[0] + t (seg[1] - seg[0])`` (``t`` = 0 for a segment of length 0: a sphere's centre)."""
    a0 = seg[0, 0]; a1 = seg[0, 1]; a2 = seg[0, 2]
    d0 = seg[1, 0] - a0; d1 = seg[1, 1] - a1; d2 = seg[1, 2] - a2
    dd = d0 * d0 + d1 * d1 + d2 * d2
    t = 0.0
    if dd > 0.0:
        t = ((p0 - a0) * d0 + (p1 - a1) * d1 + (p2 - a2) * d2) / dd
        t = min(max(t, 0.0), 1.0)
    return a0 + t * d0, a1 + t * d1, a2 + t * d2, t


@njit(cache=True, fastmath=True, inline='always')
def segment_distance2(i, x, seg):
    """Squared distance [m^2] of particle ``i``'s centre from the tool segment."""
    c0, c1, c2, t = closest_on_segment(x[i, 0], x[i, 1], x[i, 2], seg)
    e0 = x[i, 0] - c0; e1 = x[i, 1] - c1; e2 = x[i, 2] - c2
    return e0 * e0 + e1 * e1 + e2 * e2


@njit(cache=True, fastmath=True, inline='always')
def contact_vector(i, x, seg):
    """Vector ``(u0, u1, u2, t)`` [m] from the tool segment's closest point to particle ``i``'s
    centre, and where on the segment that point lies (0 at ``seg[0]``, 1 at ``seg[1]``)."""
    tc0, tc1, tc2, tseg = closest_on_segment(x[i, 0], x[i, 1], x[i, 2], seg)
    return x[i, 0] - tc0, x[i, 1] - tc1, x[i, 2] - tc2, tseg


@njit(cache=True, fastmath=True, inline='always')
def touch_normal(i, x, seg, reach):
    """Whether particle ``i`` lies within ``reach`` of the tool segment; returns ``(touching,
    overlap [m], n0, n1, n2, t)``: the unit normal along which the tool pushes it and where on
    the segment the closest point lies (see :func:`contact_vector`)."""
    if segment_distance2(i, x, seg) >= reach * reach:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    u0, u1, u2, ts = contact_vector(i, x, seg)
    r = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    if r >= reach:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    if r < 1e-12:
        # the tool's closest point exactly on the particle's centre: push along +z
        return True, reach - r, 0.0, 0.0, 1.0, ts
    return True, reach - r, u0 / r, u1 / r, u2 / r, ts


@njit(cache=True, fastmath=True, inline='always')
def penalty_push(i, v, seg_vel, ts, n0, n1, n2, overlap, k_c, c_c):
    """The push [N] along ``n`` on particle ``i`` overlapping the tool by ``overlap`` [m] where the
    tool's closest point lies at ``ts`` on its segment (ends moving at ``seg_vel``): ``k_c d - c_c
    (v_i - v_tool) . n`` (the module docstring; not positive: no push)."""
    tv0 = seg_vel[0, 0] + ts * (seg_vel[1, 0] - seg_vel[0, 0])
    tv1 = seg_vel[0, 1] + ts * (seg_vel[1, 1] - seg_vel[0, 1])
    tv2 = seg_vel[0, 2] + ts * (seg_vel[1, 2] - seg_vel[0, 2])
    vn = (v[i, 0] - tv0) * n0 + (v[i, 1] - tv1) * n1 + (v[i, 2] - tv2) * n2
    return k_c * overlap - c_c * vn


@njit(cache=True, inline='always')
def record_touch(touches, kind, idx, n0, n1, n2, held, seg, t, slot):
    """Append a pushing contact of instrument ``slot`` to ``touches`` (:class:`~.state.Touches`);
    ``held``: its friction sticks (the tangential spring acts too), ``t``: where on the tool's
    segment ``seg`` its closest point lies (inside a shaft the anchor slides with it along the axis)."""
    c = touches.count[0]
    if c < touches.idx.shape[0]:
        touches.kind[c] = kind
        touches.idx[c] = idx
        touches.normal[c, 0] = n0
        touches.normal[c, 1] = n1
        touches.normal[c, 2] = n2
        touches.held[c] = held
        touches.tool[c] = slot
        touches.axis[c, 0] = 0.0; touches.axis[c, 1] = 0.0; touches.axis[c, 2] = 0.0
        if held and 0.0 < t < 1.0:
            d0 = seg[1, 0] - seg[0, 0]; d1 = seg[1, 1] - seg[0, 1]; d2 = seg[1, 2] - seg[0, 2]
            length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if length > 0.0:
                touches.axis[c, 0] = d0 / length; touches.axis[c, 1] = d1 / length; touches.axis[c, 2] = d2 / length
        touches.count[0] = c + 1


@njit(cache=True, fastmath=True, inline='always')
def stick_slip(slot, r0, r1, r2, n0, n1, n2, push, k, mu, anchor, stuck):
    """The tangential friction force ``(f0, f1, f2)`` [N] on a contact point at ``r`` from the tool's
    closest point, pushed with ``push`` [N] along ``n`` (see the module docstring), and whether it
    sticks; sets or slides the anchor ``anchor[slot]``."""
    if not stuck[slot]:
        anchor[slot, 0] = r0; anchor[slot, 1] = r1; anchor[slot, 2] = r2
        stuck[slot] = True
    d0 = r0 - anchor[slot, 0]; d1 = r1 - anchor[slot, 1]; d2 = r2 - anchor[slot, 2]
    dn = d0 * n0 + d1 * n1 + d2 * n2
    f0 = -k * (d0 - dn * n0); f1 = -k * (d1 - dn * n1); f2 = -k * (d2 - dn * n2)
    fmag = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    cap = mu * push
    if fmag > cap:
        scale = cap / fmag
        f0 *= scale; f1 *= scale; f2 *= scale
        anchor[slot, 0] = r0 + f0 / k; anchor[slot, 1] = r1 + f1 / k; anchor[slot, 2] = r2 + f2 / k
        return f0, f1, f2, False
    return f0, f1, f2, True


@njit(cache=True, nogil=True)
def contact_vector_py(i, x, seg):
    """:func:`contact_vector` callable from Python (``(u0, u1, u2, t)``)."""
    return contact_vector(i, x, seg)


@njit(cache=True, fastmath=True)
def contact_forces(body, motion, cand, n_cand, tool, seg, seg_vel, react):
    """Add contact accelerations to ``motion.acc`` for ``cand[:n_cand]``; accumulate the reaction
    in ``react``.

    ``seg`` (2, 3) is the tool's segment now and ``seg_vel`` (2, 3) the velocities of its ends [m/s];
    ``tool`` (:class:`~.state.ToolPath`) gives the contact law: ``reach``, ``stiffness`` ``k_c``,
    ``damping`` ``c_c`` and ``friction`` (with the anchors :func:`stick_slip` keeps).
    Returns the largest overlap [m] (0 without contact).
    """
    x, v, acc, fixed, inv_mass = motion.x, motion.v, motion.acc, body.fixed, body.inv_mass
    reach, k_c, c_c, mu = tool.reach, tool.stiffness, tool.damping, tool.friction
    best = 0.0
    for t in range(n_cand):
        i = cand[t]
        touching, overlap, n0, n1, n2, ts = touch_normal(i, x, seg, reach)
        if not touching:
            tool.stuck[i] = False
            continue
        if overlap > best:
            best = overlap
        fmag = penalty_push(i, v, seg_vel, ts, n0, n1, n2, overlap, k_c, c_c)
        if fmag <= 0.0:
            tool.stuck[i] = False
            continue
        held = False
        if mu > 0.0:
            c0, c1, c2, _ = closest_on_segment(x[i, 0], x[i, 1], x[i, 2], seg)
            f0, f1, f2, held = stick_slip(i, x[i, 0] - c0, x[i, 1] - c1, x[i, 2] - c2, n0, n1, n2, fmag, k_c, mu,
                                          tool.anchor, tool.stuck)
            react[0] -= f0; react[1] -= f1; react[2] -= f2
            if not fixed[i]:
                acc[i, 0] += f0 * inv_mass; acc[i, 1] += f1 * inv_mass; acc[i, 2] += f2 * inv_mass
        react[0] -= fmag * n0
        react[1] -= fmag * n1
        react[2] -= fmag * n2
        if tool.touches.on:
            record_touch(tool.touches, TOUCH_BALL, i, n0, n1, n2, held, seg, ts, tool.slot)
        if not fixed[i]:
            acc[i, 0] += fmag * n0 * inv_mass
            acc[i, 1] += fmag * n1 * inv_mass
            acc[i, 2] += fmag * n2 * inv_mass
    return best


def first_moments(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float,
                  volume: float) -> tuple:
    """``(rows, d, cw, m)``: each reference pair's row ``i`` and ``d = X_j - X_i``, its weight
    ``cw = V_j W_ij`` and the kernel-weighted first moment ``m_i = sum_j cw (X_j - X_i)`` (N, 3):
    0 in the bulk, pointing into the material near the surface (0.24 spacings on a flat face)."""
    from .kernel import kernel_w_array

    n = len(X)
    rows = np.repeat(np.arange(n), np.diff(offsets))
    d = X[indices] - X[rows]
    cw = volume * kernel_w_array(np.linalg.norm(d, axis=1), h)
    # by bincount, one component at a time (an (nnz, 3, 3) temporary was 0.6 GB at 100k)
    m = np.stack([np.bincount(rows, weights=cw * d[:, a], minlength=n) for a in range(3)], axis=1)
    return rows, d, cw, m


@njit(cache=True, nogil=True)
def deepest_contact(x, cand, n_cand, seg, reach):
    """Collision detection (paper sec. 4.4): the candidate with the largest overlap, or -1."""
    best = -1
    best_d = 0.0
    for t in range(n_cand):
        i = cand[t]
        if segment_distance2(i, x, seg) >= reach * reach:
            continue
        u0, u1, u2, ts = contact_vector(i, x, seg)
        overlap = reach - math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        if overlap > best_d:
            best_d = overlap
            best = i
    return best
