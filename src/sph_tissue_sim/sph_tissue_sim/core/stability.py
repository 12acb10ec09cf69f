"""The dashpots' rate at the current state: a sub-step bound that follows the deformation.

Symplectic Euler integrates a dashpot of rate ``c`` (an eigenvalue of ``M^-1 C``, ``C`` the
linearised damping of the material's Kelvin-Voigt and hourglass dashpots) stably only while
``c dt < 2``. The viscous bound ``C rho h^2 / eta`` of :func:`~.integrate.substep_bounds` is the
reference configuration's, and its margin is smaller than its constant suggests: measured by
power iteration at rest, the liver's largest rate is 2835 / 4692 / 8427 / 18622 1/s at 3670 / 12k
/ 30k / 100k particles, so the sub-steps the bounds give run at ``c dt`` = 1.42 / 1.56 / 1.40 /
1.43. The dashpot's stress ``F S(sym(F^T dF/dt))`` grows with the deformation: the 12k liver
pressed 30 mm deep has ``c`` = 1.37 ``c_0``, ``c dt`` = 2.14, and its force rang by up to 1 N
from one frame to the next (the elastic part's rate grew 4.3x, but its ``omega dt`` only reached
1.16 of the 2 it may).

:class:`DashpotRate` follows ``c`` at the current positions by power iteration, one pass of the
dashpots alone over the particles being solved every few frames (every frame while the rate
rises near the limit), warm-started from the previous vector, and bounds the sub-step by
``DASHPOT_LIMIT / c`` (the contacts' dashpots are integrated backward and bound nothing). At
rest it leaves the reference bounds in charge; it only adds sub-steps where the deformation has
made the dashpots faster than they allow. Its arrays take 0.36 kB per particle (36 MB on the
100k liver, zero pages until touched: a 100k solver's RSS grows by 3 MB).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .state import Body, Motion, Sets
from .tlsph import Tlsph, TlsphPool, tlsph_pass, tlsph_pass_parallel

#: the largest ``c dt`` allowed: 80 % of symplectic Euler's limit for a dashpot (2), which leaves
#: room for the springs acting in the same modes (at rest the bounds give 1.24-1.56 on the liver)
DASHPOT_LIMIT = 1.6

#: frames between two power iterations that follow the dashpots' rate (the 12k liver pressed 30 mm
#: deep reached ``c dt`` = 2.1 at the reference bounds' sub-step and its force rang by up to 1 N per
#: frame without it)
DASHPOT_RATE_EVERY = 8

#: from this ``c dt`` on a rate that rose at its last iteration is followed every frame (a deep
#: press raised it by up to 10 % per 0.5 mm); otherwise every ``every`` frames
CLOSE = 1.0

#: a rise of the estimate by more than this fraction per frame since the last iteration counts as
#: rising (a deep press: 0.2-1 % per frame; a palpating tool or a converged iteration at a still
#: state: under 0.01 %)
RISING = 1e-3


@njit(cache=True)
def _load(u, v, idx, n):
    """``v = u / |u|`` on the particles ``idx[:n]`` (zero elsewhere already); returns ``|u|``."""
    total = 0.0
    for t in range(n):
        i = idx[t]
        total += u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2]
    norm = math.sqrt(total)
    if not norm > 0.0:
        return 0.0
    for t in range(n):
        i = idx[t]
        for c in range(3):
            v[i, c] = u[i, c] / norm
    return norm


@njit(cache=True)
def _store(acc, u, v, idx, n):
    """The next vector ``u = -acc`` (``acc = -M^-1 C v``) on ``idx[:n]``, ``v`` back to zero there;
    returns ``|acc|``: for a unit ``v``, the rate estimate (from below)."""
    total = 0.0
    for t in range(n):
        i = idx[t]
        for c in range(3):
            a = acc[i, c]
            total += a * a
            u[i, c] = -a
            v[i, c] = 0.0
    return math.sqrt(total)


class DashpotRate:
    """The largest rate [1/s] of the explicit dashpots at the current positions, tracked by power
    iteration: one pass of the dashpots every ``every`` frames, every frame while it rises past
    ``c dt`` = :data:`CLOSE`.

    Args:
        state: the scheme's state with only the dashpots on (:meth:`~.tlsph.TlsphScheme.dashpots_only`).
        n: number of particles.
        every: frames between two iterations.
    """

    def __init__(self, state: Tlsph, n: int, every: int) -> None:
        self.state = state
        self.every = every
        self._u = np.zeros((n, 3))           # the iteration's vector (warm start)
        self._v = np.zeros((n, 3))           # it as the velocities of the solved particles, else 0
        self._acc = np.zeros((n, 3))
        self._rng = np.random.default_rng(0)
        self._moving: Motion | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the state: no rate known until the next :meth:`update`."""
        self.rate = 0.0
        self._rising = False
        self._frames = 0
        self._u[:] = 0.0
        self._rng = np.random.default_rng(0)

    def update(self, body: Body, x: np.ndarray, sets: Sets, sub_dt: float) -> float:
        """Count a finished frame on ``sets`` with sub-steps of ``sub_dt`` [s] ending at positions
        ``x``; when due, one power iteration over ``sets.sph`` (the contact's dashpots are
        integrated backward and bound nothing). Returns the rate's estimate [1/s]."""
        self._frames += 1
        due = self._frames >= self.every or (self._rising and self.rate * sub_dt >= CLOSE)
        if not due or sets.n_sph == 0:
            return self.rate
        gap, self._frames = self._frames, 0
        if not _load(self._u, self._v, sets.sph, sets.n_sph) > 0.0:
            # first time here, or the area moved on
            idx = sets.sph[:sets.n_sph]
            self._u[idx] = self._rng.standard_normal((len(idx), 3))
            _load(self._u, self._v, sets.sph, sets.n_sph)
        if isinstance(self.state, TlsphPool) and sets.n_stress >= self.state.par_min:
            tlsph_pass_parallel(self.state, body, self._motion(x), sets)
        else:
            tlsph_pass(self.state, body, self._motion(x), sets)
        rate = _store(self._acc, self._u, self._v, sets.sph, sets.n_sph)
        if math.isfinite(rate):
            self._rising = rate > self.rate * (1.0 + RISING * gap)
            self.rate = rate
        else:                                # a state the frame's own checks will refuse
            self._u[sets.sph[:sets.n_sph]] = 0.0
        return self.rate

    def _motion(self, x: np.ndarray) -> Motion:
        if self._moving is None or self._moving.x is not x:
            self._moving = Motion(x, self._v, self._acc)
        return self._moving

    def bound(self) -> float:
        """The largest stable sub-step [s] at the rate last measured (inf before the first)."""
        return DASHPOT_LIMIT / self.rate if self.rate > 0.0 else math.inf
