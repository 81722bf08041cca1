"""Conversions between ROS 2 messages and numpy arrays (no cv_bridge, no sensor_msgs_py, no tf2).

Every reader accesses message fields *by name* (duck typing), so the same function works on

* rclpy message classes (``sensor_msgs.msg.Image`` ...; ``uint8[]`` fields are ``array.array('B')``
  or ``bytes``, ``float64[]`` fields are ``array.array('d')``, fixed arrays are numpy arrays), and
* rosbags typestore classes (``typestore.types['sensor_msgs/msg/Image']``; array fields are numpy
  arrays).

Every builder takes an optional ``typestore``: ``None`` builds rclpy messages (the message
modules are imported lazily, inside the builder), anything else is used as a rosbags typestore
(only its ``types`` mapping is used), so the result can be written to a bag with
``typestore.serialize_cdr(msg, msg.__msgtype__)``. This module never imports rosbags.

Conventions
-----------
* Time stamps are integer nanoseconds since the epoch (``stamp_ns``), always >= 0 and with a
  seconds part that fits the int32 ``builtin_interfaces/Time.sec`` field.
* Images are ``(H, W)`` for single-channel encodings and ``(H, W, C)`` otherwise, in the channel
  order of the encoding (``rgb8`` -> R, G, B). Pixel ``[v, u]`` is row ``v``, column ``u``.
* Poses are 4x4 homogeneous transforms ``T_parent_child`` (maps points from the child frame to the
  parent frame). Quaternions are ``(x, y, z, w)`` (ROS order), unit norm, ``w >= 0``.
* 6x6 covariances are in ROS order ``(x, y, z, rot X, rot Y, rot Z)``, serialised row-major.

There is no estimator logic here; invalid input raises :class:`ConversionError` (a ``ValueError``)
with a one-line message that names the message type and the offending field.
"""
from __future__ import annotations

import array
import importlib
import logging
import math
import numbers
from typing import Any, Mapping

import cv2
import numpy as np

from ..core import geometry as geo

logger = logging.getLogger(__name__)

__all__ = [
    'ConversionError',
    'IMAGE_ENCODINGS',
    'DISTORTION_MODELS',
    'image_to_numpy',
    'image_to_gray',
    'compressed_to_gray',
    'numpy_to_image',
    'numpy_to_compressed',
    'camera_info_to_dict',
    'validate_camera_info',
    'camera_info_from_params',
    'stamp_to_ns',
    'ns_to_stamp',
    'points_to_pointcloud2',
    'pointcloud2_to_numpy',
    'pointcloud2_to_xyz',
    'quat_xyzw_to_matrix',
    'matrix_to_quat_xyzw',
    'pose_to_odometry',
    'odometry_to_pose',
    'pose_stamped_to_matrix',
    'matrix_to_pose_stamped',
    'transform_pose_covariance',
]


class ConversionError(ValueError):
    """A message or array cannot be converted (malformed, inconsistent or unsupported)."""


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------

#: encoding -> (unsigned dtype letter + itemsize, channels). 16-bit byte order comes from
#: ``is_bigendian``. ``8UC3``/``8UC4`` are treated as BGR/BGRA (OpenCV convention) by
#: :func:`image_to_gray`.
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    'mono8': ('u1', 1),
    'mono16': ('u2', 1),
    'rgb8': ('u1', 3),
    'bgr8': ('u1', 3),
    'rgba8': ('u1', 4),
    'bgra8': ('u1', 4),
    '8UC1': ('u1', 1),
    '8UC3': ('u1', 3),
    '8UC4': ('u1', 4),
    '16UC1': ('u2', 1),
}

#: encoding -> cv2 colour conversion code to 8-bit gray (None: already single channel).
_GRAY_CODES: dict[str, int | None] = {
    'mono8': None,
    'mono16': None,
    '8UC1': None,
    '16UC1': None,
    'rgb8': cv2.COLOR_RGB2GRAY,
    'bgr8': cv2.COLOR_BGR2GRAY,
    '8UC3': cv2.COLOR_BGR2GRAY,
    'rgba8': cv2.COLOR_RGBA2GRAY,
    'bgra8': cv2.COLOR_BGRA2GRAY,
    '8UC4': cv2.COLOR_BGRA2GRAY,
}

#: distortion model -> allowed lengths of D (REP-104; ``rational_polynomial`` also accepts the
#: 5 coefficients it shares with ``plumb_bob``). ``''``/``'none'`` require an all-zero D.
DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    'plumb_bob': (5,),
    'rational_polynomial': (8, 5),
    'equidistant': (4,),
}
_NO_DISTORTION = ('', 'none')

#: sensor_msgs/PointField datatype constant -> numpy dtype (no byte-order prefix).
_POINTFIELD_DTYPES: dict[int, np.dtype] = {
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
    dt.str[1:]: code for code, dt in _POINTFIELD_DTYPES.items()}

_INT32_MAX = 2**31 - 1
_NS_PER_S = 1_000_000_000


# --------------------------------------------------------------------------------------------
# Generic helpers
# --------------------------------------------------------------------------------------------

