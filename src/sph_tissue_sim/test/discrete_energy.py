"""Shared test helpers: a field's corrected-gradient sums and the discrete neo-Hookean energy,
written out in numpy to check the kernels against."""

import numpy as np

from sph_tissue_sim.core.material import Material

#: the liver's shear modulus and Poisson ratio without dashpots: forces from the spring alone
SOFT = Material.from_shear(1800.0, 0.45, 0.0, 0.0, rho=1060.0)


def gradients(s, field: np.ndarray) -> np.ndarray:
    """``sum_j (f_j - f_i) (x) g_ij`` per particle of solver ``s``, for ``field`` (N, ...) of any
    trailing shape; (N, 3, 3) for positions."""
    sc = s.scheme
    rows = np.repeat(np.arange(s.n), np.diff(sc.offsets))
    diff = field[sc.indices] - field[rows]
    out = np.zeros(field.shape + (3,))
    np.add.at(out, rows, diff[..., None] * sc.g.reshape((-1,) + (1,) * (field.ndim - 1) + (3,)))
    return out


def neo_hookean_energy(s, F: np.ndarray) -> float:
    """``sum_i V psi(F_i)``, compressible neo-Hookean ``psi = G/2 (tr C - 3) - G ln J + lam/2 ln^2 J``
    with the material of solver ``s``."""
    G, K = s.material.G, s.material.K
    lam = K - 2.0 * G / 3.0
    J = np.linalg.det(F)
    psi = 0.5 * G * (np.einsum('nab,nab->n', F, F) - 3.0) - G * np.log(J) + 0.5 * lam * np.log(J) ** 2
    return float(s.volume * psi.sum())


def assert_forces_are_minus_the_energy_gradient(s, energy, picks, seed: int) -> None:
    """Distort solver ``s``'s body at random, run its force pass and compare each picked force
    component ``(i, a)`` with the central difference of ``energy(x)`` (no hourglass or viscosity
    may act for that to hold)."""
    import pytest

    from sph_tissue_sim.core.tlsph import tlsph_pass

    x = s.X + np.random.default_rng(seed).normal(0.0, 2e-4, s.X.shape)
    s.x[:] = x
    s.v[:] = 0.0
    tlsph_pass(s.scheme.state(None, None, 0), s.body, s.motion, s.area.global_sets(-1))
    f = s.acc * s.mass
    eps = 1e-8
    for i, a in picks:
        xp, xm = x.copy(), x.copy()
        xp[i, a] += eps
        xm[i, a] -= eps
        dE = (energy(xp) - energy(xm)) / (2.0 * eps)
        assert f[i, a] == pytest.approx(-dE, rel=1e-5, abs=1e-12 * np.abs(f).max())
