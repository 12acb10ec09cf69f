"""The one frame loop: ``n_sub`` sub-steps of internal forces, external loads, contact, integration
and transmission layers, for every scheme and integrator.

Per sub-step ``s`` (the tool's segment moves linearly from ``tool.seg0`` to ``tool.seg1``)::

    internal_forces(scheme, ...)      acc of sets.sph (the scheme's overload, :mod:`.protocols`)
    acc += f_ext / m                  constant external loads
    acc += contact / m                penalty contact with the tool; reaction summed (:mod:`.contact`,
                                      :mod:`.surface_contact`)
    advance(integrator, ...)          x, v of sets.sph (the integrator's overload, :mod:`.integrate`)
    move_layers(...)                  the transmission layers follow the contact (eqs. 20-21)

The reaction returned is the mean over the sub-steps. The loop runs without the GIL and stops
before the next sub-step once another thread sets ``abort[0]``. It is compiled without
``fastmath`` and its arithmetic lives in fast-math helpers: numba compiles a callee that does not
set ``fastmath`` itself with its caller's flags, so a fast-math loop would turn, for example, the
paper scheme's finiteness test of the positions (:func:`~.paper.search_pairs`) into "always finite".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

# the schemes and integrators register their overloads when imported
from . import paper, springs, tlsph  # noqa: F401
from .contact import contact_forces
from .surface_contact import sample_contact_forces
from .integrate import move_layers
from .protocols import (STATUS_ABORTED, STATUS_FULL, STATUS_OK, FrameScheme, advance,
                        internal_forces)
from .state import Body, Loads, Motion, Sets, ToolPath


@njit(cache=True, fastmath=True)
def _segment_velocity(seg0, seg1, frame_dt, out):
    for e in range(2):
        for a in range(3):
            out[e, a] = (seg1[e, a] - seg0[e, a]) / frame_dt


@njit(cache=True, fastmath=True)
def _segment_at(seg0, seg1, s, n_sub, out):
    frac = (s + 1.0) / n_sub
    for e in range(2):
        for a in range(3):
            out[e, a] = seg0[e, a] + frac * (seg1[e, a] - seg0[e, a])


@njit(cache=True, fastmath=True)
def _apply_loads(idx, force, n, fixed, acc, inv_mass):
    for t in range(n):
        i = idx[t]
        if not fixed[i]:
            for a in range(3):
                acc[i, a] += force[t, a] * inv_mass


@njit(cache=True, fastmath=True)
def _mean(react, n):
    for a in range(3):
        react[a] /= max(n, 1)


@njit(cache=True, nogil=True)
def run_frame(scheme, integrator, body, motion, sets, tool, loads, first, n_sub, frame_dt, react, abort):
    """Sub-steps ``first .. n_sub - 1`` of a frame; returns ``(status, next sub-step, last overlap [m])``.

    ``react`` (3,) accumulates the reaction on the tool [N] (zeroed when ``first`` is 0) and holds
    its mean over the frame once the frame is complete. A status other than ``STATUS_OK`` stops the
    frame before the sub-step it names: ``STATUS_FULL`` can resume there after the scheme grew its
    buffers; ``STATUS_BROKEN`` and ``STATUS_ABORTED`` leave the state for the caller to restore.
    The caller checks the result with :func:`~.integrate.frame_state_ok` (the kernels are fast-math).
    """
    if first == 0:
        react[0] = 0.0; react[1] = 0.0; react[2] = 0.0
    seg = np.empty((2, 3))
    seg_vel = np.empty((2, 3))
    rsum = np.zeros(3)
    _segment_velocity(tool.seg0, tool.seg1, frame_dt, seg_vel)
    overlap = 0.0
    for s in range(first, n_sub):
        if abort[0] != 0:
            return STATUS_ABORTED, s, overlap
        status = internal_forces(scheme, body, motion, sets)
        if status != STATUS_OK:
            return status, s, overlap
        _apply_loads(loads.idx, loads.force, loads.n, body.fixed, motion.acc, body.inv_mass)
        tool.touches.count[0] = 0
        if tool.on:
            _segment_at(tool.seg0, tool.seg1, s, n_sub, seg)
            rsum[0] = 0.0; rsum[1] = 0.0; rsum[2] = 0.0
            overlap = contact_forces(body, motion, sets.cand, sets.n_cand, tool, seg, seg_vel, rsum)
            if tool.samples.w_val.shape[0] > 0:
                overlap = max(overlap, sample_contact_forces(body, motion, sets.cand, sets.n_cand, tool, seg,
                                                             seg_vel, rsum))
            react[0] += rsum[0]; react[1] += rsum[1]; react[2] += rsum[2]
        advance(integrator, body, motion, sets)
        move_layers(motion.x, motion.v, body.fixed, sets.layer, sets.layer_w, sets.n_layer,
                    sets.touch, sets.touch_w, sets.n_touch, sets.contact, integrator.dt)
    _mean(react, n_sub)
    return STATUS_OK, n_sub, overlap


def run(scheme: FrameScheme, integrator: NamedTuple, body: Body, motion: Motion, sets: Sets,
        tool: ToolPath, loads: Loads, n_sub: int, frame_dt: float, react: np.ndarray,
        abort: np.ndarray, active: np.ndarray, n_active: int) -> tuple[int, float]:
    """One frame of ``scheme`` (growing its buffers as often as it asks); returns ``(status, overlap)``.

    ``active[:n_active]`` are the particles moving in local mode (some schemes search them).
    """
    state = scheme.state(sets, active, n_active)
    first = 0
    while True:
        status, first, overlap = run_frame(state, integrator, body, motion, sets, tool, loads, first,
                                           n_sub, frame_dt, react, abort)
        if status != STATUS_FULL:
            return status, overlap
        state = scheme.grow(state)
