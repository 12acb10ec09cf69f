"""A needle that pierces: it dents the surface, punctures, then slides in held by friction.

Needle insertion, after Okamura, Simone and O'Leary (IEEE TBME 2004), in three phases:

* **outside / touching**: the shaft pushes the particles beside it radially, and the tip dents the
  surface: a particle ball model lets a tip much thinner than the spacing slip between particles
  (or squeeze one out ahead of it), so the tip presses a **dent**, a point of the surface that is the
  weighted mean of the particles around where the tip met it (weights ``(1 - s^2 / R_p^2)^2`` at a
  distance ``s`` within ``R_p`` = :data:`DENT_RADIUS` spacings), plus a fixed offset that puts it
  where the tip meets the first particle (found a spacing before). The tip pushes it along the
  axis, ``k_c d`` with ``d = reach + (p - tip) . e``: the capsule stiffness of the whole dimple;
* **puncture**: once the tissue pushes back along the axis with ``F_p`` or more, the tip enters
  (the entry point and the axis are kept). ``F_p = pi d G_c`` (:func:`puncture_force`): the
  toughness paid for a crack as wide as the needle's circumference per unit depth;
* **inserted**: the tip is a cone of length ``lead`` that spreads the particles ahead of it
  aside, the shaft pushes them out radially (never along the axis), and along the axis

  - the **tip** cuts: a load ``F_t = min(k_t (q - q_f), F_c)`` on the needle, ``q`` the tip's depth
    below the entry along the axis and ``q_f`` the crack's front, pushed deeper so that ``F_t``
    never exceeds the cutting force ``F_c = G_c d``; the tissue gets ``-F_t`` on the particles
    within ``grip_reach`` of the tip, by their weights (:func:`tip_cut`);
  - the **shaft** holds each particle within ``grip_reach`` of its axis by a stick-slip spring
    along the axis, anchored where the particle sat from the tip (:func:`shaft_hold`): ``k_c w``
    capped at ``w`` times the static hold per metre while it sticks and the dynamic one once it
    slides (``w`` the particle's share of the shaft's length), so the friction grows with the
    inserted depth and pulling back drags the tissue until it slips.

So the axial force rises with the dent, drops when the tip enters, then rises with the depth as the
shaft's friction grows: the three phases. A tip drawn back above its entry point is outside again.
A needle opens no bonds: the track closes behind it when it leaves (a crack is a blade's).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import penalty_push, record_touch
from .state import TOUCH_BALL, Shaft

#: states of a needle, as ``SimMetrics.needle_state`` sends them
OUTSIDE, TOUCHING, INSERTED = 0, 1, 2
#: [-] the tip's cone: as long as the shaft's contact reach times this
LEAD = 1.0
#: [spacings] the radius of the surface a tip dents before it punctures
DENT_RADIUS = 1.5
#: [spacings] a tip this far off its dent has left it (it finds one within a spacing)
DENT_LEAVE = 1.5


def puncture_force(toughness: float, diameter: float) -> float:
    """[N] the axial force at which a needle of ``diameter`` [m] enters a tissue of ``toughness``
    ``G_c`` [J/m^2]: ``pi d G_c``."""
    return math.pi * diameter * toughness


def cut_force(toughness: float, diameter: float) -> float:
    """[N] the force that advances the tip's crack: ``G_c d`` (the work per unit depth of a crack as
    wide as the needle)."""
    return toughness * diameter


def no_shaft() -> Shaft:
    """A tool that is not inside the tissue."""
    return Shaft(False, False, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                 np.zeros(0), np.zeros(0, dtype=np.bool_), np.zeros(0, dtype=np.bool_), np.zeros(0, dtype=np.int32),
                 np.zeros(0), np.zeros(3), 0)


@njit(cache=True, fastmath=True, inline='always')
def _across(e0, e1, e2):
    """A unit vector normal to the unit ``e`` (where a particle on the axis is pushed)."""
    if abs(e2) < 0.9:
        p0, p1, p2 = -e1, e0, 0.0          # e x z
    else:
        p0, p1, p2 = 0.0, e2, -e1          # e x x
    n = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    return p0 / n, p1 / n, p2 / n


@njit(cache=True, fastmath=True, inline='always')
def _shaft_touch(i, x, seg, reach, lead, inserted):
    """Where particle ``i`` meets the needle: ``(touching, overlap [m], n0, n1, n2, a, t)``: the
    unit normal it is pushed along, its axial coordinate ``a`` [m] behind the tip (negative ahead of
    it) and where along the shaft (0..1) it is. Beside the shaft (``a >= 0``) the overlap is
    ``reach - r`` (``r`` from the axis), pushed radially; ahead of an inserted tip, the cone
    ``(reach + a reach / lead - r) cos(alpha)``, pushed outward and ahead (a tip not inserted
    presses its dent instead, :func:`dent_force`)."""
    a0 = seg[0, 0]; a1 = seg[0, 1]; a2 = seg[0, 2]
    d0 = seg[1, 0] - a0; d1 = seg[1, 1] - a1; d2 = seg[1, 2] - a2
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0 = d0 / length; e1 = d1 / length; e2 = d2 / length
    r0 = x[i, 0] - a0; r1 = x[i, 1] - a1; r2 = x[i, 2] - a2
    a = r0 * e0 + r1 * e1 + r2 * e2
    if a > length or a < (-lead if inserted else 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, a, 0.0
    p0 = r0 - a * e0; p1 = r1 - a * e1; p2 = r2 - a * e2
    r = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    slope = reach / lead
    R = reach if a >= 0.0 else reach + slope * a
    if r >= R:
        return False, 0.0, 0.0, 0.0, 0.0, a, 0.0
    if r < 1e-12:
        u0, u1, u2 = _across(e0, e1, e2)
    else:
        u0 = p0 / r; u1 = p1 / r; u2 = p2 / r
    t = a / length if a > 0.0 else 0.0
    if a >= 0.0:
        return True, R - r, u0, u1, u2, a, t
    c = 1.0 / math.sqrt(1.0 + slope * slope)
    return True, (R - r) * c, (u0 - slope * e0) * c, (u1 - slope * e1) * c, (u2 - slope * e2) * c, a, t


@njit(cache=True, fastmath=True)
def dent_force(body, motion, tool, seg, seg_vel, react):
    """A tip not yet inserted on its dent (``tool.shaft.patch_*``, module docstring): ``k_c d - c_c
    v_n`` along the axis on the dent's particles, by their weights; its reaction to ``react``.
    Explicit (one dent, the mass of a dimple). Returns the overlap ``d`` [m] (0: not touching)."""
    x, v, acc, fixed, inv_mass = motion.x, motion.v, motion.acc, body.fixed, body.inv_mass
    sh = tool.shaft
    d0 = seg[1, 0] - seg[0, 0]; d1 = seg[1, 1] - seg[0, 1]; d2 = seg[1, 2] - seg[0, 2]
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0 = d0 / length; e1 = d1 / length; e2 = d2 / length
    p0 = sh.patch_off[0]; p1 = sh.patch_off[1]; p2 = sh.patch_off[2]
    u0 = 0.0; u1 = 0.0; u2 = 0.0
    for t in range(sh.patch_n):
        j = sh.patch_idx[t]
        w = sh.patch_w[t]
        p0 += w * x[j, 0]; p1 += w * x[j, 1]; p2 += w * x[j, 2]
        u0 += w * v[j, 0]; u1 += w * v[j, 1]; u2 += w * v[j, 2]
    d = tool.reach + (p0 - seg[0, 0]) * e0 + (p1 - seg[0, 1]) * e1 + (p2 - seg[0, 2]) * e2
    if d <= 0.0:
        return 0.0
    vn = -((u0 - seg_vel[0, 0]) * e0 + (u1 - seg_vel[0, 1]) * e1 + (u2 - seg_vel[0, 2]) * e2)
    f = tool.stiffness * d - tool.damping * vn
    if f <= 0.0:
        return d
    react[0] += f * e0; react[1] += f * e1; react[2] += f * e2
    for t in range(sh.patch_n):
        j = sh.patch_idx[t]
        if not fixed[j]:
            g = f * sh.patch_w[t] * inv_mass
            acc[j, 0] -= g * e0; acc[j, 1] -= g * e1; acc[j, 2] -= g * e2
    return d


@njit(cache=True, fastmath=True, inline='always')
def _weight(s2, reach2):
    """``(1 - s^2 / R^2)^2`` within ``R`` of a point, else 0."""
    if s2 >= reach2:
        return 0.0
    u = 1.0 - s2 / reach2
    return u * u


@njit(cache=True, fastmath=True)
def shaft_hold(body, motion, cand, n_cand, tool, seg, react):
    """The inserted shaft's stick-slip hold along its axis on the particles of ``cand[:n_cand]``
    within ``grip_reach`` of it (module docstring), added to ``motion.acc``, its reaction to
    ``react``. Explicit: a particle's spring is ``k_c w`` for its share ``w`` of the shaft."""
    x, acc, fixed, inv_mass = motion.x, motion.acc, body.fixed, body.inv_mass
    sh = tool.shaft
    a0 = seg[0, 0]; a1 = seg[0, 1]; a2 = seg[0, 2]
    d0 = seg[1, 0] - a0; d1 = seg[1, 1] - a1; d2 = seg[1, 2] - a2
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0 = d0 / length; e1 = d1 / length; e2 = d2 / length
    reach2 = sh.grip_reach * sh.grip_reach
    for t in range(n_cand):
        i = cand[t]
        r0 = x[i, 0] - a0; r1 = x[i, 1] - a1; r2 = x[i, 2] - a2
        a = r0 * e0 + r1 * e1 + r2 * e2
        w = 0.0
        if 0.0 <= a <= length:
            w = sh.grip_norm * _weight(r0 * r0 + r1 * r1 + r2 * r2 - a * a, reach2)
        if w <= 0.0:
            sh.stuck[i] = False
            continue
        if not sh.stuck[i]:
            sh.anchor[i] = a
            sh.stuck[i] = True
            sh.sliding[i] = False
        k = tool.stiffness * w
        f = -k * (a - sh.anchor[i])
        cap = (sh.hold_dynamic if sh.sliding[i] else sh.hold_static) * w
        if abs(f) > cap:
            f = cap if f > 0.0 else -cap
            sh.anchor[i] = a + f / k
            sh.sliding[i] = True
        else:
            sh.sliding[i] = False
        react[0] -= f * e0; react[1] -= f * e1; react[2] -= f * e2
        if not fixed[i]:
            acc[i, 0] += f * e0 * inv_mass; acc[i, 1] += f * e1 * inv_mass; acc[i, 2] += f * e2 * inv_mass


