"""Time-domain passivity at the device port: an observer and a controller (Hannaford and Ryu).

The device holds each force ``F_k`` until the next sample (zero-order hold), so the energy the hand
has put into the virtual tissue after sample ``k`` is

    E_in(k) = - sum_{j<k} F_j . (x_{j+1} - x_j)

with ``x`` the device positions as sampled (not filtered: this is the energy the device really
exchanged). A viscoelastic tissue only dissipates, so ``E_in`` of a faithful rendering never goes
negative; sampling, delay and the solver's own integration errors can make it. When it has, the
controller adds a damper ``-alpha v`` on the measured velocity (a filtered one lags, and a damper on
a velocity of the wrong sign gives energy), sized to take the deficit back over the next sample,
``alpha = -E_in / (T |v|^2)``, and never more than ``max_damping`` (what the device can render).
It adds nothing while ``E_in >= 0``, so a passive rendering is left untouched.
"""

from __future__ import annotations

import math

import numpy as np

#: slower than this the controller cannot dissipate (alpha would be unbounded) [m/s]
MIN_SPEED = 1e-6


class PassivityObserver:
    """``E_in`` at the device port (zero-order hold)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.energy = 0.0             # E_in [J]
        self.minimum = 0.0            # lowest E_in seen [J]
        self.last: np.ndarray | None = None    # the latest sample [m]
        self._f = np.zeros(3)

    def observe(self, x) -> float:
        """The device is now at ``x`` [m]: charge the last force's work; returns ``E_in`` [J]."""
        x = np.array(x, dtype=float)
        if self.last is not None:
            self.energy -= float(self._f @ (x - self.last))
            self.minimum = min(self.minimum, self.energy)
        self.last = x
        return self.energy

    def hold(self, force) -> None:
        """``force`` [N] is what the device holds until the next sample."""
        self._f = np.array(force, dtype=float)


class PassivityController:
    """The damper that keeps ``E_in`` non-negative."""

    def __init__(self, max_damping: float) -> None:
        if not (math.isfinite(max_damping) and max_damping >= 0.0):
            raise ValueError(f'passivity max damping must be >= 0 N s/m, got {max_damping}')
        self.max_damping = max_damping
        self.alpha = 0.0              # damping added for the coming sample [N s/m]
        self.total = 0.0              # sum of alpha over samples (for averages) [N s/m]

    def damp(self, energy: float, velocity: np.ndarray, dt: float) -> np.ndarray:
        """The force [N] to add for the coming sample, given ``E_in`` and the device's velocity."""
        speed2 = float(velocity @ velocity)
        if energy >= 0.0 or dt <= 0.0 or speed2 < MIN_SPEED * MIN_SPEED:
            self.alpha = 0.0
            return np.zeros(3)
        self.alpha = min(self.max_damping, -energy / (dt * speed2))
        self.total += self.alpha
        return -self.alpha * velocity
