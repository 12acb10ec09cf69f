"""Contact with the material's surface: sample points carried by the particles.

A particle is a lump of material about one spacing wide, its centre half a spacing inside the
material's surface. Contact between the tool and the particle centres (the ball model of
:mod:`.contact`) therefore feels the surface before it is there, and it lets the tool pass
between particles: pressed into the liver between four surface particles, the tool pushed them
apart and the force fell to nothing beyond about 10 mm (pop-through). Here the tool meets the
surface itself, and the gap between particles is material.

Each surface particle ``i`` carries ``per_side**2`` *samples* on its reference patch: points

    Y_s = X_i + (s / 2) N_i + u t1 + v t2,     u, v on a grid of s / per_side,

half a spacing ``s`` outside it along its reference outward normal ``N_i`` (``t1``, ``t2`` span
the tangent plane). A sample moves with the material around it: with Shepard weights of the SPH
kernel, fixed in the reference configuration (``phi_sj = W(|Y_s - X_j|, h) / sum_k W``),

    y_s = sum_j phi_sj x_j + (Y_s - sum_j phi_sj X_j),      v_s = sum_j phi_sj v_j.

The tool pushes a sample out along the tool's normal with a penalty spring and a dashpot, and the
force acts on the particles through the same weights, ``f_j = phi_sj f_s``: the contact energy
``k/2 d(y(x))^2`` is a function of the positions alone (the coupling is passive), the weights sum
to one (momentum is conserved), and pushing the surface between particles pushes all of them.
The weights are positive on purpose: linear-reproducing (moving-least-squares) weights place a
sample exactly under any affine motion, but their negative lobes push the layer below the surface
up while the surface goes down, a particle-scale mode the SPH stress barely resists (the tool
then sank through the surface at 5-8 mm). The price is that a sample's offset from its
neighbours' mean neither rotates nor shrinks with the material.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import closest_on_segment, first_moments, record_touch, segment_distance2, stick_slip
from .kernel import kernel_w
from .neighbours import CellGrid, query_ball
from .state import Samples

#: a particle is on the surface when the kernel-weighted first moment of its neighbours is at least
#: this many spacings (0.24 on a flat face, 0.014 one layer below, 0 in the bulk)
SURFACE_MOMENT = 0.1

#: the contact surface lies this many spacings outside the surface particles' centres
SURFACE_OFFSET = 0.5


def surface_normals(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float, volume: float,
                    spacing: float) -> np.ndarray:
    """(N, 3) reference outward unit normals of the surface particles, zero in the bulk (from the
    kernel-weighted first moment of the neighbours, :func:`~.contact.first_moments`)."""
    m = first_moments(X, offsets, indices, h, volume)[3]
    mn = np.linalg.norm(m, axis=1)
    N = np.zeros((len(X), 3))
    on = mn >= SURFACE_MOMENT * spacing
    N[on] = -m[on] / mn[on, None]
    return N


@njit(cache=True)
def _sample_weights(Y, X, grid, h, count_only, w_start, w_idx, w_val):
    """Shepard interpolation weights ``W(|Y_s - X_j|, h) / sum_j W`` of the samples ``Y`` (S, 3)
    over the reference particles ``X`` (binned in ``grid``) within ``2 h``.

    With ``count_only`` returns the number of weights of each sample (S,); otherwise fills
    ``w_idx``, ``w_val`` from ``w_start`` and returns the same counts.
    """
    S = Y.shape[0]
    counts = np.zeros(S, dtype=np.int64)
    tmp = np.empty(X.shape[0], dtype=np.int32)
    for s in range(S):
        nq = min(query_ball(Y[s], 2.0 * h, X, grid, tmp), tmp.shape[0])
        counts[s] = nq
        if count_only:
            continue
        t0 = w_start[s]
        total = 0.0
        for q in range(nq):
            j = tmp[q]
            w = kernel_w(math.sqrt((X[j, 0] - Y[s, 0]) ** 2 + (X[j, 1] - Y[s, 1]) ** 2
                                   + (X[j, 2] - Y[s, 2]) ** 2), h)
            w_idx[t0 + q] = j
            w_val[t0 + q] = w
            total += w
        for q in range(nq):
            w_val[t0 + q] /= total
    return counts


def surface_samples(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float, volume: float,
                    spacing: float, per_side: int) -> tuple:
    """The contact samples of the reference body: ``(s_start, w_start, w_idx, w_val, offset, X,
    read_start, read_idx, own_reach, reach, support)``.

    Particle ``i`` owns samples ``s_start[i] .. s_start[i + 1] - 1`` (none in the bulk); sample
    ``s`` is ``sum_j w_val[k] x[w_idx[k]]`` over ``k`` in ``w_start[s] .. w_start[s + 1] - 1``.
    ``offset`` (S, 3) is added to the weighted sum. Its samples read the particles
    ``read_idx[read_start[i]:read_start[i + 1]]``, and lie at most ``own_reach[i]`` [m] from it in
    the reference configuration (:func:`samples_in_reach`). ``reach`` [m] is the largest of those
    and ``support`` [m] the farthest particle a sample reads (``2 h``).
    """
    n = len(X)
    N = surface_normals(X, offsets, indices, h, volume, spacing)
    surf = np.flatnonzero(np.any(N != 0.0, axis=1))
    # tangent basis: the axis least aligned with the normal, made orthogonal
    Ns = N[surf]
    axis = np.eye(3)[np.argmin(np.abs(Ns), axis=1)]
    t1 = np.cross(Ns, axis)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(Ns, t1)
    grid = (np.arange(per_side) - 0.5 * (per_side - 1)) * spacing / per_side
    uu, vv = (g.ravel() for g in np.meshgrid(grid, grid, indexing='ij'))
    Y = (X[surf, None, :] + SURFACE_OFFSET * spacing * Ns[:, None, :]
         + uu[None, :, None] * t1[:, None, :] + vv[None, :, None] * t2[:, None, :]).reshape(-1, 3)
    owner = np.repeat(surf, per_side * per_side).astype(np.int64)
    reach = float(np.linalg.norm([SURFACE_OFFSET * spacing, grid[-1], grid[-1]]))
    Y = np.ascontiguousarray(Y)
    bins = CellGrid(X, 2.0 * h).bundle
    counts = _sample_weights(Y, X, bins, h, True, np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32),
                             np.zeros(0))
    w_start = np.zeros(len(Y) + 1, dtype=np.int64)
    np.cumsum(counts, out=w_start[1:])
    w_idx = np.zeros(w_start[-1], dtype=np.int32)
    w_val = np.zeros(w_start[-1])
    _sample_weights(Y, X, bins, h, False, w_start, w_idx, w_val)
    s_start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=n), out=s_start[1:])
    rows = np.repeat(np.arange(len(Y)), np.diff(w_start))
    mean = np.stack([np.bincount(rows, weights=w_val * X[w_idx, a], minlength=len(Y)) for a in range(3)], axis=1)
    # per owner: the union of the particles its samples read, and its samples' farthest distance
    keys = np.unique(owner[rows] * n + w_idx)
    read_start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys // n, minlength=n), out=read_start[1:])
    own_reach = np.zeros(n)
    np.maximum.at(own_reach, owner, np.linalg.norm(Y - X[owner], axis=1))
    return (s_start, w_start, w_idx, w_val, np.ascontiguousarray(Y - mean), X, read_start,
            (keys % n).astype(np.int32), own_reach, reach, 2.0 * h)


def no_samples(n: int) -> Samples:
    """The ball model's :class:`~.state.Samples`: no particle owns a sample."""
    return Samples(np.zeros(n + 1, dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32),
                   np.zeros(0), np.zeros((0, 3)), 0.0, 0.0, 0.0, 0.0, np.zeros((n, 3)),
                   np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(n))