@njit(cache=True, fastmath=True)
def tip_cut(body, motion, cand, n_cand, tool, seg, react):
    """The inserted tip's cut ``F_t`` (module docstring): on the needle along +axis, on the particles
    of ``cand[:n_cand]`` within ``grip_reach`` of the tip along -axis, by their weights; nothing
    where no particle is (a tip out of the tissue)."""
    x, acc, fixed, inv_mass = motion.x, motion.acc, body.fixed, body.inv_mass
    sh = tool.shaft
    q = ((sh.entry[0] - seg[0, 0]) * sh.axis[0] + (sh.entry[1] - seg[0, 1]) * sh.axis[1]
         + (sh.entry[2] - seg[0, 2]) * sh.axis[2])
    f_tip = min(max(sh.cut_stiffness * (q - sh.front), 0.0), sh.cut_force)
    if f_tip <= 0.0:
        return
    reach2 = sh.grip_reach * sh.grip_reach
    total = 0.0
    for t in range(n_cand):
        i = cand[t]
        r0 = x[i, 0] - seg[0, 0]; r1 = x[i, 1] - seg[0, 1]; r2 = x[i, 2] - seg[0, 2]
        total += _weight(r0 * r0 + r1 * r1 + r2 * r2, reach2)
    if total <= 0.0:
        return
    react[0] += f_tip * sh.axis[0]; react[1] += f_tip * sh.axis[1]; react[2] += f_tip * sh.axis[2]
    for t in range(n_cand):
        i = cand[t]
        r0 = x[i, 0] - seg[0, 0]; r1 = x[i, 1] - seg[0, 1]; r2 = x[i, 2] - seg[0, 2]
        w = _weight(r0 * r0 + r1 * r1 + r2 * r2, reach2)
        if w > 0.0 and not fixed[i]:
            g = f_tip * w / total * inv_mass
            acc[i, 0] -= g * sh.axis[0]; acc[i, 1] -= g * sh.axis[1]; acc[i, 2] -= g * sh.axis[2]


