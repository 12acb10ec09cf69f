"""The paper's updated-Lagrangian SPH (eqs. 11-16, summation density eq. 15): the ``paper`` scheme.

Every sub-step works in the CURRENT configuration ``x`` (displacement ``u = x - X``):

1. neighbour search on a cell grid (cell size 2h) over the current positions (sec. 3.2), O(N),
   CSR lists. This per-step rebuild is what the total-Lagrangian scheme avoids; it is kept here
   because it is the paper's method (and its cost).
2. summation density (eq. 15), self term included::

       rho_i = sum_j m_j WIJ

3. strain (eqs. 4, 16) in the difference form, tensor (not engineering) shear, and its rate::

       eps_i    = sym( sum_j V_j (u_j - u_i) (x) DWIJ ),      V_j = m_j / rho_j
       deps_i/dt = sym( sum_j V_j (v_j - v_i) (x) DWIJ )

   Eq. 16 as printed uses ``u_j`` alone. Its strain is the difference form plus
   ``sym(u_i (x) g_i)`` with ``g_i = sum_j V_j DWIJ``; ``g_i`` vanishes only inside a perfectly
   symmetric neighbourhood, and at a free surface it is of order 1/h, so a rigid translation
   ``u = t`` would produce a strain ~|t|/h there (and a stress, and a force). The difference form
   is exact for any constant field everywhere.
4. Kelvin-Voigt stress (eqs. 1-3 with separate moduli; :class:`~.material.Material`)::

       sigma_i = 2 G dev(eps_i) + K tr(eps_i) I + 2 eta_s dev(deps_i/dt) + eta_v tr(deps_i/dt) I

   (``S = 2G e + 2 eta_s de/dt``, ``sigma_kk = 3K eps_kk + 3 eta_v deps_kk/dt``; the paper's
   ``E``/``eta`` form is :meth:`~.material.Material.paper_preset`, nu = 0.)
5. momentum (eqs. 11-14), the symmetric form, so internal forces conserve linear momentum::

       dv_i/dt = sum_j m_j (sigma_i / rho_i^2 + sigma_j / rho_j^2) . DWIJ        (eq. 14)

   (eq. 12 lost: docs/decisions/retired-paper_momentum.md).

6. symplectic Euler (eq. 22): ``v <- v + dt a``, ``x <- x + dt v`` (the frame loop, :mod:`.frame`).

Naming follows PySPH: ``XIJ = x_i - x_j``, ``WIJ = W(|XIJ|, h)``, ``DWIJ = grad_i WIJ =
dW/dr XIJ / |XIJ|``. There is no hourglass control and no kernel correction: the scheme shows the
zero-energy modes, tensile instability and surface density deficiency of plain SPH, as the paper
reports for large steps. A torn body (a solved particle without neighbours) or non-finite
positions stop the frame at the next sub-step's search, a speed above the limit is caught after
the frame (:func:`~.integrate.frame_state_ok`), and the solver restores the state.

Local mode (sec. 4): the frame's sets (:class:`~.local_area.LocalArea`) are used unchanged. The
rows that get density, strain and stress are the fully solved particles and their reference
neighbours; the grid is built over the current positions of those, one more ring of reference
neighbours and every active particle (the paper too searches only inside the area). Particles
outside the rows keep their last density and stress. The transmission layers follow the contact
by velocity as in every scheme (:func:`~.integrate.move_layers` says why).

Measured behaviour (block of liver, G = 1.8 kPa, nu = 0.45, 3 Pa s, spacing 5-7.5 mm, h = 1.3
spacings): the instability does not depend on the time step (halving the CFL number changes
nothing). With eq. 14 a free surface perturbed by 0.2 mm grows until the body tears (about 0.5 s);
eq. 12 damps the same perturbation. A 2-3 mm global press stays bounded for ~0.1-0.2 s and gives
a reaction 2-3 times below tlsph (no hourglass stiffness against a point load). In local mode
(8 x 8 x 5 block, 7.5 mm spacing, pressed 3 mm over 0.1 s and held to 1 s) the press stays bounded
with 2 layers (0.127 N) and without (0.138 N); the paper's acceleration-following layers, used
here before, gave 0.079 N. Blow-ups end in :class:`~.errors.SimError` with the state restored,
never NaN.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import overload

from .kernel import ZERO3X3, add_outer, kernel_dwdr, kernel_w
from .material import Material
from .neighbours import append_new, bin_points, cell_block
from .protocols import STATUS_BROKEN, STATUS_FULL, STATUS_OK, internal_forces, is_state

_MAX_CELLS = 50_000_000   # a larger current-configuration grid means the body flew apart


# ---------------------------------------------------------------------------- neighbour search
@njit(cache=True)
def _fill_pairs(x, search, rows, n_rows, h, pos, origin, dims, cell_start, cell_particles,
                nb_off, nb_idx, nb_dw, nb_w):
    """Pair lists of :func:`current_neighbours` into fixed buffers; -1 if they are too small.

    Kept free of allocation so the hot loop stays tight (a growable buffer in the loop made the
    search five times slower).
    """
    support = 2.0 * h
    r2max = support * support
    cap = nb_idx.shape[0]
    m = 0
    nb_off[0] = 0
    cells = np.empty(27, dtype=np.int64)
    for r in range(n_rows):
        i = rows[r]
        xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
        n_cells = cell_block(xi0, xi1, xi2, origin, support, dims, cells)
        for q in range(n_cells):
            for k in range(cell_start[cells[q]], cell_start[cells[q] + 1]):
                p = cell_particles[k]
                j = search[p]
                if j == i:
                    continue
                d0 = xi0 - pos[p, 0]; d1 = xi1 - pos[p, 1]; d2 = xi2 - pos[p, 2]
                rr = d0 * d0 + d1 * d1 + d2 * d2
                if rr >= r2max:
                    continue
                if m >= cap:
                    return -1
                rij = math.sqrt(rr)
                nb_idx[m] = j
                nb_dw[m] = kernel_dwdr(rij, h) / rij if rij > 1e-300 else 0.0
                nb_w[m] = kernel_w(rij, h)
                m += 1
        nb_off[r + 1] = m
    return m


@njit(cache=True)
def search_pairs(x, search, n_search, rows, n_rows, h, pos, nb_off, nb_idx, nb_dw, nb_w):
    """CSR neighbours (within 2h, current positions) of ``rows[:n_rows]`` among ``search[:n_search]``.

    Row ``r`` (particle ``rows[r]``) has pairs ``nb_off[r]:nb_off[r + 1]`` with neighbour
    ``nb_idx[k]``, ``nb_dw[k] = dW/dr(RIJ) / RIJ`` (so ``DWIJ = nb_dw[k] * XIJ``) and
    ``nb_w[k] = WIJ``. ``pos`` (>= n_search, 3) is scratch.

    Returns :data:`~.protocols.STATUS_OK`, :data:`~.protocols.STATUS_FULL` (the pair buffers are
    too small) or :data:`~.protocols.STATUS_BROKEN` (non-finite positions or a grid too large to
    allocate: particles flung apart); the lists are valid only with OK.
    """
    support = 2.0 * h
    lo0 = math.inf; lo1 = math.inf; lo2 = math.inf
    hi0 = -math.inf; hi1 = -math.inf; hi2 = -math.inf
    for p in range(n_search):
        j = search[p]
        a = x[j, 0]; b = x[j, 1]; c = x[j, 2]
        if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
            return STATUS_BROKEN
        pos[p, 0] = a; pos[p, 1] = b; pos[p, 2] = c
        lo0 = min(lo0, a); lo1 = min(lo1, b); lo2 = min(lo2, c)
        hi0 = max(hi0, a); hi1 = max(hi1, b); hi2 = max(hi2, c)
    if n_search == 0:
        nb_off[0] = 0
        for r in range(n_rows):
            nb_off[r + 1] = 0
        return STATUS_OK
    origin = np.empty(3)
    origin[0] = lo0 - support; origin[1] = lo1 - support; origin[2] = lo2 - support
    dims = np.empty(3, dtype=np.int64)
    ext0 = (hi0 + support - origin[0]) / support
    ext1 = (hi1 + support - origin[1]) / support
    ext2 = (hi2 + support - origin[2]) / support
    if ext0 * ext1 * ext2 > _MAX_CELLS:
        return STATUS_BROKEN
    dims[0] = max(1, int(math.ceil(ext0)))
    dims[1] = max(1, int(math.ceil(ext1)))
    dims[2] = max(1, int(math.ceil(ext2)))
    cell_start, cell_particles = bin_points(pos[:n_search], origin, support, dims)
    m = _fill_pairs(x, search, rows, n_rows, h, pos, origin, dims, cell_start, cell_particles,
                    nb_off, nb_idx, nb_dw, nb_w)
    return STATUS_OK if m >= 0 else STATUS_FULL


def grown(nb_idx: np.ndarray, nb_dw: np.ndarray, nb_w: np.ndarray):
    """Larger pair buffers (compression packs more pairs than the reference had)."""
    cap = 2 * nb_idx.shape[0] + 1024
    return np.empty(cap, dtype=nb_idx.dtype), np.empty(cap), np.empty(cap)


def current_neighbours(x, search, n_search, rows, n_rows, h, pos, nb_off, nb_idx, nb_dw, nb_w):
    """:func:`search_pairs`, growing the pair buffers until they fit.

    Returns ``(ok, nb_idx, nb_dw, nb_w)`` (the buffers may be new ones).
    """
    while True:
        status = search_pairs(x, search, n_search, rows, n_rows, h, pos, nb_off, nb_idx, nb_dw, nb_w)
        if status != STATUS_FULL:
            return status == STATUS_OK, nb_idx, nb_dw, nb_w
        nb_idx, nb_dw, nb_w = grown(nb_idx, nb_dw, nb_w)


# ---------------------------------------------------------------------------- density, strain, stress
@njit(cache=True, fastmath=True)
def summation_density(rows, n_rows, nb_off, nb_w, mass, h, rho):
    """Eq. 15 with equal masses: ``rho_i = m (W(0) + sum_j WIJ)`` for ``rows[:n_rows]``."""
    w_self = kernel_w(0.0, h)
    for r in range(n_rows):
        s = w_self
        for k in range(nb_off[r], nb_off[r + 1]):
            s += nb_w[k]
        rho[rows[r]] = mass * s


@njit(cache=True, fastmath=True)
def strain_stress(p, X, x, v, mass):
    """Strain, strain rate (difference form of eq. 16) and Kelvin-Voigt stress (eqs. 1-3).

    For ``i = rows[r]``, with ``V_j = m / rho_j`` and ``DWIJ = nb_dw[k] * (x_i - x_j)``::

        grad u_i = sum_j V_j (u_j - u_i) (x) DWIJ,   u = x - X
        grad v_i = sum_j V_j (v_j - v_i) (x) DWIJ
        eps_i = sym(grad u_i),  deps_i/dt = sym(grad v_i)
        sigma_i = 2 G dev(eps) + K tr(eps) I + 2 eta_s dev(deps/dt) + eta_v tr(deps/dt) I

    for the rows of ``p`` (a :class:`Paper`). Components are stored as (xx, yy, zz, xy, xz, yz)
    rows of ``p.eps``, ``p.epsd``, ``p.sig`` (N, 6).
    """
    rows, n_rows, nb_off, nb_idx, nb_dw, rho = p.rows, p.n_rows, p.nb_off, p.nb_idx, p.nb_dw, p.rho
    G, K, eta_s, eta_v, eps, epsd, sig = p.G, p.K, p.eta_s, p.eta_v, p.eps, p.epsd, p.sig
    for r in range(n_rows):
        i = rows[r]
        xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
        ui0 = xi0 - X[i, 0]; ui1 = xi1 - X[i, 1]; ui2 = xi2 - X[i, 2]
        vi0 = v[i, 0]; vi1 = v[i, 1]; vi2 = v[i, 2]
        a = ZERO3X3
        b = ZERO3X3
        for k in range(nb_off[r], nb_off[r + 1]):
            j = nb_idx[k]
            f = nb_dw[k] * mass / rho[j]
            g0 = f * (xi0 - x[j, 0]); g1 = f * (xi1 - x[j, 1]); g2 = f * (xi2 - x[j, 2])
            d0 = x[j, 0] - X[j, 0] - ui0; d1 = x[j, 1] - X[j, 1] - ui1; d2 = x[j, 2] - X[j, 2] - ui2
            e0 = v[j, 0] - vi0; e1 = v[j, 1] - vi1; e2 = v[j, 2] - vi2
            a = add_outer(a, d0, d1, d2, g0, g1, g2)
            b = add_outer(b, e0, e1, e2, g0, g1, g2)
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = a
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = b
        exy = 0.5 * (a01 + a10); exz = 0.5 * (a02 + a20); eyz = 0.5 * (a12 + a21)
        rxy = 0.5 * (b01 + b10); rxz = 0.5 * (b02 + b20); ryz = 0.5 * (b12 + b21)
        eps[i, 0] = a00; eps[i, 1] = a11; eps[i, 2] = a22
        eps[i, 3] = exy; eps[i, 4] = exz; eps[i, 5] = eyz
        epsd[i, 0] = b00; epsd[i, 1] = b11; epsd[i, 2] = b22
        epsd[i, 3] = rxy; epsd[i, 4] = rxz; epsd[i, 5] = ryz
        tr3 = (a00 + a11 + a22) / 3.0
        trd3 = (b00 + b11 + b22) / 3.0
        # sigma = 2G (eps - tr/3 I) + 3K tr/3 I + viscous analogue
        iso = 3.0 * K * tr3 + 3.0 * eta_v * trd3
        sig[i, 0] = 2.0 * G * (a00 - tr3) + 2.0 * eta_s * (b00 - trd3) + iso
        sig[i, 1] = 2.0 * G * (a11 - tr3) + 2.0 * eta_s * (b11 - trd3) + iso
        sig[i, 2] = 2.0 * G * (a22 - tr3) + 2.0 * eta_s * (b22 - trd3) + iso
        sig[i, 3] = 2.0 * G * exy + 2.0 * eta_s * rxy
        sig[i, 4] = 2.0 * G * exz + 2.0 * eta_s * rxz
        sig[i, 5] = 2.0 * G * eyz + 2.0 * eta_s * ryz


@njit(cache=True, fastmath=True)
def momentum_one(r, p, x, mass):
    """Internal acceleration ``(a0, a1, a2)`` of ``i = p.rows[r]`` (``p`` a :class:`Paper`), eq. 14::

        dv_i/dt = sum_j m_j (sigma_i / rho_i^2 + sigma_j / rho_j^2) . DWIJ

    antisymmetric in i, j (momentum conserving). Where summation density drops (free surfaces)
    its linear stiffness is not symmetric, whose growing modes make a free block at rest with a
    tiny perturbation fly apart at any time step (see the tests).
    """
    rows, nb_off, nb_idx, nb_dw, rho, sig = p.rows, p.nb_off, p.nb_idx, p.nb_dw, p.rho, p.sig
    i = rows[r]
    ci = 1.0 / (rho[i] * rho[i])
    si0 = sig[i, 0]; si1 = sig[i, 1]; si2 = sig[i, 2]
    si3 = sig[i, 3]; si4 = sig[i, 4]; si5 = sig[i, 5]
    xi0 = x[i, 0]; xi1 = x[i, 1]; xi2 = x[i, 2]
    a0 = 0.0; a1 = 0.0; a2 = 0.0
    for k in range(nb_off[r], nb_off[r + 1]):
        j = nb_idx[k]
        f = mass * nb_dw[k]
        g0 = f * (xi0 - x[j, 0]); g1 = f * (xi1 - x[j, 1]); g2 = f * (xi2 - x[j, 2])
        cj = 1.0 / (rho[j] * rho[j])
        t0 = si0 * ci + sig[j, 0] * cj; t1 = si1 * ci + sig[j, 1] * cj; t2 = si2 * ci + sig[j, 2] * cj
        t3 = si3 * ci + sig[j, 3] * cj; t4 = si4 * ci + sig[j, 4] * cj; t5 = si5 * ci + sig[j, 5] * cj
        a0 += t0 * g0 + t3 * g1 + t4 * g2
        a1 += t3 * g0 + t1 * g1 + t5 * g2
        a2 += t4 * g0 + t5 * g1 + t2 * g2
    return a0, a1, a2


# ---------------------------------------------------------------------------- the scheme's forces
class Paper(NamedTuple):
    """The scheme's state for the frame loop (one per frame: the row and search sets change)."""

    h: float               # [m] smoothing length
    G: float               # [Pa] shear modulus
    K: float               # [Pa] bulk modulus
    eta_s: float           # [Pa s] shear viscosity
    eta_v: float           # [Pa s] bulk viscosity
    rows: np.ndarray       # rows[:n_sph] are sets.sph; rows[:n_rows] get density, strain, stress
    n_rows: int
    search: np.ndarray     # search[:n_search] (a superset of rows) are binned for the search
    n_search: int
    rho: np.ndarray        # (N,) density
    eps: np.ndarray        # (N, 6) strain
    epsd: np.ndarray       # (N, 6) strain rate
    sig: np.ndarray        # (N, 6) stress
    pos: np.ndarray        # (N, 3) scratch
    nb_off: np.ndarray     # pair lists of the current configuration (:func:`search_pairs`)
    nb_idx: np.ndarray
    nb_dw: np.ndarray
    nb_w: np.ndarray


