"""Linearly implicit contact (``SolverConfig.contact_integration = 'implicit'``).

An explicit penalty contact must resolve the spring and dashpot of every pushing contact:
``dt <= C 2 sqrt(m / k)`` and ``dt <= m / c``. With the surface samples (9 per surface particle, each
with the balls' stiffness) that asks for about 4x the sub-steps of the material, and on fine models
(the particle mass falls with the spacing cubed, the penalty per particle does not) the contact's
bounds outgrow the CFL bound. Here the contacts that pushed in this sub-step (recorded by the
contact kernels in :class:`~.state.Touches`) are integrated backward in time along their normals:
with ``f_t = k d n - c (n . (v_t - v_tool)) n`` evaluated at the sub-step's start (the explicit
force, already in ``a``) and its change over the sub-step linearised,

    f_t'' = f_t - (dt k + c) n n^T Phi_t v'' + c n n^T Phi_t v,

where ``Phi_t v`` is the contact point's velocity (a particle's own, or a sample's weighted sum),

    (M + sum_t (dt^2 k + dt c) Phi_t^T n n^T Phi_t) v'' = M v* + sum_t dt c Phi_t^T n n^T Phi_t v

with ``v* = v + dt a``. The matrix is symmetric positive definite and touches only the particles
under the tool: a ball's block is solved in closed form, samples by a few conjugate-gradient
iterations over that handful of particles (no SPH pass). The tangential (curvature) part of the
penalty's stiffness stays explicit, and a contact that would release within the sub-step is
still held by its linearisation until the next one. The reaction on the tool gets the same
correction, so the tool and the tissue exchange equal and opposite impulses.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import overload

from .protocols import advance, is_state


class ContactTerms(NamedTuple):
    """The pushing contacts of a sub-step and their laws, for a backward-Euler solve.

    ``touches`` (:class:`~.state.Touches`) is the record the contact kernels write; ``w_start,
    w_idx, w_val`` the samples' weights; ``k_ball, c_ball`` and ``k_sample, c_sample`` the contact
    laws; ``react`` (3,) the frame's reaction accumulator; ``vn`` (cap,) each touch's normal
    velocity at the sub-step's start (scratch).
    """

    touches: tuple
    w_start: np.ndarray
    w_idx: np.ndarray
    w_val: np.ndarray
    k_ball: float
    c_ball: float
    k_sample: float
    c_sample: float
    react: np.ndarray
    vn: np.ndarray


class ImplicitContactEuler(NamedTuple):
    """Symplectic Euler with the pushing contacts backward in time; sub-step ``dt`` [s].
    ``u, r, p, q, w`` (N, 3) are scratch (``w`` stays zero off the solved set); ``stats`` (2,)
    iterations and solves."""

    dt: float
    contact: ContactTerms
    tol: float
    max_iter: int
    u: np.ndarray
    r: np.ndarray
    p: np.ndarray
    q: np.ndarray
    w: np.ndarray
    stats: np.ndarray


@njit(cache=True, fastmath=True, inline='always')
def _law(c, t):
    """``(k, c)`` of touch ``t``."""
    if c.touches.kind[t] == 0:
        return c.k_ball, c.c_ball
    return c.k_sample, c.c_sample


@njit(cache=True, fastmath=True, inline='always')
def _point_normal_velocity(c, t, vel):
    """``n_t . Phi_t vel``: the contact point's velocity along its normal."""
    tc = c.touches
    n0 = tc.normal[t, 0]; n1 = tc.normal[t, 1]; n2 = tc.normal[t, 2]
    j = tc.idx[t]
    if tc.kind[t] == 0:
        return n0 * vel[j, 0] + n1 * vel[j, 1] + n2 * vel[j, 2]
    s = 0.0
    for k in range(c.w_start[j], c.w_start[j + 1]):
        i = c.w_idx[k]
        s += c.w_val[k] * (n0 * vel[i, 0] + n1 * vel[i, 1] + n2 * vel[i, 2])
    return s


