"""A liver-shaped body sampled on a simple cubic lattice (we have no CT segmentation).

The shape is an implicit surface ``liver_field(p) < 0`` built from two lobes and a notch:

* right lobe: a superelliptic footprint (rounded-box outline seen from the front) with an
  elliptic vertical profile -- the thick dome of the right lobe;
* left lobe: a smaller, flatter lobe whose thickness tapers (smoothstep wedge) towards the
  left tip, raised so that it overhangs the base plane;
* a smooth union of the two (blend radius 20 mm), a smooth subtraction of a small notch on
  the inferior border between the lobes (gallbladder fossa / ligamentum teres notch);
* a flat posterior (bottom) face: the body is cut by the plane z = 0.

Tissue frame (metres): x from the patient's right (-x) to left (+x), y caudal (-y) to cranial
(+y), z posterior (0, the attached face) to anterior (+z, where the tool comes from). At the
default ``length = 0.2`` m the bounding box is 0.20 x 0.15 x 0.08 m, centred at x = y = 0 with
its lowest point at z = 0, and the volume is 1.15 litres (adult livers: about 1.2-1.8 l).
Every dimension scales with ``length``.

The lattice spacing is chosen by bisection (:func:`~.models.fit_spacing`) so that the particle
count is within ``tol`` of the requested one; the solver takes every particle's volume to be
``spacing**3``. The z levels of the lattice are cell-centred from the flat face (z = s/2, 3s/2,
...), so the bottom layer lies flat on the attachment.
"""

from __future__ import annotations

import time

import numpy as np

from .errors import ModelError
from .models import TissueModel, fit_spacing

REFERENCE_LENGTH = 0.2          # [m] x extent of the canonical shape below
# nominal bounding box at length 0.2 m (the lobe blend widens it by < 0.5 mm; sampling pads it)
_BOX_LO = np.array([-0.1, -0.075, 0.0])
_BOX_HI = np.array([0.1, 0.075, 0.08])

# lobe parameters: centre, semi-axes (x, y, z) [m], footprint exponent
_RIGHT = (np.array([-0.035, 0.0, 0.015]), (0.065, 0.075, 0.065), 3.0)
_LEFT = (np.array([0.035, 0.015, 0.02]), (0.065, 0.05, 0.032), 2.2)
_NOTCH = (np.array([0.0, -0.075, 0.02]), (0.012, 0.03, 0.08), 2.0)
_LEFT_TAPER = (-0.03, 0.13, 0.6)    # wedge starts at x0, spans dx, thins the lobe by this fraction
_BLEND = 0.02                       # lobe union blend radius [m]
_NOTCH_BLEND = 0.008


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union of two fields), blend width ``k``."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * h * h


def _lobe(p: np.ndarray, centre: np.ndarray, axes, expo: float, z_scale=1.0) -> np.ndarray:
    """Approximate signed distance [m] of a lobe: superelliptic footprint, elliptic profile."""
    d = p - centre
    ax, ay, az = axes
    rxy = (np.abs(d[:, 0] / ax) ** expo + np.abs(d[:, 1] / ay) ** expo) ** (1.0 / expo)
    q = np.sqrt(rxy * rxy + (d[:, 2] / (az * z_scale)) ** 2)
    return (q - 1.0) * min(axes)


def liver_field(points: np.ndarray, length: float = REFERENCE_LENGTH) -> np.ndarray:
    """Implicit function of the liver body: negative inside, positive outside (about metres).

    Args:
        points: ``(M, 3)`` positions in the tissue frame [m].
        length: x extent of the body [m]; the shape scales uniformly.

    Returns:
        ``(M,)`` field values.
    """
    if not (np.isfinite(length) and length > 0.0):
        raise ModelError(f'liver length must be positive, got {length}')
    scale = length / REFERENCE_LENGTH
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3) / scale
    f_right = _lobe(p, *_RIGHT)
    x0, dx, thin = _LEFT_TAPER
    taper = 1.0 - thin * _smoothstep((p[:, 0] - x0) / dx)
    f_left = _lobe(p, *_LEFT, z_scale=taper)
    f = _smin(f_right, f_left, _BLEND)
    f_notch = _lobe(p, *_NOTCH)
    f = -_smin(-f, f_notch, _NOTCH_BLEND)          # smooth subtraction of the notch
    f = np.maximum(f, -p[:, 2])                     # flat posterior face at z = 0
    return f * scale


