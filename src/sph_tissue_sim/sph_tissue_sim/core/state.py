"""The named bundles the frame kernels read: one tuple per kind of state, not long argument lists.

They are ``NamedTuple``s so numba passes them into ``@njit`` kernels as they are (fields keep their
names there). Arrays in them are the solver's own, preallocated buffers: building a bundle copies
nothing, and a kernel writing ``motion.x[i, 0]`` writes the solver's positions.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Body(NamedTuple):
    """The reference configuration and the constants of every particle."""

    X: np.ndarray          # (N, 3) reference positions [m]
    fixed: np.ndarray      # (N,) bool: held at X (boundary)
    mass: float            # [kg] of every particle
    inv_mass: float        # [1/kg]


class Topology(NamedTuple):
    """Reference neighbours within 2h (CSR): particle ``i``'s are ``indices[offsets[i]:offsets[i + 1]]``."""

    offsets: np.ndarray
    indices: np.ndarray


class Grid(NamedTuple):
    """A cell grid over the reference positions (:class:`~.neighbours.CellGrid`)."""

    origin: np.ndarray         # (3,) lower corner [m]
    cell: float                # [m] cell size
    dims: np.ndarray           # (3,) cells per axis
    cell_start: np.ndarray     # (ncells + 1,) CSR offsets
    cell_particles: np.ndarray  # (N,) particles bucketed by cell


class Area(NamedTuple):
    """The local area's marks and index buffers (all length N; :class:`~.local_area.LocalArea`)."""

    region: np.ndarray     # int8: 0 still, 1 solved, 1 + i layer i
    in_area: np.ndarray    # int8: inside the area (or a candidate) this frame
    in_active: np.ndarray  # int8: listed in ``active``
    active: np.ndarray     # particles moving (area, layers, still relaxing)
    stamp: np.ndarray      # int64 set membership marks (:func:`~.neighbours.append_new`)
    sph: np.ndarray        # the frame's sets (see :class:`Sets`)
    layer: np.ndarray
    layer_w: np.ndarray
    stress: np.ndarray
    cand: np.ndarray       # (2N,)
    tmp: np.ndarray        # scratch for grid queries
    touch: np.ndarray      # touched particles and their overlaps (fixed capacity, per instrument)
    touch_w: np.ndarray
    centres: np.ndarray    # (K, 3) each instrument's area's centre in reference space [m]
    layer_counts: np.ndarray  # particles per layer of the last frame
    layer_tool: np.ndarray  # int32: the instrument whose layer a layer particle is in (one in two
                            # instruments' areas is solved, not a layer)


class Motion(NamedTuple):
    """The current state, advanced in place by the frame loop."""

    x: np.ndarray          # (N, 3) positions [m]
    v: np.ndarray          # (N, 3) velocities [m/s]
    acc: np.ndarray        # (N, 3) accelerations of the last sub-step [m/s^2]


class Sets(NamedTuple):
    """The index sets of one frame (arrays with counts, so a local frame costs O(area)).

    ``sph`` are integrated fully, ``stress`` (a superset) get a stress state, ``layer`` move
    kinematically with weight ``layer_w`` (paper eqs. 20-21), ``cand`` may touch a tool.
    A layer particle ``i`` follows its instrument ``k = layer_tool[i]``: the ``touch_w``-weighted
    mean velocity of the particles that instrument touches, ``touch[touch_start[k]:touch_start[k + 1]]``,
    or of its ``contacts[k]`` particle alone when none is listed.
    """

    stress: np.ndarray
    n_stress: int
    sph: np.ndarray
    n_sph: int
    layer: np.ndarray
    layer_w: np.ndarray
    n_layer: int
    cand: np.ndarray
    n_cand: int
    touch: np.ndarray
    touch_w: np.ndarray
    touch_start: np.ndarray   # (K + 1,) int64
    contacts: np.ndarray      # (K,) int64, -1: none
    layer_tool: np.ndarray


#: :attr:`Touches.kind` of a pushing contact: a particle's ball, a surface sample, a bond's sample
TOUCH_BALL, TOUCH_SAMPLE, TOUCH_BOND = 0, 1, 2


class Samples(NamedTuple):
    """Contact samples on the material's surface (or a blade's on the bonds, :mod:`.cutting`) and
    their contact law (:mod:`.surface_contact`)."""

    start: np.ndarray      # (N + 1,) particle i owns samples start[i] .. start[i + 1] - 1
    w_start: np.ndarray    # (S + 1,) CSR of each sample's interpolation weights
    w_idx: np.ndarray      # particles read
    w_val: np.ndarray      # and their weights
    offset: np.ndarray     # (S, 3) [m] added to the weighted sum
    radius: float          # [m] the tool's radius
    stiffness: float       # [N/m] penalty stiffness per sample
    damping: float         # [N s/m] contact dashpot per sample
    margin: float          # [m] a sample is never farther than this from its owning particle
    ref: np.ndarray        # (N, 3) the reference positions (Body.X)
    read_start: np.ndarray  # (N + 1,) CSR of the particles any of particle i's samples read
    read_idx: np.ndarray
    own_reach: np.ndarray  # (N,) [m] the farthest reference distance of particle i's samples from it
    kind: int = TOUCH_SAMPLE  # what a touch of one of them is (Touches.kind)


