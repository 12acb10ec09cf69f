"""The organ itself in the report: the particle cloud at rest and at the deepest press (no rclpy).

:class:`TissueSnapshots` keeps, from the ``tissue/particles`` clouds viz_node receives, the first
(at rest), the one with the largest displacement (the deepest press) with the simulated tools of
that moment, and a short run of clouds around it for an animation. The images are drawn headless
(matplotlib Agg): every particle as a dot coloured by its displacement and, beside it, by its von
Mises stress, each tool drawn where the simulation had it and the particles it holds (the cloud's
``held`` byte: a grasp, or a needle's track) ringed in its colour
(:func:`tissue_viz.markers.instrument_colour`; one tool alone is drawn dark grey), and the cut faces
(the ``severed`` byte: particles that lost bonds to a blade) marked with black crosses; a particle a cut
removed (NaN) is not drawn. A cloud of more than
:data:`MAX_POINTS` particles is kept as a fixed, evenly spread subset (the images stay legible
and the memory bounded at 100k particles). Snapshots are saved with the report
(``tissue_snapshots.npz``) so that ``tissue_report`` can draw them again.
"""

from __future__ import annotations

import collections
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tissue_viz.markers import instrument_colour

#: particles kept per cloud (a fixed subset of a larger cloud)
MAX_POINTS = 20000
#: clouds kept before and after the deepest one for the animation
ANIMATION_SIDE = 12
#: PointField datatypes -> numpy (sensor_msgs/PointField constants)
POINTFIELD_DTYPES = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
FIELDS = ('x', 'y', 'z', 'displacement', 'von_mises', 'held', 'severed')
#: one tool alone (as before there were several): dark grey on the white report
SINGLE_TOOL_COLOUR = '0.15'


def cloud_arrays(fields, data: bytes, width: int, point_step: int, big_endian: bool = False) -> dict:
    """Columns of a PointCloud2 (``fields``: (name, offset, datatype) triples) as float arrays; the
    ones of :data:`FIELDS` it carries (x, y, z at least).

    Raises:
        ValueError: the cloud lacks x, y or z, or its data is shorter than ``width`` points.
    """
    names = {name: (offset, POINTFIELD_DTYPES.get(kind)) for name, offset, kind in fields}
    if not {'x', 'y', 'z'} <= set(names):
        raise ValueError(f'a cloud needs x, y and z fields, got {sorted(names)}')
    if len(data) < width * point_step:
        raise ValueError(f'cloud data holds {len(data)} bytes, {width} points need {width * point_step}')
    order = '>' if big_endian else '<'
    keep = [n for n in FIELDS if n in names and names[n][1] is not None]
    dtype = np.dtype({'names': keep, 'formats': [order + names[n][1] for n in keep],
                      'offsets': [names[n][0] for n in keep], 'itemsize': point_step})
    rec = np.frombuffer(data, dtype=dtype, count=width)
    return {n: rec[n].astype(np.float64) for n in keep}


Tool = tuple   # (tip (3,) [m], unit axis (3,), shaft length [m], radius [m]) in the cloud's frame


@dataclass
class Snapshot:
    """One cloud: positions (n, 3) [m], displacement (n,) [m], von Mises (n,) [Pa] (NaN where the
    cloud had no such field), its stamp [ns], each instrument's tool (:data:`Tool`, or None where it
    is lifted or unknown; index k = instrument k), the held byte (n,) (0 free, k + 1 held by
    instrument k) and the severed byte (n,) (bonds lost to a cut); None where the cloud had no
    such field."""

    xyz: np.ndarray
    displacement: np.ndarray
    von_mises: np.ndarray
    stamp_ns: int
    tools: tuple = ()
    held: np.ndarray | None = None
    severed: np.ndarray | None = None

    @property
    def first_tool(self) -> Tool | None:
        """The first instrument's tool that is there (the section runs through it)."""
        return next((t for t in self.tools if t is not None), None)

    @property
    def peak(self) -> float:
        d = self.displacement[np.isfinite(self.displacement)]
        return float(d.max()) if d.size else 0.0


