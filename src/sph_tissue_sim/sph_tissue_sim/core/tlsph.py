"""Total-Lagrangian SPH (the default scheme) with Kelvin-Voigt stress and hourglass control.

Reference neighbours and corrected gradients are fixed (no per-step search). With the reference
pair gradients ``g_ij`` of :mod:`.gradients` (Bonet-Lok, ``V_j L_i^-1 DWIJ0``)
the deformation gradient and its rate are (exact for linear fields, also at free surfaces)

    F_i = sum_j (x_j - x_i) (x) g_ij,   dF_i/dt = sum_j (v_j - v_i) (x) g_ij.

Kelvin-Voigt: an elastic spring (compressible neo-Hookean, which is exactly ``2G e + K tr(eps) I``
for small strains and stays stable under large compression) in parallel with dashpots on the
Green-Lagrange strain rate ``dE/dt = (dF^T F + F^T dF)/2``:

    P = G (F - F^-T) + (K - 2G/3) ln(J) F^-T  +  F [eta_bulk tr(dE/dt) I + 2 eta_shear dev(dE/dt)].

A stiffening or relaxing spring (the material's ``stiffening`` and ``prony``: quasi-linear
viscoelasticity) adds the exponential term of :mod:`.material` to the spring,

    P_e = P_neo-Hookean + G (exp(b (I1b - 3)) - 1) J^(-2/3) (F - I1/3 F^-T),

the exponential held at :data:`STIFFENING_CAP` beyond it (the stress continuous, the spring then
neo-Hookean at that many times ``G``),

and replaces it by ``g_inf P_e + F sum_k Q_k``: with ``S_e = F^-1 P_e`` the second Piola-Kirchhoff
stress of the spring at the instantaneous moduli, each internal variable ``Q_k`` (symmetric, per
particle) follows ``dQ_k/dt = -Q_k / tau_k + g_k dS_e/dt``, integrated exactly for ``S_e`` linear
in time since the particle's last update, ``dt`` ago (:func:`qlv_one`):

    Q_k <- exp(-dt / tau_k) Q_k + g_k (1 - exp(-dt / tau_k)) (tau_k / dt) (S_e - S_e,last),

stable for any ``dt`` and exact for a held strain, whose stress then follows the relaxation
function ``g_inf + sum_k g_k exp(-t / tau_k)`` of :class:`~.material.Material`.

Forces follow from the discrete energy ``sum_i V_i psi(F_i)`` (momentum conserving: ``F`` sees
differences only, and ``psi`` is frame-indifferent):

    f_i = -dE/dx_i = V_i P_i sum_j g_ij - sum_j V_j P_j g_ji.

Hourglass (zero-energy mode) control after Ganzenmueller (CMAME 2015): the pair error
``eps_ij = (F_i + F_j)/2 X_ij - x_ij`` (zero for any linear deformation) projected on the current
bond gives a central spring and dashpot

    f_i -= alpha V_i V_j W0_ij / R0^2 [(E eps_ij + eta deps_ij/dt) . x_ij] x_ij / |x_ij|^2.

Central (along x_ij) and antisymmetric, so it conserves linear and angular momentum; the
unprojected vector form ``-alpha V^2 W0/R0^2 (E eps + eta deps/dt)`` is cheaper but exerts a net
torque (3.9e-4 of the angular momentum scale in 0.2 s on a free block) and stiffens point
indentation (+18 % contact force at 4 mm), which made the local-area force 11 % off the global one.
Normalising by R0^2 instead of |x_ij|^2 would save a division but stiffens compressed bonds
(local-area force then 13 % off the global one at the smallest area).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numba.extending import overload

from .bonds import Bonds
from .gradients import corrected_gradients, pair_weights, reverse_pairs
from .kernel import ZERO3X3, add_outer, strain_rate
from .material import Material
from .protocols import STATUS_OK, FixedStateScheme, internal_forces, is_state

class Tlsph(NamedTuple):
    """The scheme's state for the frame loop: reference pairs, per-particle tensors, material."""

    offsets: np.ndarray    # (N + 1,) CSR of reference neighbours
    indices: np.ndarray
    g: np.ndarray          # (nnz, 3) corrected reference gradients g_ij (:mod:`.gradients`)
    gr: np.ndarray         # (nnz, 3) those of the reverse pairs, g_ji
    gsum: np.ndarray       # (N, 3) sum_j g_ij
    w0: np.ndarray         # (nnz,) hourglass pair weights
    F: np.ndarray          # (N, 3, 3) deformation gradient
    Fd: np.ndarray         # (N, 3, 3) its rate
    A: np.ndarray          # (N, 3, 3) V P
    H: np.ndarray          # (N, 3, 3) hourglass map
    volume: float          # [m^3] particle volume
    G: float               # [Pa] shear modulus
    K: float               # [Pa] bulk modulus
    eta_s: float           # [Pa s] shear viscosity
    eta_v: float           # [Pa s] bulk viscosity
    hg_k: float            # hourglass stiffness
    hg_c: float            # hourglass damping
    par_min: int           # stressed particles from which a sub-step runs on the thread pool


