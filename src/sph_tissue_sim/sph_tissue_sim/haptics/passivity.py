"""Time-domain passivity at the device port: an observer, a controller (Hannaford and Ryu) and, in
live timing, an energy bound.

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

The controller acts once ``E_in`` is below zero, and a damper cannot take much back from a slow
hand, so neither catches what a late contact model does: a live solver's answer to the press
arrives tens of milliseconds after it, so the force rises while the hand holds still and is still
high while it withdraws; more comes back than went in (-50 to -150 uJ per 3 mm poke at half real
time). In live timing the :class:`EnergyBound` therefore holds the coupling spring's force to what
the energy the hand has put in can pay back through a spring of stiffness ``k_b``::

    |F| <= sqrt(2 k_b (E_in - E_touch + E_0))

(``E_touch = min(E_in when the touch began, 0)``, a touch beginning where the rendering starts to
push, ``E_0`` an allowance for its first force). A fast withdrawal whose damper outweighs the
spring ends a touch, and each new one may forgive up to ``E_0`` and a tick's work: counting a
touch from the contact model's contact instead gave 3 one-frame reversals on quick pokes answered
40 poses late, where this gives none. Like the observer, this is passivity since the reset: energy the hand put
in during earlier touches (the tissue's and the dampers' dissipation) may be given back later. A passive rendering of a tissue at most ``k_b`` stiff stays below the bound (it took
``F^2 / 2k`` to reach ``F``); one that would give back more is held to it, and its force then
falls with the hand's withdrawal at ``k_b``, as smoothly as such a tissue's. ``k_b`` is the
contact model's stiffness as the hand feels it (in series with the coupling) averaged over
``BOUND_TIME``, and at least a floor: the model's own stiffness jumps from refresh to refresh, and
a bound that jumped with it clicked (docs/decisions/energy-bound.md). A deficit left by an earlier
touch is not carried into the next (``E_touch``): a tool that owes energy could never push again.
Only the coupling's spring is bounded: its dampers take energy, never give it.

``E_in`` moves in encoder ticks, so a force held to a bound on it is a staircase (``k_b`` times a
tick, 5.5 mN at 100 N/m, every tick). The bound reads a smooth account instead: the held force's
work along the filtered positions, whose drift from ``E_in`` (the filter's overshoot where the hand
turns) is taken out over ``ACCOUNT_TIME``, so that over any longer time it is ``E_in``'s.
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
#: ``E_0``: the energy a touch may give back before the hand has put any in [J] (at 100 N/m its
#: first force may be 6 mN, then it grows with the hand's work)
TOUCH_ALLOWANCE = 0.05e-6
#: the energy bound's stiffness follows the contact model's over about this long [s]
BOUND_TIME = 0.05
#: the energy bound's smooth account comes back to ``E_in`` over about this long [s]
ACCOUNT_TIME = 0.02


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

    @property
    def held(self) -> np.ndarray:
        """The force [N] the device holds now."""
        return self._f


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


class EnergyBound:
    """The live spring force held to what the hand's energy can pay back (module docstring)."""

    def __init__(self, min_stiffness: float) -> None:
        if not (math.isfinite(min_stiffness) and min_stiffness > 0.0):
            raise ValueError(f'energy bound stiffness must be > 0 N/m, got {min_stiffness}')
        self.min_stiffness = min_stiffness
        self.reset()

    def reset(self) -> None:
        self.stiffness = self.min_stiffness    # k_b [N/m]
        self._along = 0.0                      # the held force's work along the filtered points [J]
        self._drift = 0.0                      # E_in minus that, low-passed [J]
        self._last: np.ndarray | None = None
        self.touch_energy = 0.0                # E_touch [J]
        self.touching = False
        self.bound = math.inf                  # the latest sample's bound [N]

    @property
    def account(self) -> float:
        """The smooth account of ``E_in`` [J]."""
        return self._along + self._drift

    def track(self, x_hat: np.ndarray, held: np.ndarray, energy: float, stiffness: float,
              dt: float) -> None:
        """One sample: the filtered device point [m], the force held since the previous one [N],
        ``E_in`` [J], the contact's stiffness as felt [N/m] and the time since the previous
        sample [s]."""
        if self._last is not None:
            self._along -= float(held @ (x_hat - self._last))
        self._last = np.array(x_hat, dtype=float)
        if dt > 0.0:
            self._drift += min(dt / ACCOUNT_TIME, 1.0) * (energy - self._along - self._drift)
            self.stiffness += min(dt / BOUND_TIME, 1.0) * (max(stiffness, self.min_stiffness)
                                                           - self.stiffness)

    def limit(self, spring: np.ndarray, touching: bool) -> np.ndarray:
        """The spring's force [N] scaled down to the bound; ``touching``: the rendering pushes now
        (a touch begins where it starts to)."""
        energy = self.account
        if touching and not self.touching:
            self.touch_energy = min(energy, 0.0)
        self.touching = touching
        if not touching:
            self.bound = math.inf
            return spring
        self.bound = math.sqrt(2.0 * self.stiffness * max(energy - self.touch_energy + TOUCH_ALLOWANCE, 0.0))
        mag = math.sqrt(float(spring @ spring))
        return spring * (self.bound / mag) if mag > self.bound else spring
