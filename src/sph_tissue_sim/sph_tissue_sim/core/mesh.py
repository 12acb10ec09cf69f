"""Tissue models from a user's closed surface mesh (OBJ, STL, PLY, OFF): its inside on a lattice.

The mesh is read with trimesh (file I/O only) and must be watertight. Its inside is found by
ray parity along z: for every lattice column (x_i, y_j) the crossings of the vertical line with the
triangles are collected (numba, two passes into CSR arrays), sorted, and the lattice points between
the 1st/2nd, 3rd/4th, ... crossings are inside. The columns are shifted by a tiny irrational
fraction of the spacing for the ray test only, so no ray passes exactly through an edge or vertex
of a regular mesh (e.g. the diagonal of a box face), which would count a crossing twice.

The model is moved to the tissue frame used by the other models: centred at x = y = 0, lowest
point at z = 0 (the tool comes from +z), after scaling by ``scale`` (e.g. 0.001 for a mesh in mm).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from numba import njit

from .errors import ModelError
from .models import TissueModel, _fixed_layers, fit_spacing

# fractions of a spacing by which ray columns are shifted (irrational, far from any simple ratio)
_RAY_SHIFT = (math.sqrt(2.0) * 1e-6, math.pi * 1e-7)


@njit(cache=True)
def _column_crossings(tri, x0, y0, s, nx, ny, counts, offsets, zcross, fill):
    """Crossings of the z-parallel lines (x0 + i s, y0 + j s) with triangles ``tri`` (T, 3, 3).

    With ``fill`` False counts crossings per column into ``counts``; with ``fill`` True writes
    their z into ``zcross`` at ``offsets[col] + running count`` (``counts`` zeroed first).
    """
    for t in range(tri.shape[0]):
        ax = tri[t, 0, 0]; ay = tri[t, 0, 1]; az = tri[t, 0, 2]
        bx = tri[t, 1, 0]; by = tri[t, 1, 1]; bz = tri[t, 1, 2]
        cx = tri[t, 2, 0]; cy = tri[t, 2, 1]; cz = tri[t, 2, 2]
        det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        if abs(det) < 1e-300:
            continue                               # vertical triangle: a z ray never crosses it
        i0 = max(0, int(math.ceil((min(ax, bx, cx) - x0) / s)))
        i1 = min(nx - 1, int(math.floor((max(ax, bx, cx) - x0) / s)))
        j0 = max(0, int(math.ceil((min(ay, by, cy) - y0) / s)))
        j1 = min(ny - 1, int(math.floor((max(ay, by, cy) - y0) / s)))
        for i in range(i0, i1 + 1):
            px = x0 + i * s
            for j in range(j0, j1 + 1):
                py = y0 + j * s
                # barycentric coordinates of (px, py) in the projected triangle
                u = ((bx - px) * (cy - py) - (cx - px) * (by - py)) / det
                v = ((cx - px) * (ay - py) - (ax - px) * (cy - py)) / det
                w = 1.0 - u - v
                if u < 0.0 or v < 0.0 or w < 0.0:
                    continue
                col = i * ny + j
                if fill:
                    zcross[offsets[col] + counts[col]] = u * az + v * bz + w * cz
                counts[col] += 1


@njit(cache=True)
def _fill_inside(offsets, zcross, z0, s, nz, ny, inside):
    """Mark lattice points ``z0 + k s`` between pairs of sorted crossings. Returns odd columns."""
    odd = 0
    for col in range(len(offsets) - 1):
        a = offsets[col]
        b = offsets[col + 1]
        if b - a < 2:
            if b - a == 1:
                odd += 1
            continue
        zc = np.sort(zcross[a:b])
        if (b - a) % 2 == 1:
            odd += 1
        i = col // ny
        j = col % ny
        for p in range(0, b - a - 1, 2):
            k0 = max(0, int(math.ceil((zc[p] - z0) / s)))
            k1 = min(nz - 1, int(math.floor((zc[p + 1] - z0) / s)))
            for k in range(k0, k1 + 1):
                z = z0 + k * s
                if zc[p] < z < zc[p + 1]:
                    inside[i, j, k] = True
    return odd


def sample_inside(triangles: np.ndarray, spacing: float, lo: np.ndarray, hi: np.ndarray,
                  count_only: bool = False):
    """Points of the cell-centred lattice ``lo + (i + 1/2) s`` inside a closed triangle mesh.

    Args:
        triangles: ``(T, 3, 3)`` vertex coordinates [m].
        spacing: lattice spacing s [m].
        lo, hi: bounding box of the mesh [m].
        count_only: return only the number of inside points.

    Returns:
        ``(N, 3)`` points (or N), and as second value the number of columns whose ray crossed
        the surface an odd number of times (non-zero only for meshes that are not closed).
    """
    s = float(spacing)
    n = np.maximum(1, np.ceil((hi - lo) / s - 1e-9).astype(np.int64))
    if int(np.prod(n)) > 200_000_000:
        raise ModelError(f'spacing {s:.3g} m gives a lattice of {n.tolist()} points; too fine')
    origin = lo + 0.5 * s
    nx, ny, nz = (int(v) for v in n)
    x0 = origin[0] + _RAY_SHIFT[0] * s
    y0 = origin[1] + _RAY_SHIFT[1] * s
    counts = np.zeros(nx * ny, dtype=np.int64)
    tri = np.ascontiguousarray(triangles, dtype=np.float64)
    _column_crossings(tri, x0, y0, s, nx, ny, counts, counts, np.zeros(0), False)
    offsets = np.zeros(nx * ny + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    zcross = np.empty(offsets[-1])
    counts[:] = 0
    _column_crossings(tri, x0, y0, s, nx, ny, counts, offsets, zcross, True)
    inside = np.zeros((nx, ny, nz), dtype=np.bool_)
    odd = _fill_inside(offsets, zcross, origin[2], s, nz, ny, inside)
    if count_only:
        return int(np.count_nonzero(inside)), odd
    idx = np.argwhere(inside).astype(np.float64)
    return origin + idx * s, odd


MESH_FORMATS = ('.stl', '.obj', '.ply', '.off')


def check_mesh_file(p: Path) -> None:
    """Raise :class:`ModelError` with a sentence about the file when its bytes cannot be the mesh
    format its name says (trimesh fails on such files with unrelated errors, e.g. a missing
    text-encoding module for random bytes)."""
    ext = p.suffix.lower()
    if ext not in MESH_FORMATS:
        raise ModelError(f'{p}: unsupported mesh format {ext or "(no extension)"!r}; use one of '
                         f'{", ".join(MESH_FORMATS)}')
    data = p.read_bytes()
    if not data:
        raise ModelError(f'{p}: the file is empty')
    if ext == '.stl':
        if data[:5].lower() == b'solid' and b'\0' not in data[:1024] and b'facet' in data[:4096]:
            return                                   # ASCII STL
        if len(data) < 84:
            raise ModelError(f'{p}: not an STL file ({len(data)} bytes, shorter than a binary STL '
                             f'header)')
        n = int.from_bytes(data[80:84], 'little')
        if len(data) != 84 + 50 * n:
            raise ModelError(f'{p}: not a valid binary STL file: its header announces {n} triangles '
                             f'({84 + 50 * n} bytes) but the file has {len(data)} bytes (truncated '
                             f'or not an STL)')
        return
    if ext == '.ply':
        if not data.startswith(b'ply'):
            raise ModelError(f'{p}: not a PLY file (it does not start with "ply")')
        return
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ModelError(f'{p}: not a text {ext[1:].upper()} file (binary content at byte '
                         f'{exc.start})') from exc
    if '\0' in text:
        raise ModelError(f'{p}: not a text {ext[1:].upper()} file (it contains NUL bytes)')
    if ext == '.off' and not text.lstrip().startswith(('OFF', 'COFF', 'NOFF')):
        raise ModelError(f'{p}: not an OFF file (it does not start with "OFF")')


def _load(path, scale: float):
    """Read a mesh file with trimesh; returns the trimesh.Trimesh scaled by ``scale``."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise ModelError(f'mesh file not found: {p}')
    check_mesh_file(p)
    try:
        mesh = trimesh.load(str(p), force='mesh', process=True)
    except Exception as exc:                       # trimesh raises many types on bad files
        raise ModelError(f'{p}: not a readable {p.suffix[1:].upper()} mesh ({type(exc).__name__}: '
                         f'{exc})') from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ModelError(f'{p}: no triangles in the file (empty or not a surface mesh)')
    if not np.all(np.isfinite(mesh.vertices)):
        raise ModelError(f'{p}: non-finite vertex coordinates')
    if not mesh.is_watertight:
        _, uses = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
        raise ModelError(f'{p}: mesh is not watertight ({int(np.sum(uses == 1))} boundary edges, '
                         f'{int(np.sum(uses > 2))} non-manifold edges); close it first '
                         f'(e.g. trimesh.repair.fill_holes or MeshLab)')
    mesh.apply_scale(float(scale))
    return mesh