def _field(msg: Any, name: str, what: str, *alternatives: str) -> Any:
    """Return ``msg.<name>`` (or the first present alternative name); ConversionError if absent."""
    for n in (name, *alternatives):
        try:
            return getattr(msg, n)
        except AttributeError:
            continue
    raise ConversionError(f"{what}: message of type {type(msg).__name__} has no field '{name}'")


def _int_field(msg: Any, name: str, what: str, minimum: int = 0) -> int:
    """Read an integer field and check ``value >= minimum``."""
    value = _field(msg, name, what)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ConversionError(f'{what}: field {name}={value!r} is not an integer')
    value = int(value)
    if value < minimum:
        raise ConversionError(f'{what}: field {name}={value} must be >= {minimum}')
    return value


def _as_bytes_array(data: Any, what: str) -> np.ndarray:
    """View a ``uint8[]`` message field as a 1-D ``uint8`` numpy array, without Python loops.

    Accepts bytes/bytearray/memoryview, ``array.array`` ('B' or 'b'), numpy arrays (any integer
    dtype with values in [0, 255]) and lists/tuples of ints. Shares memory with ``data`` when it
    is a buffer (read-only for ``bytes``).
    """
    if data is None:
        raise ConversionError(f'{what}: data is None')
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8:
            return data.reshape(-1)
        if data.dtype == np.int8:
            return data.reshape(-1).view(np.uint8)
        return _checked_uint8(data, what)
    if isinstance(data, array.array):
        if data.typecode not in ('B', 'b'):
            raise ConversionError(
                f"{what}: data is array.array of typecode '{data.typecode}', expected 'B'")
        return np.frombuffer(data, dtype=np.uint8) if len(data) else np.zeros(0, np.uint8)
    if isinstance(data, (bytes, bytearray)):
        return np.frombuffer(data, dtype=np.uint8) if len(data) else np.zeros(0, np.uint8)
    if isinstance(data, memoryview):
        try:
            return np.frombuffer(data.cast('B'), dtype=np.uint8)
        except (TypeError, ValueError) as exc:
            raise ConversionError(
                f'{what}: data memoryview is not a byte buffer ({exc})') from None
    if isinstance(data, str):
        raise ConversionError(f'{what}: data is a str, expected bytes')
    if isinstance(data, (list, tuple)):
        if not data:
            return np.zeros(0, np.uint8)
        try:
            arr = np.asarray(data)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ConversionError(f'{what}: data list is not a list of bytes ({exc})') from None
        return _checked_uint8(arr, what)
    raise ConversionError(f'{what}: unsupported data container {type(data).__name__}')


def _checked_uint8(arr: np.ndarray, what: str) -> np.ndarray:
    if arr.size == 0:
        return np.zeros(0, np.uint8)
    if arr.dtype.kind not in 'iub':
        raise ConversionError(f'{what}: data has dtype {arr.dtype}, expected uint8 values')
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi > 255:
        raise ConversionError(f'{what}: data values span [{lo}, {hi}], expected [0, 255]')
    return arr.reshape(-1).astype(np.uint8)


def _as_float_array(values: Any, what: str, name: str, shape: tuple[int, ...] | None = None,
                    finite: bool = True) -> np.ndarray:
    """``np.asarray(values, float64)`` with shape and finiteness checks -> ConversionError."""
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConversionError(f'{what}: {name} is not numeric ({exc})') from None
    if shape is not None and arr.shape != shape:
        if arr.size == math.prod(shape) and arr.ndim <= 1:
            arr = arr.reshape(shape)
        else:
            raise ConversionError(f'{what}: {name} has shape {arr.shape}, expected {shape}')
    if finite and not np.isfinite(arr).all():
        raise ConversionError(f'{what}: {name} contains NaN or inf')
    return arr


class _Factory:
    """Build messages from rclpy classes (typestore None) or from a rosbags typestore.

    Also adapts array-valued fields to what each backend expects: rclpy wants
    ``array.array`` for unbounded sequences (its setters otherwise loop in Python) and float64
    numpy arrays for fixed-size arrays; rosbags wants numpy arrays everywhere.
    """

    def __init__(self, typestore: Any = None) -> None:
        self.typestore = typestore

    def cls(self, msgtype: str) -> Any:
        """Message class for ``'pkg/msg/Name'``."""
        if self.typestore is None:
            pkg, _, name = msgtype.split('/')
            return getattr(importlib.import_module(f'{pkg}.msg'), name)
        try:
            return self.typestore.types[msgtype]
        except (AttributeError, KeyError):
            raise ConversionError(f'typestore does not provide {msgtype}') from None

    def make(self, msgtype: str, **fields: Any) -> Any:
        return self.cls(msgtype)(**fields)

    def u8_seq(self, flat: np.ndarray) -> Any:
        flat = np.ascontiguousarray(flat, dtype=np.uint8).reshape(-1)
        if self.typestore is None:
            return array.array('B', flat.tobytes())
        return flat.copy()

    def f64_seq(self, values: np.ndarray) -> Any:
        values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if self.typestore is None:
            return array.array('d', values.tobytes())
        return values.copy()

    @staticmethod
    def f64_fixed(values: np.ndarray) -> np.ndarray:
        return np.array(values, dtype=np.float64).reshape(-1)

    def time(self, stamp_ns: int) -> Any:
        sec, nanosec = _split_ns(stamp_ns)
        return self.make('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        if not isinstance(frame_id, str):
            raise ConversionError(f'frame_id must be a str, got {type(frame_id).__name__}')
        return self.make('std_msgs/msg/Header', stamp=self.time(stamp_ns), frame_id=frame_id)


# --------------------------------------------------------------------------------------------
# Time
# --------------------------------------------------------------------------------------------

def _split_ns(ns: Any) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) for builtin_interfaces/Time (sec int32, >= 0)."""
    if isinstance(ns, (bool, np.bool_)) or not isinstance(ns, numbers.Integral):
        raise ConversionError(f'stamp_ns must be an integer number of nanoseconds, got {ns!r}')
    ns = int(ns)
    if ns < 0:
        raise ConversionError(f'stamp_ns={ns} is negative; ROS stamps must be >= 0')
    sec, nanosec = divmod(ns, _NS_PER_S)
    if sec > _INT32_MAX:
        raise ConversionError(
            f'stamp_ns={ns} overflows builtin_interfaces/Time.sec (int32, max {_INT32_MAX} s)')
    return sec, nanosec


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (fields ``sec``, ``nanosec``) -> integer nanoseconds (>= 0).

    Raises ConversionError for non-integer fields, negative ``sec`` or ``nanosec`` outside
    ``[0, 1e9)``.
    """
    sec = _int_field(stamp, 'sec', 'Time', minimum=0)
    nanosec = _int_field(stamp, 'nanosec', 'Time', minimum=0)
    if nanosec >= _NS_PER_S:
        raise ConversionError(f'Time: nanosec={nanosec} must be < 1e9')
    return sec * _NS_PER_S + nanosec