@njit(cache=True, fastmath=True)
def needle_forces(body, motion, cand, n_cand, tool, seg, seg_vel, react):
    """The needle ``tool.shaft`` on ``cand[:n_cand]`` (module docstring): its shaft's push, and
    inserted, its cone's, the shaft's hold and the tip's cut (else its dent), added to
    ``motion.acc``, their reaction to ``react``; every push of the shaft and cone recorded in
    ``tool.touches``. Returns the largest overlap [m]."""
    x, v, acc, fixed, inv_mass = motion.x, motion.v, motion.acc, body.fixed, body.inv_mass
    sh = tool.shaft
    reach, k_c, c_c = tool.reach, tool.stiffness, tool.damping
    best = 0.0
    for t in range(n_cand):
        i = cand[t]
        touching, overlap, n0, n1, n2, a, ts = _shaft_touch(i, x, seg, reach, sh.lead, sh.inserted)
        if not touching:
            continue
        if overlap > best:
            best = overlap
        fmag = penalty_push(i, v, seg_vel, ts, n0, n1, n2, overlap, k_c, c_c)
        if fmag <= 0.0:
            continue
        react[0] -= fmag * n0; react[1] -= fmag * n1; react[2] -= fmag * n2
        if tool.touches.on:
            record_touch(tool.touches, TOUCH_BALL, i, n0, n1, n2, False, seg, 0.0, tool.slot)
        if not fixed[i]:
            acc[i, 0] += fmag * n0 * inv_mass
            acc[i, 1] += fmag * n1 * inv_mass
            acc[i, 2] += fmag * n2 * inv_mass
    if not sh.inserted:
        if sh.patch_n > 0:
            best = max(best, dent_force(body, motion, tool, seg, seg_vel, react))
        return best
    shaft_hold(body, motion, cand, n_cand, tool, seg, react)
    tip_cut(body, motion, cand, n_cand, tool, seg, react)
    return best


