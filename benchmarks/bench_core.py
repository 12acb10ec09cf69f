#!/usr/bin/env python3
"""Benchmarks of the SPH core without ROS: the paper's Tables 1-5, scaling to 100k+ particles, memory.

Usage (from the workspace root, after ``source scripts/env.sh``)::

    python benchmarks/bench_core.py                      # everything (about 10-20 min on 2 cores)
    python benchmarks/bench_core.py --quick              # tiny sizes, a few frames (seconds)
    python benchmarks/bench_core.py --tables 1,3,targets --out /tmp/bench

What is timed: one call of ``Solver.step(tool_pos, 1e-3)``, i.e. one 1 kHz haptic frame with all of
its CFL/viscous/contact sub-steps, measured around the call (``time.perf_counter``) while the tool
presses the top of the liver (``PressScript``). Medians over the timed frames after a warm-up press;
the numba compile (or disk-cache load) time is measured once, separately, by ``warmup()``. Every row
also reports the sub-step count, the time per sub-step, the particles integrated (``n_active``) and
the time per particle-sub-step, so that schemes and sizes compare fairly.

See benchmarks/README.md for how the paper's smoothing lengths map onto our models.
"""

from __future__ import annotations

import argparse
import csv
import gc
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sph_tissue_sim.core.errors import ConfigError, ModelError, SimError
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.models import TissueModel, make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig, warmup

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / 'results'
FRAME_DT = 1e-3                       # one 1 kHz haptic frame [s]

# ---------------------------------------------------------------------------------------------
# The paper's numbers (Liu et al. 2015), seconds per frame on an AMD Phenom II X2 3.0 GHz.
PAPER_SIZES = (289, 572, 743, 1289, 3670)
PAPER_H = (0.3, 0.5, 0.6, 0.8)
PAPER_T1 = {3670: (0.00064, 0.026), 1289: (0.00037, 0.003), 289: (0.00007, 0.00018)}  # (M-S, SPH)
PAPER_T2 = {3670: (0.026, 0.089, 0.15, 0.31), 1289: (0.003, 0.011, 0.018, 0.04),
            743: (0.0012, 0.0054, 0.0069, 0.12), 572: (0.0007, 0.0022, 0.0035, 0.0073),
            289: (0.00047, 0.00056, 0.00063, 0.0011)}
PAPER_T3 = {3670: (0.0032, 0.0056, 0.0079, 0.02), 1289: (0.001, 0.0014, 0.0021, 0.0056),
            743: (0.00063, 0.00073, 0.00097, 0.0017), 572: (0.00047, 0.00052, 0.00055, 0.0012),
            289: (0.00031, 0.00033, 0.00033, 0.0004)}
PAPER_T4 = {0.5: 0.0027, 0.8: 0.0073, 1.0: 0.02}          # k1 = gain * f_ext, h = 0.6, N = 2
PAPER_T5 = {1: 0.00186, 2: 0.0027, 3: 0.00357, 4: 0.00473}  # h = 0.6, k1 = 0.5 f_ext
ANCHOR_N = 3670                 # the paper's h = 0.3 at 3670 particles ...
ANCHOR_H = 0.3                  # ... is our default h / spacing at our 3670-particle liver
TABLE4_FEXT = 2.0               # [N] f_ext of eq. 18 for Tables 4/5 (k1 = gain * f_ext pinned)

SCHEMES_SPH = ('tlsph', 'paper')
ALL_TABLES = ('1', '2', '3', '4', '5', 'scaling', 'memory', 'targets', 'cut')

CSV_FIELDS = ('table', 'label', 'scheme', 'mode', 'model', 'n_target', 'n_particles', 'spacing_mm',
              'h_paper', 'h_ratio', 'h_mm', 'k1_gain', 'k1_pinned', 'n_layers', 'status',
              'frames', 'warm_frames', 'setup_s', 'first_frame_ms', 'step_ms', 'step_p90_ms',
              'substeps', 'substep_us', 'n_active', 'n_stress', 'ns_per_particle_substep',
              'pair_visits', 'ns_per_pair_pass', 'realtime_factor',
              'force_N', 'k1', 'paper_ms', 'speedup_vs_paper', 'frame_ms', 'cg_iterations')


# ---------------------------------------------------------------------------------------------
@dataclass
class Settings:
    """Run-wide knobs (``--quick`` shrinks them)."""

    quick: bool = False
    depth: float = 0.010            # [m] indentation below first touch
    palpate_amp: float = 0.001      # [m] amplitude of the palpation during timed frames
    palpate_hz: float = 2.0
    press_frames: int = 300         # frames of the press (local mode, cheap models)
    min_press_frames: int = 20      # ... at least this many when a frame is expensive (local)
    min_press_frames_global: int = 5    # global: the cost does not depend on the indentation
    timed_frames: int = 200
    min_timed_frames: int = 5
    warm_budget_s: float = 3.0      # wall-clock budgets per case (expensive cases take fewer frames)
    timed_budget_s: float = 3.0
    # a local case whose first frame takes at most this [ms] runs the whole press and palpation
    # whatever the machine: its cost follows the press's phase (the active set), so two runs must
    # time the same frames; dearer cases, and global ones (whose cost does not), use the budgets
    fixed_frames_max_ms: float = 50.0
    sizes: tuple = PAPER_SIZES
    h_values: tuple = PAPER_H
    scaling_sizes: tuple = (3670, 10000, 25000, 50000, 100000, 150000)
    scaling_global_max: int = 150000
    memory_n: int = 100000
    targets_local_big: int = 100000
    targets_global_big: int = 50000
    targets_global_huge: int = 100000   # the implicit integrator's 30 Hz target
    model_kind: str = 'liver'

    @classmethod
    def make_quick(cls) -> 'Settings':
        return cls(quick=True, press_frames=30, min_press_frames=5, min_press_frames_global=3,
                   timed_frames=10, min_timed_frames=3,
                   warm_budget_s=0.5, timed_budget_s=0.5, sizes=(289, 572), h_values=(0.3, 0.6),
                   scaling_sizes=(289, 1289), scaling_global_max=1289, memory_n=1289,
                   targets_local_big=1289, targets_global_big=1289, targets_global_huge=1289)


@dataclass
class Case:
    """One measured configuration."""

    table: str
    label: str
    scheme: str
    mode: str
    n_target: int
    h_paper: float | None = None
    h_ratio: float | None = None
    k1_gain: float = 0.5
    k1_pinned: float | None = None       # k1_min = k1_max = this (Tables 4/5)
    n_layers: int = 2
    paper_s: float | None = None
    parallel_min: int = 0                # SolverConfig.parallel_min_particles (0: serial)
    # None: SolverConfig's default (what the product runs), else that choice
    integrator: str | None = None        # SolverConfig.integrator
    frame_dt: float = FRAME_DT           # [s] simulated time per frame (the implicit integrator: 16 ms)
    far_field: float | None = None       # SolverConfig.far_field (Tables 4/5: 0, the paper's still region)


