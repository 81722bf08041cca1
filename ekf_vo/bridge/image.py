"""sensor_msgs/Image and CompressedImage <-> numpy, and THE image decoder of the project.

Images are ``(H, W)`` for single-channel encodings and ``(H, W, C)`` otherwise, in the channel
order of the encoding (``rgb8`` -> R, G, B). Pixel ``[v, u]`` is row ``v``, column ``u``.

Image encodings (:data:`IMAGE_ENCODINGS`, the strings of sensor_msgs/image_encodings.hpp):
mono8, mono16, rgb8, bgr8, rgba8, bgra8, rgb16, bgr16, rgba16, bgra16, 8UC1, 8UC3, 8UC4,
16UC1, 16UC3, 16UC4; the raw Bayer mosaics of machine-vision cameras bayer_rggb8, bayer_bggr8,
bayer_gbrg8, bayer_grbg8 and their 16-bit bayer_*16; packed YUV 4:2:2 of v4l2/USB webcams uyvy
(alias yuv422) and yuyv (alias yuv422_yuy2). Not nv21/nv24 (planar, see ``_ENCODINGS``) nor
float/signed encodings.

:func:`decode_image` is the one decoder of Image and CompressedImage messages to an 8-bit
OpenCV image (grey, BGR, or grey only with ``gray=True``); the nodes, ``ekf-vo-run``, the
benchmarks and the bag readers all use it. :func:`image_to_numpy` is the lossless raw-array
view (any supported dtype, the encoding's channel order). Fields are read by name (see
:mod:`ekf_vo.bridge.common`).
"""
from __future__ import annotations

import numbers
from typing import Any

import cv2
import numpy as np

from .common import (COMPRESSED_IMAGE, IMAGE, ConversionError, MessageFactory, as_bytes_array,
                     get_field, get_int_field)

__all__ = ['IMAGE_ENCODINGS', 'image_to_numpy', 'decode_image', 'image_to_gray',
           'compressed_to_gray', 'numpy_to_image', 'numpy_to_compressed']

#: encoding -> (unsigned dtype letter + itemsize, channels, pixel layout): the one table of the
#: supported encodings (strings as in sensor_msgs/image_encodings.hpp). ``channels`` is what one
#: pixel holds in the message: 1 for a Bayer mosaic (one colour per pixel), 2 for packed
#: YUV 4:2:2 (luma plus alternately U or V). ``8UC3``/``8UC4``/``16UC3``/``16UC4`` are treated
#: as BGR/BGRA (OpenCV convention). Not supported: ``nv21`` and ``nv24``, planar layouts (a luma
#: plane, then a chroma plane) that ``height``/``step`` do not describe (image_encodings.hpp
#: declares them 2-channel, 16 bits a pixel, but NV21 holds 12 and NV24 24), and OpenCV has no
#: NV24 conversion; nor float/signed encodings (depth images).
_ENCODINGS: dict[str, tuple[str, int, str]] = {
    'mono8': ('u1', 1, 'gray'),
    'mono16': ('u2', 1, 'gray'),
    'rgb8': ('u1', 3, 'rgb'),
    'bgr8': ('u1', 3, 'bgr'),
    'rgba8': ('u1', 4, 'rgba'),
    'bgra8': ('u1', 4, 'bgra'),
    'rgb16': ('u2', 3, 'rgb'),
    'bgr16': ('u2', 3, 'bgr'),
    'rgba16': ('u2', 4, 'rgba'),
    'bgra16': ('u2', 4, 'bgra'),
    '8UC1': ('u1', 1, 'gray'),
    '8UC3': ('u1', 3, 'bgr'),
    '8UC4': ('u1', 4, 'bgra'),
    '16UC1': ('u2', 1, 'gray'),
    '16UC3': ('u2', 3, 'bgr'),
    '16UC4': ('u2', 4, 'bgra'),
    'bayer_rggb8': ('u1', 1, 'bayer_rggb'),
    'bayer_bggr8': ('u1', 1, 'bayer_bggr'),
    'bayer_gbrg8': ('u1', 1, 'bayer_gbrg'),
    'bayer_grbg8': ('u1', 1, 'bayer_grbg'),
    'bayer_rggb16': ('u2', 1, 'bayer_rggb'),
    'bayer_bggr16': ('u2', 1, 'bayer_bggr'),
    'bayer_gbrg16': ('u2', 1, 'bayer_gbrg'),
    'bayer_grbg16': ('u2', 1, 'bayer_grbg'),
    'uyvy': ('u1', 2, 'uyvy'),
    'yuv422': ('u1', 2, 'uyvy'),  # deprecated ROS name of uyvy
    'yuyv': ('u1', 2, 'yuyv'),
    'yuv422_yuy2': ('u1', 2, 'yuyv'),  # deprecated ROS name of yuyv
}

