"""Uniform cell-grid neighbour search (paper sec. 3.2) with CSR output, O(N), numba.

The grid has cell size ``cell >= radius`` (the solver uses ``2h``), so the neighbours of a point
are in the 27 surrounding cells. Particles are bucketed with a counting sort:
``cell_start[c] : cell_start[c + 1]`` indexes ``cell_particles`` for cell ``c``.
Neighbour lists are CSR: the neighbours of ``i`` are ``indices[offsets[i]:offsets[i + 1]]``
(self excluded, sorted by index within a cell).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .state import Grid


class CellGrid:
    """A cell grid over a fixed point set (e.g. the reference configuration).

    Attributes:
        origin: (3,) lower corner [m].
        cell: cell size [m].
        dims: (3,) int64 number of cells per axis.
        cell_start: (ncells + 1,) int64 CSR offsets.
        cell_particles: (N,) int32 particle indices bucketed by cell.
    """

    def __init__(self, points: np.ndarray, cell: float) -> None:
        points = np.ascontiguousarray(points, dtype=np.float64)
        self.cell = float(cell)
        self.origin, self.dims = grid_geometry(points, self.cell)
        self.cell_start, self.cell_particles = bin_points(points, self.origin, self.cell, self.dims)
        self.bundle = Grid(self.origin, self.cell, self.dims, self.cell_start, self.cell_particles)

    def query(self, centre: np.ndarray, radius: float, points: np.ndarray) -> np.ndarray:
        """Indices of ``points`` within ``radius`` of ``centre`` (any radius; scans the covering cells)."""
        out = np.empty(len(points), dtype=np.int32)
        n = query_ball(np.asarray(centre, dtype=np.float64), radius, points, self.bundle, out)
        return out[:n].copy()


def grid_geometry(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Origin and dimensions of a grid covering ``points`` with one cell of padding."""
    lo = points.min(axis=0) - cell
    hi = points.max(axis=0) + cell
    dims = np.maximum(1, np.ceil((hi - lo) / cell).astype(np.int64))
    if int(np.prod(dims)) > 50_000_000:
        raise MemoryError(f'cell grid of {dims} cells is too large; cell size {cell} m')
    return lo.astype(np.float64), dims


@njit(cache=True)
def _cell_of(x: float, origin: float, cell: float, dim: int) -> int:
    c = int(math.floor((x - origin) / cell))
    if c < 0:
        return 0
    if c >= dim:
        return dim - 1
    return c


@njit(cache=True, inline='always')
def cell_block(p0: float, p1: float, p2: float, origin: np.ndarray, cell: float, dims: np.ndarray,
               out: np.ndarray) -> int:
    """Ids of the cells (up to 27) in the 3x3x3 block around the cell of point ``p`` into ``out``;
    returns how many. With ``cell`` >= the search radius they hold every neighbour of ``p``."""
    cx = _cell_of(p0, origin[0], cell, dims[0])
    cy = _cell_of(p1, origin[1], cell, dims[1])
    cz = _cell_of(p2, origin[2], cell, dims[2])
    n = 0
    for ax in range(max(cx - 1, 0), min(cx + 2, dims[0])):
        for ay in range(max(cy - 1, 0), min(cy + 2, dims[1])):
            for az in range(max(cz - 1, 0), min(cz + 2, dims[2])):
                out[n] = (ax * dims[1] + ay) * dims[2] + az
                n += 1
    return n