# ---------------------------------------------------------------------------------------------
class Models:
    """Builds (and caches) the benchmark models: the liver if available, else a block."""

    def __init__(self, kind: str = 'liver') -> None:
        self.kind = kind
        self._cache: dict[int, TissueModel] = {}
        if kind == 'liver':
            try:
                make_model('liver', n_particles=289)
            except (ImportError, ModelError, TypeError) as exc:
                print(f'[bench] liver model unavailable ({exc!r}); using blocks', file=sys.stderr)
                self.kind = 'block'

    def get(self, n: int) -> TissueModel:
        if n not in self._cache:
            if self.kind == 'liver':
                self._cache[n] = make_model('liver', n_particles=n)
            else:
                self._cache[n] = block_with(n)
        return self._cache[n]

    def drop(self, n: int) -> None:
        self._cache.pop(n, None)


def block_with(n: int, spacing: float | None = None) -> TissueModel:
    """A 4:3:2 block of about ``n`` particles with the liver's size (0.2 x 0.15 x 0.08 m)."""
    k = (n / 24.0) ** (1.0 / 3.0)
    nx, ny, nz = max(2, round(4 * k)), max(2, round(3 * k)), max(2, round(2 * k))
    s = spacing if spacing is not None else 0.2 / nx
    return make_block(nx, ny, nz, spacing=s, fix='bottom')


class PressScript:
    """The tool's path: touch the top surface above the model's centre axis, press ``depth`` deep
    over ``press_frames`` frames, then palpate (sinusoid of ``amp`` at ``hz``) around that depth."""

    def __init__(self, model: TissueModel, reach: float, depth: float, press_frames: int,
                 amp: float, hz: float, frame_dt: float = FRAME_DT) -> None:
        P = model.positions
        free = ~model.fixed
        cx, cy = (0.0, 0.0) if model.name == 'liver' else (float(P[:, 0].mean()), float(P[:, 1].mean()))
        s = model.spacing
        col = free & (np.hypot(P[:, 0] - cx, P[:, 1] - cy) < 1.5 * s)
        if not col.any():
            col = free
        # a hair off the lattice axis so that the contact particle is unambiguous
        self.xy = np.array([cx + 0.13 * s, cy + 0.07 * s])
        self.z0 = float(P[col, 2].max()) + reach
        self.depth, self.press_frames, self.amp, self.hz = depth, max(1, press_frames), amp, hz
        self.frame_dt = frame_dt

    def at(self, k: int) -> np.ndarray:
        if k < self.press_frames:
            d = self.depth * (k + 1) / self.press_frames
        else:
            d = self.depth + self.amp * math.sin(2.0 * math.pi * self.hz * (k - self.press_frames) * self.frame_dt)
        return np.array([self.xy[0], self.xy[1], self.z0 - d])


def case_config(case: Case) -> SolverConfig:
    """The solver settings a case times: SolverConfig's defaults with the case's choices."""
    chosen = {'integrator': case.integrator} if case.integrator is not None else {}
    if case.far_field is not None:
        chosen['far_field'] = case.far_field
    return SolverConfig(scheme=case.scheme, mode=case.mode, n_layers=case.n_layers, k1_gain=case.k1_gain,
                        parallel_min_particles=case.parallel_min, **chosen)


def fingerprint(cfg: SolverConfig) -> str:
    """Eight hex digits naming every field of ``cfg``: a table made with other settings than
    today's defaults shows another fingerprint (the docs test compares them)."""
    text = json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def defaults_fingerprint() -> str:
    """The fingerprint of the ``targets`` table's first row, the product's default local step."""
    return fingerprint(case_config(Case('targets', 'local tlsph', 'tlsph', 'local', ANCHOR_N)))


# ---------------------------------------------------------------------------------------------
class Runner:
    """One solver driven along a :class:`PressScript`, timing each frame."""

    def __init__(self, case: Case, model: TissueModel, settings: Settings, material) -> None:
        self.case, self.model, self.st = case, model, settings
        cfg = case_config(case)
        if case.h_ratio is not None:
            cfg.h_ratio = float(case.h_ratio)
        if case.k1_pinned is not None:
            cfg.k1_min = cfg.k1_max = float(case.k1_pinned)
        t0 = time.perf_counter()
        self.solver = Solver(model, material, cfg)
        self.setup_s = time.perf_counter() - t0
        self.k = 0
        self.times: list[float] = []
        self.results = []
        self.status = 'ok'
        self.first_ms = float('nan')
        self.warm = 0
        self.script: PressScript | None = None
        self.cg: list[float] = []    # conjugate-gradient iterations per sub-step, per timed frame

    def _frame(self) -> float:
        tool = self.script.at(self.k)
        t0 = time.perf_counter()
        res = self.solver.step(tool, self.case.frame_dt)
        dt = time.perf_counter() - t0
        self.k += 1
        return dt, res

    def start(self) -> None:
        """First frame (timed alone) sets the press length from the warm-up budget."""
        st = self.st
        self.script = PressScript(self.model, self.solver.contact_reach, st.depth, 1, st.palpate_amp,
                                  st.palpate_hz, self.case.frame_dt)
        try:
            dt, _ = self._frame()
        except ConfigError as exc:
            self.status = f'n/a: {exc}'
            return
        except SimError:
            self.status = 'unstable'
            return
        self.first_ms = dt * 1e3
        floor = st.min_press_frames if self.case.mode == 'local' else st.min_press_frames_global
        press = int(min(st.press_frames, max(floor, st.warm_budget_s / max(dt, 1e-6))))
        self.script.press_frames = st.press_frames if self.fixed_frames else press
        self.k = 0
        self.solver.reset()

    def warm_up(self) -> None:
        if not self.ok:
            return
        try:
            while self.k < self.script.press_frames:
                self._frame()
                self.warm += 1
        except SimError:
            self.status = f'unstable at frame {self.k}'

    @property
    def fixed_frames(self) -> bool:
        """Whether this case runs the full press and palpation (see ``Settings.fixed_frames_max_ms``)."""
        return self.case.mode == 'local' and self.first_ms <= self.st.fixed_frames_max_ms

    def budget_frames(self) -> int:
        st = self.st
        if not self.ok:
            return 0
        if self.fixed_frames:
            return st.timed_frames
        per = max(self.first_ms * 1e-3, 1e-6)
        return int(min(st.timed_frames, max(st.min_timed_frames, st.timed_budget_s / per)))

    def timed(self, n: int) -> None:
        for _ in range(n):
            if not self.ok:
                return
            try:
                dt, res = self._frame()
            except SimError:
                self.status = f'unstable at frame {self.k}'
                return
            self.times.append(dt)
            backward = self.solver.backward
            if backward is not None:
                self.cg.append(backward.mean_iterations())
                backward.reset_stats()
            self.results.append((res.substeps, res.n_active, float(np.linalg.norm(res.force)), res.k1,
                                 getattr(self.solver, 'n_stress_last', 0),
                                 # reference pairs: what tlsph gathers (the other schemes search their own)
                                 self.solver.pair_visits_last if self.case.scheme == 'tlsph' else 0))

    @property
    def ok(self) -> bool:
        return self.status == 'ok'

    def row(self) -> dict:
        c, m = self.case, self.model
        h = self.solver.h
        row = dict(table=c.table, label=c.label, scheme=c.scheme, mode=c.mode, model=m.name,
                   n_target=c.n_target, n_particles=m.n_particles, spacing_mm=m.spacing * 1e3,
                   h_paper=c.h_paper, h_ratio=h / m.spacing, h_mm=h * 1e3, k1_gain=c.k1_gain,
                   k1_pinned=c.k1_pinned, n_layers=c.n_layers, status=self.status,
                   frames=len(self.times), warm_frames=self.warm, setup_s=self.setup_s,
                   first_frame_ms=self.first_ms, paper_ms=None if c.paper_s is None else c.paper_s * 1e3)
        if self.times:
            t = np.array(self.times)
            r = np.array(self.results, dtype=np.float64)
            sub, act = float(np.median(r[:, 0])), float(np.median(r[:, 1]))
            step = float(np.median(t))
            row.update(step_ms=step * 1e3, step_p90_ms=float(np.percentile(t, 90)) * 1e3,
                       substeps=sub, substep_us=float(np.median(t / r[:, 0])) * 1e6,
                       n_active=act, n_stress=float(np.median(r[:, 4])),
                       ns_per_particle_substep=float(np.median(t / np.maximum(r[:, 0] * r[:, 1], 1))) * 1e9,
                       # the stress and force passes' neighbour pairs per sub-step; the implicit
                       # solves' extra passes are inside the time, so theirs is per explicit pass
                       pair_visits=float(np.median(r[:, 5])),
                       ns_per_pair_pass=(float(np.median(t / (r[:, 0] * r[:, 5]))) * 1e9
                                         if np.all(r[:, 5] > 0) else None),
                       # simulated seconds per wall second (each frame simulates frame_dt)
                       realtime_factor=c.frame_dt / step, frame_ms=c.frame_dt * 1e3,
                       cg_iterations=float(np.median(self.cg)) if self.cg else None,
                       force_N=float(np.median(r[:, 2])), k1=float(np.median(r[:, 3])))
            if c.paper_s is not None:
                row['speedup_vs_paper'] = c.paper_s / step
        return row