#: encoding -> (unsigned dtype letter + itemsize, channels). 16-bit byte order comes from
#: ``is_bigendian``.
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    encoding: (kind, channels) for encoding, (kind, channels, _) in _ENCODINGS.items()}
#: Image encoding -> pixel layout (channel order, Bayer pattern or 4:2:2 packing).
_ENCODING_ORDER: dict[str, str] = {
    encoding: layout for encoding, (_, _, layout) in _ENCODINGS.items()}

#: pixel layout of the 8-bit pixels -> cv2 conversion code (to gray, to BGR); None: keep.
#: Colour to grey uses OpenCV's BT.601 weights (Bayer*2GRAY too), so every colour order gives
#: the same grey. OpenCV names a Bayer pattern by the 2x2 cell one pixel down and right of
#: ROS's (which names the top-left cell), so ROS rggb is OpenCV ``BayerBG`` (cv_bridge's
#: mapping; test_image_encodings checks it with flat colours). Bilinear demosaicing, as
#: cv_bridge. YUV 4:2:2: the grey is the luma Y as sent (no range change); OpenCV's conversion
#: to BGR assumes BT.601 video range (Y 16..235).
_CV_CODES: dict[str, tuple[int | None, int | None]] = {
    'gray': (None, None),
    'rgb': (cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
    'bgr': (cv2.COLOR_BGR2GRAY, None),
    'rgba': (cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGR),
    'bgra': (cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2BGR),
    'bayer_rggb': (cv2.COLOR_BayerBG2GRAY, cv2.COLOR_BayerBG2BGR),
    'bayer_bggr': (cv2.COLOR_BayerRG2GRAY, cv2.COLOR_BayerRG2BGR),
    'bayer_gbrg': (cv2.COLOR_BayerGR2GRAY, cv2.COLOR_BayerGR2BGR),
    'bayer_grbg': (cv2.COLOR_BayerGB2GRAY, cv2.COLOR_BayerGB2BGR),
    'uyvy': (cv2.COLOR_YUV2GRAY_UYVY, cv2.COLOR_YUV2BGR_UYVY),
    'yuyv': (cv2.COLOR_YUV2GRAY_YUY2, cv2.COLOR_YUV2BGR_YUY2),
}
#: pixel layouts that pack two pixels in one 4-byte macropixel sharing U and V (4:2:2): a row
#: must hold whole pairs, so the width must be even.
_PIXEL_PAIRS: frozenset[str] = frozenset({'uyvy', 'yuyv'})
#: channels of an image decoded by OpenCV (always BGR order) -> channel order.
_DECODED_ORDER: dict[int, str] = {1: 'gray', 3: 'bgr', 4: 'bgra'}


def _check_pixel_pairs(what: str, encoding: str, width: int) -> None:
    """ConversionError if ``encoding`` packs pixel pairs (YUV 4:2:2) and ``width`` is odd."""
    if _ENCODING_ORDER[encoding] in _PIXEL_PAIRS and width % 2:
        raise ConversionError(
            f'{what}: width={width} is odd; {encoding} (YUV 4:2:2) packs pixel pairs, '
            'so the width must be even')


def _image_layout(msg: Any) -> tuple[str, int, int, int, np.dtype, int, np.ndarray]:
    """Validate an Image message; return (encoding, height, width, step, dtype, channels, data)."""
    what = 'Image'
    encoding = get_field(msg, 'encoding', what)
    if not isinstance(encoding, str):
        raise ConversionError(f'{what}: encoding {encoding!r} is not a str')
    encoding = encoding.strip()
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"{what}: unsupported encoding '{encoding}' (supported: {', '.join(IMAGE_ENCODINGS)})")
    height = get_int_field(msg, 'height', what, minimum=0)
    width = get_int_field(msg, 'width', what, minimum=0)
    if height == 0 or width == 0:
        raise ConversionError(
            f'{what}: empty image ({height}x{width}); height and width must be > 0')
    _check_pixel_pairs(what, encoding, width)
    step = get_int_field(msg, 'step', what, minimum=0)
    kind, channels = IMAGE_ENCODINGS[encoding]
    big = bool(get_field(msg, 'is_bigendian', what))
    dtype = np.dtype(('>' if big else '<') + kind)
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ConversionError(
            f'{what}: step={step} is smaller than width*channels*bytes='
            f'{width}*{channels}*{dtype.itemsize}={row_bytes} for {encoding}')
    data = as_bytes_array(get_field(msg, 'data', what), what)
    if data.size < step * height:
        raise ConversionError(
            f'{what}: data has {data.size} bytes, expected at least '
            f'{height}*{step}={step * height} (step*height)')
    return encoding, height, width, step, dtype, channels, data


