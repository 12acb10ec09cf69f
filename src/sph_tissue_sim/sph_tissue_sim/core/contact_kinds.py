"""Contact kinds: where the tool meets the tissue, as the solver needs it.

A kind owns its reach radii, its surface samples (if any) and how it grows the local area (the
pushing contacts are integrated backward and bound no sub-step). The kinds, chosen by
``SolverConfig.contact_samples``:

- :class:`BallContact` (0): the tool against the particles' balls of ``BALL_RADIUS`` spacings; the
  tool slips between them.
- :class:`SampledContact` (n > 0): the balls, and behind them n x n samples per surface particle on
  the material's surface (:mod:`.surface_contact`) that hold the tool out of the gaps.
- :class:`NeedleContact` (a needle, whatever the setting): small balls, and the particles its
  shaft's friction holds.
- :class:`BladeContact` (a blade, whatever the setting): touching balls, and a sample on every
  intact bond where it comes closest to the edge, so that the edge rests on the bonds it must cut
  (:mod:`.cutting`).

A new kind is one class with the same attributes and methods, and its line in :func:`make_contact`.
"""

from __future__ import annotations

import numpy as np

from .state import TOUCH_BOND, Samples
from .surface_contact import SURFACE_OFFSET, no_samples, surface_samples

#: [spacings] radius of a particle's contact ball
BALL_RADIUS = 1.0
#: [spacings] the balls a blade meets: touching ones (:class:`BladeContact`)
BLADE_BALL = 0.5
#: [spacings] how thick a bond is for a blade
BOND_BALL = 0.5
#: [spacings] the balls a needle's shaft meets: the hole it opens is its radius and this
NEEDLE_BALL = 0.5
#: [spacings] a needle's shaft holds the particles this close to its axis by friction
NEEDLE_GRIP = 1.5
#: [m] where a cut bond's sample goes (from the weighted sum, which is then zero): beyond any tool
BOND_GONE = np.array([0.0, 0.0, -100.0])
#: backstop samples that push the tool grow the local area's radius by this many h (with the
#: half-space far field)
SAMPLE_AREA_GROWTH = 1.5


class BallContact:
    """The particles as balls. Reach radii [m] (tool radius included): ``contact_reach`` (where a
    first touch is), ``ball_reach`` (a ball's spring), ``detect_reach`` (the local area's centre),
    ``cand_reach`` and ``samples_reach`` (the local area's candidates before and after the samples
    push the tool)."""

    per_side = 0

    def __init__(self, tool_radius: float, spacing: float, ball: float | None = None) -> None:
        # BALL_RADIUS read at each call (None): tests shrink it for the samples alone
        self.ball_reach = tool_radius + (BALL_RADIUS if ball is None else ball) * spacing
        self.contact_reach = self.detect_reach = self.cand_reach = self.samples_reach = self.ball_reach

    @property
    def n_samples(self) -> int:
        return 0

    def samples(self, n: int, tool_radius: float, stiffness: float, damping: float) -> Samples:
        """The frame's samples (none) for ``n`` particles and a ball dashpot of ``damping`` [N s/m]."""
        return no_samples(n)

    def area(self, pushing: bool, organ: bool, Dr: float, h: float) -> tuple[float, float]:
        """(candidate reach [m], area radius [m]) of the local area: the balls' whatever happens."""
        return self.cand_reach, Dr


class SampledContact(BallContact):
    """The balls in front and ``per_side`` x ``per_side`` samples per surface particle behind them.

    The tool meets the samples on the material's surface, half a spacing outside the particle
    centres, and the particles' own balls: of the tool's size behind the samples, or of
    ``BALL_RADIUS`` in front of them (the samples then a backstop)."""

    def __init__(self, tool_radius: float, spacing: float, per_side: int, X: np.ndarray,
                 offsets: np.ndarray, indices: np.ndarray, h: float, volume: float) -> None:
        super().__init__(tool_radius, spacing)
        self.per_side = per_side
        surface_reach = tool_radius + SURFACE_OFFSET * spacing
        self.contact_reach = max(surface_reach, self.ball_reach)
        *self.arrays, reach, support = surface_samples(X, offsets, indices, h, volume, spacing, per_side)
        # a sample reads particles within `support` of it: farther than this from its owner, the
        # material around it is torn apart
        self.margin = reach + support + spacing
        # touch detection (the local area's centre) sees a particle where its samples may touch,
        # and local mode solves every particle a touching sample reads
        self.detect_reach = max(tool_radius + reach, self.ball_reach)
        self.samples_reach = max(tool_radius + reach + support, self.ball_reach)
        # a sample lies within `reach` of its owner, inside the owner's ball: until a sample
        # pushes the tool (Solver.samples_push), the balls' candidates and area suffice
        self.cand_reach = self.ball_reach

    @property
    def n_samples(self) -> int:
        return len(self.arrays[4])

    def samples(self, n: int, tool_radius: float, stiffness: float, damping: float) -> Samples:
        # a sample carries 1/per**2 of its particle's mass: the same damping ratio per sample
        return Samples(*self.arrays[:5], tool_radius, stiffness, damping / self.per_side, self.margin,
                       *self.arrays[5:])

    def area(self, pushing: bool, organ: bool, Dr: float, h: float) -> tuple[float, float]:
        """Once a sample pushes the tool: every particle a touching sample reads is solved, and with
        the half-space far field the area grows (sized for the balls, its shell is too near the
        samples' spread load: local mode 12 % too soft or 7 % too stiff at a 10 mm press); the
        organ's far field knows the organ's shape there."""
        if not pushing:
            return self.cand_reach, Dr
        return self.samples_reach, Dr if organ else Dr + SAMPLE_AREA_GROWTH * h