def run_case(case: Case, models: Models, st: Settings, material) -> dict:
    """Build, warm up and time one case alone; returns its CSV row."""
    model = models.get(case.n_target)
    try:
        r = Runner(case, model, st, material)
    except (ConfigError, ModelError, MemoryError) as exc:
        return dict(table=case.table, label=case.label, scheme=case.scheme, mode=case.mode, model=model.name,
                    n_target=case.n_target, n_particles=model.n_particles, status=f'n/a: {exc}',
                    h_paper=case.h_paper, k1_gain=case.k1_gain, n_layers=case.n_layers,
                    paper_ms=None if case.paper_s is None else case.paper_s * 1e3)
    r.start()
    r.warm_up()
    gc.collect()
    r.timed(r.budget_frames())
    return r.row()


# ---------------------------------------------------------------------------------------------
def h_unit(models: Models) -> float:
    """Metres per paper length unit: the paper's h = 0.3 at 3670 particles is our default h/s there."""
    s_anchor = models.get(ANCHOR_N).spacing
    return SolverConfig().h_ratio * s_anchor / ANCHOR_H


def h_ratio_for(models: Models, n: int, h_paper: float) -> float:
    return h_paper * h_unit(models) / models.get(n).spacing


def build_cases(tables: tuple, st: Settings, models: Models) -> list[Case]:
    cases: list[Case] = []
    sizes = st.sizes
    if '1' in tables:
        for n in [s for s in (289, 1289, 3670) if s in sizes] or list(sizes):
            ms, sph = PAPER_T1.get(n, (None, None))
            hr = h_ratio_for(models, n, ANCHOR_H)
            cases.append(Case('1', f'T1 N={n} mass-spring', 'mass_spring', 'global', n, ANCHOR_H, hr, paper_s=ms))
            for sch in SCHEMES_SPH:
                cases.append(Case('1', f'T1 N={n} {sch}', sch, 'global', n, ANCHOR_H, hr, paper_s=sph))
    for tab, mode, ref in (('2', 'global', PAPER_T2), ('3', 'local', PAPER_T3)):
        if tab not in tables:
            continue
        for n in sizes:
            for hp in st.h_values:
                hr = h_ratio_for(models, n, hp)
                paper = ref.get(n, (None,) * 4)[PAPER_H.index(hp)] if hp in PAPER_H else None
                for sch in SCHEMES_SPH:
                    cases.append(Case(tab, f'T{tab} N={n} h={hp} {sch}', sch, mode, n, hp, hr, paper_s=paper))
    n4 = ANCHOR_N if not st.quick else sizes[-1]
    if '4' in tables:
        hr = h_ratio_for(models, n4, 0.6)
        for gain, paper in PAPER_T4.items():
            for sch in SCHEMES_SPH:
                cases.append(Case('4', f'T4 k1={gain}*f {sch}', sch, 'local', n4, 0.6, hr, k1_gain=gain,
                                  k1_pinned=gain * TABLE4_FEXT, n_layers=2, paper_s=paper, far_field=0.0))
    if '5' in tables:
        hr = h_ratio_for(models, n4, 0.6)
        for nl, paper in PAPER_T5.items():
            for sch in SCHEMES_SPH:
                cases.append(Case('5', f'T5 N={nl} {sch}', sch, 'local', n4, 0.6, hr, k1_gain=0.5,
                                  k1_pinned=0.5 * TABLE4_FEXT, n_layers=nl, paper_s=paper, far_field=0.0))
    if 'scaling' in tables:
        for n in st.scaling_sizes:
            cases.append(Case('scaling', f'scaling N={n} local', 'tlsph', 'local', n))
            if n <= st.scaling_global_max:
                cases.append(Case('scaling', f'scaling N={n} global', 'tlsph', 'global', n))
        # fixed model (the largest), growing interaction area: cost follows the area
        nbig = st.scaling_sizes[-1]
        for k1 in (1.0, 2.0, 3.0, 4.0):
            cases.append(Case('area', f'area N={nbig} k1={k1}', 'tlsph', 'local', nbig, k1_pinned=k1))
    return cases