class TissueSnapshots:
    """Rest, deepest press and the clouds around it, from the clouds as they arrive."""

    def __init__(self, max_points: int = MAX_POINTS, side: int = ANIMATION_SIDE) -> None:
        self.max_points, self.side = max_points, side
        self.rest: Snapshot | None = None
        self.deepest: Snapshot | None = None
        self.frames: list[Snapshot] = []          # before the deepest, the deepest, after it
        self._recent: collections.deque = collections.deque(maxlen=side)
        self._after = 0
        self._subset: tuple[int, np.ndarray] | None = None

    def _take(self, n: int) -> np.ndarray | slice:
        if n <= self.max_points:
            return slice(None)
        if self._subset is None or self._subset[0] != n:
            self._subset = (n, np.linspace(0, n - 1, self.max_points).astype(np.int64))
        return self._subset[1]

    def copy(self) -> 'TissueSnapshots':
        """What there is now, for a report drawn on another thread while clouds keep coming."""
        out = TissueSnapshots(self.max_points, self.side)
        out.rest, out.deepest, out.frames = self.rest, self.deepest, list(self.frames)
        return out

    def add(self, columns: dict, stamp_ns: int, tools: tuple) -> None:
        """One received cloud (:func:`cloud_arrays`) and each instrument's simulated tool of that
        moment (:attr:`Snapshot.tools`)."""
        n = len(columns['x'])
        if n == 0:
            return
        pick = self._take(n)
        nan = np.full(n, np.nan)
        held, severed = columns.get('held'), columns.get('severed')
        snap = Snapshot(np.column_stack([columns['x'][pick], columns['y'][pick], columns['z'][pick]]),
                        columns.get('displacement', nan)[pick], columns.get('von_mises', nan)[pick],
                        int(stamp_ns), tuple(tools), None if held is None else held[pick].astype(np.uint8),
                        None if severed is None else severed[pick].astype(np.uint8))
        if self.rest is None:
            self.rest = snap
        if self.deepest is None or snap.peak > self.deepest.peak:
            self.deepest = snap
            self.frames = [*self._recent, snap]
            self._after = self.side
        elif self._after > 0:
            self.frames.append(snap)
            self._after -= 1
        self._recent.append(snap)

    # -- saving, so that tissue_report can draw them again -------------------------------------
    def save(self, path: Path) -> None:
        arrays = {}
        for name, snap in (('rest', self.rest), ('deepest', self.deepest),
                           *((f'frame{k:03d}', s) for k, s in enumerate(self.frames))):
            if snap is None:
                continue
            arrays[f'{name}_xyz'] = snap.xyz
            arrays[f'{name}_disp'] = snap.displacement
            arrays[f'{name}_vm'] = snap.von_mises
            arrays[f'{name}_stamp'] = np.array(snap.stamp_ns)
            if snap.tools:
                # one row per instrument, NaN for a lifted one
                arrays[f'{name}_tool'] = np.array([np.r_[t[0], t[1], t[2], t[3]] if t is not None
                                                   else np.full(8, np.nan) for t in snap.tools])
            if snap.held is not None:
                arrays[f'{name}_held'] = snap.held
            if snap.severed is not None:
                arrays[f'{name}_severed'] = snap.severed
        # np.savez_compressed's layout (np.load reads it) at zlib level 1: a quarter of the time
        # of its level 6 for 7 % more bytes
        with zipfile.ZipFile(path, 'w', compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for key, value in arrays.items():
                with zf.open(f'{key}.npy', 'w', force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)

    @classmethod
    def load(cls, path: Path) -> 'TissueSnapshots':
        out = cls()
        with np.load(path) as z:
            def snap(name):
                if f'{name}_xyz' not in z:
                    return None
                # (8,) in a file from before several instruments: one tool
                rows = np.atleast_2d(z[f'{name}_tool']) if f'{name}_tool' in z else np.zeros((0, 8))
                tools = tuple((r[:3], r[3:6], float(r[6]), float(r[7])) if np.isfinite(r).all() else None
                              for r in rows)
                return Snapshot(z[f'{name}_xyz'], z[f'{name}_disp'], z[f'{name}_vm'],
                                int(z[f'{name}_stamp']), tools,
                                z[f'{name}_held'] if f'{name}_held' in z else None,
                                z[f'{name}_severed'] if f'{name}_severed' in z else None)
            out.rest, out.deepest = snap('rest'), snap('deepest')
            k = 0
            while (s := snap(f'frame{k:03d}')) is not None:
                out.frames.append(s)
                k += 1
        return out


# -- drawing --------------------------------------------------------------------------------------
def _tool_surface(tool, n: int = 16):
    """Points of the tool's surface (sphere at the tip, plus the shaft of a capsule) to wireframe."""
    tip, axis, length, radius = tool
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n // 2))
    sphere = [tip[0] + radius * np.cos(u) * np.sin(v), tip[1] + radius * np.sin(u) * np.sin(v),
              tip[2] + radius * np.cos(v)]
    shaft = None
    a = np.asarray(axis, float)
    if length > 0.0 and np.linalg.norm(a) > 0.0:
        z = a / np.linalg.norm(a)
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        th, s = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0.0, length, 4))
        shaft = [tip[k] + radius * (np.cos(th) * x[k] + np.sin(th) * y[k]) + s * z[k] for k in range(3)]
    return sphere, shaft