@njit(cache=True)
def bin_points(points: np.ndarray, origin: np.ndarray, cell: float,
               dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Counting sort of points into cells: returns ``(cell_start, cell_particles)``."""
    n = points.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    count = np.zeros(ncell + 1, dtype=np.int64)
    cid = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx = _cell_of(points[i, 0], origin[0], cell, dims[0])
        cy = _cell_of(points[i, 1], origin[1], cell, dims[1])
        cz = _cell_of(points[i, 2], origin[2], cell, dims[2])
        c = (cx * dims[1] + cy) * dims[2] + cz
        cid[i] = c
        count[c + 1] += 1
    for c in range(ncell):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    cell_particles = np.empty(n, dtype=np.int32)
    for i in range(n):
        c = cid[i]
        cell_particles[fill[c]] = i
        fill[c] += 1
    return count, cell_particles


@njit(cache=True)
def query_ball(centre: np.ndarray, radius: float, points: np.ndarray, grid: Grid, out: np.ndarray) -> int:
    """Write indices of ``points`` (binned in ``grid``) within ``radius`` of ``centre`` into
    ``out``; return how many (possibly more than ``out`` holds: only those fit are written).

    Cost is proportional to the cells covering the ball, independent of the number of points.
    """
    origin, cell, dims, cell_start, cell_particles = grid
    r2 = radius * radius
    lo0 = _cell_of(centre[0] - radius, origin[0], cell, dims[0])
    hi0 = _cell_of(centre[0] + radius, origin[0], cell, dims[0])
    lo1 = _cell_of(centre[1] - radius, origin[1], cell, dims[1])
    hi1 = _cell_of(centre[1] + radius, origin[1], cell, dims[1])
    lo2 = _cell_of(centre[2] - radius, origin[2], cell, dims[2])
    hi2 = _cell_of(centre[2] + radius, origin[2], cell, dims[2])
    n = 0
    for cx in range(lo0, hi0 + 1):
        for cy in range(lo1, hi1 + 1):
            for cz in range(lo2, hi2 + 1):
                c = (cx * dims[1] + cy) * dims[2] + cz
                for k in range(cell_start[c], cell_start[c + 1]):
                    j = cell_particles[k]
                    d0 = points[j, 0] - centre[0]
                    d1 = points[j, 1] - centre[1]
                    d2 = points[j, 2] - centre[2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                        if n < out.shape[0]:
                            out[n] = j
                        n += 1
    return n


@njit(cache=True)
def _neighbour_pass(points, radius, origin, cell, dims, cell_start, cell_particles, offsets, indices,
                    fill):
    """Count every point's neighbours into ``offsets[i + 1]`` (``fill`` False), or write them to
    ``indices[offsets[i]:offsets[i + 1]]`` (``fill`` True, after the counts were summed)."""
    n = points.shape[0]
    r2 = radius * radius
    cells = np.empty(27, dtype=np.int64)
    for i in range(n):
        m = offsets[i] if fill else 0
        n_cells = cell_block(points[i, 0], points[i, 1], points[i, 2], origin, cell, dims, cells)
        for q in range(n_cells):
            c = cells[q]
            for k in range(cell_start[c], cell_start[c + 1]):
                j = cell_particles[k]
                if j == i:
                    continue
                d0 = points[j, 0] - points[i, 0]
                d1 = points[j, 1] - points[i, 1]
                d2 = points[j, 2] - points[i, 2]
                if d0 * d0 + d1 * d1 + d2 * d2 < r2:
                    if fill:
                        indices[m] = j
                    m += 1
        if not fill:
            offsets[i + 1] = m


@njit(cache=True)
def neighbour_lists(points: np.ndarray, radius: float, origin: np.ndarray, cell: float,
                    dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR neighbour lists of all points within ``radius`` (< ``cell``), self excluded."""
    cell_start, cell_particles = bin_points(points, origin, cell, dims)
    n = points.shape[0]
    offsets = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(0, dtype=np.int32)
    _neighbour_pass(points, radius, origin, cell, dims, cell_start, cell_particles, offsets, indices,
                    False)
    for i in range(n):
        offsets[i + 1] += offsets[i]
    indices = np.empty(offsets[n], dtype=np.int32)
    _neighbour_pass(points, radius, origin, cell, dims, cell_start, cell_particles, offsets, indices,
                    True)
    return offsets, indices


def find_neighbours(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """CSR ``(offsets, indices)`` of every point's neighbours within ``radius`` (cell size = radius)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    origin, dims = grid_geometry(points, radius)
    return neighbour_lists(points, float(radius), origin, float(radius), dims)


@njit(cache=True, nogil=True)
def append_new(items, lo, hi, stamp, stamp_val, out, n):
    """Append those of ``items[lo:hi]`` not stamped ``stamp_val`` yet to ``out[:n]`` (stamping
    them); returns the new count. One stamp array and a fresh value per set make a set O(its size).

    A range rather than one item per call: numba increfs array arguments at every call and cannot
    prune that around a branch, which made a per-item helper nine times slower than this loop.
    """
    for t in range(lo, hi):
        j = items[t]
        if stamp[j] != stamp_val:
            stamp[j] = stamp_val
            out[n] = j
            n += 1
    return n