@njit(cache=True)
def find_dent(x, cand, tip, e, reach, spacing, radius, idx, w, off):
    """Where the tip comes within a spacing of touching a particle of ``cand`` ahead of it (within a
    spacing of its axis ``e``): the particles within ``radius`` of that point on the axis into
    ``idx``, their weights ``(1 - s^2 / radius^2)^2`` (summing to 1) into ``w`` and the dent's
    offset into ``off``, placed no nearer than touching (a dent found late, or under a tip drawn
    back, starts without a jump). Returns how many (0: none ahead). Not fast-math: a replay finds the
    same dent on every CPU."""
    best = 1.0
    for t in range(cand.shape[0]):
        i = cand[t]
        r0 = x[i, 0] - tip[0]; r1 = x[i, 1] - tip[1]; r2 = x[i, 2] - tip[2]
        a = r0 * e[0] + r1 * e[1] + r2 * e[2]
        r2_axis = r0 * r0 + r1 * r1 + r2 * r2 - a * a
        if -reach - spacing < a <= 0.0 and r2_axis < spacing * spacing and (best > 0.0 or a > best):
            best = a
    if best > 0.0:
        return 0
    a_c = min(best, -reach)
    p0 = tip[0] + a_c * e[0]; p1 = tip[1] + a_c * e[1]; p2 = tip[2] + a_c * e[2]
    n = 0
    total = 0.0
    for i in range(x.shape[0]):
        d0 = x[i, 0] - p0; d1 = x[i, 1] - p1; d2 = x[i, 2] - p2
        s2 = d0 * d0 + d1 * d1 + d2 * d2
        if s2 < radius * radius and n < idx.shape[0]:
            u = 1.0 - s2 / (radius * radius)
            idx[n] = i
            w[n] = u * u
            total += u * u
            n += 1
    m0 = 0.0; m1 = 0.0; m2 = 0.0
    for t in range(n):
        w[t] /= total
        m0 += w[t] * x[idx[t], 0]; m1 += w[t] * x[idx[t], 1]; m2 += w[t] * x[idx[t], 2]
    off[0] = p0 - m0; off[1] = p1 - m1; off[2] = p2 - m2
    return n