@njit(cache=True, fastmath=True, inline='always')
def _spread(c, t, amount, out):
    """``out += amount Phi_t^T n_t`` (the contact point's normal force on its particles)."""
    tc = c.touches
    n0 = tc.normal[t, 0]; n1 = tc.normal[t, 1]; n2 = tc.normal[t, 2]
    j = tc.idx[t]
    if tc.kind[t] == 0:
        out[j, 0] += amount * n0; out[j, 1] += amount * n1; out[j, 2] += amount * n2
        return
    for k in range(c.w_start[j], c.w_start[j + 1]):
        i = c.w_idx[k]
        a = amount * c.w_val[k]
        out[i, 0] += a * n0; out[i, 1] += a * n1; out[i, 2] += a * n2


@njit(cache=True, fastmath=True)
def contact_residual(c, inv_m, dt, v, dv, r):
    """``r += -(1/m) sum_t Phi^T n [dt^2 k n . Phi v + (dt^2 k + dt c) n . Phi dv]``: the contacts'
    share of the residual at ``v* = v + dv`` (``dv`` zero off the solved set); keeps each touch's
    ``n . Phi v`` in ``c.vn`` for :func:`contact_reaction`."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        vn = _point_normal_velocity(c, t, v)
        c.vn[t] = vn
        _spread(c, t, -(dt * dt * kk * vn + (dt * dt * kk + dt * cc) * _point_normal_velocity(c, t, dv)) * inv_m, r)


@njit(cache=True, fastmath=True)
def contact_apply(c, inv_m, dt, w, q):
    """``q += sum_t (dt^2 k + dt c) / m Phi^T n n^T Phi w`` (``w`` zero off the solved set)."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        _spread(c, t, (dt * dt * kk + dt * cc) * inv_m * _point_normal_velocity(c, t, w), q)


