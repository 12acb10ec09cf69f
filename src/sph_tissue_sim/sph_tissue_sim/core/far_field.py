"""Local mode's far field: where the still particles around the solved ones are put each frame.

The paper holds everything beyond the transmission layers at rest, which clamps the area a few h
from the tool and makes it stiffer than the whole organ. A far field moves those particles with
the tissue around instead, from each instrument's contact load (``LocalArea.ff_load``, low-passed
by the area; the responses add).
Two kinds, chosen by :func:`make_far_field`:

* :class:`Organ`: the organ's own linear response (:class:`~.compliance.OrganCompliance`, factored
  once per organ and cached on disk) placed on the stress shell and the ring around it, the load
  shared by the touched particles;
* :class:`HalfSpace`: the elastic half-space's response (Boussinesq) on the stress shell, for
  organs too large to factor or schemes without a stiffness matrix.

Both are linear and elastic at the instantaneous moduli: with a relaxing spring (``Material.prony``)
the far field does not relax, so a held press's local area drifts stiffer than the whole organ
(a 4 mm press on a 10 x 10 x 5 block held 1 s, g = 0.4 + 0.4 exp(-t / 50 ms) + 0.2 exp(-t / 0.5 s):
local / global 1.086 against Kelvin-Voigt's 1.047);
a stiffening spring's extra term is of third order and does not reach it.

A new kind is one class with ``name``, ``place(area, body, x, sets)`` and ``close(timeout)``.
"""

from __future__ import annotations

import numpy as np

from .compliance import OrganCompliance, shell_and_ring
from .local_area import LocalArea, far_field_shell
from .material import Material
from .state import Body, Sets


class HalfSpace:
    """The stress shell at the elastic half-space's response to the load (:func:`~.local_area.
    far_field_shell`), for the material's shear modulus and Poisson ratio."""

    name = 'half_space'

    def __init__(self, material: Material) -> None:
        self.G, self.nu = material.G, material.nu

    def place(self, area: LocalArea, body: Body, x: np.ndarray, sets: Sets) -> None:
        area.n_ff = far_field_shell(body, x, sets, area.ff_mark, area.ff_list, area.n_ff, area.centres,
                                    area.ff_load, self.G, self.nu, area.buf_x, area.ff_buf, area.ff_buf2)

    def close(self, timeout: float = 0.0) -> bool:
        return True


class Organ:
    """The stress shell and its ring at the organ's own response to the load, shared by the
    particles the tool touched (:func:`~.compliance.shell_and_ring`,
    :meth:`~.compliance.OrganCompliance.place`)."""

    name = 'organ'

    def __init__(self, compliance: OrganCompliance) -> None:
        self.compliance = compliance

    def place(self, area: LocalArea, body: Body, x: np.ndarray, sets: Sets) -> None:
        start = area.touch_start
        for k in range(len(area.ff_at)):     # an instrument that touches nothing keeps its last place
            if start[k + 1] > start[k]:
                area.ff_at[k] = area.touch[start[k]:start[k + 1]].copy()
                area.ff_w[k] = area.touch_w[start[k]:start[k + 1]].copy()
        area.n_ff = shell_and_ring(body, area.topo, sets, area.ff_mark, area.ff_list, area.n_ff, x)
        if any(len(at) for at in area.ff_at) and area.n_ff:
            self.compliance.place_loads(x, area.X, area.ff_list[:area.n_ff],
                                        list(zip(area.ff_at, area.ff_w, area.ff_load)))

    def close(self, timeout: float = 0.0) -> bool:
        return self.compliance.close(timeout)


def make_far_field(local: bool, gain: float, material: Material,
                   organ: OrganCompliance | None) -> HalfSpace | Organ | None:
    """The far field of a solver: none in global mode or with ``gain`` 0, the organ's where its
    compliance was built, else the half-space's."""
    if not local or gain <= 0.0:
        return None
    return Organ(organ) if organ is not None else HalfSpace(material)
