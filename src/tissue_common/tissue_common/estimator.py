"""Position and velocity of an encoder-quantised device: a critically damped tracking filter.

The Omni reports positions in ticks of about 0.055 mm. At 1 kHz a one-frame difference turns a
single tick into a 55 mm/s velocity for one frame, and every damping term fed with it (contact
dashpot, coupling damper, passivity controller) kicks the hand at every tick. The filter tracks
position and velocity with a second-order loop whose two poles sit at ``lam = exp(-w T)``,
``w = 2 pi f_c`` (the cut-off ``f_c``, ``T`` the sample period)::

    predict   x- = x^ + v^ T
    correct   e  = x - x-,   x^ = x- + a e,   v^ = v^ + (b / T) e
    a = 1 - lam^2,   b = (1 - lam)^2          (characteristic polynomial (z - lam)^2)

It is an alpha-beta filter whose error dynamics are critically damped: a constant-velocity ramp is
tracked without lag (a type-2 loop), so quantised ramps come out as ramps. A single tick ``q``
moves ``x^`` by ``a q`` and ``v^`` by ``b q / T`` on its frame and the rest over about
``1 / (2 pi f_c)``: at the default 30 Hz and 1 kHz, 0.31 q and 1.6 mm/s instead of q and 55 mm/s.
Being type 2, the estimate overshoots where the motion stops or turns (at 10 Hz, 0.3 mm past the
bottom of a 3 mm, 5 Hz poke); the coupling's spring reads that estimate, so the overshoot returns
energy to the hand on the way out. Hence 30 Hz by default: on quick pokes of a stiff wall the
rendering stays passive up to 5 Hz (``benchmarks/haptic_quality.py``), at the price of a little
more of each tick in the force.
"""

from __future__ import annotations

import math

import numpy as np


class TrackingFilter:
    """Filtered position ``x`` and velocity ``v`` of a sampled 3-D position."""

    def __init__(self, cutoff: float) -> None:
        if not (math.isfinite(cutoff) and cutoff > 0.0):
            raise ValueError(f'velocity cut-off must be a positive frequency [Hz], got {cutoff}')
        self.omega = 2.0 * math.pi * cutoff
        self.x = np.zeros(3)
        self.v = np.zeros(3)
        self.started = False
        self._dt = math.nan
        self._a = self._b = 0.0

    def reset(self, x=None) -> None:
        """Forget the past; the next sample (or ``x``) starts the track at rest."""
        self.started = x is not None
        if x is not None:
            self.x = np.array(x, dtype=float)
        self.v = np.zeros(3)

    def update(self, x, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Take the sample ``x`` [m], ``dt`` [s] after the previous one; returns (x^, v^).

        The first sample, or ``dt <= 0`` (a repeated stamp), only sets or keeps the estimate."""
        x = np.asarray(x, dtype=float)
        if not self.started:
            self.reset(x)
            return self.x, self.v
        if dt <= 0.0:
            return self.x, self.v
        if dt != self._dt:
            lam = math.exp(-self.omega * dt)
            self._dt, self._a, self._b = dt, 1.0 - lam * lam, (1.0 - lam) ** 2
        pred = self.x + self.v * dt
        err = x - pred
        self.x = pred + self._a * err
        self.v = self.v + (self._b / dt) * err
        return self.x, self.v
