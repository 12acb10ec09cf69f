"""PointCloud2 packing of the particle state (numpy structured arrays, no per-point Python loop).

Point layout (little endian, 24 bytes a point)::

    offset  name          type     unit
    0       x             float32  m      (tissue frame)
    4       y             float32  m
    8       z             float32  m
    12      displacement  float32  m      |x - X|
    16      von_mises     float32  Pa     von Mises stress (0 where none was computed)
    20      region        uint8    -      0 still, 1 interaction, 1 + i transmission layer i
    21..23  padding

:func:`pack_points` is pure numpy; :func:`make_cloud` fills a ``sensor_msgs/PointCloud2`` (it
imports the message type when called, so this module stays importable without ROS).
"""

from __future__ import annotations

import array

import numpy as np

POINT_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'displacement', 'von_mises', 'region'],
    'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', 'u1'],
    'offsets': [0, 4, 8, 12, 16, 20],
    'itemsize': 24,
})

# PointField datatype constants (sensor_msgs/PointField): FLOAT32 = 7, UINT8 = 2
FIELD_SPECS = (('x', 0, 7), ('y', 4, 7), ('z', 8, 7), ('displacement', 12, 7), ('von_mises', 16, 7),
               ('region', 20, 2))


def pack_points(positions: np.ndarray, displacement: np.ndarray, von_mises: np.ndarray,
                region: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Structured array of :data:`POINT_DTYPE` from per-particle arrays.

    Args:
        positions: (N, 3) [m].
        displacement: (N,) [m].
        von_mises: (N,) [Pa].
        region: (N,) integer region codes (clipped to 0..255).
        out: optional preallocated (N,) array of POINT_DTYPE to fill (avoids an allocation per frame).

    Raises:
        ValueError: inconsistent lengths.
    """
    n = len(positions)
    if positions.shape != (n, 3) or len(displacement) != n or len(von_mises) != n or len(region) != n:
        raise ValueError(f'inconsistent particle arrays: positions {positions.shape}, displacement '
                         f'{np.shape(displacement)}, von_mises {np.shape(von_mises)}, region '
                         f'{np.shape(region)}')
    if out is None or out.shape != (n,) or out.dtype != POINT_DTYPE:
        out = np.zeros(n, dtype=POINT_DTYPE)
    out['x'] = positions[:, 0]
    out['y'] = positions[:, 1]
    out['z'] = positions[:, 2]
    out['displacement'] = displacement
    out['von_mises'] = von_mises
    out['region'] = np.clip(region, 0, 255)
    return out


def unpack_points(data: bytes | bytearray | memoryview | np.ndarray, n: int) -> np.ndarray:
    """Inverse of the packing: (n,) structured array viewing the bytes of a cloud's ``data``."""
    buf = np.frombuffer(bytes(data) if not isinstance(data, np.ndarray) else data.tobytes(),
                        dtype=np.uint8)
    if len(buf) != n * POINT_DTYPE.itemsize:
        raise ValueError(f'{len(buf)} bytes is not {n} points of {POINT_DTYPE.itemsize} bytes')
    return buf.view(POINT_DTYPE)


def make_cloud(points: np.ndarray, frame_id: str, stamp=None):
    """A ``sensor_msgs/PointCloud2`` (unordered: height 1) carrying ``points`` of POINT_DTYPE."""
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    msg.height = 1
    msg.width = len(points)
    msg.fields = [PointField(name=name, offset=off, datatype=dt, count=1) for name, off, dt in FIELD_SPECS]
    msg.is_bigendian = False  # POINT_DTYPE is explicitly little endian
    msg.point_step = POINT_DTYPE.itemsize
    msg.row_step = POINT_DTYPE.itemsize * len(points)
    msg.is_dense = True
    # an array.array('B') is taken as is; bytes would be converted element by element (~30x slower)
    data = array.array('B')
    data.frombytes(points.view(np.uint8).tobytes())
    msg.data = data
    return msg