def liver_bounds(length: float = REFERENCE_LENGTH) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (lo, hi) of the implicit body [m]."""
    scale = length / REFERENCE_LENGTH
    return _BOX_LO * scale, _BOX_HI * scale


def _axis_levels(lo: float, hi: float, s: float, phase: float) -> np.ndarray:
    """Lattice coordinates ``(i + phase) * s`` covering [lo, hi]."""
    i0 = int(np.floor(lo / s - phase)) - 1
    i1 = int(np.ceil(hi / s - phase)) + 1
    return (np.arange(i0, i1 + 1) + phase) * s


def sample_liver(spacing: float, length: float = REFERENCE_LENGTH,
                 phase: tuple[float, float] = (0.5, 0.5), count_only: bool = False):
    """Lattice points inside the liver at ``spacing`` (x, y lattice offset by ``phase`` spacings).

    Returns the ``(N, 3)`` points, or only N with ``count_only``.
    """
    lo, hi = liver_bounds(length)
    s = float(spacing)
    xs = _axis_levels(lo[0], hi[0], s, phase[0])
    ys = _axis_levels(lo[1], hi[1], s, phase[1])
    zs = (np.arange(int(np.ceil(hi[2] / s)) + 1) + 0.5) * s
    gx, gy = np.meshgrid(xs, ys, indexing='ij')
    gx = gx.ravel()
    gy = gy.ravel()
    total = 0
    out = []
    layer = np.empty((len(gx), 3))
    layer[:, 0] = gx
    layer[:, 1] = gy
    for z in zs:                       # layer by layer: bounded memory at any resolution
        layer[:, 2] = z
        inside = liver_field(layer, length) < 0.0
        if count_only:
            total += int(np.count_nonzero(inside))
        else:
            out.append(layer[inside].copy())
    if count_only:
        return total
    return np.concatenate(out) if out else np.zeros((0, 3))


def _liver_volume_estimate(length: float) -> float:
    """Volume [m^3] from a 48^3-ish lattice count (only seeds the spacing search)."""
    s = REFERENCE_LENGTH / 48.0 * length / REFERENCE_LENGTH
    return sample_liver(s, length, count_only=True) * s ** 3


def make_liver(n_particles: int = 3670, length: float = REFERENCE_LENGTH, fix: str = 'posterior',
               fixed_fraction: float = 0.1, fixed_layers: int = 1, spacing: float | None = None,
               tol: float = 0.02) -> TissueModel:
    """A liver-shaped :class:`TissueModel` with ``n_particles`` particles (within ``tol``).

    Args:
        n_particles: wanted particle count (the paper uses 289, 572, 743, 1289 and 3670).
        length: x extent of the organ [m] (0.2 m: a 0.20 x 0.15 x 0.08 m adult liver).
        fix: attached region: ``posterior`` (whole bottom lattice layers, as many as bring the
            fixed share closest to ``fixed_fraction``, at least one), ``bottom`` (exactly
            ``fixed_layers`` bottom layers) or ``none``.
        fixed_fraction: wanted share of fixed particles for ``fix='posterior'``.
        fixed_layers: bottom layers fixed for ``fix='bottom'``.
        spacing: lattice spacing [m]; if given, ``n_particles`` is ignored.
        tol: relative tolerance on the particle count.

    Raises:
        ModelError: bad count, length, spacing or fixing options, or a model that would be
            entirely fixed.
    """
    t0 = time.perf_counter()
    if not (np.isfinite(length) and length > 0.0):
        raise ModelError(f'liver length must be positive, got {length}')
    if fix not in ('posterior', 'bottom', 'none'):
        raise ModelError(f"liver fix must be 'posterior', 'bottom' or 'none', got {fix!r}")
    if not 0.0 < fixed_fraction < 1.0:
        raise ModelError(f'fixed_fraction must be in (0, 1), got {fixed_fraction}')
    if int(fixed_layers) != fixed_layers or fixed_layers < 1:
        raise ModelError(f'fixed_layers must be a positive integer, got {fixed_layers}')
    phase = (0.5, 0.5)
    if spacing is not None:
        s = float(spacing)
        if not (np.isfinite(s) and 0.0 < s < length):
            raise ModelError(f'spacing must be in (0, length), got {spacing}')
        target = None
    else:
        if isinstance(n_particles, bool) or int(n_particles) != n_particles or n_particles < 8:
            raise ModelError(f'n_particles must be an integer >= 8, got {n_particles!r}')
        target = int(n_particles)
        vol = _liver_volume_estimate(length)
        best = None
        # the count is a step function of the spacing; another lattice phase fills the gaps
        for ph in ((0.5, 0.5), (0.0, 0.0), (0.25, 0.5), (0.5, 0.25), (0.25, 0.25), (0.0, 0.5)):
            s_try, n_try = fit_spacing(lambda sp, ph=ph: sample_liver(sp, length, ph, count_only=True),
                                       target, vol, tol)
            if best is None or abs(n_try - target) < abs(best[1] - target):
                best = (s_try, n_try, ph)
            if abs(n_try - target) <= tol * target:
                break
        s, _, phase = best
    pos = sample_liver(s, length, phase)
    if len(pos) < 2:
        raise ModelError(f'liver at spacing {s:.4g} m has {len(pos)} particles; use a finer spacing')
    fixed = _liver_fixed(pos, s, fix, fixed_fraction, int(fixed_layers))
    if fixed.all():
        raise ModelError('liver: every particle would be fixed; use more particles or fewer fixed layers')
    lo, hi = liver_bounds(length)
    info = {
        'spacing': s,
        'n_target': target,
        'n_particles': len(pos),
        'count_error': None if target is None else (len(pos) - target) / target,
        'bbox': (lo.tolist(), hi.tolist()),
        'particle_bbox': (pos.min(axis=0).tolist(), pos.max(axis=0).tolist()),
        'volume': len(pos) * s ** 3,
        'fix': fix,
        'n_fixed': int(fixed.sum()),
        'fixed_layers': int(np.round(pos[fixed, 2].max() / s + 0.5)) if fixed.any() else 0,
        'length': length,
        'lattice_phase': phase,
        'build_time': time.perf_counter() - t0,
    }
    return TissueModel('liver', pos, s, fixed, info)


def _liver_fixed(pos: np.ndarray, s: float, fix: str, fraction: float, layers: int) -> np.ndarray:
    if fix == 'none':
        return np.zeros(len(pos), dtype=np.bool_)
    level = np.rint(pos[:, 2] / s - 0.5).astype(np.int64)     # 0 = bottom layer
    level -= level.min()
    if fix == 'bottom':
        return level < layers
    # posterior: whole layers, the count closest to the wanted fraction, at least one
    share = np.cumsum(np.bincount(level)) / len(pos)
    k = int(np.argmin(np.abs(share - fraction))) + 1
    return level < k