#: a stiffening spring's secant shear modulus grows up to this many times its small-strain one (the
#: tangent the CFL bound follows to 50 (1 + 2 ln 50) = 441 times, just below the cap)
STIFFENING_CAP = 50.0
LOG_STIFFENING_CAP = math.log(STIFFENING_CAP)


class TlsphQlv(NamedTuple):
    """The scheme's state with a stiffening or relaxing spring: the Kelvin-Voigt state at the
    instantaneous moduli, the stiffening exponent and the Prony series' internal variables
    (:func:`qlv_one`)."""

    base: Tlsph            # the Kelvin-Voigt state (G, K the instantaneous moduli)
    b: float               # [-] the stiffening exponent
    stiff: np.ndarray      # (1,) the largest shear stiffening factor of the frame (the CFL bound)
    g_inf: float           # [-] 1 - sum g_k
    gk: np.ndarray         # (n_terms,) [-] weights g_k
    tau: np.ndarray        # (n_terms,) [s] time constants
    Se: np.ndarray         # (N, 6) [Pa] S_e (xx, yy, zz, xy, xz, yz) at each particle's last update
    Q: np.ndarray          # (N, n_terms, 6) [Pa] the internal variables Q_k
    t_up: np.ndarray       # (N,) [s] the sim time of each particle's last update
    clock: np.ndarray      # (2,) [s] the sim time of this sub-step's stresses, the sub-step