def ns_to_stamp(ns: int, typestore: Any = None) -> Any:
    """Integer nanoseconds -> builtin_interfaces/Time (rclpy class, or rosbags if typestore).

    Raises ConversionError for non-integers, negative values and values whose seconds part
    exceeds int32 (year 2038).
    """
    return _Factory(typestore).time(ns)


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------

def _image_layout(msg: Any) -> tuple[str, int, int, int, np.dtype, int, np.ndarray]:
    """Validate an Image message; return (encoding, height, width, step, dtype, channels, data)."""
    what = 'Image'
    encoding = _field(msg, 'encoding', what)
    if not isinstance(encoding, str):
        raise ConversionError(f'{what}: encoding {encoding!r} is not a str')
    encoding = encoding.strip()
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"{what}: unsupported encoding '{encoding}' (supported: {', '.join(IMAGE_ENCODINGS)})")
    height = _int_field(msg, 'height', what, minimum=0)
    width = _int_field(msg, 'width', what, minimum=0)
    if height == 0 or width == 0:
        raise ConversionError(
            f'{what}: empty image ({height}x{width}); height and width must be > 0')
    step = _int_field(msg, 'step', what, minimum=0)
    kind, channels = IMAGE_ENCODINGS[encoding]
    big = bool(_field(msg, 'is_bigendian', what))
    dtype = np.dtype(('>' if big else '<') + kind)
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ConversionError(
            f'{what}: step={step} is smaller than width*channels*bytes='
            f'{width}*{channels}*{dtype.itemsize}={row_bytes} for {encoding}')
    data = _as_bytes_array(_field(msg, 'data', what), what)
    if data.size < step * height:
        raise ConversionError(
            f'{what}: data has {data.size} bytes, expected at least '
            f'{height}*{step}={step * height} (step*height)')
    return encoding, height, width, step, dtype, channels, data


def image_to_numpy(msg: Any, copy: bool = True) -> np.ndarray:
    """sensor_msgs/Image -> numpy array in native byte order.

    Shape ``(H, W)`` for 1-channel encodings (mono8, mono16, 8UC1, 16UC1), ``(H, W, C)`` for
    rgb8/bgr8/8UC3 (C=3) and rgba8/bgra8/8UC4 (C=4), channels in the encoding's order; dtype
    ``uint8`` or ``uint16``. Row padding (``step`` > row bytes) is skipped and ``is_bigendian``
    is honoured for 16-bit encodings. ``msg.data`` may be bytes, array.array, list or a numpy
    array.

    With ``copy=True`` (default) the result is a fresh C-contiguous writable array. With
    ``copy=False`` it may be a (strided, possibly read-only) view into ``msg.data``.

    Raises ConversionError on unknown encoding, empty size, too-small step or truncated data.
    """
    _, height, width, step, dtype, channels, data = _image_layout(msg)
    shape: tuple[int, ...] = (height, width) if channels == 1 else (height, width, channels)
    strides: tuple[int, ...] = (step, channels * dtype.itemsize)
    if channels > 1:
        strides = strides + (dtype.itemsize,)
    view = np.ndarray(shape=shape, dtype=dtype, buffer=data, offset=0, strides=strides)
    native = dtype.newbyteorder('=')
    if dtype != native:
        return view.astype(native)  # byte swap (always a copy)
    if copy:
        return np.array(view, dtype=native, order='C', copy=True)
    return view


