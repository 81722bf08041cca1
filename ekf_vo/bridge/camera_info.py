"""sensor_msgs/CameraInfo <-> plain dict, its validation, and building one from intrinsics.

Fields are read by name (rclpy and rosbags classes alike; see :mod:`ekf_vo.bridge.common`).
"""
from __future__ import annotations

import logging
import numbers
from typing import Any, Mapping

import numpy as np

from .common import (ConversionError, MessageFactory, as_float_array, get_field, get_int_field,
                     stamp_to_ns)

logger = logging.getLogger(__name__)

__all__ = ['DISTORTION_MODELS', 'camera_info_to_dict', 'validate_camera_info',
           'camera_info_from_params']

#: distortion model -> allowed lengths of D (REP-104; ``rational_polynomial`` also accepts the
#: 5 coefficients it shares with ``plumb_bob``). ``''``/``'none'`` require an all-zero D.
DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    'plumb_bob': (5,),
    'rational_polynomial': (8, 5),
    'equidistant': (4,),
}
_NO_DISTORTION = ('', 'none')


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
    K = as_float_array(get_field(msg, 'k', what, 'K'), what, 'K', (3, 3), finite=False)
    D = as_float_array(get_field(msg, 'd', what, 'D'), what, 'D', finite=False).reshape(-1)
    R = as_float_array(get_field(msg, 'r', what, 'R'), what, 'R', (3, 3), finite=False)
    P = as_float_array(get_field(msg, 'p', what, 'P'), what, 'P', (3, 4), finite=False)
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
    model = get_field(msg, 'distortion_model', what)
    return {
        'width': get_int_field(msg, 'width', what),
        'height': get_int_field(msg, 'height', what),
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
    K = as_float_array(info.get('K'), what, 'K', (3, 3), finite=False)
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
    D = as_float_array(info.get('D', ()), what, 'D', finite=False).reshape(-1)
    if not np.isfinite(D).all():
        raise ConversionError(f'{what}: D contains NaN or inf: {D.tolist()}')
    P = as_float_array(info.get('P', np.zeros((3, 4))), what, 'P', (3, 4), finite=False)
    if not np.isfinite(P).all():
        raise ConversionError(f'{what}: P contains NaN or inf')
    if info.get('R') is not None:
        as_float_array(info['R'], what, 'R', (3, 3))
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
    K = as_float_array(K, what, 'K', (3, 3), finite=False)
    D = as_float_array(D, what, 'D', finite=False).reshape(-1)
    P = np.hstack([K, np.zeros((3, 1))])
    validate_camera_info({'width': width, 'height': height, 'K': K, 'D': D, 'P': P,
                          'R': np.eye(3), 'distortion_model': distortion_model})
    f = MessageFactory(typestore)
    roi = f.make('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0, width=0,
                 do_rectify=False)
    return f.make('sensor_msgs/msg/CameraInfo', header=f.header(stamp_ns, frame_id),
                  height=int(height), width=int(width), distortion_model=distortion_model,
                  d=f.f64_seq(D), k=f.f64_fixed(K), r=f.f64_fixed(np.eye(3)),
                  p=f.f64_fixed(P), binning_x=0, binning_y=0, roi=roi)

