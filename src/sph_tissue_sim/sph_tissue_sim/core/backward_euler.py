"""Backward Euler for the implicit integrator of ``tlsph`` (``SolverConfig.integrator =
'implicit'``: the Kelvin-Voigt dashpots and the elastic forces) and for the pushing contacts
(always: the terms of :mod:`.implicit_contact`), one
conjugate-gradient solve per sub-step (:class:`BackwardEuler`). The dashpots' part first:

An explicit sub-step must resolve the dashpots' fastest mode, ``dt <= C rho h^2 / eta``, which
shrinks with the square of the spacing while the CFL bound shrinks with the spacing: on the 100k
liver it asks for 12 sub-steps per millisecond where the waves ask for 5. Here the elastic,
hourglass and contact forces stay explicit and the dashpots are implicit, one linear solve per
sub-step::

    v* = v + dt a                        (a without the dashpots: the scheme's state has eta = 0)
    (M + dt C) v' = M v*                 (f_visc = -C v at the current positions)
    x <- x + dt v'

``C`` comes from the Rayleigh dissipation ``D = sum_i V (eta_s |dev dE_i/dt|^2 + eta_b/2
tr(dE_i/dt)^2)`` with ``dE/dt = sym(F^T dF/dt)`` linear in the velocities, so ``f_visc = -dD/dv``
and ``C`` is symmetric positive semi-definite: ``M + dt C`` is solved matrix-free by conjugate
gradients over ``sets.sph``, the other particles' velocities (still particles, transmission layers)
held as they are. One product ``C p`` is the scheme's two gathers without the elastic part:

    dF_i = sum_j (p_j - p_i) (x) g_ij,   P_i = F_i S_v(sym(F_i^T dF_i)),
    f_i = V_i P_i sum_j g_ij - sum_j V_j P_j g_ji        (= -(C p)_i)

with ``F_i`` the scheme's deformation gradient of this sub-step. The dashpot is then stable at
any ``dt`` and the sub-step follows the CFL and contact bounds alone (the CFL bound alone with the
contacts in the same solve); a creep that the viscosity sets (time constant eta / G) stays exact
because the solve is the force balance itself.

The implicit integrator (``SolverConfig.integrator = 'implicit'``, ``stiffness``) puts the
elastic forces in the same solve, linearised at the sub-step's start (one Newton step of
backward Euler)::

    (M + dt C + dt^2 K + (dt hg_c + dt^2 hg_k) L) v' = M v* + dt hg_c L v,   x <- x + dt v'

``K p`` is the same two gathers with the spring's tangent ``dP_e = dP_e/dF : dF`` added to the
dashpots' stress (:func:`spring_tangent`; ``K`` is the Hessian of the discrete elastic energy, so
symmetric), projected to positive semi-definite per particle where strong compression makes it
indefinite (:func:`spring_tangents`); ``L`` is the hourglass bonds' Laplacian along the current
bonds (:func:`bond_force_one`), a symmetric stand-in for their Jacobian, whose explicit dashpot
part is moved to ``v' - v``. The matrix is then symmetric positive definite (``>= M``): stable at
any sub-step, and the equilibrium is exact whatever stand-in the matrix uses, since at rest the
right-hand side is the explicit force balance.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numba.extending import overload

from .kernel import ZERO3X3, add_outer, strain_rate
from .implicit_contact import contact_apply, contact_reaction, contact_residual, no_contact_terms
from .protocols import advance, is_state


class Operator(NamedTuple):
    """The solve's matrix, applied matrix-free (:func:`_apply`): the dashpots (``C``) and, with
    ``stiffness`` (the implicit integrator), the elastic forces (``dt K``, ``L``) of sub-step ``dt``.

    ``F`` (N, 3, 3) is the scheme's deformation gradient (read), ``A`` (N, 3, 3) scratch for the
    stresses; ``G, K`` the spring's moduli, ``w0, hg_k, hg_c`` the hourglass bonds' weights,
    stiffness and damping (:class:`~.tlsph.Tlsph`); ``T`` (N, 9, 9) the spring's tangent of the
    particles where ``projected`` (N,) is set (:func:`spring_tangents`); ``par_min`` stressed
    particles from which it runs on the thread pool. Its own tuple of arrays and numbers, which is
    what numba's parallel loops take.
    """

    dt: float
    offsets: np.ndarray
    indices: np.ndarray
    g: np.ndarray
    gr: np.ndarray
    gsum: np.ndarray
    F: np.ndarray
    A: np.ndarray
    volume: float
    eta_s: float
    eta_v: float
    stiffness: bool
    G: float
    K: float
    w0: np.ndarray
    hg_k: float
    hg_c: float
    T: np.ndarray
    projected: np.ndarray
    par_min: int


class NoOperator(NamedTuple):
    """The matrix of a solve of the pushing contacts alone: nothing besides the identity and the
    contacts. Its own type, so that the frame compiled for it holds no dashpot or elastic pass
    (they took about 25 s of the first start's compile)."""

    dt: float


class BackwardEuler(NamedTuple):
    """Symplectic Euler with the dashpots (an :class:`Operator`) and the recorded contacts
    (``contact``) backward in time, and with ``stiffness`` the elastic forces too; sub-step ``dt`` [s].

    ``op`` the matrix (:class:`Operator`, or :class:`NoOperator` for the contacts alone);
    ``u, r, p, q, w, v0`` (N, 3) scratch vectors of the
    solve (``w`` stays zero off the solved set); ``stats`` (2,) accumulates CG iterations and
    solves; ``contact`` the pushing contacts solved with the dashpots
    (:class:`~.implicit_contact.ContactTerms`; none recorded with explicit contact).
    """

    dt: float
    stiffness: bool
    op: tuple
    tol: float
    max_iter: int
    u: np.ndarray
    r: np.ndarray
    p: np.ndarray
    q: np.ndarray
    w: np.ndarray
    v0: np.ndarray
    stats: np.ndarray
    contact: tuple


@njit(cache=True, fastmath=True, inline='always')
def spring_tangent(f, b, G, K):
    """``dP_e = dP_e/dF : b`` of the compressible neo-Hookean spring of :mod:`.tlsph`,
    ``P_e = G F + t cof(F)`` with ``t = (lam ln J - G) / J``, at ``F`` (row-major 9-tuples):

        dP_e = G b + t'(J) (cof(F) : b) cof(F) + t dcof(F)[b],   t' = (lam + G - lam ln J) / J^2

    (``dcof`` the cofactor's derivative, bilinear in ``F`` and ``b``). Below ``J = 0.05`` the
    scheme holds ``t`` at its value there, so ``t'`` is 0. At ``F = I`` this is the linear spring
    ``G (b + b^T) + lam tr(b) I``. Symmetric (``P_e`` is the derivative of an energy), so the
    stiffness matrix it builds is too."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = f
    b00, b01, b02, b10, b11, b12, b20, b21, b22 = b
    c00 = f11 * f22 - f12 * f21; c01 = f12 * f20 - f10 * f22; c02 = f10 * f21 - f11 * f20
    c10 = f02 * f21 - f01 * f22; c11 = f00 * f22 - f02 * f20; c12 = f01 * f20 - f00 * f21
    c20 = f01 * f12 - f02 * f11; c21 = f02 * f10 - f00 * f12; c22 = f00 * f11 - f01 * f10
    J = f00 * c00 + f01 * c01 + f02 * c02
    lam = K - 2.0 * G / 3.0
    if J < 0.05:
        J = 0.05
        tp = 0.0
    else:
        tp = (lam + G - lam * math.log(J)) / (J * J)
    t = (lam * math.log(J) - G) / J
    e = tp * (c00 * b00 + c01 * b01 + c02 * b02 + c10 * b10 + c11 * b11 + c12 * b12
              + c20 * b20 + c21 * b21 + c22 * b22)
    return (G * b00 + e * c00 + t * (b11 * f22 + f11 * b22 - b12 * f21 - f12 * b21),
            G * b01 + e * c01 + t * (b12 * f20 + f12 * b20 - b10 * f22 - f10 * b22),
            G * b02 + e * c02 + t * (b10 * f21 + f10 * b21 - b11 * f20 - f11 * b20),
            G * b10 + e * c10 + t * (b02 * f21 + f02 * b21 - b01 * f22 - f01 * b22),
            G * b11 + e * c11 + t * (b00 * f22 + f00 * b22 - b02 * f20 - f02 * b20),
            G * b12 + e * c12 + t * (b01 * f20 + f01 * b20 - b00 * f21 - f00 * b21),
            G * b20 + e * c20 + t * (b01 * f12 + f01 * b12 - b02 * f11 - f02 * b11),
            G * b21 + e * c21 + t * (b02 * f10 + f02 * b10 - b00 * f12 - f00 * b12),
            G * b22 + e * c22 + t * (b00 * f11 + f00 * b11 - b01 * f10 - f01 * b10))


@njit(cache=True, fastmath=True, inline='always')
def _row(T, a, b):
    """Row ``a`` of a (9, 9) matrix times a 9-tuple."""
    return (T[a, 0] * b[0] + T[a, 1] * b[1] + T[a, 2] * b[2] + T[a, 3] * b[3] + T[a, 4] * b[4]
            + T[a, 5] * b[5] + T[a, 6] * b[6] + T[a, 7] * b[7] + T[a, 8] * b[8])


@njit(cache=True, fastmath=True, inline='always')
def _matvec9(T, b):
    """``T b`` for a (9, 9) matrix and a 9-tuple."""
    return (_row(T, 0, b), _row(T, 1, b), _row(T, 2, b), _row(T, 3, b), _row(T, 4, b),
            _row(T, 5, b), _row(T, 6, b), _row(T, 7, b), _row(T, 8, b))


@njit(cache=True)
def _positive_definite(T, L):
    """Whether the symmetric (9, 9) ``T`` is positive semi-definite, up to 1e-9 of its largest
    diagonal entry: a Cholesky factorisation of ``T`` plus that much of the identity into the
    scratch ``L`` (the spring's tangent at rest is only semi-definite: rotations cost nothing)."""
    shift = 0.0
    for a in range(9):
        shift = max(shift, T[a, a])
    shift *= 1e-9
    for a in range(9):
        for b in range(a + 1):
            t = T[a, b]
            if a == b:
                t += shift
            for k in range(b):
                t -= L[a, k] * L[b, k]
            if a == b:
                if not t > 0.0:
                    return False
                L[a, a] = math.sqrt(t)
            else:
                L[a, b] = t / L[b, b]
    return True


@njit(cache=True)
def spring_tangents(s, sets):
    """Mark the stressed particles whose spring tangent (:func:`spring_tangent` at ``s.F``) is
    not positive definite and store it, its negative eigenvalues set to zero, in ``s.T``.

    The compressible neo-Hookean energy is not convex everywhere (strong compression, shear under
    large stretch): an indefinite tangent would make the solve's matrix indefinite, which the
    conjugate gradients cannot solve (seen as a blow-up when random pokes crushed the liver at
    16 ms frames). Projecting each particle's tangent (as projected Newton methods do) keeps
    ``K = sum_i V B_i^T T_i B_i`` positive semi-definite and equal to the exact one wherever
    that is already convex: the test is a Cholesky factorisation, the eigen-decomposition runs
    only where it fails. Compiled without ``fastmath``: its tests must see a NaN."""
    Ti = np.empty((9, 9))
    L = np.empty((9, 9))
    for t in range(sets.n_stress):
        i = sets.stress[t]
        Fm = s.F[i]
        f = (Fm[0, 0], Fm[0, 1], Fm[0, 2], Fm[1, 0], Fm[1, 1], Fm[1, 2], Fm[2, 0], Fm[2, 1], Fm[2, 2])
        for c in range(9):
            e = (1.0 if c == 0 else 0.0, 1.0 if c == 1 else 0.0, 1.0 if c == 2 else 0.0,
                 1.0 if c == 3 else 0.0, 1.0 if c == 4 else 0.0, 1.0 if c == 5 else 0.0,
                 1.0 if c == 6 else 0.0, 1.0 if c == 7 else 0.0, 1.0 if c == 8 else 0.0)
            col = spring_tangent(f, e, s.G, s.K)
            for a in range(9):
                Ti[a, c] = col[a]
        for a in range(9):
            for c in range(a):
                m = 0.5 * (Ti[a, c] + Ti[c, a])
                Ti[a, c] = m
                Ti[c, a] = m
        if _positive_definite(Ti, L):
            s.projected[i] = 0
            continue
        w, V = np.linalg.eigh(Ti)
        for a in range(9):
            for c in range(9):
                acc = 0.0
                for k in range(9):
                    if w[k] > 0.0:
                        acc += V[a, k] * w[k] * V[c, k]
                s.T[i, a, c] = acc
        s.projected[i] = 1


@njit(cache=True, fastmath=True, inline='always')
def bond_force_one(i, s, x, vel, c):
    """``-(L vel)_i`` of the hourglass bonds' Laplacian along the current bonds ``x'_k``:
    ``sum_k c w0_k ((vel_j - vel_i) . x'_k) x'_k / |x'_k|^2`` (symmetric positive semi-definite).

    It stands in for the hourglass terms' Jacobian in the implicit integrator: the bonds' central
    springs and dashpots without the (unsymmetric) part through ``F``, which vanishes for the
    particle-scale modes the bonds exist to hold."""
    offsets, indices, w0 = s.offsets, s.indices, s.w0
    xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
    vi0 = vel[i, 0]; vi1 = vel[i, 1]; vi2 = vel[i, 2]
    f0 = 0.0; f1 = 0.0; f2 = 0.0
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        y0 = x[j, 0] - xi0; y1 = x[j, 1] - xi1; y2 = x[j, 2] - xi2
        yy = y0 * y0 + y1 * y1 + y2 * y2
        if yy > 0.0:
            d = c * w0[k] * ((vel[j, 0] - vi0) * y0 + (vel[j, 1] - vi1) * y1 + (vel[j, 2] - vi2) * y2) / yy
            f0 += d * y0
            f1 += d * y1
            f2 += d * y2
    return f0, f1, f2


@njit(cache=True, fastmath=True, inline='always')
def dashpot_stress_one(i, s, vel):
    """``A_i = V P_i`` of the dashpots for the velocity field ``vel`` (``s`` an
    :class:`Operator`), with the deformation gradient ``s.F[i]`` of this sub-step; with
    ``s.stiffness`` plus the spring's change ``dt dP_e`` over the sub-step."""
    g, offsets, indices, F = s.g, s.offsets, s.indices, s.F
    b = ZERO3X3
    vi0 = vel[i, 0]; vi1 = vel[i, 1]; vi2 = vel[i, 2]
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        b = add_outer(b, vel[j, 0] - vi0, vel[j, 1] - vi1, vel[j, 2] - vi2, g[k, 0], g[k, 1], g[k, 2])
    Fm = F[i]
    f00 = Fm[0, 0]; f01 = Fm[0, 1]; f02 = Fm[0, 2]
    f10 = Fm[1, 0]; f11 = Fm[1, 1]; f12 = Fm[1, 2]
    f20 = Fm[2, 0]; f21 = Fm[2, 1]; f22 = Fm[2, 2]
    r00, r11, r22, r01, r02, r12 = strain_rate((f00, f01, f02, f10, f11, f12, f20, f21, f22), b)
    # S_v = 2 eta_s dE/dt + (eta_v - 2 eta_s / 3) tr(dE/dt) I
    eta2 = 2.0 * s.eta_s
    lam_v = (s.eta_v - eta2 / 3.0) * (r00 + r11 + r22)
    s00 = eta2 * r00 + lam_v; s11 = eta2 * r11 + lam_v; s22 = eta2 * r22 + lam_v
    s01 = eta2 * r01; s02 = eta2 * r02; s12 = eta2 * r12
    # P = F S_v
    p00 = f00 * s00 + f01 * s01 + f02 * s02
    p01 = f00 * s01 + f01 * s11 + f02 * s12
    p02 = f00 * s02 + f01 * s12 + f02 * s22
    p10 = f10 * s00 + f11 * s01 + f12 * s02
    p11 = f10 * s01 + f11 * s11 + f12 * s12
    p12 = f10 * s02 + f11 * s12 + f12 * s22
    p20 = f20 * s00 + f21 * s01 + f22 * s02
    p21 = f20 * s01 + f21 * s11 + f22 * s12
    p22 = f20 * s02 + f21 * s12 + f22 * s22
    if s.stiffness:
        # the spring's change over the sub-step, dt dP_e[b] (b = dF/dt for the velocities vel)
        if s.projected[i]:
            d00, d01, d02, d10, d11, d12, d20, d21, d22 = _matvec9(s.T[i], b)
        else:
            d00, d01, d02, d10, d11, d12, d20, d21, d22 = spring_tangent(
                (f00, f01, f02, f10, f11, f12, f20, f21, f22), b, s.G, s.K)
        dt = s.dt
        p00 += dt * d00; p01 += dt * d01; p02 += dt * d02
        p10 += dt * d10; p11 += dt * d11; p12 += dt * d12
        p20 += dt * d20; p21 += dt * d21; p22 += dt * d22
    vol = s.volume
    Am = s.A[i]
    Am[0, 0] = vol * p00; Am[0, 1] = vol * p01; Am[0, 2] = vol * p02
    Am[1, 0] = vol * p10; Am[1, 1] = vol * p11; Am[1, 2] = vol * p12
    Am[2, 0] = vol * p20; Am[2, 1] = vol * p21; Am[2, 2] = vol * p22


@njit(cache=True, fastmath=True, inline='always')
def dashpot_force_one(i, s):
    """Dashpot force on particle ``i`` from the stresses ``s.A`` (``-(C p)_i``)."""
    offsets, indices, gr, A = s.offsets, s.indices, s.gr, s.A
    f0 = 0.0; f1 = 0.0; f2 = 0.0
    for k in range(offsets[i], offsets[i + 1]):
        Aj = A[indices[k]]
        r0 = gr[k, 0]; r1 = gr[k, 1]; r2 = gr[k, 2]
        f0 -= Aj[0, 0] * r0 + Aj[0, 1] * r1 + Aj[0, 2] * r2
        f1 -= Aj[1, 0] * r0 + Aj[1, 1] * r1 + Aj[1, 2] * r2
        f2 -= Aj[2, 0] * r0 + Aj[2, 1] * r1 + Aj[2, 2] * r2
    Ai = A[i]
    gs = s.gsum[i]
    f0 += Ai[0, 0] * gs[0] + Ai[0, 1] * gs[1] + Ai[0, 2] * gs[2]
    f1 += Ai[1, 0] * gs[0] + Ai[1, 1] * gs[1] + Ai[1, 2] * gs[2]
    f2 += Ai[2, 0] * gs[0] + Ai[2, 1] * gs[1] + Ai[2, 2] * gs[2]
    return f0, f1, f2


@njit(cache=True, fastmath=True, inline='always')
def _apply_one(i, s, x, vel, scale, base, out):
    """``out_i = base_i - scale f(vel)_i`` of :func:`_apply` for one particle (after the stresses)."""
    f0, f1, f2 = dashpot_force_one(i, s)
    if s.stiffness:
        b0, b1, b2 = bond_force_one(i, s, x, vel, s.hg_c + s.dt * s.hg_k)
        f0 += b0; f1 += b1; f2 += b2
    out[i, 0] = base[i, 0] - scale * f0
    out[i, 1] = base[i, 1] - scale * f1
    out[i, 2] = base[i, 2] - scale * f2


@njit(cache=True, fastmath=True)
def _apply(s, x, vel, sets, scale, base, out):
    """``out_i = base_i - scale f(vel)_i`` for ``i`` in ``sets.sph`` (``base`` may be ``out``):
    ``f = -C vel`` (the dashpots), with ``stiffness`` ``-(C + dt K + (hg_c + dt hg_k) L) vel``."""
    for t in range(sets.n_stress):
        dashpot_stress_one(sets.stress[t], s, vel)
    for t in range(sets.n_sph):
        _apply_one(sets.sph[t], s, x, vel, scale, base, out)


@njit(cache=True, fastmath=True, parallel=True)
def _apply_parallel(s, x, vel, sets, scale, base, out):
    """:func:`_apply` over numba's thread pool: both loops are gathers in the serial order, so
    the result is bit-identical (its own function: a serial solve must not wake the pool)."""
    stress, sph = sets.stress, sets.sph
    for t in prange(sets.n_stress):
        dashpot_stress_one(stress[t], s, vel)
    for t in prange(sets.n_sph):
        _apply_one(sph[t], s, x, vel, scale, base, out)


@njit(cache=True)
def _operator(s, x, vel, sets, scale, base, out):
    """:func:`_apply`, on the thread pool from ``s.par_min`` stressed particles."""
    if sets.n_stress >= s.par_min:
        _apply_parallel(s, x, vel, sets, scale, base, out)
    else:
        _apply(s, x, vel, sets, scale, base, out)


@njit(cache=True, fastmath=True)
def _bonds_at(s, x, vel, sets, scale, out):
    """``out_i -= scale (L vel)_i`` with the bonds' damping ``hg_c`` (:func:`bond_force_one`)."""
    for t in range(sets.n_sph):
        i = sets.sph[t]
        f0, f1, f2 = bond_force_one(i, s, x, vel, s.hg_c)
        out[i, 0] += scale * f0
        out[i, 1] += scale * f1
        out[i, 2] += scale * f2


def apply_operator(op, x, vel, sets, scale, base, out):
    """:func:`_operator` for an :class:`Operator`; nothing for a :class:`NoOperator`."""


@overload(apply_operator)
def _apply_operator(op, x, vel, sets, scale, base, out):
    if is_state(op, Operator):
        def impl(op, x, vel, sets, scale, base, out):
            _operator(op, x, vel, sets, scale, base, out)
        return impl
    if is_state(op, NoOperator):
        def nothing(op, x, vel, sets, scale, base, out):
            pass
        return nothing
    return None


def stiff_start(op, x, vel, sets, scale, r):
    """With the elastic forces (``op.stiffness``): the spring's tangents (:func:`spring_tangents`)
    and the bonds' dashpots at ``vel`` into ``r`` (:func:`_bonds_at`); nothing for a :class:`NoOperator`."""


@overload(stiff_start)
def _stiff_start(op, x, vel, sets, scale, r):
    if is_state(op, Operator):
        def impl(op, x, vel, sets, scale, r):
            if op.stiffness:
                spring_tangents(op, sets)
                _bonds_at(op, x, vel, sets, scale, r)
        return impl
    if is_state(op, NoOperator):
        def nothing(op, x, vel, sets, scale, r):
            pass
        return nothing
    return None


@njit(cache=True, fastmath=True)
def _dot(a, b, sph, n):
    t = 0.0
    for k in range(n):
        i = sph[k]
        t += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return t


@njit(cache=True)
def backward_euler_step(s, body, motion, sets):
    """One sub-step: ``v* = v + dt a``, then ``(I + dt/m C + contacts) v' = v* + ...`` (the
    dashpots with an :class:`Operator`, the contact terms of :mod:`.implicit_contact` for what the contact
    kernels recorded) by conjugate gradients from ``v*`` until the residual is ``s.tol`` times
    ``|v*|`` (or the first residual; at most ``s.max_iter`` iterations), the reaction corrected,
    ``x += dt v'``. With ``s.stiffness`` the matrix also holds ``dt^2/m K`` (the spring's projected
    tangent, :func:`spring_tangents`, and the hourglass bonds' stand-in), the solve starts from
    ``v`` and stops at ``s.tol`` times the larger of ``|v|`` and the current ``|v'|`` (or at
    ``s.tol^2`` times the first residual, for a solution at rest).
    Compiled without ``fastmath`` (its passes have their own flags) so that the stopping tests
    keep their meaning for a NaN."""
    x, v, acc = motion.x, motion.v, motion.acc
    sph, n = sets.sph, sets.n_sph
    dt = s.dt
    scale = dt * body.inv_mass
    u, r, p, q, w, v0 = s.u, s.r, s.p, s.q, s.w, s.v0
    c = s.contact
    touched = c.touches.count[0] > 0
    for k in range(n):
        i = sph[k]
        for a in range(3):
            u[i, a] = v[i, a] + dt * acc[i, a]
            w[i, a] = u[i, a] - v[i, a]
            r[i, a] = 0.0
    vnorm = 0.0
    if s.stiffness:
        # stiff: v* = v + dt a overshoots by far (the step's forces change within it), so the
        # solve starts from v, and its residual r = b - A u bounds the velocity error |A^-1 r|
        # <= |r| (A >= I): stop at tol times the speeds, of the start or of the solution
        vnorm = math.sqrt(_dot(v, v, sph, n))
        for k in range(n):
            i = sph[k]
            for a in range(3):
                r[i, a] = w[i, a]
                w[i, a] = 0.0
                u[i, a] = v[i, a]
    if touched:
        contact_residual(c, body.inv_mass, dt, v, w, r)
    # stiff: the bonds' dashpots are in a (at the velocities v of the sub-step's start); the
    # solve's stand-in for their Jacobian acts on v' - v
    stiff_start(s.op, x, v, sets, -scale, r)
    # from the guess u (v*, or v when stiff): the operator's share of r = b - (I + dt/m C) u with
    # b = v* - dt/m C_B v_B is, by linearity, dt/m f(u on the solved particles, the held
    # velocities elsewhere)
    for k in range(n):
        i = sph[k]
        for a in range(3):
            w[i, a] = 0.0
            v0[i, a] = v[i, a]
            v[i, a] = u[i, a]
    apply_operator(s.op, x, v, sets, -scale, r, r)
    unorm = math.sqrt(_dot(u, u, sph, n))
    for k in range(n):
        i = sph[k]
        for a in range(3):
            p[i, a] = r[i, a]
    rr = _dot(r, r, sph, n)
    # relative to |v*| (or to the first residual, should v* vanish); stiff: see above
    limit = s.tol * max(unorm, math.sqrt(rr))
    if s.stiffness:
        floor = s.tol * s.tol * math.sqrt(rr)
        limit = max(s.tol * vnorm, floor)
    it = 0
    while it < s.max_iter and math.sqrt(rr) > limit:
        for k in range(n):
            i = sph[k]
            for a in range(3):
                w[i, a] = p[i, a]
                q[i, a] = p[i, a]
        apply_operator(s.op, x, w, sets, scale, p, q)     # q = (I + dt/m C) p
        if touched:
            contact_apply(c, body.inv_mass, dt, w, q)
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
        if s.stiffness:
            # the velocities being solved for set the scale (from rest |v| says nothing)
            limit = max(s.tol * max(vnorm, math.sqrt(_dot(u, u, sph, n))), floor)
    if touched:
        for k in range(n):
            i = sph[k]
            for a in range(3):
                w[i, a] = u[i, a] - v0[i, a]
        contact_reaction(c, dt, w)
    for k in range(n):
        i = sph[k]
        for a in range(3):
            w[i, a] = 0.0
            v[i, a] = u[i, a]
            x[i, a] += dt * u[i, a]
    s.stats[0] += it
    s.stats[1] += 1.0


@overload(advance)
def _advance_backward_euler(integrator, body, motion, sets):
    if not is_state(integrator, BackwardEuler):
        return None

    def impl(integrator, body, motion, sets):
        backward_euler_step(integrator, body, motion, sets)
    return impl


class BackwardSolve:
    """The solve's buffers for one solver (built once; :meth:`integrator` per frame).

    ``scheme``: the ``tlsph`` scheme whose dashpots and elastic forces are solved (the implicit
    integrator), or None (the pushing contacts alone: a :class:`NoOperator`).
    """

    def __init__(self, scheme, n: int, tol: float, max_iter: int) -> None:
        self.scheme = scheme
        self.stiffness = scheme is not None
        self.tol, self.max_iter = float(tol), int(max_iter)
        if self.stiffness:
            self.A = np.zeros((n, 3, 3))
            self.T = np.zeros((n, 9, 9))
            self.projected = np.zeros(n, dtype=np.int8)
        self.u, self.r, self.p, self.q, self.w, self.v0 = (np.zeros((n, 3)) for _ in range(6))
        self.stats = np.zeros(2)
        self.eta_s = self.eta_v = 0.0

    def set_material(self, material) -> None:
        self.eta_s, self.eta_v = material.eta_shear, material.eta_bulk

    def integrator(self, dt: float, contact=None) -> BackwardEuler:
        """The frame's integrator; ``contact`` the :class:`~.implicit_contact.ContactTerms` solved
        with it (None: none)."""
        if contact is None:
            contact = no_contact_terms()
        sc = self.scheme
        if sc is None:
            op = NoOperator(dt)
        else:
            st = sc.state(None, None, 0)
            op = Operator(dt, sc.offsets, sc.indices, sc.g, sc.gr, sc.gsum, sc.F, self.A, sc.volume, self.eta_s,
                          self.eta_v, True, st.G, st.K, st.w0, st.hg_k, st.hg_c, self.T, self.projected,
                          st.par_min)
        return BackwardEuler(dt, self.stiffness, op, self.tol, self.max_iter, self.u, self.r, self.p, self.q,
                             self.w, self.v0, self.stats, contact)

    def mean_iterations(self) -> float:
        """CG iterations per sub-step since the last :meth:`reset_stats`."""
        return float(self.stats[0] / self.stats[1]) if self.stats[1] > 0 else 0.0

    def reset_stats(self) -> None:
        self.stats[:] = 0.0
