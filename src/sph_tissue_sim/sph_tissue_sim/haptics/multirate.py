"""The hand-off between the 1 kHz answer and the solver (multi-rate haptics).

Every pose is answered at once by the :class:`~.renderer.HapticRenderer`; the solver steps at the
renderer's proxy (the simulated tool) whenever it is given a :class:`SolverJob`, and its reaction
refreshes the renderer's contact model. Two schedules:

* ``every = k > 0`` (lockstep): :meth:`MultiRate.due` after every ``k``-th pose; the caller steps the
  solver then, in the pose's thread and order, so a replay of the same poses is bit-identical;
* ``every = 0`` (live): a solver thread calls :meth:`MultiRate.take` whenever it is free and gets the
  newest proxy and all the pose time since its previous job (at most ``max_dt``).

Thread-safe: :meth:`answer` runs on the pose thread, :meth:`take` and :meth:`refresh` on the solver's;
one lock guards the renderer and the job. ROS-free, like the rest of :mod:`sph_tissue_sim.haptics`.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .renderer import HapticRenderer, Rendered

#: [s] the solver's rate is its refreshes over the last this long of wall time
RATE_WINDOW = 0.25


@dataclass
class SolverJob:
    """What the solver should simulate next."""

    point: np.ndarray                 # (3,) [m] the proxy: where the tool goes (tissue frame)
    rotation: np.ndarray | None       # (3, 3) the stylus orientation (oriented tools), or None
    dt: float                         # [s] pose time to simulate (clamped to ``max_dt``)
    age: float                        # [s] pose time the contact model has served (unclamped)
    stamp: Any                        # the newest pose's stamp (for the metrics)
    generation: int = 0               # the resets before it was taken (see MultiRate.current)


@dataclass
class HapticStatus:
    """The rendering's state for metrics and diagnostics."""

    solver_rate: float                # [Hz] solver refreshes per wall-clock second, last RATE_WINDOW
    model_age: float                  # [s] pose time between the solver's last two jobs: how long a
                                      # contact model serves before the next one replaces it
    stretch: float                    # [m] coupling stretch at the newest pose
    energy: float                     # [J] E_in at the device port
    energy_min: float                 # [J] lowest E_in so far
    damping: float                    # [N s/m] passivity damping at the newest pose


class MultiRate:
    """One renderer, its solver schedule and the job between them."""

    def __init__(self, renderer: HapticRenderer, every: int, max_dt: float,
                 clock=time.perf_counter) -> None:
        if every < 0:
            raise ValueError(f'every must be >= 0 poses, got {every}')
        self.renderer = renderer
        self.every = int(every)
        self.max_dt = float(max_dt)
        self._clock = clock
        self._lock = threading.Lock()
        self._generation = 0
        self._clear()

    def _clear(self) -> None:
        self._poses = 0               # poses answered since the last job
        self._served = 0              # poses the contact model answered since its last refresh
        self._pending = 0.0           # their pose time [s]
        self._point: np.ndarray | None = None
        self._rotation = None
        self._stamp = None
        self._last: Rendered | None = None
        self._age = 0.0
        self._refreshes: collections.deque[float] = collections.deque()   # wall times [s]

    def reset(self) -> None:
        """Forget the device and the contact (the tissue was reset or rebuilt)."""
        with self._lock:
            self.renderer.reset()
            self._clear()
            self._generation += 1

    def answer(self, x, dt: float, rotation=None, stamp=None) -> Rendered:
        """The force for the device sample ``x`` [m, tissue frame], ``dt`` [s] after the previous."""
        with self._lock:
            out = self.renderer.answer(x, dt, live=self.every == 0)
            self._poses += 1
            self._served += 1
            self._pending += dt
            self._point, self._rotation, self._stamp, self._last = out.proxy, rotation, stamp, out
            return out

    def zero_held(self) -> None:
        """The device was sent a zero force outside the renderer (a rejected pose)."""
        with self._lock:
            self.renderer.observer.hold(np.zeros(3))

    def due(self) -> bool:
        """Lockstep: a solver step is due now (``every`` poses since the last)."""
        return self.every > 0 and self._poses >= self.every

    def take(self) -> SolverJob | None:
        """The solver's next job, or None when no pose came since the last one."""
        with self._lock:
            if self._poses == 0 or self._point is None:
                return None
            job = SolverJob(self._point.copy(), self._rotation, min(self._pending, self.max_dt),
                            self._pending, self._stamp, self._generation)
            self._poses = 0
            self._pending = 0.0
            return job

    def current(self, job: SolverJob) -> bool:
        """The job was taken after the last reset: a job taken before it holds pose time and a
        proxy of the device and tissue that the reset forgot, so the solver must not step it."""
        return job.generation == self._generation

    def refresh(self, job: SolverJob, result) -> None:
        """The solver stepped ``job``; ``result`` is its :class:`~..core.solver.StepResult` (the
        reaction before clamping, found with the tool where the step left it)."""
        point = result.tool_segment[0] if result.tool_segment is not None else job.point
        with self._lock:
            if self.renderer.refresh(point, result.force_raw, self._served, live=self.every == 0):
                self._served = 0
            self._age = job.age
            self._refreshes.append(self._clock())

    def rate(self) -> float:
        """Solver refreshes per wall-clock second over the last ``RATE_WINDOW`` (caller holds the
        lock): a count, so slow steps lower it as they happen (an average of 1/interval did not:
        a few 0.3 ms steps between 15 ms ones read 330-625 Hz)."""
        now = self._clock()
        times = self._refreshes
        while times and times[0] < now - RATE_WINDOW:
            times.popleft()
        return len(times) / RATE_WINDOW

    def status(self) -> HapticStatus:
        with self._lock:
            last = self._last
            obs = self.renderer.observer
            return HapticStatus(self.rate(), self._age, last.stretch if last else 0.0, obs.energy,
                                obs.minimum, last.damping if last else 0.0)
