"""Dynamic local interaction area (paper sec. 4, eqs. 17-21) with viscoelastic release.

Around each instrument's contact particle ``c`` (reference distance ``d``; a particle in two
instruments' areas is solved fully, a layer particle follows its own instrument's contact):

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
def local_prepare(body, topo, grid, area, n_active, stamp_val, Dr, layer_dr, n_layers, cand_centres,
                  cand_radii):
    """Build the index sets of one local frame in ``area`` (:class:`~.state.Area`): the union of
    the instruments' areas.

    Instrument k's area is centred on ``area.centres[k]`` (reference space; the overlap-weighted
    centroid of the particles it touches, so it moves continuously when the deepest particle
    changes), radius ``Dr[k]`` [m] (negative: no area), then ``n_layers`` layers of ``layer_dr``
    [m]; a particle in several is solved (region 1), ``area.layer_tool`` says whose layer a layer
    particle is in. The candidates are the particles within ``cand_radii[k]`` of ``cand_centres[k]``
    (none if negative), each listed once.
    Returns ``(n_active, n_sph, n_lp, n_stress, n_cand, n_interaction, n_relaxing)``;
    ``area.layer_counts[i-1]`` receives the particle count of layer i.
    """
    X, fixed = body.X, body.fixed
    offsets, indices = topo
    region, in_area, in_active, active_list, stamp = (area.region, area.in_area, area.in_active,
                                                      area.active, area.stamp)
    sph_list, layer_list, layer_w, stress_list, cand_list, tmp = (area.sph, area.layer, area.layer_w,
                                                                  area.stress, area.cand, area.tmp)
    centres, layer_counts, layer_tool = area.centres, area.layer_counts, area.layer_tool
    for t in range(n_active):
        region[active_list[t]] = 0
    for l in range(layer_counts.shape[0]):
        layer_counts[l] = 0
    # 1. the interaction areas and transmission layers around the contacts
    for k in range(Dr.shape[0]):
        if Dr[k] < 0.0:
            continue
        centre = centres[k]
        nq = query_ball(centre, Dr[k] + n_layers * layer_dr, X, grid, tmp)
        nq = min(nq, tmp.shape[0])
        for q in range(nq):
            j = tmp[q]
            if fixed[j]:
                continue
            d0 = X[j, 0] - centre[0]
            d1 = X[j, 1] - centre[1]
            d2 = X[j, 2] - centre[2]
            d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if d < Dr[k]:
                reg = 1
            else:
                layer = 1 + int((d - Dr[k]) / layer_dr)
                if layer > n_layers:
                    continue
                reg = 1 + layer
            if in_area[j] == 1:
                reg = 1           # in two instruments' areas: solved, not moved along with either
            layer_tool[j] = k
            n_active = _enter_area(j, reg, region, in_area, in_active, active_list, n_active)
    # 2. particles a tool may touch this frame: solved fully; fixed ones only feel the contact
    #    (listed once: a fixed particle twice in the list would push its tool twice)
    n_cand = 0
    for k in range(cand_radii.shape[0]):
        nq = query_ball(cand_centres[k], cand_radii[k], X, grid, tmp)
        nq = min(nq, tmp.shape[0])
        for q in range(nq):
            j = tmp[q]
            if fixed[j]:
                if in_area[j] == 0:
                    in_area[j] = 1
                    cand_list[n_cand] = j
                    n_cand += 1
                continue
            n_active = _enter_area(j, 1, region, in_area, in_active, active_list, n_active)
    for t in range(n_cand):
        in_area[cand_list[t]] = 0     # fixed particles are never active: local_release won't clear it
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
def far_field_shell(body, x, sets, mark, ff_list, n_ff, centres, loads, G, nu, buf_d, buf_u, buf_e):
    """Move the still particles that solved ones read (the stress shell) with the tissue around.

    The paper holds everything beyond the transmission layers still, which clamps the area at a
    few h from the tool and makes it stiffer than the whole organ (+24 % on the liver at 2 mm).
    Here each shell particle j is placed at ``X_j + sum_k u(X_j - centres[k])``, ``u`` the elastic
    half-space response to instrument k's contact load ``loads[k]`` (:func:`boussinesq`;
    ``buf_e`` scratch for the second and later instruments). Particles placed so in the
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
        buf_d[m, 0] = X[j, 0] - centres[0, 0]
        buf_d[m, 1] = X[j, 1] - centres[0, 1]
        buf_d[m, 2] = X[j, 2] - centres[0, 2]
        m += 1
    boussinesq(buf_d[:m], loads[0], G, nu, buf_u)
    for k in range(1, loads.shape[0]):     # the half-space is linear: the instruments' responses add
        for t in range(m):
            j = ff_list[t]
            buf_d[t, 0] = X[j, 0] - centres[k, 0]
            buf_d[t, 1] = X[j, 1] - centres[k, 1]
            buf_d[t, 2] = X[j, 2] - centres[k, 2]
        boussinesq(buf_d[:m], loads[k], G, nu, buf_e)
        for t in range(m):
            buf_u[t, 0] += buf_e[t, 0]; buf_u[t, 1] += buf_e[t, 1]; buf_u[t, 2] += buf_e[t, 2]
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
def detect_local(X, x, grid, area, n_active, seg, reach, margin, start, centre):
    """Deepest-overlap particle of the tool segment ``seg`` (2, 3) in local mode, O(active + cells
    near the tool), or -1.

    Inactive particles sit within ``margin`` of their reference position, so the reference grid
    finds them; active ones (possibly far from home) are checked directly.

    Also returns the touched particles with their overlaps as weights (``area.touch``,
    ``area.touch_w`` from ``start`` on; count as second return value) and their overlap-weighted
    reference centroid in ``centre`` (3,): the layers follow the weighted mean velocity of the
    touched particles and the area is centred on that centroid, so neither jumps when the deepest
    particle changes.
    """
    active_list, tmp, touch_idx, touch_w = area.active, area.tmp, area.touch, area.touch_w
    capacity = min(touch_idx.shape[0] - start, TOUCH_CAPACITY)
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
        for t in range(start, start + n_touch):
            if touch_idx[t] == j:
                dup = True
                break
        if dup:
            continue
        if n_touch < capacity:
            touch_idx[start + n_touch] = j
            touch_w[start + n_touch] = overlap
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


