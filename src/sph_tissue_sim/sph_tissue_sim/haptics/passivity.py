"""Time-domain passivity at the device port: an observer and a controller (Hannaford and Ryu).

The device holds each force ``F_k`` until the next sample (zero-order hold), so the energy the hand
has put into the virtual tissue after sample ``k`` is

    E_in(k) = - sum_{j<k} F_j . (x_{j+1} - x_j)

with ``x`` the device positions as sampled (not filtered: this is the energy the device really
exchanged). A viscoelastic tissue only dissipates, so ``E_in`` of a faithful rendering never goes
negative; sampling, delay and the solver's own integration errors can make it. When it has, the
controller adds a damper ``-alpha v^`` on the device's filtered velocity, sized to take the deficit
back over ``DISSIPATION_TIME``, ``alpha* = -E_in / (T_d |v^|^2)``, never more than ``max_damping``
(what the device can render). ``alpha`` moves towards ``alpha*`` by at most ``max_damping`` per
``RAMP_TIME``, so the added force changes as smoothly as the filtered velocity does. It adds
nothing while ``E_in >= 0``, so a passive rendering is left untouched.

Why the filtered velocity and a ramp: the device's positions come in encoder ticks (0.055 mm), so
the measured velocity is one tick per sample on one frame and zero on the next. A damper sized to
take the deficit back within one sample from that velocity kicked the hand by up to 0.19 N on
every tick (``alpha`` 2 N s/m times 55 mm/s, then nothing), and the force it held was charged
against the next sample's motion, usually none, so it did not even take the energy back
(docs/decisions/passivity-controller.md).
"""

from __future__ import annotations

import math

import numpy as np

#: slower than this the controller cannot dissipate (alpha would be unbounded) [m/s]
MIN_SPEED = 1e-6
#: the deficit is taken back over about this long [s]
DISSIPATION_TIME = 0.01
#: ``alpha`` takes this long to go from nothing to ``max_damping`` [s]
RAMP_TIME = 0.02


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
    """The damper that brings ``E_in`` back to zero, smoothly."""

    def __init__(self, max_damping: float) -> None:
        if not (math.isfinite(max_damping) and max_damping >= 0.0):
            raise ValueError(f'passivity max damping must be >= 0 N s/m, got {max_damping}')
        self.max_damping = max_damping
        self.alpha = 0.0              # damping added for the coming sample [N s/m]
        self.total = 0.0              # sum of alpha over samples (for averages) [N s/m]

    def reset(self) -> None:
        self.alpha = self.total = 0.0

    def damp(self, energy: float, velocity: np.ndarray, dt: float, engaged: bool = True) -> np.ndarray:
        """The force [N] to add for the coming sample, given ``E_in``, the device's filtered
        velocity and whether the rendering pushes the device now (``engaged``; out of contact the
        damper fades out: a drag in free space would be felt as a fault)."""
        if dt <= 0.0:
            return -self.alpha * velocity if self.alpha > 0.0 else np.zeros(3)
        speed2 = float(velocity @ velocity)
        target = 0.0
        if engaged and energy < 0.0:
            target = (self.max_damping if speed2 < MIN_SPEED * MIN_SPEED
                      else min(self.max_damping, -energy / (DISSIPATION_TIME * speed2)))
        step = self.max_damping * dt / RAMP_TIME
        self.alpha = min(target, self.alpha + step) if target >= self.alpha else max(target, self.alpha - step)
        if self.alpha <= 0.0:
            self.alpha = 0.0
            return np.zeros(3)
        self.total += self.alpha
        return -self.alpha * velocity
