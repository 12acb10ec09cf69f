"""A blade that cuts: which bonds its edge breaks in a frame, and what that costs.

The blade is an edge (a thin capsule, :mod:`.tools.blade`) moved by the stylus. It meets the
tissue's balls and its bonds (:class:`~.contact_kinds.BladeContact`): each frame, every bond near
the edge gets a sample at its point closest to the edge (:func:`aim_bonds`), so the edge cannot pass
between two particles without pressing on the bond that joins them, and it loads the tissue in
front of it like any tool. What a blade adds is the crack (Mahvash and Okamura's cutting
model, its growth made discrete by the bonds):

* the **cutting plane** holds the edge and the direction it last moved across itself; only the
  bonds across it open the crack (a bond beside the edge is pushed aside, not cut);
* the **work** ``W`` the blade has done on the tissue since its crack last grew,
  ``W <- max(0, W - f.dp)`` each frame (``f`` the tissue's reaction on the tool, ``dp`` the edge's
  travel), pays for the crack: while ``W >= G_c a_b``, the bond across the plane that the edge
  presses deepest breaks and ``W`` drops by ``G_c a_b`` (``a_b`` the crack area of a bond,
  :func:`~.bonds.bond_area`);
* the broken bond's middle no longer holds the edge, the particles on either side part, and the
  edge sinks to the next bonds.

So the force rises while the edge deforms the tissue, then drops when the bonds in front let go
and the tissue opens: the sawtooth of a real cut, with ``G_c`` of work per unit area of crack. A
blade off the tissue forgets its work (what it stored springs back), and work with no bond under
the edge is not banked beyond one bond's worth.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .bonds import Bonds
from .contact import closest_on_segment
from .surface_contact import sample_offset, samples_in_reach

#: [m] an edge moving less than this across itself in a frame keeps its last cutting direction
STILL = 1e-9


@njit(cache=True)
def bond_parameter(x, i, j, seg):
    """``u`` in [0, 1]: the point ``x_i + u (x_j - x_i)`` of the bond closest to the segment ``seg``."""
    d10 = x[j, 0] - x[i, 0]; d11 = x[j, 1] - x[i, 1]; d12 = x[j, 2] - x[i, 2]
    d20 = seg[1, 0] - seg[0, 0]; d21 = seg[1, 1] - seg[0, 1]; d22 = seg[1, 2] - seg[0, 2]
    r0 = x[i, 0] - seg[0, 0]; r1 = x[i, 1] - seg[0, 1]; r2 = x[i, 2] - seg[0, 2]
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * r0 + d21 * r1 + d22 * r2
    if a <= 1e-30:
        return 0.0
    c = d10 * r0 + d11 * r1 + d12 * r2
    if e <= 1e-30:
        return min(max(-c / a, 0.0), 1.0)
    b = d10 * d20 + d11 * d21 + d12 * d22
    denom = a * e - b * b
    u = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 1e-30 * a * e else 0.0
    t = (b * u + f) / e
    if t < 0.0:
        u = min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        u = min(max((b - c) / a, 0.0), 1.0)
    return u


@njit(cache=True)
def aim_bonds(x, cand, n_cand, seg, far, start, w_idx, w_val, gone):
    """Put each intact bond sample of ``cand[:n_cand]`` (particles within ``far`` [m] of the edge
    ``seg``) at its bond's point closest to the edge: weights ``1 - u``, ``u``."""
    for t in range(n_cand):
        i = cand[t]
        if start[i] == start[i + 1]:
            continue
        c0, c1, c2, _ = closest_on_segment(x[i, 0], x[i, 1], x[i, 2], seg)
        e0 = x[i, 0] - c0; e1 = x[i, 1] - c1; e2 = x[i, 2] - c2
        if e0 * e0 + e1 * e1 + e2 * e2 > far * far:
            continue
        for s in range(start[i], start[i + 1]):
            if gone[s]:
                continue
            u = bond_parameter(x, w_idx[2 * s], w_idx[2 * s + 1], seg)
            w_val[2 * s] = 1.0 - u
            w_val[2 * s + 1] = u


@njit(cache=True)
def pressed_samples(x, v, cand, n_cand, seg, normal, samples, out_s, out_d):
    """The bond samples of ``cand[:n_cand]`` inside the tool (segment ``seg`` swept by
    ``samples.radius``) whose bond crosses the cutting plane (through ``seg[0]``, of unit
    ``normal``: its two particles on either side, one on the plane on its + side): their indices
    into ``out_s`` and overlaps [m] into ``out_d``; returns how many."""
    n = 0
    radius = samples.radius
    w_idx = samples.w_idx
    for t in range(n_cand):
        i = cand[t]
        if not samples_in_reach(i, x, seg, samples, 0.0):
            continue
        for s in range(samples.start[i], samples.start[i + 1]):
            a = w_idx[2 * s]
            b = w_idx[2 * s + 1]
            sa = ((x[a, 0] - seg[0, 0]) * normal[0] + (x[a, 1] - seg[0, 1]) * normal[1]
                  + (x[a, 2] - seg[0, 2]) * normal[2])
            sb = ((x[b, 0] - seg[0, 0]) * normal[0] + (x[b, 1] - seg[0, 1]) * normal[1]
                  + (x[b, 2] - seg[0, 2]) * normal[2])
            if (sa >= 0.0) == (sb >= 0.0):
                continue
            e0, e1, e2, ts, u0, u1, u2 = sample_offset(s, x, v, seg, samples)
            r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            if r < radius:
                out_s[n] = s
                out_d[n] = radius - r
                n += 1
    return n


