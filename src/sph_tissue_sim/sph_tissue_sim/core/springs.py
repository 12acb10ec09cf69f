"""The ``mass_spring`` scheme: Kelvin-Voigt springs between reference neighbours (the paper's Table 1
baseline, the classic surgical-simulator model).

A particle ``i`` feels, from every neighbour ``j`` within ``SPRING_RADIUS`` spacings of it in the
reference configuration, with ``e = (x_j - x_i) / |x_j - x_i|``::

    f_i = sum_j k_ij [(|x_j - x_i| - l0_ij) + tau (v_j - v_i) . e] e

``l0`` is the reference length; ``k = E s / 1.8 (s / l0)^2`` is calibrated on a cubic lattice
(face and edge springs give ``E = 1.8 k_face / s``); ``tau`` is the material's retardation time, so
the springs creep like the continuum.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import overload

from .material import Material
from .neighbours import find_neighbours
from .protocols import STATUS_OK, FixedStateScheme, internal_forces, is_state

#: [spacings] a particle's springs reach its reference neighbours within this distance (face, edge
#: and corner neighbours of a cubic lattice: 1, 1.41, 1.73; 1.5 takes faces and edges)
SPRING_RADIUS = 1.5


class MassSpring(NamedTuple):
    """The scheme's state for the frame loop."""

    offsets: np.ndarray    # (N + 1,) CSR of spring neighbours
    indices: np.ndarray
    k: np.ndarray          # (nnz,) spring stiffness [N/m]
    rest: np.ndarray       # (nnz,) rest length [m]
    tau: float             # [s] dashpot time (material retardation time)


@njit(cache=True, fastmath=True)
def spring_force_one(i, x, v, offsets, indices, k_spring, rest, tau):
    """Spring force ``(f0, f1, f2)`` [N] on particle ``i``."""
    f0 = 0.0; f1 = 0.0; f2 = 0.0
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        d0 = x[j, 0] - x[i, 0]; d1 = x[j, 1] - x[i, 1]; d2 = x[j, 2] - x[i, 2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if r < 1e-12:
            continue
        e0 = d0 / r; e1 = d1 / r; e2 = d2 / r
        rate = (v[j, 0] - v[i, 0]) * e0 + (v[j, 1] - v[i, 1]) * e1 + (v[j, 2] - v[i, 2]) * e2
        mag = k_spring[k] * ((r - rest[k]) + tau * rate)
        f0 += mag * e0; f1 += mag * e1; f2 += mag * e2
    return f0, f1, f2


@njit(cache=True, fastmath=True)
def spring_pass(sph, n_sph, x, v, acc, inv_mass, offsets, indices, k_spring, rest, tau):
    """``acc = f / m`` of ``sph[:n_sph]``."""
    for t in range(n_sph):
        i = sph[t]
        f0, f1, f2 = spring_force_one(i, x, v, offsets, indices, k_spring, rest, tau)
        acc[i, 0] = f0 * inv_mass
        acc[i, 1] = f1 * inv_mass
        acc[i, 2] = f2 * inv_mass


@overload(internal_forces)
def _mass_spring_forces(scheme, body, motion, sets):
    if not is_state(scheme, MassSpring):
        return None

    def impl(scheme, body, motion, sets):
        spring_pass(sets.sph, sets.n_sph, motion.x, motion.v, motion.acc, body.inv_mass,
                    scheme.offsets, scheme.indices, scheme.k, scheme.rest, scheme.tau)
        return STATUS_OK
    return impl


class MassSpringScheme(FixedStateScheme):
    """The mass-spring springs of one model (:class:`~.protocols.FrameScheme`)."""

    name = 'mass_spring'

    def __init__(self, X: np.ndarray, spacing: float, spring_radius: float = SPRING_RADIUS) -> None:
        self.X = X
        self.spacing = spacing
        self.offsets, self.indices = find_neighbours(X, spring_radius * spacing * 1.0001)
        self._rows = np.repeat(np.arange(len(X)), np.diff(self.offsets))
        self.rest = np.linalg.norm(X[self.indices] - X[self._rows], axis=1)
        self.k = np.zeros(len(self.rest))
        self._state: MassSpring | None = None

    def set_material(self, material: Material, mass: float) -> None:
        s = self.spacing
        self.k = material.E * s / 1.8 * (s / np.maximum(self.rest, 1e-12)) ** 2
        self._state = MassSpring(self.offsets, self.indices, self.k, self.rest, material.retardation_time)
        self.E = material.E

    def wave_speed(self, material: Material, mass: float) -> float:
        """The stiffest particle's spring wave speed (the springs, not the continuum, set the CFL bound)."""
        kmax = float(np.max(np.add.reduceat(self.k, self.offsets[:-1]))) if len(self.k) else 0.0
        return max(material.wave_speed, math.sqrt(max(kmax, 1e-30) / mass) * self.spacing)

    def von_mises(self, x: np.ndarray, sets, out: np.ndarray) -> None:
        """A strain measure: E times each particle's largest spring strain (not a stress tensor)."""
        if not len(self.rest):
            return
        strain = np.abs(np.linalg.norm(x[self.indices] - x[self._rows], axis=1) / self.rest - 1.0)
        out[:] = self.E * np.maximum.reduceat(strain, self.offsets[:-1])
