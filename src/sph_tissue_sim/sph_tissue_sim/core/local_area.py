"""Dynamic local interaction area (paper sec. 4, eqs. 17-21) with viscoelastic release.

Around the contact particle ``c`` (reference distance ``d``):

    d < Dr = k1 h                                 -> interaction area, full SPH      (region 1)
    Tr_(i-1) <= d < Tr_i,  Tr_i = Dr + (i/2) h     -> transmission layer i            (region 1 + i)
                                                     a = w(i) a_c, w(i) = (N+1-i)/(N+1)
    beyond                                        -> still                            (region 0)

``k1 = clamp(k1_gain * |f_ext|, k1_min, k1_max)`` with ``f_ext`` the previous frame's contact force
[N] (eq. 18 has k1 = f_ext / 2). The area follows the tool every frame. Particles that leave the
area (or all of them once contact ends) stay *active* and are solved with full SPH until their
displacement and speed are below tolerances, so the tissue recovers instead of freezing dented.
Everything here costs O(area + active): the area comes from the reference cell grid.

Optionally (``SolverConfig.far_field``) the still particles that solved ones read are not held at
rest: :func:`far_field_shell` places them at the elastic half-space response to the contact force
(the paper's still region clamps the area and makes it too stiff).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import contact_vector, segment_distance2
from .neighbours import query_ball


@njit(cache=True)
def local_prepare(X, x, fixed, offsets, indices,
                  origin, cell, dims, cell_start, cell_particles,
                  in_active, active_list, n_active, region, in_area, stamp, stamp_val,
                  contact_idx, centre, Dr, layer_dr, n_layers,
                  cand_centre, cand_radius,
                  sph_list, layer_list, layer_w, stress_list, cand_list, tmp, layer_counts):
    """Build the index sets of one local frame.

    The area is centred on ``centre`` (reference space; the overlap-weighted centroid of the
    touched particles, so it moves continuously when the deepest particle changes).
    Returns ``(n_active, n_sph, n_lp, n_stress, n_cand, n_interaction, n_relaxing)``;
    ``layer_counts[i-1]`` receives the particle count of layer i.
    """
    for t in range(n_active):
        region[active_list[t]] = 0
    for l in range(layer_counts.shape[0]):
        layer_counts[l] = 0
    # 1. the interaction area and transmission layers around the contact particle
    if contact_idx >= 0:
        radius = Dr + n_layers * layer_dr
        nq = query_ball(centre, radius, X, origin, cell, dims, cell_start, cell_particles, tmp)
        nq = min(nq, tmp.shape[0])
        for q in range(nq):
            j = tmp[q]
            if fixed[j]:
                continue
            d0 = X[j, 0] - centre[0]
            d1 = X[j, 1] - centre[1]
            d2 = X[j, 2] - centre[2]
            d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if d < Dr:
                reg = 1
            else:
                layer = 1 + int((d - Dr) / layer_dr)
                if layer > n_layers:
                    continue
                reg = 1 + layer
            region[j] = reg
            in_area[j] = 1
            if in_active[j] == 0:
                in_active[j] = 1
                active_list[n_active] = j
                n_active += 1
    # 2. particles the tool may touch this frame: solved fully; fixed ones only feel the contact
    n_cand = 0
    nq = query_ball(cand_centre, cand_radius, X, origin, cell, dims, cell_start, cell_particles, tmp)
    nq = min(nq, tmp.shape[0])
    for q in range(nq):
        j = tmp[q]
        if fixed[j]:
            cand_list[n_cand] = j
            n_cand += 1
            continue
        region[j] = 1
        in_area[j] = 1
        if in_active[j] == 0:
            in_active[j] = 1
            active_list[n_active] = j
            n_active += 1
    # 3. split the active set: full SPH (interaction + relaxing) and kinematic layers
    n_sph = 0
    n_lp = 0
    n_interaction = 0
    n_relaxing = 0
    for t in range(n_active):
        j = active_list[t]
        cand_list[n_cand] = j
        n_cand += 1
        reg = region[j]
        if reg >= 2:
            layer_list[n_lp] = j
            layer_w[n_lp] = (n_layers + 2.0 - reg) / (n_layers + 1.0)
            layer_counts[reg - 2] += 1
            n_lp += 1
        else:
            sph_list[n_sph] = j
            n_sph += 1
            if in_area[j] == 1:
                n_interaction += 1
            else:
                n_relaxing += 1
                region[j] = 1
    # 4. stress set: the fully solved particles and all their reference neighbours
    n_stress = 0
    for t in range(n_sph):
        i = sph_list[t]
        if stamp[i] != stamp_val:
            stamp[i] = stamp_val
            stress_list[n_stress] = i
            n_stress += 1
        for k in range(offsets[i], offsets[i + 1]):
            j = indices[k]
            if stamp[j] != stamp_val:
                stamp[j] = stamp_val
                stress_list[n_stress] = j
                n_stress += 1
    return n_active, n_sph, n_lp, n_stress, n_cand, n_interaction, n_relaxing


@njit(cache=True)
def local_release(X, x, v, in_active, active_list, n_active, region, in_area, disp_tol, vel_tol):
    """Drop relaxed particles outside the area from the active set; returns the new count.

    A released particle stops (v = 0) where it is; its displacement is below ``disp_tol``.
    """
    d2tol = disp_tol * disp_tol
    v2tol = vel_tol * vel_tol
    m = 0
    for t in range(n_active):
        j = active_list[t]
        keep = True
        if in_area[j] == 0:
            d0 = x[j, 0] - X[j, 0]; d1 = x[j, 1] - X[j, 1]; d2 = x[j, 2] - X[j, 2]
            s2 = v[j, 0] * v[j, 0] + v[j, 1] * v[j, 1] + v[j, 2] * v[j, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 < d2tol and s2 < v2tol:
                keep = False
        in_area[j] = 0
        if keep:
            active_list[m] = j
            m += 1
        else:
            in_active[j] = 0
            region[j] = 0
            v[j, 0] = 0.0; v[j, 1] = 0.0; v[j, 2] = 0.0
    return m


#: cap of the imposed far-field displacement, as a fraction of the distance to the load point: the
#: point-load solution is singular there, and the shell must never be turned inside out
FAR_FIELD_MAX_STRAIN = 0.25


@njit(cache=True)
def boussinesq(d, load, G, nu, out):
    """Displacement [m] of an elastic half-space under a point load, at offsets ``d`` (n, 3).

    Boussinesq's solution for the load ``P`` [N] acting along n = P/|P| (into the body) at the
    origin, with z = d.n the depth, r the distance from the load axis, R = |d|:

        u_z = |P| / (4 pi G) (2 (1 - nu) / R + z^2 / R^3)
        u_r = |P| / (4 pi G) (r z / R^3 - (1 - 2 nu) r / (R (R + z)))

    ``out`` (n, 3) receives u = u_z n + u_r e_r, capped at ``FAR_FIELD_MAX_STRAIN * R`` (the
    solution is singular at the load point and behind it, where R + z -> 0).
    """
    pm = math.sqrt(load[0] * load[0] + load[1] * load[1] + load[2] * load[2])
    for i in range(d.shape[0]):
        out[i, 0] = 0.0; out[i, 1] = 0.0; out[i, 2] = 0.0
    if pm == 0.0:
        return
    n0 = load[0] / pm; n1 = load[1] / pm; n2 = load[2] / pm
    coef = pm / (4.0 * math.pi * G)
    for i in range(d.shape[0]):
        R = math.sqrt(d[i, 0] * d[i, 0] + d[i, 1] * d[i, 1] + d[i, 2] * d[i, 2])
        if R == 0.0:
            continue
        z = d[i, 0] * n0 + d[i, 1] * n1 + d[i, 2] * n2
        r0 = d[i, 0] - z * n0; r1 = d[i, 1] - z * n1; r2 = d[i, 2] - z * n2
        r = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        uz = coef * (2.0 * (1.0 - nu) / R + z * z / (R * R * R))
        ur = 0.0
        if r > 0.0:
            ur = coef * (r * z / (R * R * R) - (1.0 - 2.0 * nu) * r / (R * max(R + z, 1e-3 * R))) / r
        u0 = uz * n0 + ur * r0; u1 = uz * n1 + ur * r1; u2 = uz * n2 + ur * r2
        um = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        cap = FAR_FIELD_MAX_STRAIN * R
        if um > cap:
            s = cap / um
            u0 *= s; u1 *= s; u2 *= s
        out[i, 0] = u0; out[i, 1] = u1; out[i, 2] = u2


@njit(cache=True)
def far_field_shell(X, x, fixed, stress_list, n_stress, sph_list, n_sph, layer_list, n_lp,
                    mark, ff_list, n_ff, centre, load, G, nu, buf_d, buf_u):
    """Move the still particles that solved ones read (the stress shell) with the tissue around.

    The paper holds everything beyond the transmission layers still, which clamps the area at a
    few h from the tool and makes it stiffer than the whole organ (+24 % on the liver at 2 mm).
    Here each shell particle j is placed at ``X_j + u(X_j - centre)``, ``u`` the elastic
    half-space response to the contact ``load`` (:func:`boussinesq`). Particles placed so in the
    previous frame (``ff_list[:n_ff]``) that are neither solved nor in the shell now go back to
    rest. ``mark`` (n,) int8 must be zero on entry and is zero on return. Returns the new shell
    count (``ff_list[:count]``).
    """
    for t in range(n_sph):
        mark[sph_list[t]] = 1
    for t in range(n_lp):
        mark[layer_list[t]] = 1
    for t in range(n_ff):
        j = ff_list[t]
        if mark[j] == 0:
            x[j, 0] = X[j, 0]; x[j, 1] = X[j, 1]; x[j, 2] = X[j, 2]
    m = 0
    for t in range(n_stress):
        j = stress_list[t]
        if mark[j] != 0 or fixed[j]:
            continue
        mark[j] = 2
        ff_list[m] = j
        buf_d[m, 0] = X[j, 0] - centre[0]
        buf_d[m, 1] = X[j, 1] - centre[1]
        buf_d[m, 2] = X[j, 2] - centre[2]
        m += 1
    boussinesq(buf_d[:m], load, G, nu, buf_u)
    for t in range(m):
        j = ff_list[t]
        x[j, 0] = X[j, 0] + buf_u[t, 0]
        x[j, 1] = X[j, 1] + buf_u[t, 1]
        x[j, 2] = X[j, 2] + buf_u[t, 2]
        mark[j] = 0
    for t in range(n_sph):
        mark[sph_list[t]] = 0
    for t in range(n_lp):
        mark[layer_list[t]] = 0
    return m


@njit(cache=True)
def active_stats(x, X, v, idx, n, mass):
    """Max displacement [m] and kinetic energy [J] over ``idx[:n]``."""
    md2 = 0.0
    ke = 0.0
    for t in range(n):
        i = idx[t]
        d0 = x[i, 0] - X[i, 0]; d1 = x[i, 1] - X[i, 1]; d2 = x[i, 2] - X[i, 2]
        dd = d0 * d0 + d1 * d1 + d2 * d2
        if dd > md2:
            md2 = dd
        ke += 0.5 * mass * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
    return math.sqrt(md2), ke


@njit(cache=True)
def detect_local(X, x, active_list, n_active, origin, cell, dims, cell_start, cell_particles,
                 seg, reach, margin, tmp, surf, touch_idx, touch_w, centre):
    """Deepest-overlap particle of the tool segment ``seg`` (2, 3) in local mode, O(active + cells
    near the tool), or -1.

    Inactive particles sit within ``margin`` of their reference position, so the reference grid
    finds them; active ones (possibly far from home) are checked directly. The overlap is measured
    to the contact shape of :func:`~.contact.contact_forces` (``surf``).

    Also returns the touched particles with their overlaps as weights (``touch_idx``,
    ``touch_w``; count as second return value) and their overlap-weighted reference centroid in
    ``centre``: the layers follow the weighted mean velocity of the touched particles and the area
    is centred on that centroid, so neither jumps when the deepest particle changes.
    """
    best = -1
    best_d = 0.0
    n_touch = 0
    wsum = 0.0
    c0 = 0.0; c1 = 0.0; c2 = 0.0
    disc = surf[6]
    mid = np.empty(3)
    half2 = 0.0
    for a in range(3):
        mid[a] = 0.5 * (seg[0, a] + seg[1, a])
        half2 += (0.5 * (seg[1, a] - seg[0, a])) ** 2
    nq = query_ball(mid, math.sqrt(half2) + reach + margin + np.max(disc), X, origin, cell, dims,
                    cell_start, cell_particles, tmp)
    nq = min(nq, tmp.shape[0])
    for q in range(nq + n_active):
        j = tmp[q] if q < nq else active_list[q - nq]
        lim = reach + disc[j]
        if segment_distance2(j, x, seg) >= lim * lim:
            continue
        u0, u1, u2, s0, s1, s2, ts = contact_vector(j, x, seg, surf)
        overlap = reach - math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        if overlap <= 0.0:
            continue
        dup = False
        for t in range(n_touch):
            if touch_idx[t] == j:
                dup = True
                break
        if dup:
            continue
        if n_touch < touch_idx.shape[0]:
            touch_idx[n_touch] = j
            touch_w[n_touch] = overlap
            n_touch += 1
            wsum += overlap
            c0 += overlap * X[j, 0]; c1 += overlap * X[j, 1]; c2 += overlap * X[j, 2]
        if overlap > best_d:
            best_d = overlap
            best = j
    if wsum > 0.0:
        centre[0] = c0 / wsum; centre[1] = c1 / wsum; centre[2] = c2 / wsum
    return best, n_touch


@njit(cache=True)
def save_state(x, v, lists_a, na, lists_b, nb, buf_x, buf_v):
    """Copy positions/velocities of ``lists_a[:na]`` and ``lists_b[:nb]`` into buffers."""
    for t in range(na):
        i = lists_a[t]
        for a in range(3):
            buf_x[t, a] = x[i, a]
            buf_v[t, a] = v[i, a]
    for t in range(nb):
        i = lists_b[t]
        for a in range(3):
            buf_x[na + t, a] = x[i, a]
            buf_v[na + t, a] = v[i, a]


@njit(cache=True)
def restore_state(x, v, lists_a, na, lists_b, nb, buf_x, buf_v):
    """Inverse of :func:`save_state`."""
    for t in range(na):
        i = lists_a[t]
        for a in range(3):
            x[i, a] = buf_x[t, a]
            v[i, a] = buf_v[t, a]
    for t in range(nb):
        i = lists_b[t]
        for a in range(3):
            x[i, a] = buf_x[na + t, a]
            v[i, a] = buf_v[na + t, a]