# ---------------------------------------------------------------------------------------------
def run_targets(st: Settings, models: Models, material, progress) -> list[dict]:
    """The headline comparisons, all solvers alive at once and stepped round-robin (one run, so
    machine load hits every configuration alike)."""
    n = ANCHOR_N if not st.quick else st.sizes[-1]
    cases = [Case('targets', 'local tlsph', 'tlsph', 'local', n, paper_s=PAPER_T3.get(n, (None,))[0]),
             Case('targets', 'global tlsph', 'tlsph', 'global', n, paper_s=PAPER_T2.get(n, (None,))[0]),
             Case('targets', 'local paper', 'paper', 'local', n, paper_s=PAPER_T3.get(n, (None,))[0]),
             Case('targets', 'global paper', 'paper', 'global', n, paper_s=PAPER_T2.get(n, (None,))[0]),
             Case('targets', 'global mass_spring', 'mass_spring', 'global', n, paper_s=PAPER_T1.get(n, (None,))[0]),
             Case('targets', 'local tlsph big', 'tlsph', 'local', st.targets_local_big),
             Case('targets', 'global tlsph 50k', 'tlsph', 'global', st.targets_global_big)]
    if _numba_threads() > 1:
        # the same tlsph cases on numba's thread pool (SolverConfig.parallel_min_particles=1)
        cases += [Case('targets', f'{c.label} threads', c.scheme, c.mode, c.n_target, paper_s=c.paper_s,
                       parallel_min=1) for c in cases if c.scheme == 'tlsph']
    # the implicit integrator at a visual frame rate (16 ms frames, one sub-step each)
    cases += [Case('targets', f'global tlsph{size} 16ms', 'tlsph', 'global', n_big, integrator='implicit',
                   frame_dt=0.016)
              for size, n_big in (('', n), (' 50k', st.targets_global_big), (' 100k', st.targets_global_huge))]
    if _numba_threads() > 1:
        cases += [Case('targets', 'global tlsph 16ms threads', 'tlsph', 'global', n, integrator='implicit',
                       frame_dt=0.016, parallel_min=1)]
    runners = []
    for c in cases:
        try:
            r = Runner(c, models.get(c.n_target), st, material)
        except (ConfigError, ModelError) as exc:
            print(f'[bench] {c.label}: {exc}', file=sys.stderr)
            continue
        r.start()
        r.warm_up()
        runners.append(r)
        progress(c.label)
    rounds = 5
    budgets = [r.budget_frames() for r in runners]
    for k in range(rounds):
        for r, b in zip(runners, budgets):
            r.timed(max(1, math.ceil(b / rounds)))
    return [r.row() for r in runners]


#: the cut table's path: a vertical edge plunged this deep [m] into the top, then drawn this far [m] at this
#: speed [m/s]; the blade's edge and its capsule twin
CUT_DEPTH, CUT_TRAVEL, CUT_SPEED = 0.005, 0.03, 0.02
CUT_TOOL = dict(tool_radius=0.0005, tool_length=0.02)
#: and the needle's: pushed this far [m] past the top at CUT_SPEED, a needle and its capsule twin
NEEDLE_TRAVEL = 0.025
NEEDLE_TOOL = dict(tool_radius=0.0005, tool_length=0.06)


def _timed_pair(model, material, mode: str, name: str, shape: str, tool: dict, path, frames: int,
                first: int) -> list[dict]:
    """``shape`` and a capsule of its size along ``path(k)`` (a tip position per frame), stepped in
    turn; frames from ``first`` on timed. A row each, labelled ``'<name> <mode> <shape>'``."""
    solvers = {s: Solver(model, material, SolverConfig(mode=mode, tool_shape=s, **tool)) for s in ('capsule', shape)}
    times = {s: [] for s in solvers}
    forces = {s: [] for s in solvers}
    status = {s: 'ok' for s in solvers}
    for k in range(frames):
        p = path(k)
        for s in (('capsule', shape) if k % 2 else (shape, 'capsule')):
            if status[s] != 'ok':
                continue
            t0 = time.perf_counter()
            try:
                res = solvers[s].step(p, FRAME_DT, np.eye(3))
            except SimError:
                status[s] = f'unstable at frame {k}'
                continue
            if k >= first:
                times[s].append(time.perf_counter() - t0)
                forces[s].append(float(np.linalg.norm(res.tools[0].force_raw)))
    rows = []
    for s, solver in solvers.items():
        t = np.array(times[s]) * 1e3
        rows.append(dict(table='cut', label=f'{name} {mode} {s}', scheme='tlsph', mode=mode, model=model.name,
                         n_target=ANCHOR_N, n_particles=model.n_particles, status=status[s],
                         frames=len(t), step_ms=float(np.median(t)) if len(t) else None,
                         step_p90_ms=float(np.percentile(t, 90)) if len(t) else None,
                         step_p99_ms=float(np.percentile(t, 99)) if len(t) else None,
                         force_N=float(np.median(forces[s])) if forces[s] else None,
                         bonds_cut=solver.cutters[0].cut if solver.cutters else 0))
    return rows


def run_cut(st: Settings, models: Models, material, progress) -> list[dict]:
    """A frame while cutting against the same frame without: a blade and a capsule of its size drawn
    along the same path through the top of the 3670 liver (plunged ``CUT_DEPTH``, drawn ``CUT_TRAVEL``),
    stepped frame by frame in turn (one run, so machine load hits both alike); timed while drawn.
    Then a needle and a capsule of its size pushed ``NEEDLE_TRAVEL`` down into the same place; timed
    from the top on (the dent, the puncture and the shaft inside)."""
    model = models.get(ANCHOR_N if not st.quick else st.sizes[-1])
    P = model.positions
    s = model.spacing
    cx, cy = (0.0, 0.0) if model.name == 'liver' else (float(P[:, 0].mean()), float(P[:, 1].mean()))
    col = ~model.fixed & (np.hypot(P[:, 0] - cx, P[:, 1] - cy) < 1.5 * s)
    top = float(P[col if col.any() else ~model.fixed, 2].max())
    start = np.array([cx - 0.5 * CUT_TRAVEL + 0.13 * s, cy + 0.37 * s, top + 0.002])
    plunge = int((CUT_DEPTH + 0.002) / CUT_SPEED / FRAME_DT)
    drawn = int(CUT_TRAVEL / CUT_SPEED / FRAME_DT) if not st.quick else 50
    pierce = int((NEEDLE_TRAVEL + 0.002) / CUT_SPEED / FRAME_DT) if not st.quick else 200

    def cut_path(k):
        return start + (np.array([0.0, 0.0, -(k + 1) * CUT_SPEED * FRAME_DT]) if k < plunge else
                        np.array([(k - plunge + 1) * CUT_SPEED * FRAME_DT, 0.0, -CUT_DEPTH - 0.002]))

    def needle_path(k):
        return np.array([cx + 0.13 * s, cy + 0.37 * s, top + 0.002 - (k + 1) * CUT_SPEED * FRAME_DT])

    rows = []
    for mode in ('local', 'global'):
        rows += _timed_pair(model, material, mode, 'cut', 'blade', CUT_TOOL, cut_path, plunge + drawn, plunge)
        rows += _timed_pair(model, material, mode, 'needle', 'needle', NEEDLE_TOOL, needle_path, pierce,
                            int(0.002 / CUT_SPEED / FRAME_DT))
        progress(f'cut {mode}')
    return rows