@njit(cache=True, fastmath=True, inline='always')
def _piola(a, b, G, K, eta_s, eta_v):
    """First Piola-Kirchhoff stress (row-major 9-tuple) of the Kelvin-Voigt element at ``F`` = ``a``
    and ``dF/dt`` = ``b`` (row-major 9-tuples)."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = a
    r00, r11, r22, r01, r02, r12 = strain_rate(a, b)
    # viscous part: Kelvin-Voigt dashpots on the Green-Lagrange strain rate, P_v = F S_v
    lam_v = (eta_v - 2.0 * eta_s / 3.0) * (r00 + r11 + r22)
    s00 = 2.0 * eta_s * r00 + lam_v
    s11 = 2.0 * eta_s * r11 + lam_v
    s22 = 2.0 * eta_s * r22 + lam_v
    s01 = 2.0 * eta_s * r01
    s02 = 2.0 * eta_s * r02
    s12 = 2.0 * eta_s * r12
    # elastic part: compressible neo-Hookean P_e = G (F - F^-T) + lambda ln(J) F^-T, which equals
    # the linear spring 2G e + K tr(eps) for small strains and, unlike St. Venant-Kirchhoff, does
    # not collapse under strong compression (a point-like tool squeezes single particles)
    c00 = f11 * f22 - f12 * f21; c01 = f12 * f20 - f10 * f22; c02 = f10 * f21 - f11 * f20
    c10 = f02 * f21 - f01 * f22; c11 = f00 * f22 - f02 * f20; c12 = f01 * f20 - f00 * f21
    c20 = f01 * f12 - f02 * f11; c21 = f02 * f10 - f00 * f12; c22 = f00 * f11 - f01 * f10
    J = f00 * c00 + f01 * c01 + f02 * c02
    if J < 0.05:
        J = 0.05  # inverted or crushed particle: keep pushing it back out
    lam = K - 2.0 * G / 3.0
    t = (lam * math.log(J) - G) / J      # F^-T = cof(F) / J
    # P = F S_v + G F + t cof(F)
    p00 = f00 * s00 + f01 * s01 + f02 * s02 + G * f00 + t * c00
    p01 = f00 * s01 + f01 * s11 + f02 * s12 + G * f01 + t * c01
    p02 = f00 * s02 + f01 * s12 + f02 * s22 + G * f02 + t * c02
    p10 = f10 * s00 + f11 * s01 + f12 * s02 + G * f10 + t * c10
    p11 = f10 * s01 + f11 * s11 + f12 * s12 + G * f11 + t * c11
    p12 = f10 * s02 + f11 * s12 + f12 * s22 + G * f12 + t * c12
    p20 = f20 * s00 + f21 * s01 + f22 * s02 + G * f20 + t * c20
    p21 = f20 * s01 + f21 * s11 + f22 * s12 + G * f21 + t * c21
    p22 = f20 * s02 + f21 * s12 + f22 * s22 + G * f22 + t * c22
    return p00, p01, p02, p10, p11, p12, p20, p21, p22


@njit(cache=True, fastmath=True, inline='always')
def tlsph_stress_one(i, s, x, v):
    """F_i, dF_i/dt, ``A_i = V P_i`` and the hourglass map ``H_i = hg_k F_i + hg_c dF_i/dt``
    for particle ``i`` (writes rows of ``s.F``, ``s.Fd``, ``s.A``, ``s.H``; ``s`` a :class:`Tlsph`)."""
    g, offsets, indices, volume = s.g, s.offsets, s.indices, s.volume
    G, K, eta_s, eta_v, hg_k, hg_c = s.G, s.K, s.eta_s, s.eta_v, s.hg_k, s.hg_c
    F, Fd, A, H = s.F, s.Fd, s.A, s.H
    a = ZERO3X3
    b = ZERO3X3
    xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
    vi0 = v[i, 0]; vi1 = v[i, 1]; vi2 = v[i, 2]
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        g0 = g[k, 0]; g1 = g[k, 1]; g2 = g[k, 2]
        a = add_outer(a, x[j, 0] - xi0, x[j, 1] - xi1, x[j, 2] - xi2, g0, g1, g2)
        b = add_outer(b, v[j, 0] - vi0, v[j, 1] - vi1, v[j, 2] - vi2, g0, g1, g2)
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = a
    h00, h01, h02, h10, h11, h12, h20, h21, h22 = b
    Fm = F[i]
    Fdm = Fd[i]
    Fm[0, 0] = f00; Fm[0, 1] = f01; Fm[0, 2] = f02
    Fm[1, 0] = f10; Fm[1, 1] = f11; Fm[1, 2] = f12
    Fm[2, 0] = f20; Fm[2, 1] = f21; Fm[2, 2] = f22
    Fdm[0, 0] = h00; Fdm[0, 1] = h01; Fdm[0, 2] = h02
    Fdm[1, 0] = h10; Fdm[1, 1] = h11; Fdm[1, 2] = h12
    Fdm[2, 0] = h20; Fdm[2, 1] = h21; Fdm[2, 2] = h22
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = _piola(a, b, G, K, eta_s, eta_v)
    Am = A[i]
    Am[0, 0] = volume * p00; Am[0, 1] = volume * p01; Am[0, 2] = volume * p02
    Am[1, 0] = volume * p10; Am[1, 1] = volume * p11; Am[1, 2] = volume * p12
    Am[2, 0] = volume * p20; Am[2, 1] = volume * p21; Am[2, 2] = volume * p22
    Hm = H[i]
    for p in range(3):
        for q in range(3):
            Hm[p, q] = hg_k * Fm[p, q] + hg_c * Fdm[p, q]


@njit(cache=True, fastmath=True, inline='always')
def qlv_one(i, s):
    """Turn ``A_i = V P_i`` of :func:`tlsph_stress_one` (the Kelvin-Voigt element at the
    instantaneous moduli, ``s.base``) into the stiffening, relaxing spring's: ``A_i += V (g_inf P_e
    + F sum_k Q_k - P_nH)`` after updating the ``Q_k`` of particle ``i`` to ``s.clock[0]`` (``s`` a
    :class:`TlsphQlv`; the laws in the module docstring)."""
    b = s.base
    G, K = b.G, b.K
    Fm = b.F[i]
    f00 = Fm[0, 0]; f01 = Fm[0, 1]; f02 = Fm[0, 2]
    f10 = Fm[1, 0]; f11 = Fm[1, 1]; f12 = Fm[1, 2]
    f20 = Fm[2, 0]; f21 = Fm[2, 1]; f22 = Fm[2, 2]
    c00 = f11 * f22 - f12 * f21; c01 = f12 * f20 - f10 * f22; c02 = f10 * f21 - f11 * f20
    c10 = f02 * f21 - f01 * f22; c11 = f00 * f22 - f02 * f20; c12 = f01 * f20 - f00 * f21
    c20 = f01 * f12 - f02 * f11; c21 = f02 * f10 - f00 * f12; c22 = f00 * f11 - f01 * f10
    J = f00 * c00 + f01 * c01 + f02 * c02
    if J < 0.05:
        J = 0.05  # as _piola: a crushed particle keeps pushing back
    t = ((K - 2.0 * G / 3.0) * math.log(J) - G) / J        # P_nH = G F + t cof
    # the stiffening term a (F - I1/3 F^-T), a = G (e - 1) J^(-2/3), e = exp(b (I1b - 3))
    I1 = (f00 * f00 + f01 * f01 + f02 * f02 + f10 * f10 + f11 * f11 + f12 * f12
          + f20 * f20 + f21 * f21 + f22 * f22)
    jm = J ** (-2.0 / 3.0)
    x = jm * I1 - 3.0
    bx = s.b * x
    if bx < LOG_STIFFENING_CAP:
        e = math.exp(bx)
        # the shear stiffness's growth for the CFL bound: e (1 + 2 b (I1b - 3)), the tangent in
        # simple shear (the largest acoustic modulus is within about 10 % of it; CFL 0.3 covers that)
        grow = e * (1.0 + 2.0 * bx)
    else:
        # beyond the cap the spring is neo-Hookean at STIFFENING_CAP G: a crushed particle's
        # exponential would need more sub-steps than any frame has
        e = STIFFENING_CAP
        grow = STIFFENING_CAP
    a = G * (e - 1.0) * jm
    if grow > s.stiff[0]:
        s.stiff[0] = grow
    Ge = G + a                          # P_e = Ge F + te cof
    te = t - a * I1 / (3.0 * J)
    # S_e = F^-1 P_e = Ge I + te cof^T cof / J (F^-1 = cof^T / J)
    u = te / J
    se = (Ge + u * (c00 * c00 + c10 * c10 + c20 * c20),
          Ge + u * (c01 * c01 + c11 * c11 + c21 * c21),
          Ge + u * (c02 * c02 + c12 * c12 + c22 * c22),
          u * (c00 * c01 + c10 * c11 + c20 * c21),
          u * (c00 * c02 + c10 * c12 + c20 * c22),
          u * (c01 * c02 + c11 * c12 + c21 * c22))
    now = s.clock[0]
    # t_up < 0: no history yet (reset, a new material): the spring answers instantaneously
    dt = now - s.t_up[i] if s.t_up[i] >= 0.0 else 0.0
    s.t_up[i] = now
    q0 = 0.0; q1 = 0.0; q2 = 0.0; q3 = 0.0; q4 = 0.0; q5 = 0.0
    Se, Q = s.Se[i], s.Q[i]
    for k in range(len(s.gk)):
        if dt > 0.0:
            r = dt / s.tau[k]
            d = math.exp(-r)
            w = s.gk[k] * -math.expm1(-r) / r
        else:
            d = 1.0
            w = s.gk[k]
        Qk = Q[k]
        for c in range(6):
            Qk[c] = d * Qk[c] + w * (se[c] - Se[c])
        q0 += Qk[0]; q1 += Qk[1]; q2 += Qk[2]; q3 += Qk[3]; q4 += Qk[4]; q5 += Qk[5]
    for c in range(6):
        Se[c] = se[c]
    # A += V (g_inf (Ge F + te cof) + F Q - (G F + t cof)), Q = sum_k Q_k (xx yy zz xy xz yz)
    gi = s.g_inf
    pg = gi * Ge - G
    pt = gi * te - t
    vol = b.volume
    Am = b.A[i]
    Am[0, 0] += vol * (f00 * q0 + f01 * q3 + f02 * q4 + pg * f00 + pt * c00)
    Am[0, 1] += vol * (f00 * q3 + f01 * q1 + f02 * q5 + pg * f01 + pt * c01)
    Am[0, 2] += vol * (f00 * q4 + f01 * q5 + f02 * q2 + pg * f02 + pt * c02)
    Am[1, 0] += vol * (f10 * q0 + f11 * q3 + f12 * q4 + pg * f10 + pt * c10)
    Am[1, 1] += vol * (f10 * q3 + f11 * q1 + f12 * q5 + pg * f11 + pt * c11)
    Am[1, 2] += vol * (f10 * q4 + f11 * q5 + f12 * q2 + pg * f12 + pt * c12)
    Am[2, 0] += vol * (f20 * q0 + f21 * q3 + f22 * q4 + pg * f20 + pt * c20)
    Am[2, 1] += vol * (f20 * q3 + f21 * q1 + f22 * q5 + pg * f21 + pt * c21)
    Am[2, 2] += vol * (f20 * q4 + f21 * q5 + f22 * q2 + pg * f22 + pt * c22)


@njit(cache=True, fastmath=True, inline='always')
def tlsph_force_one(i, s, X, x, v):
    """Internal force ``(f0, f1, f2)`` [N] on particle ``i`` (gather over its reference neighbours).

    From ``s`` (a :class:`Tlsph`): ``hgw[k] = s.w0[k] = W(R0) / R0^2`` per pair; ``hg_k``
    [Pa m^6] = alpha E V^2 and ``hg_c`` [Pa s m^6] = alpha eta V^2 scale the hourglass bonds: with ``X'_k = X_j - X_i``, ``x'_k = x_j - x_i``,
    ``H = hg_k F + hg_c dF/dt`` (from :func:`tlsph_stress_one`) and the bond error
    ``e_k = (H_i + H_j)/2 X'_k - (hg_k x'_k + hg_c v'_k)``

        f_i = A_i gsum_i - sum_k A_j gr_k - sum_k hgw_k (e_k . x'_k) x'_k / |x'_k|^2,

    one pass over the neighbours (``A = V P``, ``gr_k = g_ji``, ``gsum_i = sum_k g_ik``). The hourglass term is central (the
    bond error projected on the current bond, as in Ganzenmueller 2015), zero for rigid motions
    and linear fields, and antisymmetric in i, j.
    """
    offsets, indices, gr, hgw, H, A, hg_k, hg_c = s.offsets, s.indices, s.gr, s.w0, s.H, s.A, s.hg_k, s.hg_c
    Xi0 = X[i, 0]; Xi1 = X[i, 1]; Xi2 = X[i, 2]
    xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
    vi0 = v[i, 0]; vi1 = v[i, 1]; vi2 = v[i, 2]
    Ai = A[i]; Hi = H[i]
    f0 = 0.0; f1 = 0.0; f2 = 0.0
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        r0 = gr[k, 0]; r1 = gr[k, 1]; r2 = gr[k, 2]
        X0 = X[j, 0] - Xi0; X1 = X[j, 1] - Xi1; X2 = X[j, 2] - Xi2
        Aj = A[j]; Hj = H[j]
        f0 -= Aj[0, 0] * r0 + Aj[0, 1] * r1 + Aj[0, 2] * r2
        f1 -= Aj[1, 0] * r0 + Aj[1, 1] * r1 + Aj[1, 2] * r2
        f2 -= Aj[2, 0] * r0 + Aj[2, 1] * r1 + Aj[2, 2] * r2
        # hourglass: bond error e = (H_i + H_j)/2 X' - (hg_k x' + hg_c v'), projected on the bond
        y0 = x[j, 0] - xi0; y1 = x[j, 1] - xi1; y2 = x[j, 2] - xi2
        e0 = (0.5 * ((Hi[0, 0] + Hj[0, 0]) * X0 + (Hi[0, 1] + Hj[0, 1]) * X1 + (Hi[0, 2] + Hj[0, 2]) * X2)
              - hg_k * y0 - hg_c * (v[j, 0] - vi0))
        e1 = (0.5 * ((Hi[1, 0] + Hj[1, 0]) * X0 + (Hi[1, 1] + Hj[1, 1]) * X1 + (Hi[1, 2] + Hj[1, 2]) * X2)
              - hg_k * y1 - hg_c * (v[j, 1] - vi1))
        e2 = (0.5 * ((Hi[2, 0] + Hj[2, 0]) * X0 + (Hi[2, 1] + Hj[2, 1]) * X1 + (Hi[2, 2] + Hj[2, 2]) * X2)
              - hg_k * y2 - hg_c * (v[j, 2] - vi2))
        yy = y0 * y0 + y1 * y1 + y2 * y2
        if yy > 0.0:
            c = hgw[k] * (e0 * y0 + e1 * y1 + e2 * y2) / yy
            f0 -= c * y0
            f1 -= c * y1
            f2 -= c * y2
    gs = s.gsum[i]
    f0 += Ai[0, 0] * gs[0] + Ai[0, 1] * gs[1] + Ai[0, 2] * gs[2]
    f1 += Ai[1, 0] * gs[0] + Ai[1, 1] * gs[1] + Ai[1, 2] * gs[2]
    f2 += Ai[2, 0] * gs[0] + Ai[2, 1] * gs[1] + Ai[2, 2] * gs[2]
    return f0, f1, f2


@njit(cache=True, fastmath=True)
def tlsph_pass(s, body, motion, sets):
    """One sub-step of TLSPH internal forces (``s`` a :class:`Tlsph`): stresses of
    ``sets.stress``, then ``acc = f / m`` of ``sets.sph`` (serial: no thread-pool wake-up on small sets)."""
    X, x, v, acc, inv_mass = body.X, motion.x, motion.v, motion.acc, body.inv_mass
    for t in range(sets.n_stress):
        tlsph_stress_one(sets.stress[t], s, x, v)
    for t in range(sets.n_sph):
        i = sets.sph[t]
        f0, f1, f2 = tlsph_force_one(i, s, X, x, v)
        acc[i, 0] = f0 * inv_mass
        acc[i, 1] = f1 * inv_mass
        acc[i, 2] = f2 * inv_mass


@njit(cache=True, fastmath=True)
def tlsph_qlv_pass(s, body, motion, sets):
    """:func:`tlsph_pass` with the relaxing spring (``s`` a :class:`TlsphQlv`): the clock moves
    on by a sub-step, each stressed particle's Kelvin-Voigt stress is turned into the relaxing
    spring's (:func:`qlv_one`), then the forces as there."""
    X, x, v, acc, inv_mass = body.X, motion.x, motion.v, motion.acc, body.inv_mass
    s.clock[0] += s.clock[1]
    b = s.base
    for t in range(sets.n_stress):
        i = sets.stress[t]
        tlsph_stress_one(i, b, x, v)
        qlv_one(i, s)
    for t in range(sets.n_sph):
        i = sets.sph[t]
        f0, f1, f2 = tlsph_force_one(i, b, X, x, v)
        acc[i, 0] = f0 * inv_mass
        acc[i, 1] = f1 * inv_mass
        acc[i, 2] = f2 * inv_mass


@njit(cache=True, fastmath=True, parallel=True)
def tlsph_pass_parallel(s, body, motion, sets):
    """:func:`tlsph_pass` over numba's thread pool (``prange``).

    Both loops are gathers (a particle writes only its own rows of F, Fd, A, H and acc) and each
    particle's sums run in the same order as in the serial pass, so the result is bit-identical
    to :func:`tlsph_pass` for any thread count. (Its own function: numba compiles ``prange`` per
    function, and a serial pass must not wake the thread pool.)
    """
    X, x, v, acc, inv_mass = body.X, motion.x, motion.v, motion.acc, body.inv_mass
    stress, sph = sets.stress, sets.sph
    for t in prange(sets.n_stress):
        tlsph_stress_one(stress[t], s, x, v)
    for t in prange(sets.n_sph):
        i = sph[t]
        f0, f1, f2 = tlsph_force_one(i, s, X, x, v)
        acc[i, 0] = f0 * inv_mass
        acc[i, 1] = f1 * inv_mass
        acc[i, 2] = f2 * inv_mass


@njit(cache=True)
def _matmul3(a, b, out):
    for p in range(3):
        for q in range(3):
            out[p, q] = a[p, 0] * b[0, q] + a[p, 1] * b[1, q] + a[p, 2] * b[2, q]


@njit(cache=True)
def _det3(a):
    return (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
            - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
            + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))