#: [m] added to :func:`samples_in_reach`'s exact bound for the rounding of the samples' sums
REACH_SLACK = 1e-9


@njit(cache=True, fastmath=True, inline='always')
def samples_in_reach(i, x, seg, samples, within):
    """Whether particle ``i`` owns samples that may come within ``within`` [m] of the tool's
    surface. A sample stays within ``samples.margin`` of its owner while the material holds
    together; and exactly, since its weights sum to one,

        y_s - x_i = (Y_s - X_i) + sum_j phi_sj (u_j - u_i),   |y_s - x_i| <= own_reach_i + max_j |u_j - u_i|

    with ``u = x - X`` over the particles its samples read: in deep contact the first test passes
    five times as many owners as the second, which costs one pass over those particles instead of
    a weighted sum per sample."""
    if samples.start[i] == samples.start[i + 1]:
        return False
    d2 = segment_distance2(i, x, seg)
    lim = samples.radius + within + samples.margin
    if d2 >= lim * lim:
        return False
    ref = samples.ref
    ui0 = x[i, 0] - ref[i, 0]; ui1 = x[i, 1] - ref[i, 1]; ui2 = x[i, 2] - ref[i, 2]
    spread2 = 0.0
    for k in range(samples.read_start[i], samples.read_start[i + 1]):
        j = samples.read_idx[k]
        e0 = x[j, 0] - ref[j, 0] - ui0; e1 = x[j, 1] - ref[j, 1] - ui1; e2 = x[j, 2] - ref[j, 2] - ui2
        spread2 = max(spread2, e0 * e0 + e1 * e1 + e2 * e2)
    lim = samples.radius + within + samples.own_reach[i] + math.sqrt(spread2) + REACH_SLACK
    return d2 < lim * lim


@njit(cache=True, fastmath=True, inline='always')
def sample_offset(s, x, v, seg, samples):
    """Sample ``s`` seen from the tool: ``(e0, e1, e2, t, u0, u1, u2)``, its offset [m] from the
    segment's closest point (at ``t`` along it) and its velocity [m/s]."""
    w_start, w_idx, w_val, off = samples.w_start, samples.w_idx, samples.w_val, samples.offset
    y0 = off[s, 0]; y1 = off[s, 1]; y2 = off[s, 2]; u0 = 0.0; u1 = 0.0; u2 = 0.0
    for k in range(w_start[s], w_start[s + 1]):
        j = w_idx[k]
        w = w_val[k]
        y0 += w * x[j, 0]; y1 += w * x[j, 1]; y2 += w * x[j, 2]
        u0 += w * v[j, 0]; u1 += w * v[j, 1]; u2 += w * v[j, 2]
    c0, c1, c2, t = closest_on_segment(y0, y1, y2, seg)
    return y0 - c0, y1 - c1, y2 - c2, t, u0, u1, u2