def _tool_colours(snap: Snapshot) -> list[tuple[int, Tool, object]]:
    """(instrument k, tool, colour) of each tool there is: dark grey for one instrument alone."""
    several = len(snap.tools) > 1
    return [(k, t, instrument_colour(k) if several else SINGLE_TOOL_COLOUR)
            for k, t in enumerate(snap.tools) if t is not None]


def _held_groups(snap: Snapshot, pick: np.ndarray | slice = slice(None)) -> list[tuple[np.ndarray, object]]:
    """(positions (m, 3) [m], colour) of the particles each instrument holds, among ``pick``."""
    if snap.held is None:
        return []
    held, xyz = snap.held[pick], snap.xyz[pick]
    return [(xyz[held == code], instrument_colour(int(code) - 1)) for code in np.unique(held) if code]


def _cut_faces(snap: Snapshot, pick: np.ndarray | slice = slice(None)) -> np.ndarray:
    """Positions (m, 3) [m] of the particles among ``pick`` that lost bonds to a cut (still there)."""
    if snap.severed is None:
        return np.zeros((0, 3))
    xyz = snap.xyz[pick]
    return xyz[(snap.severed[pick] > 0) & np.isfinite(xyz).all(axis=1)]


def _dot_size(n: int) -> float:
    return float(np.clip(20000.0 / max(n, 1), 1.0, 14.0))


def _norm(vmax: float, scale: float):
    from matplotlib.colors import PowerNorm
    # square-root scale: the pressed region's gradient stays visible beside the peak under the tool
    return PowerNorm(0.5, vmin=0.0, vmax=max(vmax * scale, 1e-12))


def _colour_scale(vmax: float, cmap: str, scale: float):
    """What a colour bar needs of the scatters it explains (their norm and colour map)."""
    from matplotlib.cm import ScalarMappable
    return ScalarMappable(norm=_norm(vmax, scale), cmap=cmap)


# A figure is built, laid out and drawn once without its clouds (axes, ticks, colour bars); each
# cloud or animation frame then draws only its particles, tool and title over a copy of that
# drawing: the axes cost far more to build, lay out and draw than the particles.
def _cloud_axes(fig, ax, label: str, limits, vmax: float, cmap: str, scale: float) -> None:
    lo, hi = limits
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('y [mm]')
    ax.set_zlabel('z [mm]')
    ax.view_init(elev=25, azim=-60)
    fig.colorbar(_colour_scale(vmax, cmap, scale), ax=ax, shrink=0.6, pad=0.12, label=label)


def _cloud_artists(ax, snap: Snapshot, values: np.ndarray, vmax: float, cmap: str,
                   scale: float, animated: bool = False) -> list:
    """The cloud in 3-D, dots coloured by ``values`` (grey where not finite), and the tool."""
    xyz = snap.xyz * 1e3
    there = np.isfinite(xyz).all(axis=1)          # a particle a cut removed is NaN
    ok = np.isfinite(values) & there
    artists = [ax.scatter(xyz[ok, 0], xyz[ok, 1], xyz[ok, 2], c=values[ok] * scale,
                          s=_dot_size(len(xyz)), cmap=cmap, norm=_norm(vmax, scale),
                          depthshade=False, linewidths=0, animated=animated)]
    grey = ~ok & there
    if grey.any():
        artists.append(ax.scatter(xyz[grey, 0], xyz[grey, 1], xyz[grey, 2], s=2, color='0.7',
                                  depthshade=False, animated=animated))
    faces = _cut_faces(snap) * 1e3
    if len(faces):
        artists.append(ax.scatter(faces[:, 0], faces[:, 1], faces[:, 2], s=2 * _dot_size(len(xyz)), marker='x',
                                  color='k', linewidths=0.6, depthshade=False, animated=animated))
    for pts, colour in _held_groups(snap):
        pts = pts * 1e3
        artists.append(ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=3 * _dot_size(len(xyz)),
                                  facecolors='none', edgecolors=[colour], linewidths=1.0,
                                  depthshade=False, animated=animated))
    for _, tool, colour in _tool_colours(snap):
        sphere, shaft = _tool_surface(tool)
        artists.append(ax.plot_wireframe(*(c * 1e3 for c in sphere), color=colour, linewidth=0.5,
                                         animated=animated))
        if shaft is not None:
            artists.append(ax.plot_wireframe(*(c * 1e3 for c in shaft), color=colour,
                                             linewidth=0.5, animated=animated))
    return artists