def target_lines(rows: list[dict]) -> list[str]:
    """The issue's targets and the ratios, from the interleaved run."""
    by = {r['label']: r for r in rows if r.get('table') == 'targets'}

    def ms(label):
        r = by.get(label)
        return r.get('step_ms') if r and r.get('status') == 'ok' else None

    def pps(label):
        r = by.get(label)
        return r.get('ns_per_particle_substep') if r and r.get('status') == 'ok' else None

    out = []
    n = by.get('local tlsph', {}).get('n_particles', '?')
    n_ref = by.get('local tlsph', {}).get('n_target')

    def verdict(ok):
        return 'MET' if ok else 'MISSED'

    lt, gt = ms('local tlsph'), ms('global tlsph')
    if lt is not None:
        paper = by['local tlsph'].get('paper_ms')
        sp = paper / lt if paper else float('nan')
        out.append(f'local tlsph step, {n}-particle model, N=2: {lt:.4f} ms = {sp:.1f}x faster than the paper '
                   f'({paper} ms); target >= 30x and <= 0.1 ms: {verdict(sp >= 30 and lt <= 0.1)}')
    if gt is not None:
        paper = by['global tlsph'].get('paper_ms')
        out.append(f'global tlsph step, {n} particles: {gt:.3f} ms ({paper / gt if paper else float("nan"):.1f}x '
                   f'faster than the paper\'s {paper} ms); target <= 1 ms: {verdict(gt <= 1.0)}')
    lb = ms('local tlsph big')
    if lb is not None and lt:
        nb = by['local tlsph big']['n_particles']
        out.append(f'local tlsph step, {nb} particles: {lb:.4f} ms = {lb / lt:.2f}x the {n}-particle local step '
                   f'(per sub-step {by["local tlsph big"]["substep_us"]:.1f} us vs {by["local tlsph"]["substep_us"]:.1f} us, '
                   f'{by["local tlsph big"]["substeps"]:.0f} vs {by["local tlsph"]["substeps"]:.0f} sub-steps); '
                   f'target <= 2x: {verdict(lb / lt <= 2.0)}')
    gb = ms('global tlsph 50k')
    if gb is not None:
        nb = by['global tlsph 50k']['n_particles']
        out.append(f'global tlsph step, {nb} particles: {gb:.2f} ms ({by["global tlsph 50k"]["substeps"]:.0f} sub-steps); '
                   f'target <= 16 ms: {verdict(gb <= 16.0)}')
    for size, budget, rate in (('', 1000.0 / 60.0, '60 Hz'), (' 50k', 16.0, '60 Hz'), (' 100k', 33.0, '30 Hz')):
        r = by.get(f'global tlsph{size} 16ms')
        gi = ms(f'global tlsph{size} 16ms')
        if gi is None:
            continue
        explicit = ms('global tlsph' + (' 50k' if size == ' 50k' else '')) if size != ' 100k' else None
        vs = (f'; 16 explicit 1 ms frames take {16.0 * explicit:.1f} ms ({16.0 * explicit / gi:.2f}x this)'
              if explicit else '')
        out.append(f'implicit integrator, global, {r["n_particles"]} particles, 16 ms frames: {gi:.1f} ms per frame '
                   f'({r["substeps"]:.0f} sub-step, {r.get("cg_iterations") or 0:.0f} CG iterations){vs}; '
                   f'target <= {budget:.0f} ms ({rate}): {verdict(gi <= budget)}')
    lp, gp, lbp, gbp = (ms(f'{k} threads') for k in ('local tlsph', 'global tlsph', 'local tlsph big',
                                                       'global tlsph 50k'))
    if lp is not None and lt is not None:
        paper = by['local tlsph'].get('paper_ms')
        sp = paper / lp if paper else float('nan')
        out.append(f'with {_numba_threads()} numba threads (parallel_min_particles=1; not the default, see '
                   f'README): local {lp:.4f} ms ({lt / lp:.2f}x the serial step, {sp:.1f}x the paper): '
                   f'{verdict(sp >= 30 and lp <= 0.1)}' + (
                       f'; global {gp:.3f} ms ({gt / gp:.2f}x): {verdict(gp <= 1.0)}' if gp and gt else '') + (
                       f'; local big {lbp / lp:.2f}x the local step: {verdict(lbp / lp <= 2.0)}' if lbp else '') + (
                       f'; global 50k {gbp:.2f} ms: {verdict(gbp <= 16.0)}' if gbp else ''))
    for mode in ('global', 'local'):
        a, b = pps(f'{mode} tlsph'), pps(f'{mode} paper')
        if a is not None and b is not None:
            out.append(f'{mode}: tlsph {a:.1f} ns vs paper scheme {b:.1f} ns per particle-sub-step -> '
                       f'tlsph {b / a:.2f}x faster; target > 1x: {verdict(b > a)}')
        elif a is not None:
            out.append(f'{mode}: tlsph {a:.1f} ns per particle-sub-step; paper scheme n/a '
                       f'({by.get(f"{mode} paper", {}).get("status", "not run")})')
    if gt is not None and lt is not None:
        ref = (f'{PAPER_T2[n_ref][0] / PAPER_T3[n_ref][0]:.1f}x' if n_ref in PAPER_T2 else 'n/a')
        out.append(f'global / local tlsph at {n} particles: {gt / lt:.1f}x (paper Table 2/3 at h=0.3: {ref})')
    msp = ms('global mass_spring')
    if msp is not None and gt is not None:
        out.append(f'global mass-spring {msp:.3f} ms vs global tlsph {gt:.3f} ms: SPH/M-S = {gt / msp:.2f}x '
                   f'(paper Table 1: {PAPER_T1[3670][1] / PAPER_T1[3670][0]:.1f}x)' if n_ref == 3670 else
                   f'global mass-spring {msp:.3f} ms vs global tlsph {gt:.3f} ms')
    return out


# ---------------------------------------------------------------------------------------------
def _status_kb(key: str) -> int:
    try:
        for line in Path('/proc/self/status').read_text().splitlines():
            if line.startswith(key + ':'):
                return int(line.split()[1])
    except OSError:
        pass
    return -1


def memory_child(n: int, kind: str, quick: bool) -> dict:
    """Peak RSS and traced allocations per phase for an ``n``-particle model (run in a fresh process)."""
    import tracemalloc

    out = {'n_target': n, 'phases': []}

    def mark(phase, t0):
        cur, peak = tracemalloc.get_traced_memory()
        out['phases'].append(dict(phase=phase, seconds=time.perf_counter() - t0,
                                  rss_mb=_status_kb('VmRSS') / 1024, peak_rss_mb=_status_kb('VmHWM') / 1024,
                                  ru_maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                                  traced_mb=cur / 2**20, traced_peak_mb=peak / 2**20))
        tracemalloc.reset_peak()

    t0 = time.perf_counter()
    warmup('tlsph')
    mark('import + numba warmup', t0)
    tracemalloc.start()
    t0 = time.perf_counter()
    models = Models(kind)
    model = models.get(n)
    out['n_particles'] = model.n_particles
    mark('model build', t0)
    st = Settings.make_quick() if quick else Settings()
    for mode, frames in (('local', 200 if not quick else 20), ('global', 3)):
        t0 = time.perf_counter()
        r = Runner(Case('memory', mode, 'tlsph', mode, n), model, st, liver_default())
        out[f'nnz_{mode}'] = int(len(r.solver.indices))
        mark(f'solver init ({mode})', t0)
        t0 = time.perf_counter()
        r.script = PressScript(model, r.solver.contact_reach, st.depth, frames, st.palpate_amp, st.palpate_hz)
        for _ in range(frames):
            r._frame()
        mark(f'{frames} {mode} frames', t0)
        del r
        gc.collect()
    return out


def run_memory(st: Settings, kind: str) -> list[dict]:
    cmd = [sys.executable, str(Path(__file__).resolve()), '--memory-child', str(st.memory_n), '--model', kind]
    if st.quick:
        cmd.append('--quick')
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    if proc.returncode != 0:
        return [dict(table='memory', label='memory', status=f'failed: {proc.stderr[-300:]}')]
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    rows = []
    for ph in data['phases']:
        rows.append(dict(table='memory', label=ph['phase'], n_target=data['n_target'],
                         n_particles=data.get('n_particles'), status='ok', **{k: v for k, v in ph.items() if k != 'phase'}))
    for key in ('nnz_local', 'nnz_global'):
        if key in data:
            rows[-1][key] = data[key]
    return rows


