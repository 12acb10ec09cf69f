"""The one frame loop: ``n_sub`` sub-steps of internal forces, external loads, contact, integration
and transmission layers, for every scheme and integrator.

Per sub-step ``s`` (each instrument's segment moves linearly from its ``seg0`` to its ``seg1``)::

    internal_forces(scheme, ...)      acc of sets.sph (the scheme's overload, :mod:`.protocols`)
    acc += f_ext / m                  constant external loads
    acc += contact / m                penalty contact with each tool and the springs of the particles
                                      it holds (a needle: its own shaft and tip); its
                                      reaction summed (:mod:`.contact`, :mod:`.surface_contact`,
                                      :mod:`.grasp`, :mod:`.needle`)
    advance(integrator, ...)          x, v of sets.sph (the integrator's overload, :mod:`.integrate`)
    move_layers(...)                  the transmission layers follow the contact (eqs. 20-21)

The reactions returned are the means over the sub-steps. The loop runs without the GIL and stops
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
from .grasp import grip_forces
from .needle import needle_forces
from .surface_contact import sample_contact_forces
from .integrate import move_layers, move_layers_tools
from .protocols import (STATUS_ABORTED, STATUS_FULL, STATUS_OK, FrameScheme, advance,
                        internal_forces)
from .state import Body, Loads, Motion, Sets


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
    for k in range(react.shape[0]):
        for a in range(3):
            react[k, a] /= max(n, 1)


@njit(cache=True, nogil=True)
def run_frame(scheme, integrator, body, motion, sets, tools, loads, first, n_sub, frame_dt, react, overlap,
              abort):
    """Sub-steps ``first .. n_sub - 1`` of a frame; returns ``(status, next sub-step)``.

    ``tools`` is a tuple of :class:`~.state.ToolPath`, one per instrument; ``react`` (K, 3)
    accumulates the reaction on each tool [N] (zeroed when ``first`` is 0) and holds its mean over
    the frame once the frame is complete; ``overlap`` (K,) receives each tool's largest overlap [m]
    in the last sub-step. A status other than ``STATUS_OK`` stops the
    frame before the sub-step it names: ``STATUS_FULL`` can resume there after the scheme grew its
    buffers; ``STATUS_BROKEN`` and ``STATUS_ABORTED`` leave the state for the caller to restore.
    The caller checks the result with :func:`~.integrate.frame_state_ok` (the kernels are fast-math).
    """
    n_tools = len(tools)
    if first == 0:
        for k in range(n_tools):
            react[k, 0] = 0.0; react[k, 1] = 0.0; react[k, 2] = 0.0
    seg = np.empty((2, 3))
    seg_vel = np.empty((n_tools, 2, 3))
    rsum = np.zeros(3)
    for k in range(n_tools):
        _segment_velocity(tools[k].seg0, tools[k].seg1, frame_dt, seg_vel[k])
    for s in range(first, n_sub):
        if abort[0] != 0:
            return STATUS_ABORTED, s
        status = internal_forces(scheme, body, motion, sets)
        if status != STATUS_OK:
            return status, s
        _apply_loads(loads.idx, loads.force, loads.n, body.fixed, motion.acc, body.inv_mass)
        tools[0].touches.count[0] = 0
        for k in range(n_tools):
            tool = tools[k]
            if not tool.on:
                continue
            _segment_at(tool.seg0, tool.seg1, s, n_sub, seg)
            rsum[0] = 0.0; rsum[1] = 0.0; rsum[2] = 0.0
            if tool.shaft.needle:
                depth = needle_forces(body, motion, sets.cand, sets.n_cand, tool, seg, seg_vel[k], rsum)
            else:
                depth = contact_forces(body, motion, sets.cand, sets.n_cand, tool, seg, seg_vel[k], rsum)
            if tool.samples.w_val.shape[0] > 0:
                depth = max(depth, sample_contact_forces(body, motion, sets.cand, sets.n_cand, tool, seg,
                                                         seg_vel[k], rsum))
            overlap[k] = depth
            if tool.grip.n > 0:
                grip_forces(body, motion, tool, seg, (s + 1.0) / n_sub, frame_dt, seg_vel[k], rsum)
            react[k, 0] += rsum[0]; react[k, 1] += rsum[1]; react[k, 2] += rsum[2]
        advance(integrator, body, motion, sets)
        if n_tools == 1:
            move_layers(motion.x, motion.v, body.fixed, sets.layer, sets.layer_w, sets.n_layer,
                        sets.touch, sets.touch_w, sets.touch_start[1], sets.contacts[0], integrator.dt)
        else:
            move_layers_tools(motion.x, motion.v, body.fixed, sets.layer, sets.layer_w, sets.n_layer,
                              sets.layer_tool, sets.touch, sets.touch_w, sets.touch_start, sets.contacts,
                              integrator.dt)
    _mean(react, n_sub)
    return STATUS_OK, n_sub


def run(scheme: FrameScheme, integrator: NamedTuple, body: Body, motion: Motion, sets: Sets,
        tools: tuple, loads: Loads, n_sub: int, frame_dt: float, react: np.ndarray, overlap: np.ndarray,
        abort: np.ndarray, active: np.ndarray, n_active: int) -> int:
    """One frame of ``scheme`` (growing its buffers as often as it asks); returns the status.

    ``tools``: a :class:`~.state.ToolPath` per instrument (they share one ``touches`` record);
    ``react`` (K, 3) and ``overlap`` (K,) as in :func:`run_frame`. ``active[:n_active]`` are the
    particles moving in local mode (some schemes search them).
    """
    state = scheme.state(sets, active, n_active)
    first = 0
    overlap[:] = 0.0
    while True:
        status, first = run_frame(state, integrator, body, motion, sets, tools, loads, first,
                                  n_sub, frame_dt, react, overlap, abort)
        if status != STATUS_FULL:
            return status
        state = scheme.grow(state)