#: touched particles recorded per instrument and frame (the rest still push; they do not steer the area)
TOUCH_CAPACITY = 256


class LocalArea:
    """The moving particle sets of one model: the local interaction area (the union of each
    instrument's), its transmission layers, the particles still relaxing, the tools' candidates and
    the optional far-field shell.

    ``Solver`` asks it, once per frame, for the :class:`~.state.Sets` to solve
    (:meth:`global_sets`, or :meth:`detect` or :meth:`hold` per instrument then :meth:`prepare`),
    and to :meth:`save`, :meth:`restore` and :meth:`release` around the frame. Everything costs
    O(area + active).

    Args:
        X: (N, 3) reference positions; fixed: (N,) boundary mask.
        topo: reference neighbours within 2h; grid: the reference cell grid.
        h: smoothing length [m]; n_layers: transmission layers; instruments: how many tools.
    """

    def __init__(self, X: np.ndarray, fixed: np.ndarray, topo: Topology, grid: Grid, h: float,
                 n_layers: int, instruments: int = 1) -> None:
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
        self.layer_tool = np.zeros(n, dtype=np.int32)
        self.stress = np.zeros(n, dtype=np.int32)
        self.cand = np.zeros(2 * n, dtype=np.int32)
        self.tmp = np.zeros(n, dtype=np.int32)
        self.touch = np.zeros(TOUCH_CAPACITY * instruments, dtype=np.int32)
        self.touch_w = np.zeros(TOUCH_CAPACITY * instruments)
        # instrument k's touched particles this frame: touch[touch_start[k]:touch_start[k + 1]]
        self.touch_start = np.zeros(instruments + 1, dtype=np.int64)
        self.centres = np.zeros((instruments, 3))
        # prepare()'s per-instrument inputs, filled in place each frame
        self.cand_centres = np.zeros((instruments, 3))
        self.cand_radii = np.zeros(instruments)
        self.radii = np.zeros(instruments)
        self.contacts = np.zeros(instruments, dtype=np.int64)
        self.layer_counts = np.zeros(max(n_layers, 1), dtype=np.int64)
        self.buf_x = np.zeros((n, 3))
        self.buf_v = np.zeros((n, 3))
        # far-field shell (far_field > 0): allocated on first use
        self.ff_list = np.zeros(0, dtype=np.int32)
        self.n_ff = 0
        self.ff_mark = np.zeros(0, dtype=np.int8)
        self.ff_buf = np.zeros((0, 3))
        self.ff_buf2 = np.zeros((0, 3))
        self.ff_load = np.zeros((instruments, 3))
        # where the organ's far field applies each instrument's load (the particles it touched
        # last, their weights)
        self.ff_at = [np.zeros(0, dtype=np.int32)] * instruments
        self.ff_w = [np.zeros(0)] * instruments
        self.bundle = Area(self.region, self.in_area, self.in_active, self.active, self.stamp, self.sph,
                           self.layer, self.layer_w, self.stress, self.cand, self.tmp, self.touch,
                           self.touch_w, self.centres, self.layer_counts, self.layer_tool)

    def reset(self, global_mode: bool) -> None:
        """No active particle; in global mode every free particle is in the interaction area."""
        self.region[:] = 0
        self.in_active[:] = 0
        self.in_area[:] = 0
        self.n_active = 0
        self.n_ff = 0
        self.touch_start[:] = 0
        self.ff_load[:] = 0.0
        self.ff_at = [np.zeros(0, dtype=np.int32)] * len(self.ff_at)
        self.ff_w = [np.zeros(0)] * len(self.ff_w)
        self.free = np.flatnonzero(~self.fixed).astype(np.int32)
        if global_mode:
            self.region[self.free] = 1

    def drop(self, idx: np.ndarray) -> None:
        """Particles ``idx`` left the simulation (now ``fixed``): out of the active set and of global
        mode's free particles."""
        active = self.active[:self.n_active]
        keep = active[~np.isin(active, idx)]
        self.n_active = len(keep)
        self.active[:self.n_active] = keep
        self.in_active[idx] = 0
        self.in_area[idx] = 0
        self.region[idx] = 0
        self.free = np.flatnonzero(~self.fixed).astype(np.int32)

    def global_sets(self, contacts) -> Sets:
        """Every free particle solved, every particle stressed and a candidate, no layer;
        ``contacts``: each instrument's contact particle (or one, -1: none)."""
        n = len(self.all)
        contacts = np.atleast_1d(np.asarray(contacts, dtype=np.int64))
        return Sets(self.all, n, self.free, len(self.free), self.layer, self.layer_w, 0,
                    self.all, n, self.touch, self.touch_w, np.zeros(len(contacts) + 1, dtype=np.int64),
                    contacts, self.layer_tool)

    def detect(self, x: np.ndarray, seg: np.ndarray, reach: float, margin: float, k: int = 0) -> int:
        """The deepest particle instrument ``k``'s segment touches (or -1); records the touched
        ones after the previous instruments' and centres its area on their overlap-weighted
        centroid (:func:`detect_local`). Call in the instruments' order, each once a frame."""
        start = int(self.touch_start[k])
        deepest, n = detect_local(self.X, x, self.grid, self.bundle, self.n_active, seg, reach, margin,
                                  start, self.centres[k])
        self.touch_start[k + 1] = start + n
        return deepest

    def hold(self, idx: np.ndarray, k: int = 0) -> int:
        """Centre instrument ``k``'s area on particles it holds, for a frame in which it touches
        nothing (a grasp that lifts): they are its touched ones, of equal weight; returns one of
        them (the area's contact particle)."""
        start = int(self.touch_start[k])
        n = min(len(idx), TOUCH_CAPACITY)
        self.touch[start:start + n] = idx[:n]
        self.touch_w[start:start + n] = 1.0
        self.touch_start[k + 1] = start + n
        self.centres[k] = self.X[idx].mean(axis=0)
        return int(idx[0])

    def skip(self, k: int) -> None:
        """Instrument ``k`` touches and holds nothing this frame."""
        self.touch_start[k + 1] = self.touch_start[k]

    def prepare(self, body: Body, tools: list, margin: float, on_contact: bool) -> tuple[Sets, int, int]:
        """The sets of a local frame; returns ``(sets, n_interaction, n_relaxing)``.

        ``tools`` holds per instrument ``(seg0, seg1, reach, contact, Dr)``: ``Dr`` [m] is its
        area's radius, from its contact particle (``on_contact``, the paper's sec. 4.2) or from the
        edge of its touched patch (so a load spread over several particles is inside); no area
        without a contact (-1). Its candidates are every particle it can reach anywhere on its way
        through the frame (``seg0`` to ``seg1``; ``seg0`` None: no tool).
        """
        cand_centres, cand_radii, radii, contacts = self.cand_centres, self.cand_radii, self.radii, self.contacts
        cand_radii[:] = -1.0
        radii[:] = -1.0
        for k, (seg0, seg1, reach, contact, Dr) in enumerate(tools):
            centre = self.centres[k]
            if seg0 is not None:
                # scalar maths: numpy's per-call overhead on 4 points is a few per cent of a local step
                ends = seg0.tolist() + seg1.tolist()
                c = [0.25 * (ends[0][a] + ends[1][a]) + 0.25 * (ends[2][a] + ends[3][a]) for a in range(3)]
                cand_centres[k] = c
                cand_radii[k] = max(math.dist(e, c) for e in ends) + reach + margin
            if on_contact:
                if contact >= 0:
                    centre[:] = self.X[contact]
            elif self.touch_start[k + 1] > self.touch_start[k]:
                ti = self.touch[self.touch_start[k]:self.touch_start[k + 1]]
                d = self.X[ti] - centre
                Dr += float(np.sqrt((d * d).sum(axis=1)).max())
            if contact >= 0:
                radii[k] = Dr
            contacts[k] = contact
        self.stamp_val += 1
        (self.n_active, n_sph, n_lp, n_stress, n_cand, n_inter, n_relax) = local_prepare(
            body, self.topo, self.grid, self.bundle, self.n_active, self.stamp_val, radii,
            0.5 * self.h, self.n_layers, cand_centres, cand_radii)
        sets = Sets(self.stress, n_stress, self.sph, n_sph, self.layer, self.layer_w, n_lp,
                    self.cand, n_cand, self.touch, self.touch_w, self.touch_start, contacts, self.layer_tool)
        return sets, n_inter, n_relax

    def far_field(self, body: Body, x: np.ndarray, sets: Sets, react: np.ndarray, factor: float,
                  blend: float, model) -> None:
        """Move each instrument's load ``ff_load[k]`` ``blend`` (0..1] of the way to ``-factor *
        react[k]`` (``react`` (K, 3)) and let the far field ``model`` (:mod:`.far_field`; None:
        none) place the still particles around the solved ones at its response; they return to
        rest once ``factor`` is 0.

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
            self.ff_buf2 = np.zeros((n, 3)) if len(self.ff_load) > 1 else np.zeros((0, 3))
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
