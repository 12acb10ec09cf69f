"""Sub-stepped symplectic Euler frame loop (paper eq. 22) shared by the tlsph and mass-spring schemes.

One call advances the tissue by ``n_sub`` sub-steps of ``dt``: internal forces of the fully solved
set, contact forces, then

    v <- v + dt a,    x <- x + dt v          (symplectic Euler, eq. 22)

for every fully solved free particle, while transmission-layer particles move with
``v = w(i) * v_contact`` (paper eq. 21, ``a = w(i) a_contact``, integrated once). All index sets are preallocated arrays with counts, so a local
step costs in proportion to the active area, never to the model size.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import contact_forces
from .tlsph import tlsph_pass, tlsph_pass_parallel

SCHEME_TLSPH = 1
SCHEME_MASS_SPRING = 2


@njit(cache=True, fastmath=True)
def spring_force_one(i, x, v, offsets, indices, k_spring, rest, tau, out):
    """Kelvin-Voigt springs to reference neighbours: ``f = k (l - l0) e + k tau (dv . e) e``."""
    f0 = 0.0; f1 = 0.0; f2 = 0.0
    for k in range(offsets[i], offsets[i + 1]):
        j = indices[k]
        d0 = x[j, 0] - x[i, 0]; d1 = x[j, 1] - x[i, 1]; d2 = x[j, 2] - x[i, 2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if r < 1e-12:
            continue
        e0 = d0 / r; e1 = d1 / r; e2 = d2 / r
        rate = (v[j, 0] - v[i, 0]) * e0 + (v[j, 1] - v[i, 1]) * e1 + (v[j, 2] - v[i, 2]) * e2
        mag = k_spring[k] * ((r - rest[k]) + tau * rate)
        f0 += mag * e0; f1 += mag * e1; f2 += mag * e2
    out[0] = f0
    out[1] = f1
    out[2] = f2


@njit(cache=True, fastmath=True, nogil=True)
def run_frame(scheme, X, x, v, acc, fixed, inv_mass, volume,
              offsets, indices, dw, w0, Linv, F, Fd, A, H, gv,
              G, K, eta_s, eta_v, hg_k, hg_c, tau,
              stress_list, n_stress, sph_list, n_sph, layer_list, layer_w, n_lp,
              cand, n_cand, contact_idx,
              seg0, seg1, tool_on, reach, k_c, c_c,
              n_sub, dt, frame_dt, react, fbuf, ext_idx, ext_force, n_ext, surf,
              touch_idx, touch_w, n_touch, par_min, abort):
    """Advance ``n_sub`` sub-steps; returns the last overlap [m].

    ``seg0``, ``seg1`` (2, 3) are the tool's segment (:mod:`.contact`, :mod:`.tools`) at the start
    and the end of the frame: both ends move linearly across the sub-steps.
    ``react`` (3,) receives the mean reaction force on the tool over the sub-steps [N].
    ``H`` (N, 3, 3) is scratch for the TLSPH hourglass map of the stressed particles.
    ``gv`` (nnz, 3) holds the TLSPH reference pair gradients ``V_j DWIJ0`` (:func:`~.tlsph.pair_gradients`).
    The caller checks the result with :func:`frame_state_ok` (not here: ``fastmath`` assumes finite
    values and may drop a NaN test).
    ``ext_force[t]`` [N] is a constant external load on free particle ``ext_idx[t]`` (``t < n_ext``).
    ``surf`` is the contact surface geometry (see :func:`~.contact.contact_forces`).
    Layers follow the ``touch_w``-weighted mean velocity of the touched particles ``touch_idx[:n_touch]``
    (the contact particle alone when ``n_touch`` is 0).
    The TLSPH pass runs on numba's thread pool when at least ``par_min`` particles are stressed
    (bit-identical to the serial pass; small local areas stay serial: no thread wake-up).
    The frame stops before the next sub-step once another thread sets ``abort[0]`` (the GIL is
    released while it runs); the caller then restores the state.
    """
    react[0] = 0.0; react[1] = 0.0; react[2] = 0.0
    seg = np.empty((2, 3))
    seg_vel = np.empty((2, 3))
    rsum = np.zeros(3)
    for e in range(2):
        for a in range(3):
            seg_vel[e, a] = (seg1[e, a] - seg0[e, a]) / frame_dt
    overlap = 0.0
    for s in range(n_sub):
        if abort[0] != 0:
            break
        frac = (s + 1.0) / n_sub
        for e in range(2):
            for a in range(3):
                seg[e, a] = seg0[e, a] + frac * (seg1[e, a] - seg0[e, a])
        # internal forces
        if scheme == SCHEME_TLSPH and n_stress >= par_min:
            tlsph_pass_parallel(stress_list, n_stress, sph_list, n_sph, X, x, v, acc, inv_mass, volume,
                                offsets, indices, dw, gv, w0, Linv, F, Fd, A, H, G, K, eta_s, eta_v,
                                hg_k, hg_c)
        elif scheme == SCHEME_TLSPH:
            tlsph_pass(stress_list, n_stress, sph_list, n_sph, X, x, v, acc, inv_mass, volume,
                       offsets, indices, dw, gv, w0, Linv, F, Fd, A, H, G, K, eta_s, eta_v, hg_k, hg_c)
        else:
            for t in range(n_sph):
                i = sph_list[t]
                spring_force_one(i, x, v, offsets, indices, dw, w0, tau, fbuf)
                acc[i, 0] = fbuf[0] * inv_mass
                acc[i, 1] = fbuf[1] * inv_mass
                acc[i, 2] = fbuf[2] * inv_mass
        for t in range(n_ext):
            i = ext_idx[t]
            if not fixed[i]:
                for a in range(3):
                    acc[i, a] += ext_force[t, a] * inv_mass
        # contact (pushes the tissue, reaction on the tool)
        if tool_on:
            rsum[0] = 0.0; rsum[1] = 0.0; rsum[2] = 0.0
            overlap = contact_forces(x, v, fixed, acc, inv_mass, cand, n_cand, seg, seg_vel, reach,
                                     k_c, c_c, rsum, surf)
            react[0] += rsum[0]; react[1] += rsum[1]; react[2] += rsum[2]
        # symplectic Euler
        for t in range(n_sph):
            i = sph_list[t]
            for a in range(3):
                v[i, a] += dt * acc[i, a]
                x[i, a] += dt * v[i, a]
        # transmission layers (paper eqs. 20-21): a = w(i) a_c, integrated once as v = w(i) v_c.
        # Integrating the acceleration instead keeps each layer particle's own integration
        # constant (its velocity when it joined the layer, or a jump when the contact particle
        # changes), which then drifts unopposed (layers feel no elastic force) and pumps energy
        # into the solved area: deep random poking blew up within 1 s that way.
        if n_lp > 0:
            vc0 = 0.0; vc1 = 0.0; vc2 = 0.0
            if n_touch > 0:
                # weighted by overlap, so a particle entering or leaving contact changes it smoothly
                wsum = 0.0
                for t in range(n_touch):
                    i = touch_idx[t]
                    w = touch_w[t]
                    wsum += w
                    if not fixed[i]:
                        vc0 += w * v[i, 0]; vc1 += w * v[i, 1]; vc2 += w * v[i, 2]
                if wsum > 0.0:
                    vc0 /= wsum; vc1 /= wsum; vc2 /= wsum
            elif contact_idx >= 0 and not fixed[contact_idx]:
                vc0 = v[contact_idx, 0]; vc1 = v[contact_idx, 1]; vc2 = v[contact_idx, 2]
            for t in range(n_lp):
                i = layer_list[t]
                w = layer_w[t]
                v[i, 0] = w * vc0
                v[i, 1] = w * vc1
                v[i, 2] = w * vc2
                for a in range(3):
                    x[i, a] += dt * v[i, a]
    for a in range(3):
        react[a] /= max(n_sub, 1)
    return overlap


@njit(cache=True)
def frame_state_ok(x, v, sph_list, n_sph, layer_list, n_lp, v_limit, react):
    """False if a moved particle's position or velocity is non-finite or a speed exceeds
    ``v_limit`` [m/s], or the reaction on the tool is non-finite.

    Compiled without ``fastmath``: under fast-math LLVM assumes no NaN or inf and may fold these
    tests to "finite" (seen with numba: ``isfinite`` answered True for a NaN).
    """
    vl2 = v_limit * v_limit
    for part in range(2):
        idx = sph_list if part == 0 else layer_list
        n = n_sph if part == 0 else n_lp
        for t in range(n):
            i = idx[t]
            s2 = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
            if not (s2 <= vl2):  # also False for NaN
                return False
            if not (math.isfinite(x[i, 0]) and math.isfinite(x[i, 1]) and math.isfinite(x[i, 2])):
                return False
    return math.isfinite(react[0]) and math.isfinite(react[1]) and math.isfinite(react[2])


def substep_bounds(h: float, wave_speed: float, rho: float, eta_long: float, mass: float,
                   contact_stiffness: float, cfl: float) -> dict:
    """Stable sub-step sizes [s]: CFL ``C h / c``, viscous ``C rho h^2 / eta`` and contact ``C 2 sqrt(m/k)``."""
    bounds = {'cfl': cfl * h / wave_speed}
    if eta_long > 0.0:
        bounds['viscous'] = cfl * rho * h * h / eta_long
    if contact_stiffness > 0.0:
        bounds['contact'] = cfl * 2.0 * math.sqrt(mass / contact_stiffness)
    return bounds


def substeps_for(frame_dt: float, dt_max: float, max_substeps: int) -> tuple[int, float, bool]:
    """Number of sub-steps and their size for a frame; capped at ``max_substeps`` (time then lags)."""
    n = max(1, int(math.ceil(frame_dt / dt_max - 1e-9)))
    if n > max_substeps:
        return max_substeps, dt_max, True
    return n, frame_dt / n, False
