"""Tissue models: particle sets sampled on a lattice, with an attached (fixed) region.

Every model is a :class:`TissueModel`; :func:`make_model` builds one by name so that nodes and
benchmarks can select it from a parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .errors import ModelError


@dataclass
class TissueModel:
    """Reference configuration of a tissue body.

    Attributes:
        name: Model name (``block``, ``beam``, ``liver``, ``mesh:<file>``).
        positions: ``(N, 3)`` float64 reference positions [m].
        spacing: Lattice spacing [m]; every particle has volume ``spacing**3``.
        fixed: ``(N,)`` bool mask of attached particles (never move).
        info: Free-form description of how the model was built.
    """

    name: str
    positions: np.ndarray
    spacing: float
    fixed: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.positions = np.ascontiguousarray(self.positions, dtype=np.float64)
        self.fixed = np.ascontiguousarray(self.fixed, dtype=np.bool_)
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ModelError(f'{self.name}: positions must be (N, 3), got {self.positions.shape}')
        if len(self.positions) == 0:
            raise ModelError(f'{self.name}: the model has no particles')
        if self.fixed.shape != (len(self.positions),):
            raise ModelError(f'{self.name}: fixed mask must have shape ({len(self.positions)},)')
        if not np.all(np.isfinite(self.positions)):
            raise ModelError(f'{self.name}: non-finite particle positions')
        if not (np.isfinite(self.spacing) and self.spacing > 0.0):
            raise ModelError(f'{self.name}: spacing must be positive, got {self.spacing}')
        if self.fixed.all():
            raise ModelError(f'{self.name}: every particle is fixed; nothing can move')

    @property
    def n_particles(self) -> int:
        return len(self.positions)

    @property
    def particle_volume(self) -> float:
        return float(self.spacing) ** 3


def lattice(nx: int, ny: int, nz: int, spacing: float, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Simple cubic lattice of ``nx * ny * nz`` points, cell-centred from ``origin``."""
    if min(nx, ny, nz) < 1:
        raise ModelError(f'lattice needs at least one point per axis, got {(nx, ny, nz)}')
    ix, iy, iz = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing='ij')
    pts = np.stack([ix.ravel(), iy.ravel(), iz.ravel()], axis=1).astype(np.float64)
    return (pts + 0.5) * spacing + np.asarray(origin, dtype=np.float64)


def make_block(nx: int = 10, ny: int = 10, nz: int = 10, spacing: float = 0.005,
               fix: str = 'bottom', fixed_layers: int = 1) -> TissueModel:
    """A rectangular block; ``fix`` is ``bottom`` (lowest z layers), ``none`` or ``left`` (lowest x)."""
    pos = lattice(nx, ny, nz, spacing)
    fixed = _fixed_layers(pos, spacing, fix, fixed_layers)
    return TissueModel('block', pos, spacing, fixed, {'shape': (nx, ny, nz), 'fix': fix})


def make_beam(length: float = 0.1, width: float = 0.02, height: float = 0.02, spacing: float = 0.0025,
              fixed_layers: int = 2) -> TissueModel:
    """A cantilever beam along +x, clamped at its x = 0 end by ``fixed_layers`` particle layers."""
    nx = int(round(length / spacing))
    ny = max(1, int(round(width / spacing)))
    nz = max(1, int(round(height / spacing)))
    pos = lattice(nx + fixed_layers, ny, nz, spacing, origin=(-fixed_layers * spacing, 0.0, 0.0))
    fixed = pos[:, 0] < 0.0
    return TissueModel('beam', pos, spacing, fixed,
                       {'length': nx * spacing, 'width': ny * spacing, 'height': nz * spacing,
                        'fixed_layers': fixed_layers})


def _fixed_layers(pos: np.ndarray, spacing: float, fix: str, layers: int) -> np.ndarray:
    if fix == 'none':
        return np.zeros(len(pos), dtype=np.bool_)
    axis = {'bottom': 2, 'left': 0}.get(fix)
    if axis is None:
        raise ModelError(f"fix must be 'bottom', 'left' or 'none', got {fix!r}")
    return pos[:, axis] < pos[:, axis].min() + layers * spacing - 1e-12


def fit_spacing(count_at: Callable[[float], int], n_target: int, volume: float,
                tol: float = 0.02, max_iter: int = 60) -> tuple[float, int]:
    """Lattice spacing whose particle count is closest to ``n_target`` (bisection on log spacing).

    ``count_at(s)`` is the number of lattice points inside the body at spacing ``s``; it falls
    roughly as ``volume / s**3`` but in steps, so the search keeps the best spacing seen and stops
    once the count is within ``tol / 4`` of the target (or the bracket has collapsed).

    Args:
        count_at: particle count at a spacing [m].
        n_target: wanted particle count (>= 1).
        volume: estimate of the body's volume [m^3] (sets the starting bracket).
        tol: relative count tolerance the caller will accept.
        max_iter: bisection steps.

    Returns:
        (spacing, count) of the best spacing found.

    Raises:
        ModelError: bad target or volume, or no spacing brackets the target.
    """
    if int(n_target) != n_target or n_target < 1:
        raise ModelError(f'particle count must be a positive integer, got {n_target!r}')
    if not (math.isfinite(volume) and volume > 0.0):
        raise ModelError(f'body volume must be positive, got {volume}')
    n_target = int(n_target)
    s0 = (volume / n_target) ** (1.0 / 3.0)
    best = (math.inf, s0, 0)

    def probe(s: float) -> int:
        nonlocal best
        c = int(count_at(s))
        if abs(c - n_target) < best[0]:
            best = (abs(c - n_target), s, c)
        return c

    lo, hi = 0.8 * s0, 1.25 * s0           # count(lo) >= n >= count(hi)
    for _ in range(30):
        if probe(lo) >= n_target:
            break
        lo *= 0.8
    else:
        raise ModelError(f'no lattice spacing gives {n_target} particles (body too thin?)')
    for _ in range(30):
        if probe(hi) <= n_target:
            break
        hi *= 1.25
    good = max(1.0, 0.25 * tol * n_target)
    for _ in range(max_iter):
        if best[0] <= good or hi / lo < 1.0 + 1e-9:
            break
        mid = math.sqrt(lo * hi)
        if probe(mid) > n_target:
            lo = mid
        else:
            hi = mid
    return best[1], best[2]