@njit(cache=True, nogil=True)
def tlsph_von_mises(F, Fd, G, K, eta_s, eta_v, idx, n, out):
    """Von Mises stress [Pa] of the Cauchy stress ``sigma = F S F^T / J`` for ``idx[:n]`` into ``out``."""
    S = np.empty((3, 3))
    FS = np.empty((3, 3))
    E = np.empty((3, 3))
    Ed = np.empty((3, 3))
    sig = np.empty((3, 3))
    for t in range(n):
        i = idx[t]
        Fi = F[i]
        Fdi = Fd[i]
        for p in range(3):
            for q in range(3):
                s = 0.0
                r = 0.0
                for k in range(3):
                    s += Fi[k, p] * Fi[k, q]
                    r += Fdi[k, p] * Fi[k, q] + Fi[k, p] * Fdi[k, q]
                E[p, q] = 0.5 * s
                Ed[p, q] = 0.5 * r
            E[p, p] -= 0.5
        trE = E[0, 0] + E[1, 1] + E[2, 2]
        trEd = Ed[0, 0] + Ed[1, 1] + Ed[2, 2]
        for p in range(3):
            for q in range(3):
                S[p, q] = 2.0 * G * E[p, q] + 2.0 * eta_s * Ed[p, q]
            S[p, p] += (K - 2.0 * G / 3.0) * trE + (eta_v - 2.0 * eta_s / 3.0) * trEd
        J = _det3(Fi)
        if abs(J) < 1e-9:
            J = 1e-9
        _matmul3(Fi, S, FS)
        for p in range(3):
            for q in range(3):
                sig[p, q] = (FS[p, 0] * Fi[q, 0] + FS[p, 1] * Fi[q, 1] + FS[p, 2] * Fi[q, 2]) / J
        tr = (sig[0, 0] + sig[1, 1] + sig[2, 2]) / 3.0
        d0 = sig[0, 0] - tr
        d1 = sig[1, 1] - tr
        d2 = sig[2, 2] - tr
        out[i] = math.sqrt(1.5 * (d0 * d0 + d1 * d1 + d2 * d2
                                  + 2.0 * (sig[0, 1] ** 2 + sig[0, 2] ** 2 + sig[1, 2] ** 2)))


