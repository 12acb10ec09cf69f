"""The seams of the frame loop (:mod:`.frame`): two functions numba dispatches on a state's type,
and what the loop's Python side needs of a scheme object (:class:`FrameScheme`).

A deformation scheme is a ``NamedTuple`` of its arrays and constants plus an ``@overload`` of
:func:`internal_forces` for that type; an integrator is a ``NamedTuple`` plus an ``@overload`` of
:func:`advance`. The one frame loop calls both and compiles a specialisation per (scheme,
integrator) pair, so adding either is a new file, never a new loop. The overloads return an
implementation only for their own type (``instance_class``), so they do not collide.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np

#: :func:`internal_forces` results
STATUS_OK = 0
STATUS_BROKEN = 1      # the body tore apart or a position is non-finite: restore the state
STATUS_FULL = 2        # a pair buffer is too small: grow it (:meth:`~.protocols.FrameScheme.grow`) and resume
STATUS_ABORTED = 3     # (the frame loop only) another thread asked it to stop


def internal_forces(scheme, body, motion, sets):
    """Set ``motion.acc[i]`` to the internal acceleration of every ``i`` in ``sets.sph[:n_sph]``
    (and update the scheme's own state, e.g. stresses of ``sets.stress``). Returns a ``STATUS_*``.

    Called at the start of every sub-step, before anything moves, so a frame that stops on
    :data:`STATUS_FULL` can resume at the same sub-step. Only callable from ``@njit`` code.
    """
    raise NotImplementedError('internal_forces is dispatched by numba; call it from a kernel')


def advance(integrator, body, motion, sets):
    """Advance ``sets.sph[:n_sph]`` by one sub-step from ``motion.acc`` (the integrator's own step
    size). Only callable from ``@njit`` code."""
    raise NotImplementedError('advance is dispatched by numba; call it from a kernel')


def is_state(ty, cls) -> bool:
    """Whether the numba type ``ty`` is the type of a ``cls`` named tuple (for the overloads)."""
    return getattr(ty, 'instance_class', None) is cls


class FrameScheme(Protocol):
    """What :func:`~.frame.run` needs of a scheme object (``TlsphScheme``, ``PaperScheme``, ``MassSpringScheme``)."""

    name: str

    def set_material(self, material, mass: float) -> None:
        """Take a new material (and particle mass)."""

    def wave_speed(self, material, mass: float) -> float:
        """[m/s] the speed that bounds the explicit sub-step (CFL)."""

    def reset(self) -> None:
        """Back to the reference state (after the positions were reset)."""

    def start_frame(self, time: float, sub_dt: float) -> None:
        """A frame of sub-steps of ``sub_dt`` [s] starts at sim time ``time`` [s] (for schemes
        with a memory of time: a relaxing spring)."""

    def stiffness_growth(self) -> float:
        """[-] how much stiffer in shear than at small strain the last frame's tissue was at most
        (a stiffening spring; 1 otherwise): the CFL bound follows it."""

    def state(self, sets, active: np.ndarray, n_active: int) -> NamedTuple:
        """The named tuple the scheme's ``internal_forces`` overload takes, for this frame."""

    def grow(self, state: NamedTuple) -> NamedTuple:
        """The state with larger buffers, after ``internal_forces`` returned ``STATUS_FULL``."""

    def frame_done(self, ok: bool) -> None:
        """The frame of the last :meth:`state` finished (``ok``) or was undone."""

    def von_mises(self, x: np.ndarray, sets, out: np.ndarray) -> None:
        """(N,) von Mises stress [Pa] of the last finished frame (``sets``) into ``out``."""


class FixedStateScheme:
    """Base of the schemes whose frame state is the same tuple every frame (``self._state``, built
    by ``set_material``) and whose buffers never grow."""

    _state: NamedTuple

    def reset(self) -> None:
        pass

    def start_frame(self, time: float, sub_dt: float) -> None:
        pass

    def stiffness_growth(self) -> float:
        return 1.0

    def state(self, sets, active: np.ndarray, n_active: int) -> NamedTuple:
        return self._state

    def grow(self, state: NamedTuple) -> NamedTuple:
        raise AssertionError(f'the {self.name} scheme has no growing buffers')

    def frame_done(self, ok: bool) -> None:
        pass
