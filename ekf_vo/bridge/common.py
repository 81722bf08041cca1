"""Shared ground of the message bridge: errors, message-type names, field readers, stamps.

Every reader in :mod:`ekf_vo.bridge` accesses message fields *by name* (duck typing), so the
same function works on

* rclpy message classes (``sensor_msgs.msg.Image`` ...; ``uint8[]`` fields are ``array.array('B')``
  or ``bytes``, ``float64[]`` fields are ``array.array('d')``, fixed arrays are numpy arrays), and
* rosbags typestore classes (``typestore.types['sensor_msgs/msg/Image']``; array fields are numpy
  arrays).

Every builder takes an optional ``typestore``: ``None`` builds rclpy messages (the message
modules are imported lazily, inside :class:`MessageFactory`), anything else is used as a
rosbags typestore (only its ``types`` mapping is used), so the result can be written to a bag
with ``typestore.serialize_cdr(msg, msg.__msgtype__)``. The bridge never imports rclpy or
rosbags; ROS message packages are imported only when an rclpy message is built.

Time stamps are integer nanoseconds since the epoch (``stamp_ns``), always >= 0 and with a
seconds part that fits the int32 ``builtin_interfaces/Time.sec`` field. Invalid input raises
:class:`ConversionError` (a ``ValueError``) with a one-line message that names the message
type and the offending field.
"""
from __future__ import annotations

import array
import importlib
import math
import numbers
from typing import Any

import numpy as np

__all__ = ['ConversionError', 'IMAGE', 'COMPRESSED_IMAGE', 'CAMERA_INFO', 'POSE_STAMPED',
           'stamp_to_ns', 'ns_to_stamp']

#: ROS 2 message type names (as rosbag2 records them).
IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'

INT32_MAX = 2**31 - 1
NS_PER_S = 1_000_000_000


class ConversionError(ValueError):
    """A message or array cannot be converted (malformed, inconsistent or unsupported)."""


# --------------------------------------------------------------------------------------------
# Field readers and message building
# --------------------------------------------------------------------------------------------

def get_field(msg: Any, name: str, what: str, *alternatives: str) -> Any:
    """Return ``msg.<name>`` (or the first present alternative name); ConversionError if absent."""
    for n in (name, *alternatives):
        try:
            return getattr(msg, n)
        except AttributeError:
            continue
    raise ConversionError(f"{what}: message of type {type(msg).__name__} has no field '{name}'")


def get_int_field(msg: Any, name: str, what: str, minimum: int = 0) -> int:
    """Read an integer field and check ``value >= minimum``."""
    value = get_field(msg, name, what)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ConversionError(f'{what}: field {name}={value!r} is not an integer')
    value = int(value)
    if value < minimum:
        raise ConversionError(f'{what}: field {name}={value} must be >= {minimum}')
    return value


def as_bytes_array(data: Any, what: str) -> np.ndarray:
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


def as_float_array(values: Any, what: str, name: str, shape: tuple[int, ...] | None = None,
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


class MessageFactory:
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
        sec, nanosec = split_ns(stamp_ns)
        return self.make('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        if not isinstance(frame_id, str):
            raise ConversionError(f'frame_id must be a str, got {type(frame_id).__name__}')
        return self.make('std_msgs/msg/Header', stamp=self.time(stamp_ns), frame_id=frame_id)


# --------------------------------------------------------------------------------------------
# Time
# --------------------------------------------------------------------------------------------

def split_ns(ns: Any) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) for builtin_interfaces/Time (sec int32, >= 0)."""
    if isinstance(ns, (bool, np.bool_)) or not isinstance(ns, numbers.Integral):
        raise ConversionError(f'stamp_ns must be an integer number of nanoseconds, got {ns!r}')
    ns = int(ns)
    if ns < 0:
        raise ConversionError(f'stamp_ns={ns} is negative; ROS stamps must be >= 0')
    sec, nanosec = divmod(ns, NS_PER_S)
    if sec > INT32_MAX:
        raise ConversionError(
            f'stamp_ns={ns} overflows builtin_interfaces/Time.sec (int32, max {INT32_MAX} s)')
    return sec, nanosec


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (fields ``sec``, ``nanosec``) -> integer nanoseconds (>= 0).

    Raises ConversionError for non-integer fields, negative ``sec`` or ``nanosec`` outside
    ``[0, 1e9)``.
    """
    sec = get_int_field(stamp, 'sec', 'Time', minimum=0)
    nanosec = get_int_field(stamp, 'nanosec', 'Time', minimum=0)
    if nanosec >= NS_PER_S:
        raise ConversionError(f'Time: nanosec={nanosec} must be < 1e9')
    return sec * NS_PER_S + nanosec


def ns_to_stamp(ns: int, typestore: Any = None) -> Any:
    """Integer nanoseconds -> builtin_interfaces/Time (rclpy class, or rosbags if typestore).

    Raises ConversionError for non-integers, negative values and values whose seconds part
    exceeds int32 (year 2038).
    """
    return MessageFactory(typestore).time(ns)
