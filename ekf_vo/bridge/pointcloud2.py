"""sensor_msgs/PointCloud2 <-> numpy (any field layout, row padding, byte order).

Fields are read by name (rclpy and rosbags classes alike; see :mod:`ekf_vo.bridge.common`).
"""
from __future__ import annotations

import numbers
from typing import Any, Mapping

import numpy as np

from .common import (INT32_MAX, ConversionError, MessageFactory, as_bytes_array, get_field,
                     get_int_field)

__all__ = ['POINTFIELD_DTYPES', 'points_to_pointcloud2', 'pointcloud2_to_numpy',
           'pointcloud2_to_xyz']

#: sensor_msgs/PointField datatype constant -> numpy dtype (no byte-order prefix).
POINTFIELD_DTYPES: dict[int, np.dtype] = {
    1: np.dtype('i1'),  # INT8
    2: np.dtype('u1'),  # UINT8
    3: np.dtype('i2'),  # INT16
    4: np.dtype('u2'),  # UINT16
    5: np.dtype('i4'),  # INT32
    6: np.dtype('u4'),  # UINT32
    7: np.dtype('f4'),  # FLOAT32
    8: np.dtype('f8'),  # FLOAT64
}
_DTYPE_TO_POINTFIELD: dict[str, int] = {
    dt.str[1:]: code for code, dt in POINTFIELD_DTYPES.items()}



def _extra_dtype(name: str, values: np.ndarray) -> np.ndarray:
    """Cast an extra-field column to a PointField dtype (rules in points_to_pointcloud2)."""
    what = 'points_to_pointcloud2'
    dt = values.dtype
    if dt.kind == 'b':
        return values.astype(np.uint8)
    if dt.kind == 'f':
        if dt.itemsize in (4, 8):
            return values
        if dt.itemsize < 4:
            return values.astype(np.float32)
    if dt.kind in 'iu':
        if dt.itemsize <= 4:
            return values
        if values.size == 0:
            return values.astype(np.uint32 if dt.kind == 'u' else np.int32)
        lo, hi = int(values.min()), int(values.max())
        if 0 <= lo and hi <= 2**32 - 1:
            return values.astype(np.uint32)
        if -2**31 <= lo and hi <= INT32_MAX:
            return values.astype(np.int32)
        raise ConversionError(
            f"{what}: extra field '{name}' values [{lo}, {hi}] do not fit 32 bits")
    raise ConversionError(f"{what}: extra field '{name}' has unsupported dtype {dt}")


def points_to_pointcloud2(xyz: np.ndarray, stamp_ns: int, frame_id: str,
                          extra_fields: Mapping[str, np.ndarray] | None = None,
                          typestore: Any = None, point_step_padding: int = 0) -> Any:
    """(N, 3) points in ``frame_id`` -> unorganised sensor_msgs/PointCloud2 (height 1, width N).

    Fields ``x, y, z`` are FLOAT32 at offsets 0, 4, 8; each ``extra_fields[name]`` (shape
    ``(N,)``) follows in insertion order, aligned to its size, keeping its dtype when it is a
    PointField type (int8/uint8/int16/uint16/int32/uint32/float32/float64); bool -> UINT8,
    float16 -> FLOAT32, 64-bit ints -> UINT32 (or INT32 if negative) when the values fit. Data
    is little-endian; ``point_step`` is the struct size (multiple of the largest field size)
    plus ``point_step_padding`` zero bytes. ``is_dense`` is False iff any xyz is NaN/inf.
    """
    what = 'points_to_pointcloud2'
    try:
        pts = np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConversionError(f'{what}: xyz is not numeric ({exc})') from None
    if pts.ndim == 1 and pts.size == 0:
        pts = pts.reshape(0, 3)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ConversionError(f'{what}: xyz has shape {pts.shape}, expected (N, 3)')
    if isinstance(point_step_padding, bool) \
            or not isinstance(point_step_padding, numbers.Integral) or point_step_padding < 0:
        raise ConversionError(
            f'{what}: point_step_padding={point_step_padding!r} must be an int >= 0')
    n = pts.shape[0]
    columns: list[tuple[str, np.ndarray]] = [('x', pts[:, 0].astype(np.float32)),
                                             ('y', pts[:, 1].astype(np.float32)),
                                             ('z', pts[:, 2].astype(np.float32))]
    for name, values in (extra_fields or {}).items():
        if not isinstance(name, str) or not name:
            raise ConversionError(f'{what}: extra field name {name!r} must be a non-empty str')
        if name in ('x', 'y', 'z') or any(name == c for c, _ in columns):
            raise ConversionError(f"{what}: extra field name '{name}' clashes with another field")
        col = np.asarray(values)
        if col.shape != (n,):
            raise ConversionError(
                f"{what}: extra field '{name}' has shape {col.shape}, expected ({n},)")
        columns.append((name, _extra_dtype(name, col)))
    names, formats, offsets = [], [], []
    offset, align = 0, 1
    for name, col in columns:
        size = col.dtype.itemsize
        offset = -(-offset // size) * size
        names.append(name)
        formats.append('<' + col.dtype.str[1:])
        offsets.append(offset)
        offset += size
        align = max(align, size)
    point_step = -(-offset // align) * align + int(point_step_padding)
    struct = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                       'itemsize': point_step})
    packed = np.zeros(n, dtype=struct)
    for name, col in columns:
        packed[name] = col
    f = MessageFactory(typestore)
    fields = [f.make('sensor_msgs/msg/PointField', name=name, offset=off,
                     datatype=_DTYPE_TO_POINTFIELD[fmt[1:]], count=1)
              for name, fmt, off in zip(names, formats, offsets)]
    return f.make('sensor_msgs/msg/PointCloud2', header=f.header(stamp_ns, frame_id), height=1,
                  width=n, fields=fields, is_bigendian=False, point_step=point_step,
                  row_step=point_step * n, data=f.u8_seq(packed.view(np.uint8).reshape(-1)),
                  is_dense=bool(np.isfinite(pts).all()))


