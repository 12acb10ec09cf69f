"""Time integration: the sub-step bounds, the transmission layers' kinematics (paper eqs. 20-21)
and the check of a frame's result.

An integrator is a ``NamedTuple`` with an ``@overload`` of :func:`~.protocols.advance`; the frame
loop (:mod:`.frame`) calls it once per sub-step after the forces. The one integrator,
:class:`~.backward_euler.BackwardEuler`, is the paper's symplectic Euler (eq. 22)
``v <- v + dt a, x <- x + dt v`` with the pushing contacts (and, as an option, the dashpots and
the elastic forces) taken backward in time.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, fastmath=True)
def move_layers(x, v, fixed, layer, layer_w, n_layer, touch, touch_w, n_touch, contact, dt):
    """Transmission layers (paper eqs. 20-21) follow the contact: ``v_i = w(i) v_c``, ``x_i += dt v_i``.

    ``v_c`` is the ``touch_w``-weighted mean velocity of the touched particles (weighted by
    overlap, so a particle entering or leaving contact changes it smoothly), or the ``contact``
    particle's velocity when none is listed. Every scheme uses this velocity rule: following the
    contact particle's acceleration (``a = w(i) a_c`` integrated) keeps each layer particle's own
    integration constant (its velocity when it joined the layer, or a jump when the contact
    particle changes), which then drifts unopposed (layers feel no elastic force) and pumps
    energy into the solved area: deep random poking blew up within 1 s that way.
    """
    if n_layer == 0:
        return
    vc0 = 0.0; vc1 = 0.0; vc2 = 0.0
    if n_touch > 0:
        wsum = 0.0
        for t in range(n_touch):
            i = touch[t]
            w = touch_w[t]
            wsum += w
            if not fixed[i]:
                vc0 += w * v[i, 0]; vc1 += w * v[i, 1]; vc2 += w * v[i, 2]
        if wsum > 0.0:
            vc0 /= wsum; vc1 /= wsum; vc2 /= wsum
    elif contact >= 0 and not fixed[contact]:
        vc0 = v[contact, 0]; vc1 = v[contact, 1]; vc2 = v[contact, 2]
    for t in range(n_layer):
        i = layer[t]
        w = layer_w[t]
        v[i, 0] = w * vc0
        v[i, 1] = w * vc1
        v[i, 2] = w * vc2
        for a in range(3):
            x[i, a] += dt * v[i, a]


@njit(cache=True, fastmath=True)
def move_layers_tools(x, v, fixed, layer, layer_w, n_layer, layer_tool, touch, touch_w, touch_start, contacts, dt):
    """:func:`move_layers` of several instruments: a layer particle ``i`` follows its instrument
    ``k = layer_tool[i]``, the particles it touches (``touch[touch_start[k]:touch_start[k + 1]]``)
    or its ``contacts[k]`` particle. (One instrument keeps :func:`move_layers`: the same sums in
    another loop may vectorise, and round, otherwise.)"""
    if n_layer == 0:
        return
    n_tools = contacts.shape[0]
    vc = np.zeros((n_tools, 3))
    for k in range(n_tools):
        contact = contacts[k]
        if touch_start[k + 1] > touch_start[k]:
            wsum = 0.0
            for t in range(touch_start[k], touch_start[k + 1]):
                i = touch[t]
                w = touch_w[t]
                wsum += w
                if not fixed[i]:
                    for a in range(3):
                        vc[k, a] += w * v[i, a]
            if wsum > 0.0:
                for a in range(3):
                    vc[k, a] /= wsum
        elif contact >= 0 and not fixed[contact]:
            for a in range(3):
                vc[k, a] = v[contact, a]
    for t in range(n_layer):
        i = layer[t]
        k = layer_tool[i]
        for a in range(3):
            v[i, a] = layer_w[t] * vc[k, a]
            x[i, a] += dt * v[i, a]


@njit(cache=True, nogil=True)
def frame_state_ok(x, v, sph, n_sph, layer, n_layer, v_limit, react):
    """False if a moved particle's position or velocity is non-finite or a speed exceeds
    ``v_limit`` [m/s], or a reaction on a tool (``react``, flat) is non-finite.

    Compiled without ``fastmath``: under fast-math LLVM assumes no NaN or inf and may fold these
    tests to "finite" (seen with numba: ``isfinite`` answered True for a NaN).
    """
    vl2 = v_limit * v_limit
    for part in range(2):
        idx = sph if part == 0 else layer
        n = n_sph if part == 0 else n_layer
        for t in range(n):
            i = idx[t]
            s2 = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
            if not (s2 <= vl2):  # also False for NaN
                return False
            if not (math.isfinite(x[i, 0]) and math.isfinite(x[i, 1]) and math.isfinite(x[i, 2])):
                return False
    for a in range(react.shape[0]):
        if not math.isfinite(react[a]):
            return False
    return True


def substep_bounds(h: float, wave_speed: float, rho: float, eta_long: float, cfl: float) -> dict:
    """Stable sub-step sizes [s] of the explicit material forces: CFL ``C h / c`` and viscous
    ``C rho h^2 / eta``."""
    bounds = {'cfl': cfl * h / wave_speed}
    if eta_long > 0.0:
        bounds['viscous'] = cfl * rho * h * h / eta_long
    return bounds


def substeps_for(frame_dt: float, dt_max: float, max_substeps: int) -> tuple[int, float, bool]:
    """Number of sub-steps and their size for a frame; capped at ``max_substeps`` (time then lags)."""
    n = max(1, int(math.ceil(frame_dt / dt_max - 1e-9)))
    if n > max_substeps:
        return max_substeps, dt_max, True
    return n, frame_dt / n, False