def image_to_numpy(msg: Any, copy: bool = True) -> np.ndarray:
    """sensor_msgs/Image -> numpy array in native byte order, the pixels as sent.

    Shape ``(H, W)`` for 1-channel encodings (mono8/16, 8UC1, 16UC1 and the Bayer mosaics
    bayer_*8/16, not demosaiced), ``(H, W, 2)`` for packed YUV 4:2:2 (uyvy/yuv422: U Y0 V Y1;
    yuyv/yuv422_yuy2: Y0 U Y1 V; ``[v, u]`` is pixel u's luma and its U or V byte, as packed),
    ``(H, W, C)`` for rgb8/bgr8/rgb16/bgr16/8UC3/16UC3 (C=3) and rgba8/bgra8/rgba16/bgra16/
    8UC4/16UC4 (C=4), channels in the encoding's order; dtype ``uint8`` or ``uint16``. Row
    padding (``step`` > row bytes) is skipped and ``is_bigendian`` is honoured for 16-bit
    encodings. ``msg.data`` may be bytes, array.array, list or a numpy array.

    With ``copy=True`` (default) the result is a fresh C-contiguous writable array. With
    ``copy=False`` it may be a (strided, possibly read-only) view into ``msg.data``.

    Raises ConversionError on unknown encoding, empty size, odd width for YUV 4:2:2, too-small
    step or truncated data.
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


def decode_image(msgtype: str, msg: Any, *, gray: bool = False) -> np.ndarray:
    """Decode an Image or CompressedImage message to a fresh 8-bit OpenCV image.

    ``msgtype`` is ``'sensor_msgs/msg/Image'`` or ``'sensor_msgs/msg/CompressedImage'``
    (:data:`~ekf_vo.bridge.common.IMAGE`, :data:`~ekf_vo.bridge.common.COMPRESSED_IMAGE`).
    Returns ``uint8`` of shape ``(H, W)`` for grey data and ``(H, W, 3)`` in BGR order for
    colour data (alpha dropped); with ``gray=True`` always ``(H, W)``, colour converted with
    OpenCV's BT.601 weights. 16-bit data (mono16, 16UC1, 16-bit colour and Bayer, 16-bit PNG)
    is reduced to its high byte (``value >> 8``), a fixed scale (not max-normalised), so
    brightness is consistent across frames. Bayer mosaics are demosaiced by OpenCV (bilinear,
    as cv_bridge; the grey with its ``Bayer*2GRAY``). YUV 4:2:2 (uyvy, yuyv and their
    deprecated names yuv422, yuv422_yuy2) gives the luma Y as sent for grey, and OpenCV's
    BT.601 video-range conversion for BGR.

    Image: every encoding of :data:`IMAGE_ENCODINGS` (row padding and ``is_bigendian``
    honoured). CompressedImage: jpeg/png, recognised from the data (``format`` is only checked
    for the unsupported ``compressedDepth``), decoded as stored (``IMREAD_UNCHANGED``: no EXIF
    rotation), so a PNG frame gives the same pixels as the raw Image it came from. The result
    never aliases ``msg.data``. Raises ConversionError on anything else.
    """
    if msgtype == IMAGE:
        encoding = _image_layout(msg)[0]
        img, order = image_to_numpy(msg, copy=False), _ENCODING_ORDER[encoding]
    elif msgtype == COMPRESSED_IMAGE:
        img = _imdecode(msg)
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        order = _DECODED_ORDER[img.shape[2]] if img.ndim == 3 else 'gray'
    else:
        raise ConversionError(f'not an image message type: {msgtype}')
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    code = _CV_CODES[order][0 if gray else 1]
    if code is None:
        return np.array(img, dtype=np.uint8, order='C', copy=True)
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def _imdecode(msg: Any) -> np.ndarray:
    """OpenCV decode (IMREAD_UNCHANGED) of a CompressedImage: uint8/uint16, 1, 3 or 4 channels."""
    what = 'CompressedImage'
    fmt = getattr(msg, 'format', '') or ''
    if 'compresseddepth' in str(fmt).lower():
        raise ConversionError(f"{what}: format '{fmt}' (compressedDepth) is not supported")
    data = as_bytes_array(get_field(msg, 'data', what), what)
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
    if img.dtype not in (np.uint8, np.uint16):
        raise ConversionError(f'{what}: decoded image has unsupported depth {img.dtype}')
    if img.ndim == 3 and img.shape[2] not in (1, *_DECODED_ORDER):
        raise ConversionError(
            f'{what}: decoded image has unsupported channel count {img.shape[2]}')
    return img


def image_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/Image -> ``uint8`` grey ``(H, W)``: ``decode_image(IMAGE, msg, gray=True)``."""
    return decode_image(IMAGE, msg, gray=True)