@njit(cache=True)
def dent_overlap(x, idx, w, off, tip, e, reach):
    """[m] how far the tip presses its dent (negative: short of it); not fast-math (as :func:`find_dent`)."""
    p0 = off[0]; p1 = off[1]; p2 = off[2]
    for t in range(idx.shape[0]):
        p0 += w[t] * x[idx[t], 0]; p1 += w[t] * x[idx[t], 1]; p2 += w[t] * x[idx[t], 2]
    return reach + (p0 - tip[0]) * e[0] + (p1 - tip[1]) * e[1] + (p2 - tip[2]) * e[2]


class Puncture:
    """One needle's phase across frames (outside, touching, inserted) and what it keeps: its dent
    before, its entry point, axis and crack front after the puncture.

    Args:
        n: particles of the tissue.
        diameter: the needle's [m].
        kind: its :class:`~.contact_kinds.NeedleContact` (the reach of its shaft and of its hold).
        stiffness: [N/m] the contact's, which the tip's load below the front and the hold use too.
        spacing: [m] the particles' (the dent's radius is :data:`DENT_RADIUS` of it).
    """

    def __init__(self, n: int, diameter: float, kind, stiffness: float, spacing: float) -> None:
        self.diameter, self.stiffness, self.spacing = diameter, stiffness, spacing
        self.reach, self.grip_reach = kind.ball_reach, kind.grip_reach
        # a particle's share of the shaft: its volume over the weighted section, int w dA = pi R^2 / 3
        self.grip_norm = 3.0 * spacing ** 3 / (math.pi * self.grip_reach ** 2)
        self._idx = np.zeros(n, dtype=np.int32)     # find_dent's buffers
        self._w = np.zeros(n)
        self.anchor = np.zeros(n)
        self.stuck = np.zeros(n, dtype=np.bool_)
        self.sliding = np.zeros(n, dtype=np.bool_)
        self.entry = np.zeros(3)
        self.axis = np.array([0.0, 0.0, 1.0])
        self.reset()

    def reset(self) -> None:
        """Outside, no dent, no track."""
        self.state = OUTSIDE
        self.front = 0.0             # [m] the crack's front below the entry
        self._depth = 0.0
        self.stuck[:] = False
        self.punctures = 0           # since the last reset
        self.punctured = False       # in the last frame
        self._no_dent()

    def _no_dent(self) -> None:
        self.dent_idx = np.zeros(0, dtype=np.int32)
        self.dent_w = np.zeros(0)
        self.dent_off = np.zeros(3)

    @property
    def depth(self) -> float:
        """[m] how far the tip is below its entry point along the axis (0 unless inserted)."""
        return self._depth if self.state == INSERTED else 0.0

    def holding(self) -> np.ndarray:
        """The particles the needle loads beyond its shaft's balls: its dent's, or those its shaft
        holds (int32)."""
        if self.state == INSERTED:
            return np.flatnonzero(self.stuck).astype(np.int32)
        return self.dent_idx

    def shaft(self, toughness: float, hold: tuple) -> Shaft:
        """The frame's :class:`~.state.Shaft` in a tissue of ``toughness`` [J/m^2] that the shaft
        holds with ``hold`` (static, dynamic) [N/m]."""
        return Shaft(True, self.state == INSERTED, self.entry, self.axis, self.front, LEAD * self.reach,
                     cut_force(toughness, self.diameter), self.stiffness, self.grip_reach, self.grip_norm,
                     hold[0], hold[1], self.anchor, self.stuck, self.sliding,
                     self.dent_idx, self.dent_w, self.dent_off, len(self.dent_idx))

    def _find_dent(self, x: np.ndarray, cand: np.ndarray, tip: np.ndarray, e: np.ndarray) -> None:
        n = find_dent(x, cand, tip, e, self.reach, self.spacing, DENT_RADIUS * self.spacing, self._idx, self._w,
                      self.dent_off)
        self.dent_idx, self.dent_w = self._idx[:n].copy(), self._w[:n].copy()

    def update(self, seg: np.ndarray | None, reaction: np.ndarray, touching: bool, toughness: float,
               x: np.ndarray, cand: np.ndarray) -> bool:
        """After a frame that left the needle at ``seg`` (None: lifted) with the tissue's
        ``reaction`` [N] on it (``touching``: it touched), the particles at ``x`` and ``cand`` those
        near it: its next state. Returns True (and sets :attr:`punctured`) when it punctured in
        this frame."""
        self.punctured = False
        if seg is None:
            self.state = OUTSIDE
            self.stuck[:] = False      # lifted: the shaft's anchors go with it
            self._no_dent()
            return False
        tip = seg[0]
        # scalar arithmetic in a fixed order: a replay punctures at the same frame on every CPU
        t0, t1, t2 = tip.tolist()
        if self.state == INSERTED:
            n0, n1, n2 = self.axis.tolist()
            q0, q1, q2 = self.entry.tolist()
            self._depth = (q0 - t0) * n0 + (q1 - t1) * n1 + (q2 - t2) * n2
            if self._depth > 0.0:
                # the crack reaches as deep as the cutting force has pushed it
                self.front = max(self.front, self._depth - cut_force(toughness, self.diameter) / self.stiffness)
                return False
            self.stuck[:] = False      # drawn out above its entry point: outside again
        a0, a1, a2 = seg[1].tolist()
        a0, a1, a2 = a0 - t0, a1 - t1, a2 - t2
        size = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        e = np.array([a0 / size, a1 / size, a2 / size]) if size > 0.0 else self.axis.copy()
        if len(self.dent_idx) and (dent_overlap(x, self.dent_idx, self.dent_w, self.dent_off, tip, e, self.reach)
                                   < -DENT_LEAVE * self.spacing):
            self._no_dent()            # the tip has left its dent
        if not len(self.dent_idx):
            self._find_dent(x, cand, tip, e)
        self.state = TOUCHING if touching or len(self.dent_idx) else OUTSIDE
        f0, f1, f2 = reaction.tolist()
        e0, e1, e2 = e.tolist()
        if self.state != TOUCHING or f0 * e0 + f1 * e1 + f2 * e2 < puncture_force(toughness, self.diameter):
            return False
        self.state = INSERTED
        self.entry[:] = tip
        self.axis[:] = e
        self.stuck[:] = False          # a new track: no anchor from an earlier one
        self.front = 0.0
        self._depth = 0.0
        self.punctures += 1
        self.punctured = True
        self._no_dent()
        return True
