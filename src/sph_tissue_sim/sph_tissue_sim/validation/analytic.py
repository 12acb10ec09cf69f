"""Closed-form reference answers from continuum mechanics (SI units).

None of them comes from a run of the solver; each docstring names its source and its assumptions.
"""

from __future__ import annotations

import math

import numpy as np

#: beta L of the first clamped-free bending mode (root of cos x cosh x = -1)
CANTILEVER_BETA_L = 1.8751


def creep_strain(sigma0: float, E: float, tau: float, t: float) -> float:
    """Kelvin-Voigt creep under a constant uniaxial stress from rest: sigma0/E (1 - exp(-t/tau))."""
    return sigma0 / E * (1.0 - math.exp(-t / tau))


def relaxing_creep_strain(sigma0: float, E0: float, tau_v: float, prony, t: float) -> float:
    """Creep under a constant uniaxial stress from rest of a relaxing spring (quasi-linear
    viscoelastic: instantaneous modulus ``E0``, relaxation ``g(t) = g_inf + sum_k g_k
    exp(-t / tau_k)`` from ``prony = ((g_k, tau_k), ...)``) in parallel with a dashpot of
    retardation ``tau_v`` (stress ``E0 tau_v deps/dt``), inertia neglected (linear
    viscoelasticity: Findley, Lai and Onaran, Creep and Relaxation of Nonlinear Viscoelastic
    Materials, 1976, ch. 5). In Laplace space

        eps(s) = sigma0 / (E0 s M(s)),   M(s) = g_inf + sum_k g_k s tau_k / (s tau_k + 1) + tau_v s,

    and with ``P(s) = prod_k (s tau_k + 1)``, ``N(s) = M(s) P(s)`` (a polynomial whose roots ``r``
    are real and negative) the residues give

        eps(t) = sigma0 / E0 [1 / g_inf + sum_r P(r) exp(r t) / (r N'(r))].
    """
    from numpy.polynomial import Polynomial as Poly

    g_inf = 1.0 - sum(g for g, _ in prony)
    P = Poly([1.0])
    for _, tau in prony:
        P = P * Poly([1.0, tau])
    N = (g_inf + Poly([0.0, tau_v])) * P
    for k, (g, tau) in enumerate(prony):
        term = Poly([0.0, g * tau])
        for j, (_, tau_j) in enumerate(prony):
            if j != k:
                term = term * Poly([1.0, tau_j])
        N = N + term
    dN = N.deriv()
    total = 1.0 / g_inf
    for r in N.roots():
        total += float(np.real(P(r) * np.exp(r * t) / (r * dN(r))))
    return sigma0 / E0 * total


def euler_bernoulli_f1(length: float, height: float, E: float, rho: float) -> float:
    """First bending frequency [Hz] of a clamped-free Euler-Bernoulli beam of rectangular section
    bent across ``height``: (beta L)^2 / (2 pi L^2) sqrt(E I / (rho A)), I / A = H^2 / 12."""
    return CANTILEVER_BETA_L ** 2 / (2.0 * math.pi * length ** 2) * math.sqrt(E * height ** 2 / 12.0 / rho)


def _expm(M: np.ndarray) -> np.ndarray:
    """Matrix exponential (scaling and squaring of a 24-term Taylor series; numpy only)."""
    n_sq = max(0, int(math.ceil(math.log2(max(float(np.abs(M).sum(axis=1).max()), 1e-300)))) + 1)
    B = M / 2.0 ** n_sq
    out = np.eye(len(M))
    term = np.eye(len(M))
    for k in range(1, 25):
        term = term @ B / k
        out = out + term
    for _ in range(n_sq):
        out = out @ out
    return out


def timoshenko_f1(length: float, height: float, width: float, E: float, nu: float, rho: float) -> float:
    """First bending frequency [Hz] of a clamped-free Timoshenko beam (rectangular section).

    Harmonic solutions w(x), psi(x) of  kappa G A (w'' - psi') + rho A omega^2 w = 0  and
    E I psi'' + kappa G A (w' - psi) + rho I omega^2 psi = 0  with w = psi = 0 at the clamp and
    E I psi' = kappa G A (w' - psi) = 0 at the free end; Cowper's shear coefficient
    kappa = 10 (1 + nu) / (12 + 11 nu). The ODEs have constant coefficients, so the state at x = L
    is exp(M L) times the state at the clamp, and omega is the lowest root of the 2 x 2 boundary
    determinant (bisection). Tends to Euler-Bernoulli's for slender beams (ratio 0.99993 at
    L/H = 100, 0.988 at 8, 0.955 at 4).
    """
    kappa = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)
    G = E / (2.0 * (1.0 + nu))
    A, I = width * height, width * height ** 3 / 12.0
    s_gA = kappa * G * A

    def boundary_det(omega: float) -> float:
        w2 = omega * omega
        # state (w, w', psi, psi')
        M = np.array([[0.0, 1.0, 0.0, 0.0],
                      [-rho * w2 / (kappa * G), 0.0, 0.0, 1.0],
                      [0.0, 0.0, 0.0, 1.0],
                      [0.0, -s_gA / (E * I), s_gA / (E * I) - rho * w2 / E, 0.0]])
        Y = _expm(M * length)[:, [1, 3]]       # unknown slopes w'(0), psi'(0)
        return float(np.linalg.det(np.array([Y[3], Y[1] - Y[2]])))

    f_eb = euler_bernoulli_f1(length, height, E, rho)
    grid = np.linspace(0.3, 1.2, 200) * 2.0 * math.pi * f_eb
    d = [boundary_det(w) for w in grid]
    k = next(k for k in range(len(grid) - 1) if d[k] * d[k + 1] < 0.0)
    lo, hi, d_lo = grid[k], grid[k + 1], d[k]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        d_mid = boundary_det(mid)
        if d_lo * d_mid <= 0.0:
            hi = mid
        else:
            lo, d_lo = mid, d_mid
    return 0.5 * (lo + hi) / (2.0 * math.pi)


def hertz_force(E: float, nu: float, radius: float, depth) -> np.ndarray:
    """Rigid sphere of ``radius`` pressed ``depth`` into an elastic half-space (Hertz):
    F = 4/3 E* sqrt(R) d^1.5 with E* = E / (1 - nu^2). Valid while d << R."""
    d = np.clip(np.asarray(depth, dtype=float), 0.0, None)
    return 4.0 / 3.0 * E / (1.0 - nu * nu) * math.sqrt(radius) * d ** 1.5
