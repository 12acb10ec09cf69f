"""Tissue models by name: the one factory that the node, the benchmarks and the tests use.

``make_model('liver', n_particles=3670)``, ``make_model('block', size=(0.08, 0.08, 0.04),
n_particles=2048)``, ``make_model('mesh', path='organ.stl', n_particles=5000)``. The shape modules
(:mod:`.models` for lattices, :mod:`.liver`, :mod:`.mesh`) import only :mod:`.models`; this module
imports them all, so there is no import circle.
"""

from __future__ import annotations

import numpy as np

from .errors import ConfigError, ModelError
from .liver import make_liver
from .mesh import load_mesh_model
from .models import TissueModel, make_beam, make_block

#: the model kinds, in the order the node's parameter lists them
MODELS = ('liver', 'block', 'beam', 'mesh')


def _sized_spacing(name: str, size, n_particles: int) -> tuple[np.ndarray, float]:
    """(size as 3 lengths [m], the lattice spacing [m] that fills it with about n_particles)."""
    size = np.asarray(size, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise ConfigError(f'{name} size must be 3 positive lengths [m], got {size.tolist()}')
    if int(n_particles) < 1:
        raise ConfigError(f'n_particles must be >= 1, got {n_particles}')
    return size, (float(np.prod(size)) / int(n_particles)) ** (1.0 / 3.0)


def block_of(size, n_particles: int) -> TissueModel:
    """A block of about ``n_particles`` particles filling ``size`` [m] (bottom layer fixed)."""
    size, s = _sized_spacing('block', size, n_particles)
    dims = [max(2, int(round(L / s))) for L in size]
    return make_block(*dims, spacing=s, fix='bottom')


def beam_of(size, n_particles: int) -> TissueModel:
    """A cantilever of about ``n_particles`` particles, ``size`` = (length, width, height) [m]."""
    size, s = _sized_spacing('beam', size, n_particles)
    return make_beam(float(size[0]), float(size[1]), float(size[2]), spacing=s)


def make_model(kind: str, **kwargs) -> TissueModel:
    """Build a model by name.

    ``block`` / ``beam``: ``size`` [m] and ``n_particles`` (:func:`block_of`, :func:`beam_of`), or
    the lattice arguments of :func:`~.models.make_block` / :func:`~.models.make_beam`; ``liver``:
    :func:`~.liver.make_liver`'s; ``mesh``: :func:`~.mesh.load_mesh_model`'s (``path=`` a surface
    mesh).
    """
    if kind == 'block':
        return block_of(**kwargs) if 'size' in kwargs else make_block(**kwargs)
    if kind == 'beam':
        return beam_of(**kwargs) if 'size' in kwargs else make_beam(**kwargs)
    if kind == 'liver':
        return make_liver(**kwargs)
    if kind == 'mesh':
        return load_mesh_model(**kwargs)
    raise ModelError(f"unknown model {kind!r}; expected one of {', '.join(MODELS)}")