@njit(cache=True, nogil=True)
def piola_von_mises(F, A, volume, idx, n, out):
    """Von Mises stress [Pa] of the Cauchy stress ``sigma = P F^T / J`` (``P = A / volume``) for
    ``idx[:n]`` into ``out``."""
    sig = np.empty((3, 3))
    for t in range(n):
        i = idx[t]
        Fi = F[i]
        J = _det3(Fi)
        if abs(J) < 1e-9:
            J = 1e-9
        for p in range(3):
            for q in range(3):
                sig[p, q] = (A[i, p, 0] * Fi[q, 0] + A[i, p, 1] * Fi[q, 1] + A[i, p, 2] * Fi[q, 2]) / (volume * J)
        tr = (sig[0, 0] + sig[1, 1] + sig[2, 2]) / 3.0
        d0 = sig[0, 0] - tr
        d1 = sig[1, 1] - tr
        d2 = sig[2, 2] - tr
        s01 = 0.5 * (sig[0, 1] + sig[1, 0])
        s02 = 0.5 * (sig[0, 2] + sig[2, 0])
        s12 = 0.5 * (sig[1, 2] + sig[2, 1])
        out[i] = math.sqrt(1.5 * (d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (s01 ** 2 + s02 ** 2 + s12 ** 2)))