def compressed_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage -> ``uint8`` grey ``(H, W)``:
    ``decode_image(COMPRESSED_IMAGE, msg, gray=True)``."""
    return decode_image(COMPRESSED_IMAGE, msg, gray=True)


def numpy_to_image(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, *,
                   step_padding: int = 0, typestore: Any = None,
                   is_bigendian: bool = False) -> Any:
    """numpy array -> sensor_msgs/Image (rclpy class, or rosbags class if ``typestore``).

    ``array`` must be ``(H, W)`` (or ``(H, W, 1)``) for 1-channel encodings and ``(H, W, C)``
    otherwise, dtype uint8 for 8-bit and uint16 for 16-bit encodings, pixels as the encoding
    lays them out (the shapes of :func:`image_to_numpy`: a Bayer mosaic ``(H, W)``, YUV 4:2:2
    packed ``(H, W, 2)`` with an even W). ``step_padding`` extra zero bytes are appended to each row
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
    _check_pixel_pairs(what, encoding, int(arr.shape[1]))
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
    f = MessageFactory(typestore)
    return f.make('sensor_msgs/msg/Image', header=f.header(stamp_ns, frame_id), height=height,
                  width=width, encoding=encoding,
                  is_bigendian=1 if (is_bigendian and out_dtype.itemsize > 1) else 0,
                  step=step, data=f.u8_seq(rows))


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
    f = MessageFactory(typestore)
    return f.make('sensor_msgs/msg/CompressedImage', header=f.header(stamp_ns, frame_id),
                  format=f'{encoding}; {fmt_l} compressed {encoding}',
                  data=f.u8_seq(buf.reshape(-1)))