# ---------------------------------------------------------------------------------------------
def _f(v, fmt='{:.3f}', na='n/a'):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return na
    return fmt.format(v)


def _cell(row: dict | None, key='step_ms') -> str:
    if row is None:
        return '-'
    if row.get('status') != 'ok':
        return 'n/a' if str(row.get('status', '')).startswith('n/a') else 'unstable'
    v = row.get(key)
    return _f(v, '{:.4f}' if v is not None and v < 1 else '{:.3f}' if v < 100 else '{:.1f}')


def print_tables(rows: list[dict], meta: dict) -> str:
    lines = []
    p = lines.append
    idx = {}
    for r in rows:
        idx[r.get('label')] = r
    p('')
    p(f"Core benchmark, {meta['date']}  host {meta['host']} ({meta['cpus']} CPUs, load {meta['load']})  "
      f"model: {meta['model_kind']}")
    p(f"numba warmup (compile or disk-cache load): {meta['numba_warmup_s']:.2f} s "
      f"(cache was {'warm' if meta['numba_cache_warm'] else 'cold'}); times are medians of Solver.step "
      f"(one 1 kHz frame incl. sub-steps) in ms; paper = Liu et al. 2015 (AMD Phenom II X2, 2009).")
    p(f"core: {meta.get('core_path', '?')} (workspace git {meta.get('git', '?')})")
    p(f"h mapping: paper h x {meta['h_unit_mm']:.2f} mm = our h (paper h=0.3 at 3670 <-> h/s = "
      f"{SolverConfig().h_ratio}); k1 for Tables 4/5 pinned to gain x {TABLE4_FEXT} N.")
    t1 = [r for r in rows if r.get('table') == '1']
    if t1:
        p('')
        p('Table 1: mass-spring vs global SPH [ms per frame]')
        p(f"{'N':>6} {'N ours':>7} | {'paper M-S':>9} {'ours M-S':>9} | {'paper SPH':>9} {'tlsph':>9} {'paper-sch':>9}"
          f" | {'sub':>3} {'ns/p-sub tlsph':>14} {'paper-sch':>9} {'M-S':>7}")
        for n in sorted({r['n_target'] for r in t1}, reverse=True):
            ms = idx.get(f'T1 N={n} mass-spring')
            tl = idx.get(f'T1 N={n} tlsph')
            pa = idx.get(f'T1 N={n} paper')
            ref = PAPER_T1.get(n, (None, None))
            p(f"{n:>6} {(tl or {}).get('n_particles', ''):>7} | {_f(ref[0] and ref[0] * 1e3):>9} {_cell(ms):>9} | "
              f"{_f(ref[1] and ref[1] * 1e3):>9} {_cell(tl):>9} {_cell(pa):>9} | {_f((tl or {}).get('substeps'), '{:.0f}'):>3} "
              f"{_cell(tl, 'ns_per_particle_substep'):>14} {_cell(pa, 'ns_per_particle_substep'):>9} "
              f"{_cell(ms, 'ns_per_particle_substep'):>7}")
    for tab, title in (('2', 'Table 2: global SPH'), ('3', 'Table 3: local interaction area (N = 2)')):
        tr = [r for r in rows if r.get('table') == tab]
        if not tr:
            continue
        hs = sorted({r['h_paper'] for r in tr})
        p('')
        p(f'{title} [ms per frame]: each cell "paper | tlsph | paper-scheme", then h/s and n_active of tlsph')
        p(f"{'N':>6} " + ' '.join(f"{'h=' + str(h):^34}" for h in hs))
        for n in sorted({r['n_target'] for r in tr}, reverse=True):
            cells = []
            for h in hs:
                tl = idx.get(f'T{tab} N={n} h={h} tlsph')
                pa = idx.get(f'T{tab} N={n} h={h} paper')
                ref = (tl or {}).get('paper_ms')
                cells.append(f"{_f(ref, '{:.2f}'):>6}|{_cell(tl):>8}|{_cell(pa):>8} "
                             f"{_f((tl or {}).get('h_ratio'), '{:.2f}'):>4} {_f((tl or {}).get('n_active'), '{:.0f}'):>5}")
            p(f'{n:>6} ' + ' '.join(cells))
    for tab, title, key in (('4', 'Table 4: interaction radius k1 = gain x f_ext (h = 0.6, N = 2)', 'k1_gain'),
                            ('5', 'Table 5: transmission layers N (h = 0.6, k1 = 0.5 f_ext)', 'n_layers')):
        tr = [r for r in rows if r.get('table') == tab]
        if not tr:
            continue
        p('')
        p(f'{title} [ms per frame]')
        p(f"{key:>8} | {'paper':>7} {'tlsph':>8} {'paper-sch':>9} | {'k1':>4} {'n_active':>8} {'n_stress':>8} {'sub':>3} {'us/sub':>7}")
        for r in [r for r in tr if r['scheme'] == 'tlsph']:
            other = idx.get(r['label'].replace(' tlsph', ' paper'))
            p(f"{r[key]:>8} | {_f(r.get('paper_ms'), '{:.2f}'):>7} {_cell(r):>8} {_cell(other):>9} | "
              f"{_f(r.get('k1'), '{:.1f}'):>4} {_f(r.get('n_active'), '{:.0f}'):>8} {_f(r.get('n_stress'), '{:.0f}'):>8} "
              f"{_f(r.get('substeps'), '{:.0f}'):>3} {_cell(r, 'substep_us'):>7}")
    sc = [r for r in rows if r.get('table') in ('scaling', 'area')]
    if sc:
        p('')
        p('Scaling (tlsph, default h/s): step [ms], sub-steps, per sub-step [us], n_active, n_stress')
        p(f"{'label':<24} {'N':>7} {'s[mm]':>6} {'step ms':>9} {'p90':>8} {'sub':>3} {'us/sub':>8} {'n_active':>8} "
          f"{'n_stress':>8} {'ns/p-sub':>8} {'setup s':>7}")
        for r in sc:
            p(f"{r['label']:<24} {r.get('n_particles', ''):>7} {_f(r.get('spacing_mm'), '{:.2f}'):>6} {_cell(r):>9} "
              f"{_cell(r, 'step_p90_ms'):>8} {_f(r.get('substeps'), '{:.0f}'):>3} {_cell(r, 'substep_us'):>8} "
              f"{_f(r.get('n_active'), '{:.0f}'):>8} {_f(r.get('n_stress'), '{:.0f}'):>8} "
              f"{_cell(r, 'ns_per_particle_substep'):>8} {_f(r.get('setup_s'), '{:.2f}'):>7}")
    mem = [r for r in rows if r.get('table') == 'memory']
    if mem:
        p('')
        p(f"Memory, {mem[0].get('n_particles')}-particle model (fresh process): per phase")
        p(f"{'phase':<28} {'s':>6} {'RSS MB':>7} {'peak RSS MB':>11} {'traced MB':>9} {'traced peak':>11}")
        for r in mem:
            p(f"{r['label']:<28} {_f(r.get('seconds'), '{:.2f}'):>6} {_f(r.get('rss_mb'), '{:.0f}'):>7} "
              f"{_f(r.get('peak_rss_mb'), '{:.0f}'):>11} {_f(r.get('traced_mb'), '{:.1f}'):>9} "
              f"{_f(r.get('traced_peak_mb'), '{:.1f}'):>11}")
    cut = [r for r in rows if r.get('table') == 'cut']
    if cut:
        p('')
        p(f'Cutting: a blade ({CUT_TOOL["tool_radius"] * 1e3:g} mm, {CUT_TOOL["tool_length"] * 1e3:g} mm edge) against a '
          f'capsule of its size, drawn {CUT_TRAVEL * 1e3:g} mm at {CUT_SPEED * 1e3:g} mm/s, '
          f'{CUT_DEPTH * 1e3:g} mm deep (frames stepped in turn; timed while drawn); a needle '
          f'({NEEDLE_TOOL["tool_radius"] * 1e3:g} mm) against a capsule of its size pushed {NEEDLE_TRAVEL * 1e3:g} mm '
          f'down (timed from the top) [ms per frame]')
        p(f"{'config':<22} {'N':>6} {'frames':>6} {'median':>8} {'p90':>8} {'p99':>8} {'force N':>8} {'bonds cut':>9} "
          f"{'x capsule':>9} {'status'}")
        for r in cut:
            twin = idx.get(r['label'].rsplit(' ', 1)[0] + ' capsule')
            ratio = (r['step_ms'] / twin['step_ms'] if r.get('step_ms') and twin and twin.get('step_ms') else None)
            p(f"{r['label']:<22} {r.get('n_particles', ''):>6} {r.get('frames', 0):>6} {_cell(r):>8} "
              f"{_cell(r, 'step_p90_ms'):>8} {_cell(r, 'step_p99_ms'):>8} {_f(r.get('force_N'), '{:.2f}'):>8} "
              f"{r.get('bonds_cut', 0):>9} {_f(ratio, '{:.2f}x', ''):>9} {r.get('status')}")
    tg = [r for r in rows if r.get('table') == 'targets']
    if tg:
        p('')
        p('Targets and ratios (one interleaved run: all solvers alive, stepped round-robin)')
        p(f"  defaults fingerprint {meta.get('defaults_fingerprint', defaults_fingerprint())} (SolverConfig as "
          f"the first row timed it; benchmarks/README.md's table must name the same)")
        if meta.get('quick'):
            p('  (--quick: small stand-in sizes, so the verdicts below do not judge the real targets)')
        p(f"{'config':<26} {'N':>7} {'frame':>5} {'step ms':>9} {'p90':>8} {'sub':>3} {'CG':>4} {'us/sub':>8} "
          f"{'n_active':>8} {'ns/p-sub':>8} {'ns/pair':>7} {'RT x':>6} {'status'}")
        for r in tg:
            p(f"{r['label']:<26} {r.get('n_particles', ''):>7} {_f(r.get('frame_ms'), '{:.0f}'):>5} {_cell(r):>9} "
              f"{_cell(r, 'step_p90_ms'):>8} {_f(r.get('substeps'), '{:.0f}'):>3} "
              f"{_f(r.get('cg_iterations'), '{:.0f}', ''):>4} {_cell(r, 'substep_us'):>8} "
              f"{_f(r.get('n_active'), '{:.0f}'):>8} "
              f"{_cell(r, 'ns_per_particle_substep'):>8} {_f(r.get('ns_per_pair_pass'), '{:.2f}'):>7} "
              f"{_f(r.get('realtime_factor'), '{:.3f}'):>6} {r.get('status')}")
        p('  (frame: simulated ms per step; CG: conjugate-gradient iterations per sub-step of the implicit '
          'solves; ns/pair: sub-step time per neighbour pair of the stress and force passes, the implicit '
          'solves\' passes included; RT x: simulated seconds per wall second, 1 = real time)')
        for line in target_lines(rows):
            p('  - ' + line)
    text = '\n'.join(lines)
    print(text)
    return text