def _field_layout(msg: Any, point_step: int, big: bool
                  ) -> tuple[list[str], list[Any], list[int], list[int]]:
    """Validated ``(names, numpy formats, offsets, counts)`` of a PointCloud2's fields."""
    what = 'PointCloud2'
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    counts: list[int] = []
    for fld in list(get_field(msg, 'fields', what) or []):
        name = get_field(fld, 'name', 'PointField')
        if not isinstance(name, str) or not name:
            raise ConversionError(f'{what}: field name {name!r} must be a non-empty str')
        if name in names:
            raise ConversionError(f"{what}: duplicate field '{name}'")
        datatype = get_int_field(fld, 'datatype', f"PointField '{name}'")
        if datatype not in POINTFIELD_DTYPES:
            raise ConversionError(f"{what}: field '{name}' has unknown datatype {datatype} (1..8)")
        offset = get_int_field(fld, 'offset', f"PointField '{name}'")
        count = get_int_field(fld, 'count', f"PointField '{name}'", minimum=1)
        base = POINTFIELD_DTYPES[datatype].newbyteorder('>' if big else '<')
        end = offset + base.itemsize * count
        if end > point_step:
            raise ConversionError(
                f"{what}: field '{name}' spans bytes [{offset}, {end}) "
                f'beyond point_step={point_step}')
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
        counts.append(count)
    return names, formats, offsets, counts


def pointcloud2_to_numpy(msg: Any, organized: bool = False,
                         copy: bool = False) -> dict[str, np.ndarray]:
    """sensor_msgs/PointCloud2 -> ``{field name: array}`` in native byte order.

    Each field is read by its ``name``/``offset``/``datatype``/``count``; ``point_step``,
    ``row_step`` (row padding), ``height`` > 1 and ``is_bigendian`` are honoured. Arrays have
    shape ``(H*W,)`` (``(H*W, count)`` when count > 1) in row-major point order, or
    ``(H, W[, count])`` with ``organized=True``. Without ``copy``, little-endian data is
    returned as strided zero-copy views into ``msg.data`` (read-only if it is ``bytes``; note
    that reshaping row-padded organised data to ``(H*W,)`` copies). Raises ConversionError on
    unknown datatypes, duplicate/empty names, fields outside ``point_step``, a too small
    ``row_step`` or truncated data.
    """
    what = 'PointCloud2'
    height = get_int_field(msg, 'height', what)
    width = get_int_field(msg, 'width', what)
    point_step = get_int_field(msg, 'point_step', what)
    row_step = get_int_field(msg, 'row_step', what)
    big = bool(get_field(msg, 'is_bigendian', what))
    names, formats, offsets, counts = _field_layout(msg, point_step, big)
    n_points = height * width
    if n_points and row_step < width * point_step:
        raise ConversionError(
            f'{what}: row_step={row_step} is smaller than width*point_step={width}*{point_step}')
    data = as_bytes_array(get_field(msg, 'data', what), what)
    if n_points and data.size < row_step * height:
        raise ConversionError(
            f'{what}: data has {data.size} bytes, expected at least '
            f'{height}*{row_step}={row_step * height} (row_step*height)')
    shape: tuple[int, ...] = (height, width)
    out: dict[str, np.ndarray] = {}
    if n_points == 0:
        for name, fmt, count in zip(names, formats, counts):
            base = fmt if count == 1 else fmt[0]
            tail = () if count == 1 else (count,)
            out[name] = np.zeros((shape if organized else (0,)) + tail,
                                 dtype=base.newbyteorder('='))
        return out
    if not names:
        return out
    try:
        struct = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                           'itemsize': point_step})
    except (TypeError, ValueError) as exc:  # defensive; layout was validated above
        raise ConversionError(f'{what}: invalid field layout ({exc})') from None
    grid = np.ndarray(shape=shape, dtype=struct, buffer=data, offset=0,
                      strides=(row_step, point_step))
    for name, count in zip(names, counts):
        col = grid[name]
        if not col.dtype.isnative:
            col = col.astype(col.dtype.newbyteorder('='))
        elif copy:
            col = col.copy()
        if not organized:
            col = col.reshape((n_points,) if count == 1 else (n_points, count))
        out[name] = col
    return out


def pointcloud2_to_xyz(msg: Any, drop_invalid: bool = False) -> np.ndarray:
    """PointCloud2 -> ``(N, 3)`` float64 xyz in the message's frame (count-1 fields x, y, z).

    ``drop_invalid=True`` removes points with a NaN/inf coordinate.
    """
    cols = pointcloud2_to_numpy(msg)
    missing = [c for c in ('x', 'y', 'z') if c not in cols]
    if missing:
        raise ConversionError(f'PointCloud2: missing field(s) {missing}; have {sorted(cols)}')
    if any(cols[c].ndim != 1 for c in 'xyz'):
        raise ConversionError('PointCloud2: x, y, z fields must have count 1')
    xyz = np.stack([cols['x'], cols['y'], cols['z']], axis=1).astype(np.float64)
    if drop_invalid:
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return xyz

