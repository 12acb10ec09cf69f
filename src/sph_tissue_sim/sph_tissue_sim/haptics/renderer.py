"""One device's haptic renderer: estimator, virtual coupling, passivity, in that order.

Per device sample (tissue frame, SI units)::

    E_in  <- observer.observe(x)            energy of the force held since the last sample
    x^, v^ <- estimator.update(x, dt)
    proxy, F <- coupling.render(x^, v^)      against the contact model
    F <- F + controller.damp(E_in, v^, dt)   only while E_in < 0, in contact
    F <- F - spring + bound.limit(spring)    live timing only: the coupling's spring held to E_in
    F <- clamp(F, force_limit); observer.hold(F)

The proxy is where the solver should put its tool; after each solver step, :meth:`refresh` hands
the reaction it found there to the contact model. How often that happens (every pose, every ``k``
poses, or whenever a solver thread finishes) is the caller's choice; the renderer answers every
sample at once either way. A solver thread's model is late (live timing): its answers also pass
the energy bound (:class:`~.passivity.EnergyBound`). Lockstep answers do not: a model refreshed at
the proxy every pose or every few is passive as rendered (``benchmarks/haptic_quality.py``), and
the goldens replay bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tissue_common.force import HARD_FORCE_LIMIT, clamp_norm

from .coupling import ContactModel, VirtualCoupling
from tissue_common.estimator import TrackingFilter
from .passivity import EnergyBound, PassivityController, PassivityObserver

#: the contact model's stiffness may reach this many times the coupling's: it linearises the tissue
#: for the proxy's implicit update (a stiffer solver than the model destabilises the proxy), while the
#: hand never feels more than the coupling
STIFFNESS_CEILING = 50.0

#: (lowest, highest) of every :class:`RendererConfig` field, both included
RENDERER_RANGES = {
    'velocity_cutoff': (0.5, 500.0),
    'coupling_stiffness': (1.0, 3000.0),
    'coupling_damping': (0.0, 10.0),
    'proxy_damping': (0.01, 100.0),
    'passivity_max_damping': (0.0, 10.0),
    'energy_bound_stiffness': (10.0, 3000.0),
    'force_limit': (0.0, math.inf),    # in the renderer's units: the device's clamp is the caller's
}


@dataclass
class RendererConfig:
    """Renderer settings (SI units).

    Attributes:
        velocity_cutoff: cut-off of the position/velocity tracking filter [Hz] (see
            :mod:`tissue_common.estimator`); lower is smoother but overshoots more where the hand turns
            (which is active).
        coupling_stiffness: ``K_c`` of the virtual coupling [N/m]; the hand never feels more.
            Default 700 N/m, what a PHANTOM Omni renders (about 0.7 N/mm).
        coupling_damping: ``B_c`` on the device's velocity along the spring in contact [N s/m];
            passivity of the held spring needs ``B_c > K_c T / 2`` (0.35 at 700 N/m and 1 kHz);
            more covers the loop through the solver (see :mod:`.coupling`).
        proxy_damping: ``B_p`` on the simulated tool's offset from the device [N s/m].
        passivity_max_damping: the most damping the passivity controller may add [N s/m].
        energy_bound_stiffness: the least ``k_b`` of the live energy bound [N/m]: in live timing
            the force never gives back more than a spring of the contact's stiffness (at least
            this) would from the energy the hand put in (see :mod:`.passivity`).
            The floor is what a touch is felt as before the contact model has learned a stiffness,
            and what a force held to the bound falls at: 100 N/m changes it by 5.5 mN per
            encoder tick.
        force_limit: norm of the rendered force at most this [N] (set it to what the device
            receives, so that the passivity observer charges the force really held); also the
            most the coupling pushes the simulated tool into the tissue with (see :mod:`.coupling`).
    """

    velocity_cutoff: float = 30.0
    coupling_stiffness: float = 700.0
    coupling_damping: float = 1.5
    proxy_damping: float = 4.0
    passivity_max_damping: float = 2.0
    energy_bound_stiffness: float = 100.0
    force_limit: float = HARD_FORCE_LIMIT

    def validate(self) -> 'RendererConfig':
        """Raise ``ValueError`` naming the first field outside :data:`RENDERER_RANGES`."""
        for name, (lo, hi) in RENDERER_RANGES.items():
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and lo <= val <= hi):
                raise ValueError(f'{name} must be in [{lo:g}, {hi:g}], got {val!r}')
        return self


@dataclass
class Rendered:
    """One sample's answer."""

    force: np.ndarray       # (3,) [N] for the device (tissue frame), clamped
    proxy: np.ndarray       # (3,) [m] where the simulated tool should be
    energy: float           # E_in before this sample's force [J]
    damping: float          # damping the passivity controller added [N s/m]
    stretch: float          # coupling stretch [m]