def _legend(ax, **kw) -> None:
    """A legend for the panels that drew something (``--tables`` may leave a panel empty)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kw)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.get('status') == 'ok' and r.get('step_ms') is not None]
    fig, axes = plt.subplots(2, 3, figsize=(17, 10))
    ax = axes[0, 0]
    t1 = [r for r in ok if r['table'] == '1']
    ns = sorted({r['n_target'] for r in t1})
    series = [('paper M-S', lambda n: PAPER_T1.get(n, (None, None))[0]), ('paper SPH', lambda n: PAPER_T1.get(n, (None, None))[1])]
    for sch, lab in (('mass_spring', 'ours M-S'), ('tlsph', 'ours tlsph'), ('paper', 'ours paper-scheme')):
        series.append((lab, lambda n, sch=sch: next((r['step_ms'] * 1e-3 for r in t1 if r['n_target'] == n and r['scheme'] == sch), None)))
    w = 0.8 / len(series)
    for i, (lab, fn) in enumerate(series):
        vals = [fn(n) for n in ns]
        xs = [j + i * w for j, v in enumerate(vals) if v]
        ax.bar(xs, [v * 1e3 for v in vals if v], w, label=lab)
    ax.set_xticks([j + 0.4 - w / 2 for j in range(len(ns))], [f'N={n}' for n in ns])
    ax.set_yscale('log'); ax.set_ylabel('ms per frame'); ax.set_title('Table 1: mass-spring vs global SPH')
    _legend(ax, fontsize=7)
    for ax, tab, ref, title in ((axes[0, 1], '2', PAPER_T2, 'Table 2: global'), (axes[0, 2], '3', PAPER_T3, 'Table 3: local')):
        tr = [r for r in ok if r['table'] == tab and r['scheme'] == 'tlsph']
        for k, h in enumerate(sorted({r['h_paper'] for r in tr})):
            pts = sorted((r['n_particles'], r['step_ms']) for r in tr if r['h_paper'] == h)
            line, = ax.plot(*zip(*pts), 'o-', label=f'tlsph h={h}')
            pp = sorted((n, v[PAPER_H.index(h)] * 1e3) for n, v in ref.items() if h in PAPER_H)
            ax.plot(*zip(*pp), 's--', color=line.get_color(), alpha=0.5, label=f'paper h={h}')
            pa = sorted((r['n_particles'], r['step_ms']) for r in ok if r['table'] == tab and r['scheme'] == 'paper' and r['h_paper'] == h)
            if pa:
                ax.plot(*zip(*pa), 'x:', color=line.get_color(), label=f'paper-scheme h={h}')
        ax.set_xscale('log'); ax.set_yscale('log'); ax.set_xlabel('particles'); ax.set_ylabel('ms per frame')
        ax.set_title(title); _legend(ax, fontsize=6, ncol=2)
    ax = axes[1, 0]
    xs_all, labels = [], []
    for tab, key, ref, xlab in (('4', 'k1_gain', PAPER_T4, 'k1='), ('5', 'n_layers', PAPER_T5, 'N=')):
        tr = [r for r in ok if r['table'] == tab and r['scheme'] == 'tlsph']
        if not tr:
            continue
        xs = np.arange(len(tr)) + (0 if tab == '4' else len(PAPER_T4) + 1)
        ax.bar(xs - 0.2, [ref[r[key]] * 1e3 for r in tr], 0.4, color='grey', label='paper' if tab == '4' else None)
        ax.bar(xs + 0.2, [r['step_ms'] for r in tr], 0.4, color='C0', label='ours tlsph' if tab == '4' else None)
        pa = [(x, r2['step_ms']) for x, r in zip(xs, tr)
              for r2 in ok if r2['label'] == r['label'].replace(' tlsph', ' paper')]
        if pa:
            ax.plot(*zip(*pa), 'rx', label='ours paper-scheme' if tab == '4' else None)
        xs_all += list(xs)
        labels += [f'T{tab} {xlab}{r[key]}' for r in tr]
    ax.set_xticks(xs_all, labels, rotation=30, fontsize=7)
    ax.set_yscale('log'); ax.set_ylabel('ms per frame'); ax.set_title('Tables 4 and 5 (h = 0.6)'); _legend(ax, fontsize=7)
    ax = axes[1, 1]
    sc = [r for r in ok if r['table'] == 'scaling']
    for mode, mk in (('global', 'o-'), ('local', 's-')):
        pts = sorted((r['n_particles'], r['step_ms'], r['substep_us'], r['n_active']) for r in sc if r['mode'] == mode)
        if pts:
            a = np.array(pts)
            ax.plot(a[:, 0], a[:, 1], mk, label=f'{mode}: frame')
            ax.plot(a[:, 0], a[:, 2] * 1e-3, mk.replace('-', ':'), label=f'{mode}: per sub-step')
    ax.axhline(1.0, color='k', lw=0.5, ls='--'); ax.axhline(16.0, color='r', lw=0.5, ls='--')
    ax.set_xscale('log'); ax.set_yscale('log'); ax.set_xlabel('particles'); ax.set_ylabel('ms')
    ax.set_title('Scaling, tlsph (1 ms and 16 ms lines)'); _legend(ax, fontsize=7)
    ax = axes[1, 2]
    pts = [r for r in ok if r['table'] in ('scaling', 'area') and r['mode'] == 'local']
    if pts:
        for tab, mk, lab in (('scaling', 'o', 'local, growing model'), ('area', 's', 'local, fixed model, growing k1')):
            a = np.array(sorted((r['n_stress'], r['substep_us'], r['n_particles']) for r in pts if r['table'] == tab))
            if len(a):
                ax.plot(a[:, 0], a[:, 1], mk, label=lab)
                for x, y, n in a:
                    ax.annotate(f'{int(n)}', (x, y), fontsize=6)
        ax.set_xlabel('particles whose stress is computed per sub-step (n_stress)')
        ax.set_ylabel('us per sub-step'); ax.set_xscale('log'); ax.set_yscale('log')
        ax.set_title('Local cost follows the interaction area, not the model size'); _legend(ax, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
def numba_cache_warm() -> bool:
    import sph_tissue_sim.core as core
    cache = Path(core.__file__).resolve().parent / '__pycache__'
    return any(cache.glob('frame.run_frame*.nbi'))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--quick', action='store_true', help='tiny sizes and a few frames (a smoke run)')
    ap.add_argument('--tables', default=','.join(ALL_TABLES),
                    help=f'comma list of {",".join(ALL_TABLES)} (default: all)')
    ap.add_argument('--out', default=str(DEFAULT_OUT), help='output directory for CSV/PNG/JSON/TXT')
    ap.add_argument('--model', default='liver', choices=('liver', 'block'))
    ap.add_argument('--memory-child', type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.memory_child:
        print(json.dumps(memory_child(args.memory_child, args.model, args.quick)))
        return 0
    tables = tuple(t.strip() for t in args.tables.split(',') if t.strip())
    bad = [t for t in tables if t not in ALL_TABLES]
    if bad:
        ap.error(f'unknown table(s) {bad}; choose from {ALL_TABLES}')
    st = Settings.make_quick() if args.quick else Settings()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    cache_warm = numba_cache_warm()
    t0 = time.perf_counter()
    warm_s = warmup()
    meta = dict(date=time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime()), host=platform.node(),
                cpus=os.cpu_count(), load=' '.join(f'{x:.2f}' for x in os.getloadavg()),
                python=platform.python_version(), numba_warmup_s=warm_s, numba_cache_warm=cache_warm,
                quick=st.quick, tables=tables, numba_threads=_numba_threads())
    try:
        meta['git'] = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=HERE, capture_output=True,
                                     text=True).stdout.strip()
    except OSError:
        meta['git'] = ''
    import sph_tissue_sim
    meta['core_path'] = str(Path(sph_tissue_sim.__file__).resolve().parent)
    material = liver_default()
    models = Models(args.model)
    meta['model_kind'] = models.kind
    meta['defaults_fingerprint'] = defaults_fingerprint()
    meta['h_unit_mm'] = h_unit(models) * 1e3
    cases = build_cases(tables, st, models)
    n_total = (len(cases) + ((19 if _numba_threads() > 1 else 14) if 'targets' in tables else 0)
               + (1 if 'memory' in tables else 0) + (2 if 'cut' in tables else 0))
    rows: list[dict] = []
    with tqdm(total=n_total, desc='bench', unit='case', file=sys.stderr, dynamic_ncols=True) as bar:
        for case in cases:
            bar.set_postfix_str(case.label)
            rows.append(run_case(case, models, st, material))
            bar.update(1)
            if case.n_target >= 50000 and case.table not in ('scaling', 'area'):
                models.drop(case.n_target)
        if 'targets' in tables:
            def progress(label):
                bar.set_postfix_str(f'targets: {label}')
                bar.update(1)
            rows.extend(run_targets(st, models, material, progress))
        if 'cut' in tables:
            def progress(label):
                bar.set_postfix_str(label)
                bar.update(1)
            rows.extend(run_cut(st, models, material, progress))
        if 'memory' in tables:
            bar.set_postfix_str(f'memory N={st.memory_n}')
            rows.extend(run_memory(st, models.kind))
            bar.update(1)
    meta['total_s'] = time.perf_counter() - t0
    stem = 'bench_core_quick' if st.quick else 'bench_core'
    with open(out / f'{stem}.csv', 'w', newline='') as fh:
        extra = sorted({k for r in rows for k in r} - set(CSV_FIELDS))
        w = csv.DictWriter(fh, fieldnames=list(CSV_FIELDS) + extra)
        w.writeheader()
        for r in rows:
            w.writerow({k: ('' if v is None else v) for k, v in r.items()})
    text = print_tables(rows, meta)
    (out / f'{stem}.txt').write_text(text + '\n')
    (out / f'{stem}.json').write_text(json.dumps(dict(meta=meta, targets=target_lines(rows)), indent=1, default=str))
    plot(rows, out / f'{stem}.png')
    print(f'\nwrote {out / (stem + ".csv")}, .png, .txt, .json in {meta["total_s"]:.0f} s')
    return 0


def _numba_threads() -> int:
    try:
        import numba
        return int(numba.config.NUMBA_NUM_THREADS)
    except Exception:  # noqa: BLE001 - informative only
        return -1


if __name__ == '__main__':
    sys.exit(main())