def _pair_arrays(X, offsets, indices, h, volume):
    """``g``, its reverse pairs' ``gr``, the per-particle sums ``gsum`` and the hourglass weights
    (:func:`~.gradients.corrected_gradients`)."""
    g, w0 = corrected_gradients(X, offsets, indices, h, volume)
    rev = reverse_pairs(offsets, indices)
    if len(rev) and rev.min() < 0:
        raise ValueError('the reference neighbour lists are not symmetric')
    gsum = np.zeros((len(X), 3))
    rows = np.repeat(np.arange(len(X)), np.diff(offsets))
    np.add.at(gsum, rows, g)
    return g, np.ascontiguousarray(g[rev]), gsum, w0


class TlsphPool(Tlsph):
    """A :class:`Tlsph` whose passes over at least ``par_min`` stressed particles run on numba's
    thread pool. Its own type, so that the frame of a plain :class:`Tlsph` (threads off, the
    default) holds no parallel pass (about 7 s of a first start's compile)."""

    __slots__ = ()


@overload(internal_forces)
def _tlsph_forces(scheme, body, motion, sets):
    if is_state(scheme, TlsphPool):
        def pooled(scheme, body, motion, sets):
            if sets.n_stress >= scheme.par_min:
                tlsph_pass_parallel(scheme, body, motion, sets)
            else:
                tlsph_pass(scheme, body, motion, sets)
            return STATUS_OK
        return pooled
    if is_state(scheme, Tlsph):
        def serial(scheme, body, motion, sets):
            tlsph_pass(scheme, body, motion, sets)
            return STATUS_OK
        return serial
    if is_state(scheme, TlsphQlv):
        def relaxing(scheme, body, motion, sets):
            tlsph_qlv_pass(scheme, body, motion, sets)
            return STATUS_OK
        return relaxing
    return None