def _section(snap: Snapshot, reference: Snapshot) -> np.ndarray:
    """Particles of the slab one spacing thick (in the reference configuration) through the tool's
    tip, or through the most displaced particle: the x-z section of the press."""
    ref = reference.xyz if len(reference.xyz) == len(snap.xyz) else snap.xyz
    ys = np.unique(np.round(ref[:, 1], 6))
    gap = float(np.median(np.diff(ys))) if ys.size > 1 else 1.0
    if snap.first_tool is not None:
        y0 = float(snap.first_tool[0][1])
    else:
        d = np.where(np.isfinite(snap.displacement), snap.displacement, -np.inf)
        y0 = float(ref[int(np.argmax(d)), 1])
    near = ys[np.argmin(np.abs(ys - y0))]
    return np.abs(ref[:, 1] - near) <= 0.5 * gap


def _section_axes(fig, ax, label: str, limits, vmax: float, cmap: str, scale: float) -> None:
    lo, hi = limits
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[2], hi[2])
    ax.set_aspect('equal')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('z [mm]')
    ax.set_title('section through the tool (one particle layer)', fontsize=9)
    fig.colorbar(_colour_scale(vmax, cmap, scale), ax=ax, shrink=0.8, label=label)


def _section_artists(ax, snap: Snapshot, reference: Snapshot, values: np.ndarray, vmax: float,
                     cmap: str, scale: float, animated: bool = False) -> list:
    """The section's particles coloured by ``values`` (those held ringed in their instrument's
    colour), and the tools projected on the section plane."""
    pick = _section(snap, reference) & np.isfinite(values) & np.isfinite(snap.xyz).all(axis=1)
    xz = snap.xyz[pick][:, [0, 2]] * 1e3
    size = 4 * _dot_size(int(pick.sum()))
    artists = [ax.scatter(xz[:, 0], xz[:, 1], c=values[pick] * scale, s=size, cmap=cmap,
                          norm=_norm(vmax, scale), linewidths=0, animated=animated)]
    for pts, colour in _held_groups(snap, pick):
        artists.append(ax.scatter(pts[:, 0] * 1e3, pts[:, 2] * 1e3, s=2 * size, facecolors='none',
                                  edgecolors=[colour], linewidths=1.0, animated=animated))
    faces = _cut_faces(snap, pick) * 1e3
    if len(faces):
        artists.append(ax.scatter(faces[:, 0], faces[:, 2], s=size, marker='x', color='k', linewidths=0.8,
                                  animated=animated))
    th = np.linspace(0.0, 2.0 * np.pi, 64)
    for _, (tip, axis, length, radius), colour in _tool_colours(snap):
        artists += ax.plot((tip[0] + radius * np.cos(th)) * 1e3,
                           (tip[2] + radius * np.sin(th)) * 1e3, color=colour, linewidth=1.0,
                           animated=animated)
        if length > 0.0 and np.linalg.norm(axis) > 0.0:
            end = np.asarray(tip) + length * np.asarray(axis) / np.linalg.norm(axis)
            artists += ax.plot([tip[0] * 1e3, end[0] * 1e3], [tip[2] * 1e3, end[2] * 1e3],
                               color=colour, linewidth=2 * radius * 1e3 * 2.0, alpha=0.3,
                               solid_capstyle='round', animated=animated)
    return artists


def _limits(snaps) -> tuple[np.ndarray, np.ndarray]:
    pts = np.vstack([s.xyz for s in snaps if s is not None]) * 1e3
    pts = pts[np.isfinite(pts).all(axis=1)]            # a particle a cut removed is NaN
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * np.max(hi - lo) + 1.0
    return lo - pad, hi + pad


def _finite_max(*arrays) -> float:
    vals = np.concatenate([a[np.isfinite(a)] for a in arrays])
    return float(vals.max()) if vals.size else 0.0