class Cutter:
    """One blade's crack across frames: the work it has to spend and the bonds it broke.

    Args:
        bonds: the scheme's :class:`~.bonds.Bonds`.
        kind: the blade's :class:`~.contact_kinds.BladeContact` (its bonds' samples).
    """

    def __init__(self, bonds: Bonds, kind) -> None:
        self.bonds, self.kind = bonds, kind
        self.out_s = np.zeros(kind.n_samples, dtype=np.int64)
        self.out_d = np.zeros(kind.n_samples)
        self.normal = np.zeros(3)
        self.reset()

    def reset(self) -> None:
        """Off the tissue, nothing cut."""
        self.work = 0.0                            # [J] done since the crack last grew
        self.length = 0.0                          # [m] the edge's travel across itself while cutting
        self._pending = 0.0                        # [m] and since the crack last grew, this touch
        self.direction: tuple | None = None        # the edge's last motion across itself (unit)
        self.cut = 0                               # bonds this blade broke
        self.last_cut = 0                          # in the last frame
        self.bond_energy = 0.0                     # [J] what a bond cost in the last frame: G_c a_b

    def aim(self, x: np.ndarray, seg: np.ndarray, cand: np.ndarray, n_cand: int) -> None:
        """Before a frame that ends with the edge at ``seg`` (2, 3): its bonds' samples where the
        bonds of ``cand[:n_cand]`` come closest to it (:func:`aim_bonds`)."""
        k = self.kind
        aim_bonds(x, cand, n_cand, seg, k.aim_reach, k.arrays[0], k.w_idx, k.w_val, k.gone)

    def frame(self, x: np.ndarray, v: np.ndarray, seg0: np.ndarray, seg1: np.ndarray,
              reaction: np.ndarray, touching: bool, cand: np.ndarray, n_cand: int, samples,
              toughness: float) -> np.ndarray:
        """After a frame that took the edge from ``seg0`` to ``seg1`` (2, 3) with the tissue's
        ``reaction`` [N] on it (``touching``: it touched): add its work, and pick the bonds it pays
        for at ``G_c`` = ``toughness`` [J/m^2], deepest first, among the bonds' ``samples`` of
        ``cand[:n_cand]``. Returns their pair indices (for :meth:`Bonds.cut`)."""
        self.last_cut = 0
        self.bond_energy = toughness * self.bonds.area
        none = np.zeros(0, dtype=np.int64)
        if not touching:
            self.work = self._pending = 0.0
            return none
        # scalar arithmetic in a fixed order: the crack a replay opens is the same on every CPU
        d0, d1, d2 = (seg1[0] - seg0[0]).tolist()
        r0, r1, r2 = reaction.tolist()
        self.work = max(0.0, self.work - (r0 * d0 + r1 * d1 + r2 * d2))
        e0, e1, e2 = (seg1[1] - seg1[0]).tolist()
        n = max(math.sqrt(e0 * e0 + e1 * e1 + e2 * e2), 1e-12)
        e0, e1, e2 = e0 / n, e1 / n, e2 / n
        along = d0 * e0 + d1 * e1 + d2 * e2
        a0, a1, a2 = d0 - along * e0, d1 - along * e1, d2 - along * e2
        across = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        self._pending += across
        if across > STILL:
            self.direction = (a0 / across, a1 / across, a2 / across)
        if self.work < self.bond_energy or self.direction is None:
            return none
        # the cutting plane holds the edge and its motion: the bonds across it open the crack
        m0, m1, m2 = self.direction
        n0, n1, n2 = e1 * m2 - e2 * m1, e2 * m0 - e0 * m2, e0 * m1 - e1 * m0
        size = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if size < 1e-9:          # the edge turned along its last motion: no plane
            return none
        self.normal[:] = (n0 / size, n1 / size, n2 / size)
        n = pressed_samples(x, v, cand, n_cand, seg1, self.normal, samples, self.out_s, self.out_d)
        if n == 0:
            self.work = self.bond_energy    # nothing under the edge to spend it on: not banked
            return none
        afford = min(n, int(self.work // self.bond_energy))
        order = np.lexsort((self.out_s[:n], -self.out_d[:n]))[:afford]    # deepest first, then by sample
        self.work -= afford * self.bond_energy
        if self.cut:                 # the cut runs from the first bond on: its length is the way since
            self.length += self._pending
        self._pending = 0.0
        self.cut += afford
        self.last_cut = afford
        return self.kind.pair_of[self.out_s[:n][order]]
