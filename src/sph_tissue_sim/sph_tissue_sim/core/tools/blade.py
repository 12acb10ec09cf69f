"""A scalpel's blade: an edge that cuts, oriented by the stylus."""

from __future__ import annotations

from .capsule import Capsule


class Blade(Capsule):
    """An edge of ``length`` [m] from the tip along the tool frame's +z (the stylus's axis, as the
    capsule's shaft), ``radius`` [m] thick: it presses like a capsule and breaks the bonds its edge
    loads (:mod:`~sph_tissue_sim.core.cutting`); the tissue meets it as balls, not surface samples
    (a crack face has none)."""

    name = 'blade'
    cuts = True
