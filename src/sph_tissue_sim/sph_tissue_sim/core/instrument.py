"""What one instrument keeps between frames in a :class:`~.solver.Solver`.

Several instruments touch one tissue in the same frame (the frame loop runs the contact of each,
:mod:`.frame`); each has its own place, its own friction anchors, the particles it holds
(:mod:`.grasp`) and its own reaction. The solver holds one :class:`Instrument` per instrument and
hands their :class:`~.state.ToolPath` to the frame; their results come back as one
:class:`ToolResult` each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ToolResult:
    """One instrument's share of a :class:`~.solver.StepResult` (tissue frame, SI units)."""

    force: np.ndarray                 # (3,) [N] reaction of the tissue on the tool, clamped
    force_raw: np.ndarray             # (3,) [N] before clamping
    clamped: bool
    contact_index: int                # -1 without contact
    penetration: float                # [m] overlap of the deepest contacted particle or sample
    tool_lag: float = 0.0             # [m] requested minus simulated tool position (max_tool_speed)
    tool_segment: np.ndarray | None = None  # (2, 3) [m] the tool's segment after the step (None: lifted)
    grasped: int = 0                  # particles it holds after the step
    bonds_cut: int = 0                # a blade: the bonds it has cut since the last reset


class Instrument:
    """One instrument: its tool's shape and contact kind, and its state across frames: where its
    tool was, the particle it touches (kept while it still touches, see
    :meth:`~.solver.Solver._sticky_contact`), its friction anchors (:func:`~.contact.stick_slip`: a
    slot per particle, then per surface sample) and the particles it holds, with their anchors in
    the tool's frame."""

    def __init__(self, slots: int, tool, kind) -> None:
        self.tool = tool                 # its shape (:mod:`.tools`)
        self.kind = kind                 # its contact kind (:mod:`.contact_kinds`): reaches, samples
        self.samples = None              # its contact samples, set with the material
        self.anchor = np.zeros((slots, 3))
        self.stuck = np.zeros(slots, dtype=np.bool_)
        self.reset()

    def reset(self) -> None:
        """Lifted: no place, no contact, no anchor, nothing held."""
        self.stuck[:] = False
        self.tip: np.ndarray | None = None      # the tip position [m] of the previous frame
        self.segment: np.ndarray | None = None  # and the tool's segment (2, 3)
        self.rotation: np.ndarray | None = None  # and its orientation (3, 3)
        self.let_go()
        self.contact = -1                        # the particle it touched last frame
        #: backstop samples: one has pushed the tool, and the tool has touched the tissue ever since
        #: (the local area is the samples')
        self.samples_push = False

    def hold(self, idx: np.ndarray, local: np.ndarray) -> None:
        """Hold the particles ``idx`` at ``local`` (G, 3) [m]: where they sit from the tip, in the
        tool's frame."""
        self.grip_idx = np.ascontiguousarray(idx, dtype=np.int32)
        self.grip_local = np.ascontiguousarray(local, dtype=np.float64).reshape(-1, 3)
        self.grip_held = np.ones(len(self.grip_idx), dtype=np.bool_)
        self.grip_trail = np.zeros(3)     # [m] the anchors' base from the tip (grasp.trail_after)

    def let_go(self) -> int:
        """Release everything held; returns how many particles were."""
        held = self.holding if hasattr(self, 'grip_held') else 0
        self.hold(np.zeros(0, dtype=np.int32), np.zeros((0, 3)))
        return held

    @property
    def holding(self) -> int:
        """Particles held now (those that slipped are not)."""
        return int(np.count_nonzero(self.grip_held))