class TlsphScheme(FixedStateScheme):
    """The total-Lagrangian scheme of one model (:class:`~.protocols.FrameScheme`).

    Args:
        X: (N, 3) reference positions [m]; offsets, indices: their neighbours within 2h (CSR).
        h: smoothing length [m]; volume: particle volume [m^3].
        hourglass: the hourglass coefficient alpha [-].
        par_min: stressed particles from which a sub-step uses the thread pool.
        explicit_dashpots: False leaves the material's dashpots out of the forces (an implicit
            integrator applies them, :mod:`.backward_euler`); the hourglass dashpot stays.
    """

    name = 'tlsph'

    def __init__(self, X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, h: float,
                 volume: float, hourglass: float, par_min: int, explicit_dashpots: bool = True) -> None:
        n = len(X)
        self.explicit_dashpots = explicit_dashpots
        self.offsets, self.indices, self.volume = offsets, indices, volume
        self.hourglass = hourglass
        self.par_min = par_min
        self.X, self.h = X, h
        self.g, self.gr, self.gsum, self.w0 = _pair_arrays(X, offsets, indices, h, volume)
        self._bonds: Bonds | None = None
        self.F = np.zeros((n, 3, 3))
        self.Fd = np.zeros((n, 3, 3))
        self.A = np.zeros((n, 3, 3))
        self.H = np.zeros((n, 3, 3))
        self._state: Tlsph | None = None
        #: with a relaxing material: its state, and what a frame that is undone puts back
        self._relax: TlsphQlv | None = None
        self._saved: tuple | None = None
        self._growth = 1.0
        self.reset()

    def set_material(self, material: Material, mass: float) -> None:
        vol2 = self.volume ** 2
        hg_k = self.hourglass * material.E * vol2
        # the hourglass dashpot uses the viscous analogue of E (9 eta_b eta_s / (3 eta_b + eta_s)),
        # so hourglass bonds creep with the material's own retardation time (eta_longitudinal
        # would give them (K + 4G/3)/E times that and slow the creep of non-linear fields)
        eta_s, eta_b = material.eta_shear, material.eta_bulk
        eta_e = 9.0 * eta_b * eta_s / (3.0 * eta_b + eta_s) if eta_b + eta_s > 0.0 else 0.0
        hg_c = self.hourglass * eta_e * vol2
        self.material = material
        on = 1.0 if self.explicit_dashpots else 0.0
        kind = TlsphPool if self.par_min <= len(self.F) else Tlsph
        self._state = kind(self.offsets, self.indices, self.g, self.gr, self.gsum, self.w0,
                           self.F, self.Fd, self.A, self.H, self.volume, material.G, material.K,
                           on * eta_s, on * eta_b, hg_k, hg_c, self.par_min)
        self._relax = None
        if material.beyond_kelvin_voigt:
            # a new material starts its relaxation afresh; the Kelvin-Voigt part runs serially
            n, m = len(self.F), len(material.prony)
            base = Tlsph(*self._state)
            self._relax = TlsphQlv(base, material.stiffening, np.ones(1), material.g_inf,
                                   np.array([g for g, _ in material.prony], dtype=np.float64),
                                   np.array([tau for _, tau in material.prony], dtype=np.float64),
                                   np.zeros((n, 6)), np.zeros((n, m, 6)), np.full(n, -1.0), np.zeros(2))
        # the deformation a new material meets is not measured yet: the largest growth until a frame is
        self._growth = STIFFENING_CAP * (1.0 + 2.0 * LOG_STIFFENING_CAP) if material.stiffening > 0.0 else 1.0

    def stiffness_growth(self) -> float:
        """[-] the largest growth of the shear stiffness over its small-strain value in the last
        finished frame (1 without stiffening): the CFL bound follows it."""
        return self._growth

    def start_frame(self, time: float, sub_dt: float) -> None:
        if self._relax is not None:
            self._relax.clock[0] = time - sub_dt    # each sub-step's pass moves it on first
            self._relax.clock[1] = sub_dt
            self._relax.stiff[0] = 1.0

    def state(self, sets, active: np.ndarray, n_active: int) -> Tlsph | TlsphQlv:
        """The frame's state; ``sets`` None: the Kelvin-Voigt state of the instantaneous moduli (the
        organ's linear response, the implicit solves)."""
        r = self._relax
        if r is None or sets is None:
            return self._state
        idx = sets.stress[:sets.n_stress].copy()
        self._saved = (idx, r.Se[idx], r.Q[idx], r.t_up[idx])
        return r

    def frame_done(self, ok: bool) -> None:
        if self._relax is not None:
            grown = float(self._relax.stiff[0])
            # an undone frame may have stiffened within itself: its retry takes the larger bound
            self._growth = grown if ok else max(self._growth, grown if math.isfinite(grown) else 0.0)
        if not ok and self._saved is not None and self._relax is not None:
            idx, Se, Q, t_up = self._saved
            self._relax.Se[idx], self._relax.Q[idx], self._relax.t_up[idx] = Se, Q, t_up
        self._saved = None

    def wave_speed(self, material: Material, mass: float) -> float:
        return material.wave_speed

    def dashpots_only(self) -> Tlsph | None:
        """The state of the last :meth:`set_material` with the elastic and hourglass springs off and
        tensors of its own: a pass over it gives the forces of the explicit dashpots alone, ``-C v``
        at the positions given (:class:`~.stability.DashpotRate`). None when the dashpots are
        integrated implicitly."""
        st = self._state
        if not self.explicit_dashpots or st is None:
            return None
        n = len(self.F)
        return st._replace(G=0.0, K=0.0, hg_k=0.0, F=np.zeros((n, 3, 3)), Fd=np.zeros((n, 3, 3)),
                           A=np.zeros((n, 3, 3)), H=np.zeros((n, 3, 3)))

    def hourglass_damping_bound(self, mass: float, cfl: float) -> float:
        """Stable explicit sub-step of the hourglass dashpot alone [s]: ``C m / max_i sum_j
        W0_ij hg_c`` (its bonds' damping summed per particle; Gershgorin). Far looser than the
        viscous bound (liver: 0.35 against 1.3 sub-steps per ms at 3670 particles, 3.2 against
        12 at 100k); it binds only where the dashpots are implicit and the viscosity is extreme."""
        st = self._state
        rows = np.repeat(np.arange(len(self.offsets) - 1), np.diff(self.offsets))
        per = np.bincount(rows, weights=self.w0 * st.hg_c, minlength=len(self.offsets) - 1)
        top = float(per.max()) if len(per) else 0.0
        return cfl * mass / top if top > 0.0 else math.inf

    def bonds(self, fixed: np.ndarray) -> Bonds:
        """The reference bonds, made breakable (:mod:`.bonds`; ``fixed``: particles never removed)."""
        if self._bonds is None:
            dw, _ = pair_weights(self.X, self.offsets, self.indices, self.h)
            self._bonds = Bonds(self.X, self.offsets, self.indices, dw, reverse_pairs(self.offsets, self.indices),
                                self.volume, fixed, self.g, self.gr, self.gsum, self.w0)
        return self._bonds

    def reset(self) -> None:
        if self._bonds is not None:
            self._bonds.reset()          # the intact organ again
        self.F[:] = np.eye(3)
        self.Fd[:] = 0.0
        self.A[:] = 0.0
        self.H[:] = 0.0
        if self._relax is not None:
            for a in (self._relax.Se, self._relax.Q, self._relax.clock):
                a[:] = 0.0
            self._relax.t_up[:] = -1.0
        self._growth = 1.0

    def von_mises(self, x: np.ndarray, sets, out: np.ndarray) -> None:
        """Von Mises stress of the stress set of the last frame (``sets``; with a relaxing spring
        from the stresses the frame used, ``A = V P``)."""
        m = self.material
        if self._relax is not None:
            piola_von_mises(self.F, self.A, self.volume, sets.stress, sets.n_stress, out)
            return
        tlsph_von_mises(self.F, self.Fd, m.G, m.K, m.eta_shear, m.eta_bulk, sets.stress, sets.n_stress, out)