def load_mesh_model(path, n_particles: int | None = None, spacing: float | None = None,
                    scale: float = 1.0, fix: str = 'bottom', fixed_layers: int = 1,
                    tol: float = 0.02) -> TissueModel:
    """A :class:`TissueModel` sampled inside a closed surface mesh.

    Args:
        path: OBJ/STL/PLY/OFF file.
        n_particles: wanted particle count (the spacing is found by bisection, within ``tol``).
        spacing: lattice spacing [m] (after scaling); give this or ``n_particles``. With neither,
            3670 particles (the paper's liver).
        scale: factor from file units to metres (0.001 for mm).
        fix: ``bottom`` (lowest ``fixed_layers`` z layers), ``left`` (lowest x layers) or ``none``.
        fixed_layers: number of fixed lattice layers.
        tol: relative tolerance on the particle count.

    Raises:
        ModelError: missing, unreadable, empty or open (non-watertight) mesh, bad options, or
            a spacing so coarse that nothing (or only fixed particles) remains.
    """
    t0 = time.perf_counter()
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0.0):
        raise ModelError(f'scale must be a positive number, got {scale!r}')
    if n_particles is not None and spacing is not None:
        raise ModelError('give n_particles or spacing, not both')
    if int(fixed_layers) != fixed_layers or fixed_layers < 1:
        raise ModelError(f'fixed_layers must be a positive integer, got {fixed_layers}')
    if fix not in ('bottom', 'left', 'none'):
        raise ModelError(f"mesh fix must be 'bottom', 'left' or 'none', got {fix!r}")
    mesh = _load(path, scale)
    tri = np.ascontiguousarray(mesh.triangles, dtype=np.float64)
    lo, hi = mesh.bounds[0].copy(), mesh.bounds[1].copy()
    volume = abs(float(mesh.volume))
    if not volume > 0.0:
        raise ModelError(f'{path}: mesh encloses no volume')
    if spacing is not None:
        s = float(spacing)
        if not (math.isfinite(s) and s > 0.0):
            raise ModelError(f'spacing must be positive, got {spacing!r}')
        target = None
    else:
        target = 3670 if n_particles is None else n_particles
        if isinstance(target, bool) or int(target) != target or target < 8:
            raise ModelError(f'n_particles must be an integer >= 8, got {target!r}')
        target = int(target)
        s, _ = fit_spacing(lambda sp: sample_inside(tri, sp, lo, hi, count_only=True)[0],
                           target, volume, tol)
    pos, odd = sample_inside(tri, s, lo, hi)
    if len(pos) < 2:
        raise ModelError(f'{path}: spacing {s:.4g} m leaves {len(pos)} particles inside the mesh; '
                         f'use a finer spacing')
    # tissue frame: centred in x, y; lowest point of the mesh at z = 0
    shift = np.array([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2]])
    pos += shift
    fixed = _fixed_layers(pos, s, fix, int(fixed_layers))
    if fixed.all():
        raise ModelError(f'{path}: every particle would be fixed; use a finer spacing or fewer layers')
    name = f'mesh:{Path(path).name}'
    info = {
        'path': str(path),
        'spacing': s,
        'n_target': target,
        'n_particles': len(pos),
        'count_error': None if target is None else (len(pos) - target) / target,
        'bbox': ((lo + shift).tolist(), (hi + shift).tolist()),
        'mesh_volume': volume,
        'volume': len(pos) * s ** 3,
        'n_triangles': len(tri),
        'odd_columns': int(odd),
        'scale': scale,
        'shift': shift.tolist(),
        'fix': fix,
        'n_fixed': int(fixed.sum()),
        'build_time': time.perf_counter() - t0,
    }
    return TissueModel(name, pos, s, fixed, info)