@njit(cache=True)
def nearest_sample_gap(x, v, cand, n_cand, seg, samples, within):
    """The smallest distance [m] between the tool (segment ``seg`` swept by ``samples.radius``)
    and a sample of ``cand[:n_cand]`` (negative: one is inside the tool), exact up to ``within``
    [m]; beyond it a larger positive distance or ``inf``."""
    gap = np.inf
    for t in range(n_cand):
        i = cand[t]
        if samples_in_reach(i, x, seg, samples, within):
            for s in range(samples.start[i], samples.start[i + 1]):
                e0, e1, e2, ts, u0, u1, u2 = sample_offset(s, x, v, seg, samples)
                gap = min(gap, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) - samples.radius)
    return gap


@njit(cache=True, fastmath=True)
def sample_contact_forces(body, motion, cand, n_cand, tool, seg, seg_vel, react):
    """Contact of the samples (``tool.samples``) of ``cand[:n_cand]`` with the tool (segment ``seg``
    (2, 3) swept by a sphere of ``samples.radius`` [m], its ends moving at ``seg_vel`` [m/s]).

    A sample inside the tool gets ``f = max(0, k d - c (v_s - v_tool) . n) n`` (``d`` the overlap,
    ``n`` from the tool's closest point to the sample, ``k``, ``c`` the sample's stiffness and
    damping) and, with ``tool.friction``, the stick-slip force of :func:`~.contact.stick_slip` (its
    anchor in slot ``N + s``), spread on its particles' accelerations by its weights; the reaction
    is accumulated in ``react`` and a pushing sample recorded in ``tool.touches``
    (:class:`~.state.Touches`, for an implicit contact update). Returns the largest overlap [m]
    (0 without contact).
    """
    x, v, acc, fixed, inv_mass = motion.x, motion.v, motion.acc, body.fixed, body.inv_mass
    samples, touches, mu, stuck = tool.samples, tool.touches, tool.friction, tool.stuck
    start, w_start, w_idx, w_val = samples.start, samples.w_start, samples.w_idx, samples.w_val
    radius, k_s, c_s = samples.radius, samples.stiffness, samples.damping
    n = x.shape[0]
    best = 0.0
    for t in range(n_cand):
        i = cand[t]
        if not samples_in_reach(i, x, seg, samples, 0.0):
            for s in range(start[i], start[i + 1]):
                stuck[n + s] = False
            continue
        for s in range(start[i], start[i + 1]):
            e0, e1, e2, ts, u0, u1, u2 = sample_offset(s, x, v, seg, samples)
            r2 = e0 * e0 + e1 * e1 + e2 * e2
            if r2 >= radius * radius:
                stuck[n + s] = False
                continue
            r = math.sqrt(r2)
            if r < 1e-12:
                n0 = 0.0; n1 = 0.0; n2 = 1.0
            else:
                n0 = e0 / r; n1 = e1 / r; n2 = e2 / r
            overlap = radius - r
            if overlap > best:
                best = overlap
            tv0 = seg_vel[0, 0] + ts * (seg_vel[1, 0] - seg_vel[0, 0])
            tv1 = seg_vel[0, 1] + ts * (seg_vel[1, 1] - seg_vel[0, 1])
            tv2 = seg_vel[0, 2] + ts * (seg_vel[1, 2] - seg_vel[0, 2])
            vn = (u0 - tv0) * n0 + (u1 - tv1) * n1 + (u2 - tv2) * n2
            fmag = k_s * overlap - c_s * vn
            if fmag <= 0.0:
                stuck[n + s] = False
                continue
            held = False
            g0 = 0.0; g1 = 0.0; g2 = 0.0
            if mu > 0.0:
                g0, g1, g2, held = stick_slip(n + s, e0, e1, e2, n0, n1, n2, fmag, k_s, mu, tool.anchor, stuck)
                react[0] -= g0; react[1] -= g1; react[2] -= g2
            react[0] -= fmag * n0
            react[1] -= fmag * n1
            react[2] -= fmag * n2
            if touches.on:
                record_touch(touches, samples.kind, s, n0, n1, n2, held, seg, ts, tool.slot)
            for k in range(w_start[s], w_start[s + 1]):
                j = w_idx[k]
                if not fixed[j]:
                    a = w_val[k] * fmag * inv_mass
                    acc[j, 0] += a * n0
                    acc[j, 1] += a * n1
                    acc[j, 2] += a * n2
                    if mu > 0.0:
                        a = w_val[k] * inv_mass
                        acc[j, 0] += a * g0
                        acc[j, 1] += a * g1
                        acc[j, 2] += a * g2
    return best
