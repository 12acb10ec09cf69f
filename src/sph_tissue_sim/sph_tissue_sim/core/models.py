"""Tissue models: particle sets sampled on a lattice, with an attached (fixed) region.

Every model is a :class:`TissueModel`; :func:`make_model` builds one by name so that nodes and
benchmarks can select it from a parameter.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


def make_model(kind: str, **kwargs) -> TissueModel:
    """Build a model by name: ``block``, ``beam``, ``liver`` or ``mesh`` (``path=`` a surface mesh)."""
    if kind == 'block':
        return make_block(**kwargs)
    if kind == 'beam':
        return make_beam(**kwargs)
    if kind == 'liver':
        from .liver import make_liver
        return make_liver(**kwargs)
    if kind == 'mesh':
        from .mesh import load_mesh_model
        return load_mesh_model(**kwargs)
    raise ModelError(f"unknown model {kind!r}; expected 'liver', 'block', 'beam' or 'mesh'")