class Touches(NamedTuple):
    """The contacts of the last sub-step that pushed (for an implicit contact update,
    :mod:`.implicit_contact`): ``kind[t]`` :data:`TOUCH_BALL`, :data:`TOUCH_SAMPLE` or
    :data:`TOUCH_BOND`, ``idx[t]`` the particle or sample, ``normal[t]`` its unit normal, ``held[t]`` whether its friction sticks
    (its tangential spring acts too), ``axis[t]`` the tool's axis where the closest point is
    inside a shaft (the spring then does not act along it; zero elsewhere) and ``tool[t]`` the
    instrument whose contact or grasp it is; ``count[0]`` of them. ``on`` False: the contact kernels record
    nothing."""

    on: bool
    kind: np.ndarray       # (cap,) int8
    idx: np.ndarray        # (cap,) int32
    normal: np.ndarray     # (cap, 3)
    count: np.ndarray      # (1,) int64
    held: np.ndarray       # (cap,) bool
    axis: np.ndarray       # (cap, 3)
    tool: np.ndarray       # (cap,) int32


def no_touches() -> Touches:
    """Touches that record nothing (explicit contact)."""
    return Touches(False, np.zeros(1, dtype=np.int8), np.zeros(1, dtype=np.int32), np.zeros((1, 3)),
                   np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.bool_), np.zeros((1, 3)),
                   np.zeros(1, dtype=np.int32))


class Grip(NamedTuple):
    """The particles a tool holds (:mod:`.grasp`): ``idx[t]`` for ``t < n`` while ``held[t]``, each
    pulled towards the tool's tip plus ``off0[t]`` at the frame's start and ``off1[t]`` at its end
    [m] (the anchor turned with the tool), let go above ``limit`` [N]."""

    idx: np.ndarray        # (G,) int32
    n: int
    off0: np.ndarray       # (G, 3) [m]
    off1: np.ndarray       # (G, 3) [m]
    held: np.ndarray       # (G,) bool, cleared by the kernel when a particle slips
    limit: float           # [N]


class Shaft(NamedTuple):
    """A needle (:mod:`.needle`): once inserted its entry point and axis at the puncture, the
    crack's front ahead of its tip, the laws of its tip and shaft and the shaft's hold on each
    particle; before, its dent (``needle`` False: a tool that is not a needle, its arrays empty)."""

    needle: bool
    inserted: bool         # it has punctured the surface
    entry: np.ndarray      # (3,) [m] where the tip was when it punctured
    axis: np.ndarray       # (3,) unit: the needle's +z then (the tip advances along -axis)
    front: float           # [m] how deep, from the entry along -axis, the tip's crack reaches
    lead: float            # [m] the tip's cone: it spreads the particles this far ahead of the tip
    cut_force: float       # [N] the force that advances the crack at the tip
    cut_stiffness: float   # [N/m] the tip's load below it, per metre short of the front
    grip_reach: float      # [m] the shaft holds the particles this close to its axis
    grip_norm: float       # [m] a particle's share of the shaft's length at the axis
    hold_static: float     # [N/m] per metre of shaft: the most it holds the tissue with, sticking
    hold_dynamic: float    # [N/m] and sliding
    anchor: np.ndarray     # (N,) [m] where along the shaft (from the tip) a held particle sticks
    stuck: np.ndarray      # (N,) bool: it has an anchor
    sliding: np.ndarray    # (N,) bool: it slides (the dynamic hold)
    patch_idx: np.ndarray  # (P,) int32: not inserted, the particles of the surface under the tip
    patch_w: np.ndarray    # (P,) their weights (summing to 1)
    patch_off: np.ndarray  # (3,) [m] the dent's point: sum w x + patch_off
    patch_n: int           # 0: no dent


class ToolPath(NamedTuple):
    """The tool across one frame and the contact law (see :mod:`.contact`)."""

    seg0: np.ndarray       # (2, 3) the tool's segment at the start of the frame [m]
    seg1: np.ndarray       # (2, 3) and at its end (both ends move linearly across the sub-steps)
    on: bool               # False: no tool this frame (no contact forces)
    reach: float           # [m] contact distance: tool radius + particle contact radius
    stiffness: float       # [N/m] penalty stiffness per particle
    damping: float         # [N s/m] contact dashpot per particle
    samples: Samples       # contact samples (none: the particles' ball model alone)
    touches: Touches       # where the pushing contacts are recorded (implicit contact)
    friction: float        # Coulomb coefficient of the stick-slip friction (0: frictionless)
    anchor: np.ndarray     # (N + S, 3) [m] where a stuck particle (0..N-1) or sample (N + s) sits
                           # relative to the tool's closest point
    stuck: np.ndarray      # (N + S,) bool: it holds an anchor (it touched in the last sub-step)
    slot: int              # which of the solver's instruments this is (the row of its reaction)
    grip: Grip             # the particles it holds (none: n = 0)
    shaft: Shaft           # a needle's shaft once inserted (:mod:`.needle`)


class Loads(NamedTuple):
    """Constant external forces: ``force[t]`` [N] on free particle ``idx[t]`` for ``t < n``."""

    idx: np.ndarray
    force: np.ndarray
    n: int