def image_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/Image (any supported encoding) -> ``uint8`` gray image of shape ``(H, W)``.

    Colour is converted with OpenCV's BT.601 weights (``cv2.COLOR_RGB2GRAY`` for rgb8,
    ``BGR2GRAY`` for bgr8/8UC3, ``RGBA2GRAY`` for rgba8, ``BGRA2GRAY`` for bgra8/8UC4).
    16-bit mono is reduced to its high byte (``value >> 8``), a fixed scale (not
    max-normalised), so brightness is consistent across frames. The result never aliases
    ``msg.data``.
    """
    encoding = _image_layout(msg)[0]
    img = image_to_numpy(msg, copy=False)
    code = _GRAY_CODES[encoding]
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    if code is None:
        return np.array(img, dtype=np.uint8, order='C', copy=True)
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def numpy_to_image(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, *,
                   step_padding: int = 0, typestore: Any = None,
                   is_bigendian: bool = False) -> Any:
    """numpy array -> sensor_msgs/Image (rclpy class, or rosbags class if ``typestore``).

    ``array`` must be ``(H, W)`` (or ``(H, W, 1)``) for 1-channel encodings and ``(H, W, C)``
    otherwise, dtype uint8 for 8-bit and uint16 for 16-bit encodings, channels already in the
    order the encoding names. ``step_padding`` extra zero bytes are appended to each row
    (``step = W*C*bytes + step_padding``; useful to test readers). ``is_bigendian`` selects the
    byte order of 16-bit data.
    """
    what = 'numpy_to_image'
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"{what}: unsupported encoding '{encoding}' (supported: {', '.join(IMAGE_ENCODINGS)})")
    if isinstance(step_padding, bool) or not isinstance(step_padding, numbers.Integral) \
            or step_padding < 0:
        raise ConversionError(f'{what}: step_padding={step_padding!r} must be an int >= 0')
    kind, channels = IMAGE_ENCODINGS[encoding]
    arr = np.asarray(array)
    if arr.ndim == 3 and channels == 1 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    expected_ndim = 2 if channels == 1 else 3
    if arr.ndim != expected_ndim or (channels > 1 and arr.shape[2] != channels):
        want = '(H, W)' if channels == 1 else f'(H, W, {channels})'
        raise ConversionError(
            f'{what}: array shape {arr.shape} does not fit {encoding}, expected {want}')
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ConversionError(f'{what}: empty array of shape {arr.shape}')
    if arr.dtype.kind != 'u' or arr.dtype.itemsize != int(kind[1]):
        raise ConversionError(f'{what}: dtype {arr.dtype} does not fit {encoding}, '
                              f'expected uint{8 * int(kind[1])}')
    height, width = int(arr.shape[0]), int(arr.shape[1])
    out_dtype = np.dtype(('>' if is_bigendian else '<') + kind)
    row_bytes = width * channels * out_dtype.itemsize
    rows = np.ascontiguousarray(arr, dtype=out_dtype).view(np.uint8).reshape(height, row_bytes)
    step = row_bytes + int(step_padding)
    if step_padding:
        padded = np.zeros((height, step), dtype=np.uint8)
        padded[:, :row_bytes] = rows
        rows = padded
    f = _Factory(typestore)
    return f.make('sensor_msgs/msg/Image', header=f.header(stamp_ns, frame_id), height=height,
                  width=width, encoding=encoding,
                  is_bigendian=1 if (is_bigendian and out_dtype.itemsize > 1) else 0,
                  step=step, data=f.u8_seq(rows))


def compressed_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg/png, any colour) -> ``uint8`` gray image ``(H, W)``.

    ``format`` is only checked for the unsupported ``compressedDepth`` variant; the codec is
    recognised from the data. The image is decoded as stored (``IMREAD_UNCHANGED``: no EXIF
    rotation) and reduced to gray exactly like :func:`image_to_gray` (``BGR2GRAY``/``BGRA2GRAY``,
    16-bit -> high byte), so a PNG frame gives the same pixels as the raw Image it came from.
    Raises ConversionError on empty or undecodable data.
    """
    what = 'CompressedImage'
    fmt = getattr(msg, 'format', '') or ''
    if 'compresseddepth' in str(fmt).lower():
        raise ConversionError(f"{what}: format '{fmt}' (compressedDepth) is not supported")
    data = _as_bytes_array(_field(msg, 'data', what), what)
    if data.size == 0:
        raise ConversionError(f"{what}: data is empty (format '{fmt}')")
    try:
        img = cv2.imdecode(np.ascontiguousarray(data), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise ConversionError(
            f"{what}: OpenCV failed to decode {data.size} bytes (format '{fmt}'): {detail}"
        ) from None
    if img is None or img.size == 0:
        raise ConversionError(f"{what}: could not decode {data.size} bytes (format '{fmt}')")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ConversionError(f'{what}: decoded image has unsupported depth {img.dtype}')
    if img.ndim == 2:
        return img
    code = {1: None, 3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(img.shape[2], -1)
    if code == -1:
        raise ConversionError(
            f'{what}: decoded image has unsupported channel count {img.shape[2]}')
    return np.ascontiguousarray(img[:, :, 0]) if code is None else cv2.cvtColor(img, code)


def numpy_to_compressed(image: np.ndarray, fmt: str, stamp_ns: int, frame_id: str,
                        typestore: Any = None, *, jpeg_quality: int = 95,
                        png_compression: int = 3) -> Any:
    """Gray ``(H, W)`` / BGR ``(H, W, 3)`` array -> sensor_msgs/CompressedImage.

    ``fmt`` is ``'jpeg'`` (alias ``'jpg'``; uint8 only, lossy) or ``'png'`` (uint8 or uint16
    gray, lossless). The ``format`` field follows image_transport, e.g.
    ``'bgr8; jpeg compressed bgr8'``.
    """
    what = 'numpy_to_compressed'
    fmt_l = str(fmt).lower()
    if fmt_l == 'jpg':
        fmt_l = 'jpeg'
    if fmt_l not in ('jpeg', 'png'):
        raise ConversionError(f"{what}: format '{fmt}' not supported (use 'jpeg' or 'png')")
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) or 0 in img.shape:
        raise ConversionError(f'{what}: image shape {img.shape} is not (H, W) or (H, W, 3)')
    if img.dtype == np.uint16 and img.ndim == 2 and fmt_l == 'png':
        encoding = 'mono16'
    elif img.dtype == np.uint8:
        encoding = 'mono8' if img.ndim == 2 else 'bgr8'
    else:
        raise ConversionError(f'{what}: dtype {img.dtype} not supported for {fmt_l} '
                              '(uint8, or uint16 gray for png)')
    if fmt_l == 'jpeg':
        ok, buf = cv2.imencode('.jpg', np.ascontiguousarray(img),
                               [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        ok, buf = cv2.imencode('.png', np.ascontiguousarray(img),
                               [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)])
    if not ok:
        raise ConversionError(
            f'{what}: OpenCV failed to encode {img.shape} {img.dtype} as {fmt_l}')
    f = _Factory(typestore)
    return f.make('sensor_msgs/msg/CompressedImage', header=f.header(stamp_ns, frame_id),
                  format=f'{encoding}; {fmt_l} compressed {encoding}',
                  data=f.u8_seq(buf.reshape(-1)))


# --------------------------------------------------------------------------------------------
# CameraInfo
# --------------------------------------------------------------------------------------------

def camera_info_to_dict(msg: Any) -> dict[str, Any]:
    """sensor_msgs/CameraInfo -> plain dict (no validation beyond array sizes).

    Keys: ``width``, ``height`` (int), ``K`` (3x3), ``D`` (1-D), ``distortion_model`` (str),
    ``R`` (3x3), ``P`` (3x4) (float64 arrays, copies), ``binning_x``, ``binning_y`` (int),
    ``roi`` (dict x_offset, y_offset, width, height, do_rectify), ``frame_id`` (str) and
    ``stamp_ns`` (int, or None when the header stamp is invalid). Reads the lower-case rclpy /
    rosbags field names ``k, d, r, p`` and falls back to the ROS 1 upper-case ``K, D, R, P``.
    Pass the result to :func:`validate_camera_info` before using it.
    """
    what = 'CameraInfo'
    K = _as_float_array(_field(msg, 'k', what, 'K'), what, 'K', (3, 3), finite=False)
    D = _as_float_array(_field(msg, 'd', what, 'D'), what, 'D', finite=False).reshape(-1)
    R = _as_float_array(_field(msg, 'r', what, 'R'), what, 'R', (3, 3), finite=False)
    P = _as_float_array(_field(msg, 'p', what, 'P'), what, 'P', (3, 4), finite=False)
    roi_msg = getattr(msg, 'roi', None)
    roi = {
        'x_offset': int(getattr(roi_msg, 'x_offset', 0)),
        'y_offset': int(getattr(roi_msg, 'y_offset', 0)),
        'width': int(getattr(roi_msg, 'width', 0)),
        'height': int(getattr(roi_msg, 'height', 0)),
        'do_rectify': bool(getattr(roi_msg, 'do_rectify', False)),
    }
    header = getattr(msg, 'header', None)
    stamp_ns: int | None = None
    if header is not None and getattr(header, 'stamp', None) is not None:
        try:
            stamp_ns = stamp_to_ns(header.stamp)
        except ConversionError:
            stamp_ns = None
    model = _field(msg, 'distortion_model', what)
    return {
        'width': _int_field(msg, 'width', what),
        'height': _int_field(msg, 'height', what),
        'K': K,
        'D': D,
        'distortion_model': str(model),
        'R': R,
        'P': P,
        'binning_x': int(getattr(msg, 'binning_x', 0)),
        'binning_y': int(getattr(msg, 'binning_y', 0)),
        'roi': roi,
        'frame_id': str(getattr(header, 'frame_id', '')) if header is not None else '',
        'stamp_ns': stamp_ns,
    }


def validate_camera_info(info: Mapping[str, Any]) -> None:
    """Raise ConversionError unless ``info`` (as from :func:`camera_info_to_dict`) is usable.

    Checks: width/height > 0; K is 3x3 and finite with K[0,0] != 0 (all-zero K means an
    uncalibrated camera), fx, fy > 0 and last row (0, 0, 1); D and P (and R if present) finite;
    ``distortion_model`` one of plumb_bob (5 coefficients), rational_polynomial (8, or 5),
    equidistant (4), or ''/'none' with an all-zero D.
    """
    what = 'CameraInfo'
    for key in ('width', 'height'):
        value = info.get(key)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
            raise ConversionError(f'{what}: {key}={value!r} must be a positive integer')
    K = _as_float_array(info.get('K'), what, 'K', (3, 3), finite=False)
    if not np.isfinite(K).all():
        raise ConversionError(f'{what}: K contains NaN or inf: {K.reshape(-1).tolist()}')
    if K[0, 0] == 0.0:
        raise ConversionError(f'{what}: K[0] (fx) is 0, the camera is uncalibrated')
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ConversionError(
            f'{what}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}')
    if not np.allclose(K[2], (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
        raise ConversionError(
            f'{what}: K must be upper triangular with last row (0, 0, 1), got {K.tolist()}')
    D = _as_float_array(info.get('D', ()), what, 'D', finite=False).reshape(-1)
    if not np.isfinite(D).all():
        raise ConversionError(f'{what}: D contains NaN or inf: {D.tolist()}')
    P = _as_float_array(info.get('P', np.zeros((3, 4))), what, 'P', (3, 4), finite=False)
    if not np.isfinite(P).all():
        raise ConversionError(f'{what}: P contains NaN or inf')
    if info.get('R') is not None:
        _as_float_array(info['R'], what, 'R', (3, 3))
    model = info.get('distortion_model', '')
    if not isinstance(model, str):
        raise ConversionError(f'{what}: distortion_model {model!r} is not a str')
    if model in _NO_DISTORTION:
        if np.any(D != 0.0):
            raise ConversionError(
                f"{what}: distortion_model '{model}' requires D to be all zero, got {D.tolist()}")
        return
    if model not in DISTORTION_MODELS:
        raise ConversionError(
            f"{what}: unknown distortion_model '{model}' "
            f"(allowed: {', '.join(DISTORTION_MODELS)}, '' or 'none')")
    lengths = DISTORTION_MODELS[model]
    if D.size not in lengths:
        raise ConversionError(
            f"{what}: distortion_model '{model}' needs {' or '.join(map(str, lengths))} "
            f'coefficients in D, got {D.size}')
    if model == 'rational_polynomial' and D.size == 5:
        logger.debug('CameraInfo: rational_polynomial with 5 coefficients (same as plumb_bob)')


def camera_info_from_params(width: int, height: int, K: np.ndarray, D: Any,
                            distortion_model: str, stamp_ns: int, frame_id: str,
                            typestore: Any = None) -> Any:
    """Build a sensor_msgs/CameraInfo for an unrectified monocular camera.

    ``K`` is the 3x3 intrinsic matrix (pixels), ``D`` the distortion coefficients of
    ``distortion_model``. R = I and P = [K | 0] (no rectification, no stereo baseline); binning
    and ROI are zero. The parameters are validated first (see :func:`validate_camera_info`).
    """
    what = 'camera_info_from_params'
    K = _as_float_array(K, what, 'K', (3, 3), finite=False)
    D = _as_float_array(D, what, 'D', finite=False).reshape(-1)
    P = np.hstack([K, np.zeros((3, 1))])
    validate_camera_info({'width': width, 'height': height, 'K': K, 'D': D, 'P': P,
                          'R': np.eye(3), 'distortion_model': distortion_model})
    f = _Factory(typestore)
    roi = f.make('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0, width=0,
                 do_rectify=False)
    return f.make('sensor_msgs/msg/CameraInfo', header=f.header(stamp_ns, frame_id),
                  height=int(height), width=int(width), distortion_model=distortion_model,
                  d=f.f64_seq(D), k=f.f64_fixed(K), r=f.f64_fixed(np.eye(3)),
                  p=f.f64_fixed(P), binning_x=0, binning_y=0, roi=roi)


# --------------------------------------------------------------------------------------------
# PointCloud2
# --------------------------------------------------------------------------------------------

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
        if -2**31 <= lo and hi <= _INT32_MAX:
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
    f = _Factory(typestore)
    fields = [f.make('sensor_msgs/msg/PointField', name=name, offset=off,
                     datatype=_DTYPE_TO_POINTFIELD[fmt[1:]], count=1)
              for name, fmt, off in zip(names, formats, offsets)]
    return f.make('sensor_msgs/msg/PointCloud2', header=f.header(stamp_ns, frame_id), height=1,
                  width=n, fields=fields, is_bigendian=False, point_step=point_step,
                  row_step=point_step * n, data=f.u8_seq(packed.view(np.uint8).reshape(-1)),
                  is_dense=bool(np.isfinite(pts).all()))


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
    height = _int_field(msg, 'height', what)
    width = _int_field(msg, 'width', what)
    point_step = _int_field(msg, 'point_step', what)
    row_step = _int_field(msg, 'row_step', what)
    big = bool(_field(msg, 'is_bigendian', what))
    fields = list(_field(msg, 'fields', what) or [])
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    counts: list[int] = []
    for fld in fields:
        name = _field(fld, 'name', 'PointField')
        if not isinstance(name, str) or not name:
            raise ConversionError(f'{what}: field name {name!r} must be a non-empty str')
        if name in names:
            raise ConversionError(f"{what}: duplicate field '{name}'")
        datatype = _int_field(fld, 'datatype', f"PointField '{name}'")
        if datatype not in _POINTFIELD_DTYPES:
            raise ConversionError(f"{what}: field '{name}' has unknown datatype {datatype} (1..8)")
        offset = _int_field(fld, 'offset', f"PointField '{name}'")
        count = _int_field(fld, 'count', f"PointField '{name}'", minimum=1)
        base = _POINTFIELD_DTYPES[datatype].newbyteorder('>' if big else '<')
        end = offset + base.itemsize * count
        if end > point_step:
            raise ConversionError(
                f"{what}: field '{name}' spans bytes [{offset}, {end}) "
                f'beyond point_step={point_step}')
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
        counts.append(count)
    n_points = height * width
    if n_points and row_step < width * point_step:
        raise ConversionError(
            f'{what}: row_step={row_step} is smaller than width*point_step={width}*{point_step}')
    data = _as_bytes_array(_field(msg, 'data', what), what)
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


# --------------------------------------------------------------------------------------------
# Rotations, poses, odometry
# --------------------------------------------------------------------------------------------

def quat_xyzw_to_matrix(q: Any) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` -> 3x3 rotation matrix (normalised first).

    Raises ConversionError for non-finite or (near-)zero quaternions.
    """
    qa = _as_float_array(q, 'quat_xyzw_to_matrix', 'quaternion', (4,))
    if float(np.linalg.norm(qa)) < 1e-12:
        raise ConversionError(f'quat_xyzw_to_matrix: quaternion {qa.tolist()} has zero norm')
    return geo.quat_to_matrix(geo.quat_xyzw_to_wxyz(qa))


def _check_rotation(R: Any, what: str, tol: float = 1e-6) -> np.ndarray:
    Ra = _as_float_array(R, what, 'rotation', (3, 3))
    err = float(np.abs(Ra.T @ Ra - np.eye(3)).max())
    if err > tol or np.linalg.det(Ra) <= 0:
        raise ConversionError(
            f'{what}: not a rotation matrix '
            f'(|R^T R - I|max={err:.2e}, det={np.linalg.det(Ra):.6f})')
    return Ra


def matrix_to_quat_xyzw(R: Any, tol: float = 1e-6) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion ``(x, y, z, w)`` with ``w >= 0``.

    Computed by core.geometry.matrix_to_quat (Shepperd's method, accurate near 180 degrees). Canonical sign as scipy's ``as_quat(canonical=True)``: ``w > 0``, or if
    ``w == 0`` the first non-zero component positive. Raises ConversionError when ``R`` is not
    orthonormal within ``tol`` or has det <= 0.
    """
    q = geo.quat_wxyz_to_xyzw(geo.matrix_to_quat(_check_rotation(R, 'matrix_to_quat_xyzw', tol)))
    if q[3] < 0 or (q[3] == 0 and q[np.flatnonzero(q)[0]] < 0):
        q = -q
    return q


def _check_transform(T: Any, what: str) -> np.ndarray:
    Ta = _as_float_array(T, what, 'T', (4, 4))
    if not np.allclose(Ta[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9, rtol=0.0):
        raise ConversionError(f'{what}: last row of T must be (0, 0, 0, 1), got {Ta[3].tolist()}')
    _check_rotation(Ta[:3, :3], what)
    return Ta


def _check_cov6(cov: Any, what: str, name: str) -> np.ndarray:
    """Validate a 6x6 covariance: finite, symmetric, positive diagonal, PSD; return symmetrised."""
    C = _as_float_array(cov, what, name, (6, 6), finite=False)
    if not np.isfinite(C).all():
        raise ConversionError(f'{what}: {name} contains NaN or inf')
    scale = float(np.abs(C).max())
    asym = float(np.abs(C - C.T).max())
    if asym > 1e-8 * scale:
        raise ConversionError(f'{what}: {name} is not symmetric (max |C - C^T| = {asym:.3e})')
    diag = np.diag(C)
    if np.any(diag <= 0.0):
        raise ConversionError(
            f'{what}: {name} has a non-positive diagonal {diag.tolist()}; refusing to publish '
            'zero/unknown covariance')
    C = 0.5 * (C + C.T)
    min_eig = float(np.linalg.eigvalsh(C).min())
    if min_eig < -1e-9 * scale:
        raise ConversionError(
            f'{what}: {name} is not positive semi-definite (min eigenvalue {min_eig:.3e})')
    return C


def _vec3(obj: Any, what: str) -> np.ndarray:
    return np.array([float(_field(obj, 'x', what)), float(_field(obj, 'y', what)),
                     float(_field(obj, 'z', what))])


def pose_msg_to_matrix(pose: Any, what: str = 'Pose') -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 (quaternion normalised first)."""
    position = _field(pose, 'position', what)
    orientation = _field(pose, 'orientation', what)
    q = [float(_field(orientation, c, what)) for c in 'xyzw']
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(q)
    T[:3, 3] = _vec3(position, what)
    return T


def _matrix_to_pose_msg(f: _Factory, T: np.ndarray) -> Any:
    q = matrix_to_quat_xyzw(T[:3, :3])
    t = T[:3, 3]
    return f.make('geometry_msgs/msg/Pose',
                  position=f.make('geometry_msgs/msg/Point',
                                  x=float(t[0]), y=float(t[1]), z=float(t[2])),
                  orientation=f.make('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]),
                                     z=float(q[2]), w=float(q[3])))


def pose_to_odometry(T_odom_base: np.ndarray, cov6_pose: np.ndarray, twist_lin: Any,
                     twist_ang: Any, cov6_twist: np.ndarray, stamp_ns: int, frame_id: str,
                     child_frame_id: str, typestore: Any = None) -> Any:
    """Build nav_msgs/Odometry from a pose, a twist and their covariances.

    * ``T_odom_base``: 4x4 pose of ``child_frame_id`` (base) in ``frame_id`` (odom).
    * ``cov6_pose``: 6x6 covariance of (x, y, z, rot X, rot Y, rot Z) about fixed axes of
      ``frame_id`` (use :func:`transform_pose_covariance` to re-express it).
    * ``twist_lin``, ``twist_ang``: (3,) linear [m/s] and angular [rad/s] velocity expressed in
      ``child_frame_id`` (nav_msgs/Odometry convention); ``cov6_twist`` their 6x6 covariance.

    Covariances are written row-major. Refuses (ConversionError) NaN/inf anywhere, a
    non-rotation T, and covariances that are not symmetric, have a non-positive diagonal or are
    not positive semi-definite: zero or NaN covariance is never published.
    """
    what = 'pose_to_odometry'
    T = _check_transform(T_odom_base, what)
    C_pose = _check_cov6(cov6_pose, what, 'pose covariance')
    C_twist = _check_cov6(cov6_twist, what, 'twist covariance')
    v = _as_float_array(twist_lin, what, 'twist_lin', (3,))
    w = _as_float_array(twist_ang, what, 'twist_ang', (3,))
    if not isinstance(child_frame_id, str):
        raise ConversionError(f'{what}: child_frame_id must be a str')
    f = _Factory(typestore)
    pose = f.make('geometry_msgs/msg/PoseWithCovariance', pose=_matrix_to_pose_msg(f, T),
                  covariance=f.f64_fixed(C_pose))
    twist = f.make(
        'geometry_msgs/msg/TwistWithCovariance',
        twist=f.make('geometry_msgs/msg/Twist',
                     linear=f.make('geometry_msgs/msg/Vector3',
                                   x=float(v[0]), y=float(v[1]), z=float(v[2])),
                     angular=f.make('geometry_msgs/msg/Vector3',
                                    x=float(w[0]), y=float(w[1]), z=float(w[2]))),
        covariance=f.f64_fixed(C_twist))
    return f.make('nav_msgs/msg/Odometry', header=f.header(stamp_ns, frame_id),
                  child_frame_id=child_frame_id, pose=pose, twist=twist)


def odometry_to_pose(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """nav_msgs/Odometry -> ``(T 4x4, pose cov 6x6, twist (6,) = (v, w), twist cov 6x6)``.

    Frames as in :func:`pose_to_odometry`. Covariances are read row-major and not validated
    (a subscriber decides what to do with a zero covariance); the quaternion is normalised.
    """
    what = 'Odometry'
    pwc = _field(msg, 'pose', what)
    twc = _field(msg, 'twist', what)
    T = pose_msg_to_matrix(_field(pwc, 'pose', what), what)
    C_pose = _as_float_array(_field(pwc, 'covariance', what), what, 'pose covariance', (6, 6),
                             finite=False)
    tw = _field(twc, 'twist', what)
    twist = np.concatenate([_vec3(_field(tw, 'linear', what), what),
                            _vec3(_field(tw, 'angular', what), what)])
    C_twist = _as_float_array(_field(twc, 'covariance', what), what, 'twist covariance', (6, 6),
                              finite=False)
    return T, C_pose, twist, C_twist


def pose_stamped_to_matrix(msg: Any) -> np.ndarray:
    """geometry_msgs/PoseStamped -> 4x4 ``T_frame_body`` (pose of the body in header.frame_id)."""
    return pose_msg_to_matrix(_field(msg, 'pose', 'PoseStamped'), 'PoseStamped')


def matrix_to_pose_stamped(T: np.ndarray, stamp_ns: int, frame_id: str,
                           typestore: Any = None) -> Any:
    """4x4 ``T_frame_body`` -> geometry_msgs/PoseStamped in ``frame_id`` (quaternion w >= 0)."""
    Ta = _check_transform(T, 'matrix_to_pose_stamped')
    f = _Factory(typestore)
    return f.make('geometry_msgs/msg/PoseStamped', header=f.header(stamp_ns, frame_id),
                  pose=_matrix_to_pose_msg(f, Ta))


def transform_pose_covariance(cov6: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Re-express a 6x6 pose covariance from frame A in frame B: ``J C J^T``, ``J = diag(R, R)``.

    ``cov6`` is the covariance of a perturbation ``(dt, dtheta)`` (translation, small rotation
    vector; ROS order x, y, z, rot X, rot Y, rot Z) whose components are expressed in frame A;
    ``R = R_BA`` (3x3 rotation) maps A coordinates to B coordinates. Only the axes change, so
    this is exact for a pure change of the frame the perturbation is written in; it does not
    add the lever-arm coupling of a translated reference point (that needs the full SE(3)
    adjoint). The result is symmetrised.
    """
    what = 'transform_pose_covariance'
    C = _as_float_array(cov6, what, 'cov6', (6, 6))
    Ra = _check_rotation(R, what)
    J = np.zeros((6, 6))
    J[:3, :3] = Ra
    J[3:, 3:] = Ra
    out = J @ C @ J.T
    return 0.5 * (out + out.T)
