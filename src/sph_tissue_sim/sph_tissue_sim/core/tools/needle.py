"""A needle: a thin shaft that pierces the tissue, oriented by the stylus."""

from __future__ import annotations

from .capsule import Capsule


class Needle(Capsule):
    """A shaft of ``length`` [m] from the tip along the tool frame's +z (the stylus's axis, as the
    capsule's), ``radius`` [m]: it presses like a capsule until the tissue pushes back along its
    axis with the puncture force, then enters (:mod:`~sph_tissue_sim.core.needle`)."""

    name = 'needle'
    pierces = True
