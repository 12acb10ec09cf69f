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
rest: a far field (:mod:`.far_field`) places them at the organ's or the elastic half-space's
response to the contact force (the paper's still region clamps the area and makes it too stiff);
:func:`far_field_shell` is the half-space's kernel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import contact_vector, segment_distance2
from .neighbours import append_new, query_ball
from .state import Area, Body, Grid, Sets, Topology


@njit(cache=True, inline='always')
def _enter_area(j, reg, region, in_area, in_active, active_list, n_active):
    """Particle ``j`` is in the area this frame (region ``reg``) and active; returns the active count."""
    region[j] = reg
    in_area[j] = 1
    if in_active[j] == 0:
        in_active[j] = 1
        active_list[n_active] = j
        n_active += 1
    return n_active


@njit(cache=True, nogil=True)
def local_prepare(body, topo, grid, area, n_active, stamp_val, contact_idx, Dr, layer_dr, n_layers,
                  cand_centre, cand_radius):
    """Build the index sets of one local frame in ``area`` (:class:`~.state.Area`).

    The area is centred on ``area.centre`` (reference space; the overlap-weighted centroid of the
    touched particles, so it moves continuously when the deepest particle changes), radius ``Dr``
    [m], then ``n_layers`` layers of ``layer_dr`` [m]; the candidates are the particles within
    ``cand_radius`` of ``cand_centre`` (none if negative).
    Returns ``(n_active, n_sph, n_lp, n_stress, n_cand, n_interaction, n_relaxing)``;
    ``area.layer_counts[i-1]`` receives the particle count of layer i.
    """
    X, fixed = body.X, body.fixed
    offsets, indices = topo
    region, in_area, in_active, active_list, stamp = (area.region, area.in_area, area.in_active,
                                                      area.active, area.stamp)
    sph_list, layer_list, layer_w, stress_list, cand_list, tmp = (area.sph, area.layer, area.layer_w,
                                                                  area.stress, area.cand, area.tmp)
    centre, layer_counts = area.centre, area.layer_counts
    for t in range(n_active):
        region[active_list[t]] = 0
    for l in range(layer_counts.shape[0]):
        layer_counts[l] = 0
    # 1. the interaction area and transmission layers around the contact particle
    if contact_idx >= 0:
        radius = Dr + n_layers * layer_dr
        nq = query_ball(centre, radius, X, grid, tmp)
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
            n_active = _enter_area(j, reg, region, in_area, in_active, active_list, n_active)
    # 2. particles the tool may touch this frame: solved fully; fixed ones only feel the contact
    n_cand = 0
    nq = query_ball(cand_centre, cand_radius, X, grid, tmp)
    nq = min(nq, tmp.shape[0])
    for q in range(nq):
        j = tmp[q]
        if fixed[j]:
            cand_list[n_cand] = j
            n_cand += 1
            continue
        n_active = _enter_area(j, 1, region, in_area, in_active, active_list, n_active)
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
        n_stress = append_new(sph_list, t, t + 1, stamp, stamp_val, stress_list, n_stress)
        n_stress = append_new(indices, offsets[i], offsets[i + 1], stamp, stamp_val, stress_list, n_stress)
    return n_active, n_sph, n_lp, n_stress, n_cand, n_interaction, n_relaxing


@njit(cache=True, nogil=True)
def local_release(X, x, v, area, n_active, disp_tol, vel_tol):
    """Drop relaxed particles outside the area from ``area.active[:n_active]``; returns the new count.

    A released particle stops (v = 0) where it is; its displacement is below ``disp_tol``.
    """
    in_active, active_list, region, in_area = area.in_active, area.active, area.region, area.in_area
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


@njit(cache=True, nogil=True)
def far_field_shell(body, x, sets, mark, ff_list, n_ff, centre, load, G, nu, buf_d, buf_u):
    """Move the still particles that solved ones read (the stress shell) with the tissue around.

    The paper holds everything beyond the transmission layers still, which clamps the area at a
    few h from the tool and makes it stiffer than the whole organ (+24 % on the liver at 2 mm).
    Here each shell particle j is placed at ``X_j + u(X_j - centre)``, ``u`` the elastic
    half-space response to the contact ``load`` (:func:`boussinesq`). Particles placed so in the
    previous frame (``ff_list[:n_ff]``) that are neither solved nor in the shell now go back to
    rest. ``mark`` (n,) int8 must be zero on entry and is zero on return. Returns the new shell
    count (``ff_list[:count]``).
    """
    X, fixed = body.X, body.fixed
    stress_list, n_stress, sph_list, n_sph = sets.stress, sets.n_stress, sets.sph, sets.n_sph
    layer_list, n_lp = sets.layer, sets.n_layer
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def detect_local(X, x, grid, area, n_active, seg, reach, margin):
    """Deepest-overlap particle of the tool segment ``seg`` (2, 3) in local mode, O(active + cells
    near the tool), or -1.

    Inactive particles sit within ``margin`` of their reference position, so the reference grid
    finds them; active ones (possibly far from home) are checked directly.

    Also returns the touched particles with their overlaps as weights (``area.touch``,
    ``area.touch_w``; count as second return value) and their overlap-weighted reference centroid
    in ``area.centre``: the layers follow the weighted mean velocity of the touched particles and
    the area is centred on that centroid, so neither jumps when the deepest particle changes.
    """
    active_list, tmp, touch_idx, touch_w, centre = (area.active, area.tmp, area.touch, area.touch_w,
                                                    area.centre)
    best = -1
    best_d = 0.0
    n_touch = 0
    wsum = 0.0
    c0 = 0.0; c1 = 0.0; c2 = 0.0
    mid = np.empty(3)
    half2 = 0.0
    for a in range(3):
        mid[a] = 0.5 * (seg[0, a] + seg[1, a])
        half2 += (0.5 * (seg[1, a] - seg[0, a])) ** 2
    nq = query_ball(mid, math.sqrt(half2) + reach + margin, X, grid, tmp)
    nq = min(nq, tmp.shape[0])
    for q in range(nq + n_active):
        j = tmp[q] if q < nq else active_list[q - nq]
        if segment_distance2(j, x, seg) >= reach * reach:
            continue
        u0, u1, u2, ts = contact_vector(j, x, seg)
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


@njit(cache=True, nogil=True)
def copy_rows(x, v, a, na, b, nb, buf_x, buf_v, save):
    """Copy positions and velocities of ``a[:na]`` then ``b[:nb]`` into the buffers (``save``) or
    back from them."""
    for t in range(na + nb):
        i = a[t] if t < na else b[t - na]
        for c in range(3):
            if save:
                buf_x[t, c] = x[i, c]
                buf_v[t, c] = v[i, c]
            else:
                x[i, c] = buf_x[t, c]
                v[i, c] = buf_v[t, c]


class LocalArea:
    """The moving particle sets of one model: the local interaction area, its transmission layers,
    the particles still relaxing, the tool's candidates and the optional far-field shell.

    ``Solver`` asks it, once per frame, for the :class:`~.state.Sets` to solve
    (:meth:`global_sets` or :meth:`detect` then :meth:`prepare`), and to :meth:`save`,
    :meth:`restore` and :meth:`release` around the frame. Everything costs O(area + active).

    Args:
        X: (N, 3) reference positions; fixed: (N,) boundary mask.
        topo: reference neighbours within 2h; grid: the reference cell grid.
        h: smoothing length [m]; n_layers: transmission layers.
    """

    def __init__(self, X: np.ndarray, fixed: np.ndarray, topo: Topology, grid: Grid, h: float,
                 n_layers: int) -> None:
        n = len(X)
        self.X, self.fixed, self.topo = X, fixed, topo
        self.grid, self.h, self.n_layers = grid, h, n_layers
        self.free = np.flatnonzero(~fixed).astype(np.int32)
        self.all = np.arange(n, dtype=np.int32)
        self.region = np.zeros(n, dtype=np.int8)
        self.in_active = np.zeros(n, dtype=np.int8)
        self.in_area = np.zeros(n, dtype=np.int8)
        self.stamp = np.zeros(n, dtype=np.int64)
        self.stamp_val = 0
        self.active = np.zeros(n, dtype=np.int32)
        self.n_active = 0
        self.sph = np.zeros(n, dtype=np.int32)
        self.layer = np.zeros(n, dtype=np.int32)
        self.layer_w = np.zeros(n)
        self.stress = np.zeros(n, dtype=np.int32)
        self.cand = np.zeros(2 * n, dtype=np.int32)
        self.tmp = np.zeros(n, dtype=np.int32)
        self.touch = np.zeros(256, dtype=np.int32)
        self.touch_w = np.zeros(256)
        self.n_touch = 0
        self.centre = np.zeros(3)
        self.layer_counts = np.zeros(max(n_layers, 1), dtype=np.int64)
        self.buf_x = np.zeros((n, 3))
        self.buf_v = np.zeros((n, 3))
        # far-field shell (far_field > 0): allocated on first use
        self.ff_list = np.zeros(0, dtype=np.int32)
        self.n_ff = 0
        self.ff_mark = np.zeros(0, dtype=np.int8)
        self.ff_buf = np.zeros((0, 3))
        self.ff_load = np.zeros(3)
        # where the organ's far field applies the load (the last touched particles, their weights)
        self.ff_at = np.zeros(0, dtype=np.int32)
        self.ff_w = np.zeros(0)
        self.bundle = Area(self.region, self.in_area, self.in_active, self.active, self.stamp, self.sph,
                           self.layer, self.layer_w, self.stress, self.cand, self.tmp, self.touch,
                           self.touch_w, self.centre, self.layer_counts)

    def reset(self, global_mode: bool) -> None:
        """No active particle; in global mode every free particle is in the interaction area."""
        self.region[:] = 0
        self.in_active[:] = 0
        self.in_area[:] = 0
        self.n_active = 0
        self.n_ff = 0
        self.n_touch = 0
        self.ff_load[:] = 0.0
        self.ff_at = np.zeros(0, dtype=np.int32)
        if global_mode:
            self.region[self.free] = 1

    def global_sets(self, contact: int) -> Sets:
        """Every free particle solved, every particle stressed and a candidate, no layer."""
        n = len(self.all)
        return Sets(self.all, n, self.free, len(self.free), self.layer, self.layer_w, 0,
                    self.all, n, self.touch, self.touch_w, 0, contact)

    def detect(self, x: np.ndarray, seg: np.ndarray, reach: float, margin: float) -> int:
        """The deepest touched particle of the tool's segment (or -1); records the touched ones
        and centres the area on their overlap-weighted centroid (:func:`detect_local`)."""
        deepest, self.n_touch = detect_local(self.X, x, self.grid, self.bundle, self.n_active, seg,
                                             reach, margin)
        return deepest

    def hold(self, idx: np.ndarray) -> int:
        """Centre the area on particles a tool holds, for a frame in which it touches nothing (a
        grasp that lifts): they are the touched ones, of equal weight; returns one of them (the
        area's contact particle)."""
        n = min(len(idx), len(self.touch))
        self.touch[:n] = idx[:n]
        self.touch_w[:n] = 1.0
        self.n_touch = n
        self.centre[:] = self.X[idx].mean(axis=0)
        return int(idx[0])

    def prepare(self, body: Body, seg0: np.ndarray | None, seg1: np.ndarray | None, reach: float, margin: float,
                contact: int, Dr: float, on_contact: bool) -> tuple[Sets, int, int]:
        """The sets of a local frame; returns ``(sets, n_interaction, n_relaxing)``.

        ``Dr`` [m] is the area's radius: from the contact particle (``on_contact``, the paper's
        sec. 4.2) or from the edge of the touched patch (so a load spread over several particles
        is inside). The candidates are every particle the tool can reach
        anywhere on its way through the frame (``seg0`` to ``seg1``; None: no tool).
        """
        if seg0 is not None:
            # scalar maths: numpy's per-call overhead on 4 points is a few per cent of a local step
            ends = seg0.tolist() + seg1.tolist()
            c = [0.25 * (ends[0][a] + ends[1][a]) + 0.25 * (ends[2][a] + ends[3][a]) for a in range(3)]
            cand_centre = np.array(c)
            cand_radius = max(math.dist(e, c) for e in ends) + reach + margin
        else:
            cand_centre = self.centre
            cand_radius = -1.0
        if on_contact:
            if contact >= 0:
                self.centre[:] = self.X[contact]
        elif self.n_touch > 0:
            ti = self.touch[:self.n_touch]
            d = self.X[ti] - self.centre
            Dr += float(np.sqrt((d * d).sum(axis=1)).max())
        self.stamp_val += 1
        (self.n_active, n_sph, n_lp, n_stress, n_cand, n_inter, n_relax) = local_prepare(
            body, self.topo, self.grid, self.bundle, self.n_active, self.stamp_val, contact, Dr,
            0.5 * self.h, self.n_layers, cand_centre, cand_radius)
        sets = Sets(self.stress, n_stress, self.sph, n_sph, self.layer, self.layer_w, n_lp,
                    self.cand, n_cand, self.touch, self.touch_w, self.n_touch, contact)
        return sets, n_inter, n_relax

    def far_field(self, body: Body, x: np.ndarray, sets: Sets, react: np.ndarray, factor: float,
                  blend: float, model) -> None:
        """Move the load ``ff_load`` ``blend`` (0..1] of the way to ``-factor * react`` and let the
        far field ``model`` (:mod:`.far_field`; None: none) place the still particles around the
        solved ones at its response; they return to rest once ``factor`` is 0.

        Why the low pass: the shell's displacement follows the force, which follows the shell.
        Near the load (a small area: ``k1 h`` shrinks with the spacing) that loop's gain passes 1
        and the force rings and grows from frame to frame (30k liver, surface samples, 11 mm deep:
        by up to 1 N); relaxing the load (a few ms, well below the organ's shear-wave time of tens
        of ms) damps it and leaves the quasi-static response as it was.
        """
        if model is None or (factor <= 0.0 and self.n_ff == 0):
            return
        self.ff_load += blend * (-factor * react - self.ff_load)
        n = len(self.X)
        if len(self.ff_list) != n:
            self.ff_list = np.zeros(n, dtype=np.int32)
            self.ff_mark = np.zeros(n, dtype=np.int8)
            self.ff_buf = np.zeros((n, 3))
        model.place(self, body, x, sets)

    def save(self, x: np.ndarray, v: np.ndarray, sets: Sets) -> None:
        """Keep the state of the particles a frame on ``sets`` moves."""
        copy_rows(x, v, sets.sph, sets.n_sph, sets.layer, sets.n_layer, self.buf_x, self.buf_v, True)

    def restore(self, x: np.ndarray, v: np.ndarray, sets: Sets) -> None:
        """Undo a frame on ``sets`` (after :meth:`save`)."""
        copy_rows(x, v, sets.sph, sets.n_sph, sets.layer, sets.n_layer, self.buf_x, self.buf_v, False)

    def release(self, x: np.ndarray, v: np.ndarray, disp_tol: float, vel_tol: float) -> None:
        """Drop relaxed particles outside the area from the active set (:func:`local_release`)."""
        self.n_active = local_release(self.X, x, v, self.bundle, self.n_active, disp_tol, vel_tol)

    def stats(self, x: np.ndarray, v: np.ndarray, mass: float) -> tuple[float, float]:
        """Max displacement [m] and kinetic energy [J] of the active particles."""
        return active_stats(x, self.X, v, self.active, self.n_active, mass)
