"""PointCloud2 packing of the particle state, in place and without the GIL.

Point layout (little endian, 24 bytes a point)::

    offset  name          type     unit
    0       x             float32  m      (tissue frame)
    4       y             float32  m
    8       z             float32  m
    12      displacement  float32  m      |x - X|
    16      von_mises     float32  Pa     von Mises stress (0 where none was computed)
    20      region        uint8    -      0 still, 1 interaction, 1 + i transmission layer i
    21      held          uint8    -      0 free, k + 1 held by instrument k (the order of the
                                          ``instruments`` parameter; held by two: the later's):
                                          grasped, or along its inserted needle (the track)
    22      severed       uint8    -      reference bonds the particle lost to a cut (at most 255):
                                          the cut faces
    23      padding

A particle a cut removed (:attr:`~.core.solver.Solver.removed`) is an invalid point: x, y, z are
NaN, and the cloud is then not dense (``is_dense`` False), as PointCloud2 marks missing points.

:class:`CloudBuffer` owns one message-sized byte buffer and refills it with a numba kernel that
releases the GIL: packing a 100k-particle liver (2.4 MB) then never holds up the thread that answers
the poses, and nothing is copied between the packing and ``publish``. The message type is imported
when first asked for, so this module stays importable without ROS.
"""

from __future__ import annotations

import array
import math
from typing import Sequence

import numpy as np
from numba import njit

POINT_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'displacement', 'von_mises', 'region', 'held', 'severed'],
    'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', 'u1', 'u1', 'u1'],
    'offsets': [0, 4, 8, 12, 16, 20, 21, 22],
    'itemsize': 24,
})

# PointField datatype constants (sensor_msgs/PointField): FLOAT32 = 7, UINT8 = 2
FIELD_SPECS = (('x', 0, 7), ('y', 4, 7), ('z', 8, 7), ('displacement', 12, 7), ('von_mises', 16, 7),
               ('region', 20, 2), ('held', 21, 2), ('severed', 22, 2))
REGION_BYTE, HELD_BYTE, SEVERED_BYTE = 20, 21, 22


@njit(cache=True, nogil=True)
def pack_rows(x, X, von_mises, region, held_idx, held_code, severed, removed, f32, u8):
    """Point i of the cloud from x[i], |x[i] - X[i]|, von_mises[i], region[i] and severed[i]
    (clipped to 0..255; a ``removed`` one's x, y, z NaN), then ``held`` = held_code[j] at point
    held_idx[j] (0 elsewhere; the indices are checked by the caller); ``f32`` (N, 6) and ``u8``
    (N, 24) view the same bytes (f32[:, 5] is region, held, severed and padding, never written as
    a float)."""
    for i in range(x.shape[0]):
        d0 = x[i, 0] - X[i, 0]
        d1 = x[i, 1] - X[i, 1]
        d2 = x[i, 2] - X[i, 2]
        if removed[i]:
            f32[i, 0] = math.nan
            f32[i, 1] = math.nan
            f32[i, 2] = math.nan
            f32[i, 3] = 0.0
        else:
            f32[i, 0] = x[i, 0]
            f32[i, 1] = x[i, 1]
            f32[i, 2] = x[i, 2]
            f32[i, 3] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        f32[i, 4] = von_mises[i]
        r = region[i]
        u8[i, REGION_BYTE] = 0 if r < 0 else (255 if r > 255 else r)
        u8[i, HELD_BYTE] = 0
        c = severed[i]
        u8[i, SEVERED_BYTE] = 0 if c < 0 else (255 if c > 255 else c)
    for j in range(held_idx.shape[0]):
        u8[held_idx[j], HELD_BYTE] = held_code[j]