class BladeContact(BallContact):
    """Touching balls (:data:`BLADE_BALL`) and a sample on every intact bond (i, j), ``(1 - u) x_i +
    u x_j`` at the point closest to the edge (``u`` set each frame, :func:`~.cutting.aim_bonds`), of
    reach :data:`BOND_BALL` spacings: an edge between two particles meets the bond that joins them,
    which a ball model lets it slip through. A cut bond's sample leaves (:meth:`drop`); :meth:`reset`
    brings them all back. ``sample_of[k]``: pair k's sample, ``pair_of[s]``: sample s's pair (the
    one from its lower particle)."""

    def __init__(self, tool_radius: float, spacing: float, X: np.ndarray, offsets: np.ndarray,
                 indices: np.ndarray, rev: np.ndarray) -> None:
        super().__init__(tool_radius, spacing, BLADE_BALL)
        n = len(X)
        owner = np.repeat(np.arange(n), np.diff(offsets))
        lower = np.flatnonzero(owner < indices)           # each bond once, from its lower particle
        self.pair_of = lower
        self.sample_of = np.full(len(indices), -1, dtype=np.int64)
        self.sample_of[lower] = np.arange(len(lower))
        self.sample_of[rev[lower]] = np.arange(len(lower))
        i, j = owner[lower], indices[lower]
        start = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(i, minlength=n), out=start[1:])
        self.w_idx = np.ascontiguousarray(np.stack([i, j], axis=1).reshape(-1), dtype=np.int32)
        self.w_val = np.full(2 * len(lower), 0.5)
        self.offset = np.zeros((len(lower), 3))
        # a particle's samples read it and its higher neighbours, at most half a bond from it
        read_start = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(i, minlength=n) + (np.bincount(i, minlength=n) > 0), out=read_start[1:])
        read = np.zeros(read_start[-1], dtype=np.int32)
        for p in np.unique(i):
            read[read_start[p]:read_start[p + 1]] = np.concatenate([[p], j[start[p]:start[p + 1]]])
        own_reach = np.zeros(n)
        np.maximum.at(own_reach, i, np.linalg.norm(X[j] - X[i], axis=1))
        self.gone = np.zeros(len(lower), dtype=np.bool_)
        self.bond_reach = tool_radius + BOND_BALL * spacing
        self.margin = float(own_reach.max()) + spacing     # a stretched bond's far end, from its owner
        #: [m] the bonds of particles this close to the edge are aimed at it
        self.aim_reach = self.bond_reach + self.margin
        self.arrays = (start, np.arange(0, 2 * len(lower) + 1, 2, dtype=np.int64), self.w_idx, self.w_val,
                       self.offset, X, read_start, read, own_reach)
        self.contact_reach = self.detect_reach = max(self.ball_reach, self.bond_reach)
        self.cand_reach = self.samples_reach = max(self.ball_reach, self.bond_reach + float(own_reach.max()))

    @property
    def n_samples(self) -> int:
        return len(self.offset)

    def samples(self, n: int, tool_radius: float, stiffness: float, damping: float) -> Samples:
        """The bonds' samples: reach :data:`BOND_BALL` spacings past the edge, the balls' contact law."""
        return Samples(*self.arrays[:5], self.bond_reach, stiffness, damping, self.margin, *self.arrays[5:],
                       TOUCH_BOND)

    def drop(self, pairs: np.ndarray) -> None:
        """The bonds ``pairs`` (pair indices, either direction) are cut: their samples leave."""
        s = np.unique(self.sample_of[pairs])
        self.gone[s] = True
        self.w_val[2 * s] = 0.0
        self.w_val[2 * s + 1] = 0.0
        self.offset[s] = BOND_GONE

    def reset(self) -> None:
        """Every bond's sample back (the organ whole again)."""
        self.gone[:] = False
        self.w_val[:] = 0.5
        self.offset[:] = 0.0


class NeedleContact(BallContact):
    """Balls of :data:`NEEDLE_BALL` spacings (a needle opens a hole about its own size) and the
    particles within :data:`NEEDLE_GRIP` spacings of its axis as candidates: its shaft's friction
    holds them (:mod:`.needle`)."""

    def __init__(self, tool_radius: float, spacing: float) -> None:
        super().__init__(tool_radius, spacing, NEEDLE_BALL)
        self.grip_reach = NEEDLE_GRIP * spacing
        self.cand_reach = self.samples_reach = max(self.ball_reach, self.grip_reach)


def make_contact(per_side: int, tool_radius: float, spacing: float, X: np.ndarray, offsets: np.ndarray,
                 indices: np.ndarray, h: float, volume: float) -> BallContact:
    """The contact kind of ``per_side`` samples per side (0: the balls alone)."""
    if per_side == 0:
        return BallContact(tool_radius, spacing)
    return SampledContact(tool_radius, spacing, per_side, X, offsets, indices, h, volume)