class HapticRenderer:
    """Answers each device sample at once from the latest contact model."""

    def __init__(self, config: RendererConfig | None = None) -> None:
        self.config = (config or RendererConfig()).validate()
        c = self.config
        self.estimator = TrackingFilter(c.velocity_cutoff)
        self.model = ContactModel(k_max=STIFFNESS_CEILING * c.coupling_stiffness)
        # the proxy is pushed into the tissue with no more than the device can render
        self.coupling = VirtualCoupling(c.coupling_stiffness, c.coupling_damping, c.proxy_damping,
                                        self.model, c.force_limit)
        self.observer = PassivityObserver()
        self.controller = PassivityController(c.passivity_max_damping)
        self.bound = EnergyBound(c.energy_bound_stiffness)
        self.proxy = np.zeros(3)

    def reset(self) -> None:
        """Forget the device's past and the contact (e.g. after the tissue was reset)."""
        self.estimator.reset()
        self.model.clear()
        self.coupling.reset()
        self.observer.reset()
        self.controller.reset()
        self.bound.reset()

    def set_force_limit(self, limit: float) -> None:
        """A new force limit [N]: the clamp and the most the coupling pulls the tool with."""
        self.config.force_limit = limit
        self.coupling.push_limit = limit

    def answer(self, x, dt: float, live: bool = False) -> Rendered:
        """The force for the device sample ``x`` [m] taken ``dt`` [s] after the previous one;
        ``live``: the contact model comes from a solver thread (the energy bound applies)."""
        energy = self.observer.observe(x)
        if dt > 0.0:
            self.model.advance()
        x_hat, v_hat = self.estimator.update(x, dt)
        proxy, force = self.coupling.render(x_hat, v_hat, dt)
        pushing = bool(force.any())
        force = force + self.controller.damp(energy, v_hat, dt, engaged=pushing)
        if self.controller.alpha > 0.0:
            # the damper may slow the hand, never pull it into the tissue or push where the
            # coupling does not
            n = self.model.normal
            if not pushing or float(force @ n) <= 0.0:
                force = np.zeros(3)
        if live:
            kc, k = self.config.coupling_stiffness, self.model.stiffness
            self.bound.track(x_hat, self.observer.held, energy, kc * k / (kc + k), dt)
            # only the spring gives energy back: the dampers' parts pass
            spring = self.coupling.spring
            force = force - spring + self.bound.limit(spring, pushing)
            if pushing and float(force @ self.model.normal) <= 0.0:
                force = np.zeros(3)
        force, _ = clamp_norm(force, self.config.force_limit)
        self.observer.hold(force)
        self.proxy = proxy
        return Rendered(force, proxy, energy, self.controller.alpha, self.coupling.stretch)

    def refresh(self, point, force, served: int = 1, live: bool = False) -> bool:
        """The solver found the reaction ``force`` [N] with its tool at ``point`` [m]; the contact
        model it replaces answered ``served`` poses: a stale one's successor is blended in from the
        force at the proxy, and a solver thread's (``live``) first answer without contact is kept
        over (:class:`~.coupling.ContactModel`; returns False then)."""
        return self.model.refresh(point, force, served, self.proxy, live)
