"""Linearly implicit contact: every pushing contact, with or without the surface samples.

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
under the tool; it is solved by the conjugate gradients of :mod:`.backward_euler` (alone a few
iterations over that handful of particles, no SPH pass; with implicit dashpots, in the same
system). The tangential (curvature) part of the
penalty's stiffness stays explicit, and a contact that would release within the sub-step is
still held by its linearisation until the next one. The reaction on the tool gets the same
correction, so the tool and the tissue exchange equal and opposite impulses.

A contact whose friction sticks (:func:`~.contact.stick_slip`) is held by its tangential spring
too, ``f'' = f - dt k P Phi_t v''`` with ``P`` the projection on its friction's tangent plane: its
``n n^T`` above becomes ``n n^T + P`` in the stiffness terms (the dashpot stays normal). Sliding
contacts pull with a constant ``mu |f_n|`` and stay explicit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from .state import TOUCH_BALL, TOUCH_SAMPLE



class ContactTerms(NamedTuple):
    """The pushing contacts of a sub-step and their laws, for a backward-Euler solve.

    ``touches`` (:class:`~.state.Touches`) is the record the contact kernels write; ``w_start,
    w_idx, w_val`` the surface samples' weights and ``b_start, b_idx, b_val`` a blade's bond
    samples' (the two sets may share the tissue); ``k_ball, c_ball``, ``k_sample, c_sample`` and
    ``k_bond, c_bond`` the contact laws; ``react`` (K, 3) the frame's reaction accumulator, a row per
    instrument; ``vn`` (cap,) each touch's normal velocity at the sub-step's start and ``vt`` (cap, 3)
    its tangential one (scratch).
    """

    touches: tuple
    w_start: np.ndarray
    w_idx: np.ndarray
    w_val: np.ndarray
    b_start: np.ndarray
    b_idx: np.ndarray
    b_val: np.ndarray
    k_ball: float
    c_ball: float
    k_sample: float
    c_sample: float
    k_bond: float
    c_bond: float
    react: np.ndarray
    vn: np.ndarray
    vt: np.ndarray


@njit(cache=True, fastmath=True, inline='always')
def _law(c, t):
    """``(k, c)`` of touch ``t``."""
    kind = c.touches.kind[t]
    if kind == TOUCH_BALL:
        return c.k_ball, c.c_ball
    if kind == TOUCH_SAMPLE:
        return c.k_sample, c.c_sample
    return c.k_bond, c.c_bond


@njit(cache=True, fastmath=True, inline='always')
def _weights(c, t):
    """``(start, idx, val)``: the weights CSR of sample touch ``t``'s set."""
    if c.touches.kind[t] == TOUCH_SAMPLE:
        return c.w_start, c.w_idx, c.w_val
    return c.b_start, c.b_idx, c.b_val


@njit(cache=True, fastmath=True, inline='always')
def _point_normal_velocity(c, t, vel):
    """``n_t . Phi_t vel``: the contact point's velocity along its normal."""
    tc = c.touches
    n0 = tc.normal[t, 0]; n1 = tc.normal[t, 1]; n2 = tc.normal[t, 2]
    j = tc.idx[t]
    if tc.kind[t] == TOUCH_BALL:
        return n0 * vel[j, 0] + n1 * vel[j, 1] + n2 * vel[j, 2]
    w_start, w_idx, w_val = _weights(c, t)
    s = 0.0
    for k in range(w_start[j], w_start[j + 1]):
        i = w_idx[k]
        s += w_val[k] * (n0 * vel[i, 0] + n1 * vel[i, 1] + n2 * vel[i, 2])
    return s


@njit(cache=True, fastmath=True, inline='always')
def _spread(c, t, amount, out):
    """``out += amount Phi_t^T n_t`` (the contact point's normal force on its particles)."""
    tc = c.touches
    n0 = tc.normal[t, 0]; n1 = tc.normal[t, 1]; n2 = tc.normal[t, 2]
    j = tc.idx[t]
    if tc.kind[t] == TOUCH_BALL:
        out[j, 0] += amount * n0; out[j, 1] += amount * n1; out[j, 2] += amount * n2
        return
    w_start, w_idx, w_val = _weights(c, t)
    for k in range(w_start[j], w_start[j + 1]):
        i = w_idx[k]
        a = amount * w_val[k]
        out[i, 0] += a * n0; out[i, 1] += a * n1; out[i, 2] += a * n2


@njit(cache=True, fastmath=True, inline='always')
def _tangential_velocity(c, t, vel):
    """``P_t Phi_t vel``, ``P_t = I - n_t n_t^T - a_t a_t^T``: the contact point's velocity across
    its normal (and, inside a shaft, across the tool's axis ``a_t``: the friction's tangent plane)."""
    j = c.touches.idx[t]
    if c.touches.kind[t] == TOUCH_BALL:
        u0 = vel[j, 0]; u1 = vel[j, 1]; u2 = vel[j, 2]
    else:
        w_start, w_idx, w_val = _weights(c, t)
        u0 = 0.0; u1 = 0.0; u2 = 0.0
        for k in range(w_start[j], w_start[j + 1]):
            i = w_idx[k]
            w = w_val[k]
            u0 += w * vel[i, 0]; u1 += w * vel[i, 1]; u2 += w * vel[i, 2]
    n0 = c.touches.normal[t, 0]; n1 = c.touches.normal[t, 1]; n2 = c.touches.normal[t, 2]
    a0 = c.touches.axis[t, 0]; a1 = c.touches.axis[t, 1]; a2 = c.touches.axis[t, 2]
    un = n0 * u0 + n1 * u1 + n2 * u2
    ua = a0 * u0 + a1 * u1 + a2 * u2
    return u0 - un * n0 - ua * a0, u1 - un * n1 - ua * a1, u2 - un * n2 - ua * a2