@njit(cache=True, fastmath=True)
def contact_reaction(c, dt, dv):
    """The reaction's share of the solve: ``react += (dt k n . Phi v'' + c n . Phi (v'' - v)) n``
    with ``dv = v'' - v`` (zero off the solved set) and ``n . Phi v`` from :func:`contact_residual`."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        d = _point_normal_velocity(c, t, dv)
        g = dt * kk * (c.vn[t] + d) + cc * d
        c.react[0] += g * c.touches.normal[t, 0]
        c.react[1] += g * c.touches.normal[t, 1]
        c.react[2] += g * c.touches.normal[t, 2]


@njit(cache=True, fastmath=True)
def _dot(a, b, sph, n):
    t = 0.0
    for k in range(n):
        i = sph[k]
        t += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return t


@njit(cache=True, fastmath=True)
def _set_on(dst, src, sub, sph, n):
    """``dst = src - sub`` on the solved set."""
    for k in range(n):
        i = sph[k]
        for a in range(3):
            dst[i, a] = src[i, a] - sub[i, a]


@njit(cache=True, fastmath=True)
def _zero_on(dst, sph, n):
    for k in range(n):
        i = sph[k]
        for a in range(3):
            dst[i, a] = 0.0


@njit(cache=True)
def implicit_contact_step(s, body, motion, sets):
    """One sub-step: ``v* = v + dt a``, the contact system above by conjugate gradients from
    ``v*`` (to ``s.tol`` of ``|v*|``), the reaction corrected, ``x += dt v''``. Without
    ``fastmath`` (its passes have their own flags) so that the stopping tests hold for a NaN."""
    x, v, acc = motion.x, motion.v, motion.acc
    sph, n = sets.sph, sets.n_sph
    dt = s.dt
    inv_m = body.inv_mass
    u, r, p, q, w = s.u, s.r, s.p, s.q, s.w
    c = s.contact
    for k in range(n):
        i = sph[k]
        for a in range(3):
            u[i, a] = v[i, a] + dt * acc[i, a]
    it = 0
    if c.touches.count[0] > 0:
        _set_on(w, u, v, sph, n)
        _zero_on(r, sph, n)
        contact_residual(c, inv_m, dt, v, w, r)
        _zero_on(w, sph, n)
        for k in range(n):
            i = sph[k]
            for a in range(3):
                p[i, a] = r[i, a]
        rr = _dot(r, r, sph, n)
        limit = s.tol * max(math.sqrt(_dot(u, u, sph, n)), math.sqrt(rr))
        while it < s.max_iter and math.sqrt(rr) > limit:
            for k in range(n):
                i = sph[k]
                for a in range(3):
                    w[i, a] = p[i, a]
                    q[i, a] = p[i, a]
            contact_apply(c, inv_m, dt, w, q)   # q = p + the contact terms
            _zero_on(w, sph, n)
            pq = _dot(p, q, sph, n)
            if not pq > 0.0:
                break
            alpha = rr / pq
            for k in range(n):
                i = sph[k]
                for a in range(3):
                    u[i, a] += alpha * p[i, a]
                    r[i, a] -= alpha * q[i, a]
            rr_new = _dot(r, r, sph, n)
            beta = rr_new / rr
            rr = rr_new
            for k in range(n):
                i = sph[k]
                for a in range(3):
                    p[i, a] = r[i, a] + beta * p[i, a]
            it += 1
        _set_on(w, u, v, sph, n)
        contact_reaction(c, dt, w)
        _zero_on(w, sph, n)
    for k in range(n):
        i = sph[k]
        for a in range(3):
            v[i, a] = u[i, a]
            x[i, a] += dt * u[i, a]
    s.stats[0] += it
    s.stats[1] += 1.0


@overload(advance)
def _advance_implicit_contact(integrator, body, motion, sets):
    if not is_state(integrator, ImplicitContactEuler):
        return None

    def impl(integrator, body, motion, sets):
        implicit_contact_step(integrator, body, motion, sets)
    return impl


class ContactSolve:
    """The implicit contact's record and buffers for one solver (:meth:`integrator` per frame)."""

    def __init__(self, n: int, n_samples: int, tol: float, max_iter: int) -> None:
        from .state import Touches

        cap = n + n_samples
        self.touches = Touches(True, np.zeros(cap, dtype=np.int8), np.zeros(cap, dtype=np.int32),
                               np.zeros((cap, 3)), np.zeros(1, dtype=np.int64))
        self.vn = np.zeros(cap)
        self.tol, self.max_iter = float(tol), int(max_iter)
        self.u, self.r, self.p, self.q, self.w = (np.zeros((n, 3)) for _ in range(5))
        self.stats = np.zeros(2)

    def terms(self, samples, k_ball: float, c_ball: float, react: np.ndarray) -> ContactTerms:
        return contact_terms(self.touches, samples, k_ball, c_ball, react, self.vn)

    def integrator(self, dt: float, samples, k_ball: float, c_ball: float,
                   react: np.ndarray) -> ImplicitContactEuler:
        return ImplicitContactEuler(dt, self.terms(samples, k_ball, c_ball, react), self.tol,
                                    self.max_iter, self.u, self.r, self.p, self.q, self.w, self.stats)

    def mean_iterations(self) -> float:
        """CG iterations per sub-step (0 for sub-steps without contact)."""
        return float(self.stats[0] / self.stats[1]) if self.stats[1] > 0 else 0.0


def contact_terms(touches, samples, k_ball: float, c_ball: float, react: np.ndarray,
                  vn: np.ndarray) -> ContactTerms:
    """The :class:`ContactTerms` of ``touches`` with ``samples`` (a :class:`~.state.Samples`)."""
    return ContactTerms(touches, samples.w_start, samples.w_idx, samples.w_val, k_ball, c_ball,
                        samples.stiffness, samples.damping, react, vn)


def no_contact_terms() -> ContactTerms:
    """Terms with nothing recorded (a solve without implicit contacts)."""
    from .state import no_touches

    return ContactTerms(no_touches(), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0),
                        0.0, 0.0, 0.0, 0.0, np.zeros(3), np.zeros(1))