@overload(internal_forces)
def _paper_forces(scheme, body, motion, sets):
    if not is_state(scheme, Paper):
        return None

    def impl(scheme, body, motion, sets):
        p = scheme
        x = motion.x
        status = search_pairs(x, p.search, p.n_search, p.rows, p.n_rows, p.h, p.pos, p.nb_off,
                              p.nb_idx, p.nb_dw, p.nb_w)
        if status != STATUS_OK:
            return status
        for r in range(sets.n_sph):
            if p.nb_off[r + 1] == p.nb_off[r]:
                return STATUS_BROKEN   # a solved particle with no neighbour left: the body tore apart
        summation_density(p.rows, p.n_rows, p.nb_off, p.nb_w, body.mass, p.h, p.rho)
        strain_stress(p, body.X, x, motion.v, body.mass)
        acc = motion.acc
        for r in range(sets.n_sph):
            i = p.rows[r]
            a0, a1, a2 = momentum_one(r, p, x, body.mass)
            acc[i, 0] = a0
            acc[i, 1] = a1
            acc[i, 2] = a2
        return STATUS_OK
    return impl


# ---------------------------------------------------------------------------- local-mode sets
@njit(cache=True, nogil=True)
def local_rows(offsets, indices, sph, n_sph, stress, n_stress, active, n_active,
               stamp, stamp_val, rows, search):
    """Rows (``sph`` first, then the rest of ``stress``) and the search set for a local frame.

    The search set is the rows, their reference neighbours and every active particle (active
    particles may have moved far from home). Returns ``(n_rows, n_search)``.
    """
    n_rows = append_new(sph, 0, n_sph, stamp, stamp_val, rows, 0)
    n_rows = append_new(stress, 0, n_stress, stamp, stamp_val, rows, n_rows)
    search[:n_rows] = rows[:n_rows]
    n_search = n_rows
    for t in range(n_rows):
        i = rows[t]
        n_search = append_new(indices, offsets[i], offsets[i + 1], stamp, stamp_val, search, n_search)
    return n_rows, append_new(active, 0, n_active, stamp, stamp_val, search, n_search)