@njit(cache=True, fastmath=True, inline='always')
def _spread_vector(c, t, f0, f1, f2, out):
    """``out += Phi_t^T f``: a force ``f`` on the contact point, on its particles."""
    j = c.touches.idx[t]
    if c.touches.kind[t] == TOUCH_BALL:
        out[j, 0] += f0; out[j, 1] += f1; out[j, 2] += f2
        return
    w_start, w_idx, w_val = _weights(c, t)
    for k in range(w_start[j], w_start[j + 1]):
        i = w_idx[k]
        w = w_val[k]
        out[i, 0] += w * f0; out[i, 1] += w * f1; out[i, 2] += w * f2


@njit(cache=True, fastmath=True)
def contact_residual(c, inv_m, dt, v, dv, r):
    """``r += -(1/m) sum_t Phi^T [dt^2 K_t Phi v + (dt^2 K_t + dt c n n^T) Phi dv]``, ``K_t = k n n^T``
    (``k (n n^T + P_t)`` where the friction sticks: :attr:`~.state.Touches.held`, ``P_t`` of
    :func:`_tangential_velocity`): the contacts' share of the
    residual at ``v* = v + dv`` (``dv`` zero off the solved set); keeps each touch's ``n . Phi v``
    and ``P_t Phi v`` in ``c.vn``, ``c.vt`` for :func:`contact_reaction`."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        vn = _point_normal_velocity(c, t, v)
        c.vn[t] = vn
        _spread(c, t, -(dt * dt * kk * vn + (dt * dt * kk + dt * cc) * _point_normal_velocity(c, t, dv)) * inv_m, r)
    for t in range(c.touches.count[0]):
        if c.touches.held[t]:
            kk, cc = _law(c, t)
            u0, u1, u2 = _tangential_velocity(c, t, v)
            c.vt[t, 0] = u0; c.vt[t, 1] = u1; c.vt[t, 2] = u2
            w0, w1, w2 = _tangential_velocity(c, t, dv)
            a = -dt * dt * kk * inv_m
            _spread_vector(c, t, a * (u0 + w0), a * (u1 + w1), a * (u2 + w2), r)


@njit(cache=True, fastmath=True)
def contact_apply(c, inv_m, dt, w, q):
    """``q += sum_t (1/m) Phi^T (dt^2 K_t + dt c n n^T) Phi w`` (``w`` zero off the solved set)."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        _spread(c, t, (dt * dt * kk + dt * cc) * inv_m * _point_normal_velocity(c, t, w), q)
    for t in range(c.touches.count[0]):
        if c.touches.held[t]:
            kk, cc = _law(c, t)
            w0, w1, w2 = _tangential_velocity(c, t, w)
            a = dt * dt * kk * inv_m
            _spread_vector(c, t, a * w0, a * w1, a * w2, q)


@njit(cache=True, fastmath=True)
def contact_reaction(c, dt, dv):
    """The reaction's share of the solve: ``react += dt K_t Phi v'' + c n n^T Phi (v'' - v)`` with
    ``dv = v'' - v`` (zero off the solved set) and ``Phi v`` from :func:`contact_residual`."""
    for t in range(c.touches.count[0]):
        kk, cc = _law(c, t)
        d = _point_normal_velocity(c, t, dv)
        g = dt * kk * (c.vn[t] + d) + cc * d
        k = c.touches.tool[t]
        c.react[k, 0] += g * c.touches.normal[t, 0]
        c.react[k, 1] += g * c.touches.normal[t, 1]
        c.react[k, 2] += g * c.touches.normal[t, 2]
    for t in range(c.touches.count[0]):
        if c.touches.held[t]:
            kk, cc = _law(c, t)
            w0, w1, w2 = _tangential_velocity(c, t, dv)
            k = c.touches.tool[t]
            c.react[k, 0] += dt * kk * (c.vt[t, 0] + w0)
            c.react[k, 1] += dt * kk * (c.vt[t, 1] + w1)
            c.react[k, 2] += dt * kk * (c.vt[t, 2] + w2)


def make_touches(cap: int):
    """A :class:`~.state.Touches` record for up to ``cap`` pushing contacts (implicit contact)."""
    from .state import Touches

    return Touches(True, np.zeros(cap, dtype=np.int8), np.zeros(cap, dtype=np.int32), np.zeros((cap, 3)),
                   np.zeros(1, dtype=np.int64), np.zeros(cap, dtype=np.bool_), np.zeros((cap, 3)),
                   np.zeros(cap, dtype=np.int32))


def contact_terms(touches, samples, bonds, k_ball: float, c_ball: float, react: np.ndarray,
                  vn: np.ndarray, vt: np.ndarray) -> ContactTerms:
    """The :class:`ContactTerms` of ``touches`` with the surface ``samples`` and a blade's ``bonds``
    (each a :class:`~.state.Samples`, maybe empty)."""
    return ContactTerms(touches, samples.w_start, samples.w_idx, samples.w_val, bonds.w_start, bonds.w_idx,
                        bonds.w_val, k_ball, c_ball, samples.stiffness, samples.damping, bonds.stiffness,
                        bonds.damping, react, vn, vt)


def no_contact_terms() -> ContactTerms:
    """Terms with nothing recorded (a solve without implicit contacts)."""
    from .state import no_touches

    return ContactTerms(no_touches(), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0),
                        np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0),
                        0.0, 0.0, 0.0, 0.0, 0.0, 0.0, np.zeros((1, 3)), np.zeros(1), np.zeros((1, 3)))