class SnapshotFigure:
    """The figure of :func:`draw_snapshot` for snapshots that share scales: built, laid out and
    drawn once without data; each snapshot then draws only its clouds, tool and title over a copy
    of that drawing.

    ``scale_from``: snapshots whose range the colour scales and axes share; ``reference``: the
    cloud at rest, which picks the section's particles (None: each snapshot itself).
    """

    def __init__(self, scale_from: list, reference: Snapshot | None = None) -> None:
        from tissue_viz import figures

        group = [s for s in scale_from if s is not None]
        limits = _limits(group)
        dmax = _finite_max(*(s.displacement for s in group))
        vmax = _finite_max(*(s.von_mises for s in group))
        self.reference = reference
        self.fig = figures.new_figure((12, 9), 100)
        self.panels = []        # (3-D axes, section axes, which values, vmax, cmap, scale)
        for k, (which, label, top, cmap, scale) in enumerate((
                ('displacement', 'displacement [mm]', dmax, 'viridis', 1e3),
                ('von_mises', 'von Mises stress [Pa]', vmax, 'inferno', 1.0))):
            ax3 = self.fig.add_subplot(2, 2, k + 1, projection='3d')
            _cloud_axes(self.fig, ax3, label, limits, top, cmap, scale)
            ax2 = self.fig.add_subplot(2, 2, k + 3)
            _section_axes(self.fig, ax2, label, limits, top, cmap, scale)
            self.panels.append((ax3, ax2, which, top, cmap, scale))
        self.title = self.fig.suptitle(' ', animated=True)
        self._background = None

    def save(self, snap: Snapshot, path: Path, title: str) -> None:
        from tissue_viz import figures

        self.title.set_text(title)
        if self._background is None:
            self.fig.tight_layout()
            self.fig.canvas.draw()
            self._background = self.fig.canvas.copy_from_bbox(self.fig.bbox)
        else:
            self.fig.canvas.restore_region(self._background)
        for ax3, ax2, which, top, cmap, scale in self.panels:
            values = getattr(snap, which)
            cloud = _cloud_artists(ax3, snap, values, top, cmap, scale, animated=True)
            # as Axes3D.draw does: project, then draw the farthest first
            for artist in sorted(cloud, key=lambda a: a.do_3d_projection(), reverse=True):
                ax3.draw_artist(artist)
            section = _section_artists(ax2, snap, self.reference or snap, values, top, cmap,
                                       scale, animated=True)
            for artist in section:
                ax2.draw_artist(artist)
            for artist in (*cloud, *section):
                artist.remove()
        self.fig.draw_artist(self.title)
        figures.write_png(figures.pixels(self.fig), path)


def draw_snapshot(snap: Snapshot, path: Path, title: str, scale_from=None,
                  reference: Snapshot | None = None) -> None:
    """One cloud, coloured by displacement [mm] (left) and von Mises stress [Pa] (right): in 3-D
    (top) and as the x-z section through the tool (bottom).

    ``scale_from``: snapshots whose range the colour scales and axes share (rest and deepest read on
    one scale); ``reference``: the cloud at rest, which picks the section's particles. Several
    snapshots on one scale are drawn faster by one :class:`SnapshotFigure`."""
    SnapshotFigure(scale_from or [snap], reference).save(snap, path, title)


def draw_animation(frames: list[Snapshot], path: Path, title: str, fps: int = 6,
                   reference: Snapshot | None = None) -> None:
    """The clouds around the deepest press as an animated GIF: the x-z section through the tool,
    coloured by displacement (a 3-D scatter per frame would take seconds each).

    The axes, ticks and colour bar are the same in every frame: they are drawn once and each frame
    draws only its particles, tool and title over a copy of them.
    """
    from PIL import Image

    from tissue_viz import figures

    limits = _limits(frames)
    dmax = _finite_max(*(s.displacement for s in frames))
    t0 = frames[0].stamp_ns
    fig = figures.new_figure((7, 4.5), 80)
    ax = fig.add_subplot(1, 1, 1)
    _section_axes(fig, ax, 'displacement [mm]', limits, dmax, 'viridis', 1e3)
    ax.title.set_animated(True)
    fig.canvas.draw()
    background = fig.canvas.copy_from_bbox(fig.bbox)
    images = []
    for snap in frames:
        fig.canvas.restore_region(background)
        artists = _section_artists(ax, snap, reference or frames[0], snap.displacement, dmax,
                                   'viridis', 1e3, animated=True)
        ax.set_title(f'{title}: t = {(snap.stamp_ns - t0) * 1e-9:.2f} s, largest displacement '
                     f'{snap.peak * 1e3:.1f} mm', fontsize=9)
        for artist in (*artists, ax.title):
            ax.draw_artist(artist)
        # fast octree, as Pillow picks for RGBA frames: its median cut of RGB takes 10 times longer
        images.append(Image.fromarray(figures.pixels(fig)).quantize(
            256, method=Image.Quantize.FASTOCTREE))
        for artist in artists:
            artist.remove()
    images[0].save(path, format='GIF', save_all=True, append_images=images[1:],
                   duration=int(1000 / fps), loop=0)