@njit(cache=True, nogil=True)
def von_mises_rows(sig, rows, n_rows, out):
    """Von Mises stress ``sqrt(3/2 s:s)`` (s = dev sigma) of ``rows[:n_rows]`` into ``out``."""
    for r in range(n_rows):
        i = rows[r]
        p = (sig[i, 0] + sig[i, 1] + sig[i, 2]) / 3.0
        d0 = sig[i, 0] - p; d1 = sig[i, 1] - p; d2 = sig[i, 2] - p
        out[i] = math.sqrt(1.5 * (d0 * d0 + d1 * d1 + d2 * d2
                                  + 2.0 * (sig[i, 3] ** 2 + sig[i, 4] ** 2 + sig[i, 5] ** 2)))


# ---------------------------------------------------------------------------- whole-body evaluation
def paper_fields(X: np.ndarray, x: np.ndarray, v: np.ndarray, fixed: np.ndarray, h: float,
                 volume: float, material) -> dict:
    """Density, strain, strain rate, stress and internal acceleration of every particle (global).

    For analysis and tests: one call of the same kernels the frame loop uses, with all particles
    as rows (fixed ones get fields but zero acceleration).

    Returns:
        dict with ``rho`` (N,), ``eps``, ``epsd``, ``sig`` (N, 6; xx, yy, zz, xy, xz, yz) and
        ``acc`` (N, 3).
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    x = np.ascontiguousarray(x, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    fixed = np.ascontiguousarray(fixed, dtype=np.bool_)
    n = len(X)
    mass = material.rho * volume
    rows = np.concatenate([np.flatnonzero(~fixed), np.flatnonzero(fixed)]).astype(np.int32)
    nb_off = np.zeros(n + 1, dtype=np.int64)
    ok, nb_idx, nb_dw, nb_w = current_neighbours(x, rows, n, rows, n, h, np.empty((n, 3)), nb_off,
                                                 np.empty(64 * n, dtype=np.int32), np.empty(64 * n),
                                                 np.empty(64 * n))
    if not ok:
        raise ValueError('positions are non-finite or too far apart for a cell grid')
    p = Paper(h, material.G, material.K, material.eta_shear, material.eta_bulk, rows, n, rows, n,
              np.empty(n), np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6)), np.empty((n, 3)),
              nb_off, nb_idx, nb_dw, nb_w)
    acc = np.zeros((n, 3))
    summation_density(rows, n, nb_off, nb_w, mass, h, p.rho)
    strain_stress(p, X, x, v, mass)
    for r in range(int((~fixed).sum())):
        acc[rows[r]] = momentum_one(r, p, x, mass)
    return dict(rho=p.rho, eps=p.eps, epsd=p.epsd, sig=p.sig, acc=acc)


# ---------------------------------------------------------------------------- the scheme object
class PaperScheme:
    """The paper's scheme for one model (:class:`~.protocols.FrameScheme`): densities, strains,
    stresses and the current-configuration pair lists, and the rows of each frame.

    Args:
        X: (N, 3) reference positions [m]; x: the solver's live positions; fixed: (N,) boundary mask.
        offsets, indices: reference neighbours (CSR), for the local rows and the first pair capacity.
        h: smoothing length [m].
    """

    name = 'paper'

    def __init__(self, X: np.ndarray, x: np.ndarray, fixed: np.ndarray, offsets: np.ndarray, indices: np.ndarray,
                 h: float) -> None:
        n = len(X)
        self.X, self.x, self.offsets, self.indices, self.h = X, x, offsets, indices, h
        self.rho = np.empty(n)
        self.eps = np.zeros((n, 6))
        self.epsd = np.zeros((n, 6))
        self.sig = np.zeros((n, 6))
        self.pos = np.empty((n, 3))
        self.rows = np.zeros(n, dtype=np.int32)
        self.search = np.zeros(n, dtype=np.int32)
        self.stamp = np.zeros(n, dtype=np.int64)
        self.stamp_val = 0
        self.nb_off = np.zeros(n + 1, dtype=np.int64)
        cap = len(indices) + len(indices) // 4 + 1024   # grows if compression packs more
        self.nb_idx = np.empty(cap, dtype=np.int32)
        self.nb_dw = np.empty(cap)
        self.nb_w = np.empty(cap)
        free = np.flatnonzero(~fixed).astype(np.int32)
        self.n_free = len(free)
        self.global_rows = np.concatenate([free, np.flatnonzero(fixed)]).astype(np.int32)
        self.n_rows_last = 0
        self._rows_last = self.global_rows
        self.material: Material | None = None
        self.mass = 0.0
        self._frame: tuple = ()

    def set_material(self, material: Material, mass: float) -> None:
        self.material = material
        self.mass = mass
        self._refresh_density()

    def wave_speed(self, material: Material, mass: float) -> float:
        return material.wave_speed

    def reset(self) -> None:
        """Reference state (call after the positions are reset): zero strain and stress."""
        self.eps[:] = 0.0
        self.epsd[:] = 0.0
        self.sig[:] = 0.0
        self.n_rows_last = 0
        self._refresh_density()

    def _refresh_density(self) -> None:
        """Summation density of every particle at the current positions (particles outside a
        local frame's rows keep this value); redone when the particle mass changes."""
        n = len(self.X)
        ok, self.nb_idx, self.nb_dw, self.nb_w = current_neighbours(
            self.x, self.global_rows, n, self.global_rows, n, self.h, self.pos, self.nb_off,
            self.nb_idx, self.nb_dw, self.nb_w)
        if ok:
            summation_density(self.global_rows, n, self.nb_off, self.nb_w, self.mass, self.h, self.rho)
        elif self.material is not None:
            self.rho[:] = self.material.rho

    def start_frame(self, time: float, sub_dt: float) -> None:
        pass

    def stiffness_growth(self) -> float:
        return 1.0

    def state(self, sets, active: np.ndarray, n_active: int) -> Paper:
        """This frame's state: every particle as rows in global mode (``sets.sph`` is every free
        one), else the solved particles, their stress set and the search set around them."""
        if sets.n_sph == self.n_free and sets.n_stress == len(self.X):
            rows, n_rows = self.global_rows, len(self.X)
            search, n_search = self.global_rows, len(self.X)
        else:
            self.stamp_val += 1
            n_rows, n_search = local_rows(self.offsets, self.indices, sets.sph, sets.n_sph, sets.stress,
                                          sets.n_stress, active, n_active, self.stamp, self.stamp_val,
                                          self.rows, self.search)
            rows, search = self.rows, self.search
        self._frame = (rows, n_rows)
        m = self.material
        return Paper(self.h, m.G, m.K, m.eta_shear, m.eta_bulk, rows, n_rows, search,
                     n_search, self.rho, self.eps, self.epsd, self.sig, self.pos, self.nb_off,
                     self.nb_idx, self.nb_dw, self.nb_w)

    def grow(self, state: Paper) -> Paper:
        """The same state with larger pair buffers (:data:`~.protocols.STATUS_FULL`)."""
        self.nb_idx, self.nb_dw, self.nb_w = grown(self.nb_idx, self.nb_dw, self.nb_w)
        return state._replace(nb_idx=self.nb_idx, nb_dw=self.nb_dw, nb_w=self.nb_w)

    def frame_done(self, ok: bool) -> None:
        self._rows_last, n_rows = self._frame
        self.n_rows_last = n_rows if ok else 0

    def von_mises(self, x: np.ndarray, sets, out: np.ndarray) -> None:
        """Von Mises stress of the last frame's stress rows (0 elsewhere)."""
        if self.n_rows_last > 0:
            von_mises_rows(self.sig, self._rows_last, self.n_rows_last, out)