class CloudBuffer:
    """The bytes of one PointCloud2 of ``n`` points, refilled in place by :meth:`pack`."""

    def __init__(self, n: int, frame_id: str) -> None:
        self.n = int(n)
        self.frame_id = frame_id
        # an array.array('B') is what the message's uint8[] field takes without converting element
        # by element; the numpy views write straight into it
        self._bind(array.array('B', bytes(self.n * POINT_DTYPE.itemsize)))
        self._msg = None
        self._uncut = np.zeros(self.n, dtype=np.int32)     # no cut: nothing severed, nothing removed
        self._whole = np.zeros(self.n, dtype=np.bool_)
        self._dense = True

    def _bind(self, data: array.array) -> None:
        self.data = data
        raw = np.frombuffer(data, dtype=np.uint8)
        self._u8 = raw.reshape(self.n, POINT_DTYPE.itemsize)
        self._f32 = raw.view('<f4').reshape(self.n, POINT_DTYPE.itemsize // 4)
        self.points = raw.view(POINT_DTYPE)

    def pack(self, x: np.ndarray, X: np.ndarray, von_mises: np.ndarray, region: np.ndarray,
             held: Sequence[np.ndarray] = (), severed: np.ndarray | None = None,
             removed: np.ndarray | None = None) -> np.ndarray:
        """Fill the points from positions ``x`` and reference positions ``X`` ((N, 3) [m]), von Mises
        stress (N,) [Pa], region codes (N,), ``held``: per instrument k the indices of the
        particles it holds (``held`` k + 1 there, 0 elsewhere), the bonds each particle lost to a
        cut ``severed`` (N,) and the particles a cut ``removed`` (N,) bool (None: no cut); returns
        them as an (N,) array of POINT_DTYPE (a view of the buffer, current until the next
        :meth:`message`).

        Raises:
            ValueError: arrays of another length than the buffer's, more than 255 instruments or a
                held index outside the cloud.
        """
        n = self.n
        severed = self._uncut if severed is None else severed
        removed = self._whole if removed is None else removed
        if (np.shape(x) != (n, 3) or np.shape(X) != (n, 3) or np.shape(von_mises) != (n,)
                or np.shape(region) != (n,) or np.shape(severed) != (n,) or np.shape(removed) != (n,)):
            raise ValueError(f'particle arrays do not match a cloud of {n} points: x {np.shape(x)}, '
                             f'X {np.shape(X)}, von_mises {np.shape(von_mises)}, region '
                             f'{np.shape(region)}')
        if len(held) > 255:
            raise ValueError(f'{len(held)} instruments do not fit the held byte (at most 255)')
        idx = np.concatenate([np.asarray(h, dtype=np.int64).ravel() for h in held] or [np.zeros(0, np.int64)])
        code = np.repeat(np.arange(1, len(held) + 1, dtype=np.uint8), [np.size(h) for h in held])
        # the kernel writes where the indices say: they are checked here, once per cloud
        if idx.size and not (0 <= idx.min() and idx.max() < n):
            raise ValueError(f'held particle indices must lie in [0, {n}), got {idx.min()} to {idx.max()}')
        pack_rows(x, X, von_mises, region, idx, code, severed, removed, self._f32, self._u8)
        self._dense = not removed.any()
        return self.points

    def message(self, stamp=None):
        """The ``sensor_msgs/PointCloud2`` (unordered: height 1) over the buffer, with ``stamp``."""
        if self._msg is None:
            from sensor_msgs.msg import PointCloud2, PointField

            msg = PointCloud2()
            msg.header.frame_id = self.frame_id
            msg.height = 1
            msg.width = self.n
            msg.fields = [PointField(name=name, offset=off, datatype=dt, count=1)
                          for name, off, dt in FIELD_SPECS]
            msg.is_bigendian = False  # POINT_DTYPE is explicitly little endian
            msg.point_step = POINT_DTYPE.itemsize
            msg.row_step = POINT_DTYPE.itemsize * self.n
            msg.is_dense = True
            msg.data = self.data
            # the field setter keeps a copy unless ROS_PYTHON_CHECK_FIELDS=1: pack into the array the
            # message holds from now on
            self._bind(msg.data)
            self._msg = msg
        self._msg.is_dense = self._dense
        if stamp is not None:
            self._msg.header.stamp = stamp
        return self._msg


def unpack_points(data: bytes | bytearray | memoryview | np.ndarray, n: int) -> np.ndarray:
    """Inverse of the packing: (n,) structured array viewing the bytes of a cloud's ``data``."""
    buf = np.frombuffer(bytes(data) if not isinstance(data, np.ndarray) else data.tobytes(),
                        dtype=np.uint8)
    if len(buf) != n * POINT_DTYPE.itemsize:
        raise ValueError(f'{len(buf)} bytes is not {n} points of {POINT_DTYPE.itemsize} bytes')
    return buf.view(POINT_DTYPE)
