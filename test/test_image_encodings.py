"""The encodings camera drivers publish besides mono/rgb/bgr: Bayer mosaics (machine-vision
drivers without a debayer node), packed YUV 4:2:2 (v4l2/USB webcams) and 16-bit colour.

Every message is a real rclpy ``sensor_msgs.msg.Image`` (built by ``numpy_to_image`` or by
hand, field by field); the expected images are made here in numpy from a known colour image:
the mosaic in the ROS pattern, the 4:2:2 packing with BT.601 video-range YUV, so a wrong
pattern or byte order in the decoder shows as wrong colours.
"""
from __future__ import annotations

import array
from itertools import islice

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import Image

from ekf_vo import bridge as cv
from ekf_vo.bridge import IMAGE, ConversionError, decode_image, select_camera_topics
from ekf_vo.io.bag import bag_topics, iter_bag
from ekf_vo.tools.demo import demo_bag

#: ROS Bayer encoding -> its pattern, the top-left 2x2 cell row by row.
BAYER = {f'bayer_{p.lower()}{bits}': p
         for p in ('RGGB', 'BGGR', 'GBRG', 'GRBG') for bits in (8, 16)}
#: YUV 4:2:2 encoding -> byte order of a pixel pair (the deprecated names are aliases).
YUV422 = {'uyvy': 'UYVY', 'yuv422': 'UYVY', 'yuyv': 'YUYV', 'yuv422_yuy2': 'YUYV'}
#: 16-bit colour encoding -> channel order (16UCn: OpenCV's BGR convention).
COLOUR16 = {'rgb16': 'RGB', 'bgr16': 'BGR', 'rgba16': 'RGBA', 'bgra16': 'BGRA',
            '16UC3': 'BGR', '16UC4': 'BGRA'}
NEW = sorted([*BAYER, *YUV422, *COLOUR16])
FLAT = {'red': (0, 0, 255), 'green': (0, 255, 0), 'blue': (255, 0, 0),
        'orange': (20, 140, 230), 'teal': (160, 150, 30)}


def textured_bgr(h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth colour texture (each channel its own sinusoids), uint8 BGR."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    b = 128 + 90 * np.sin(u / 11.0 + 0.5) * np.cos(v / 13.0)
    g = 128 + 90 * np.cos(u / 9.0) * np.sin(v / 8.0 + 1.0)
    r = 128 + 90 * np.sin((u + v) / 10.0)
    return np.clip(np.stack([b, g, r], axis=-1), 0, 255).round().astype(np.uint8)


def flat_bgr(colour: tuple[int, int, int], h: int = 8, w: int = 10) -> np.ndarray:
    return np.broadcast_to(np.array(colour, np.uint8), (h, w, 3)).copy()


def to16(img8: np.ndarray, seed: int = 0) -> np.ndarray:
    """uint16 with ``img8`` as high byte and a random low byte (which decoding must drop)."""
    low = np.random.default_rng(seed).integers(0, 256, img8.shape, dtype=np.uint16)
    return (img8.astype(np.uint16) << 8) | low


def mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic a sensor with the ROS ``pattern`` (e.g. 'RGGB') records of ``bgr``."""
    channel = {'B': 0, 'G': 1, 'R': 2}
    raw = np.empty(bgr.shape[:2], bgr.dtype)
    for k, colour in enumerate(pattern):
        dy, dx = divmod(k, 2)
        raw[dy::2, dx::2] = bgr[dy::2, dx::2, channel[colour]]
    return raw


def bt601_video(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Y, U, V (float) of BT.601 in video range (Y 16..235), what a YUV camera sends."""
    b, g, r = (bgr[..., k].astype(float) / 255 for k in range(3))
    y = 0.299 * r + 0.587 * g + 0.114 * b
    return 16 + 219 * y, 128 + 224 * (b - y) / 1.772, 128 + 224 * (r - y) / 1.402


def pack_422(y: np.ndarray, u: np.ndarray, v: np.ndarray, order: str) -> np.ndarray:
    """(H, W, 2) uint8 as the message holds it: each pixel pair shares its mean U and V."""
    h, w = y.shape
    u2 = u.reshape(h, w // 2, 2).mean(axis=2)
    v2 = v.reshape(h, w // 2, 2).mean(axis=2)

    def to_u8(a: np.ndarray) -> np.ndarray:
        return np.clip(np.round(a), 0, 255).astype(np.uint8)

    pairs = {'Y0': to_u8(y[:, 0::2]), 'Y1': to_u8(y[:, 1::2]), 'U': to_u8(u2), 'V': to_u8(v2)}
    names = ['U', 'Y0', 'V', 'Y1'] if order == 'UYVY' else ['Y0', 'U', 'Y1', 'V']
    return np.stack([pairs[n] for n in names], axis=-1).reshape(h, w, 2)


def message(encoding: str, bgr: np.ndarray, *, padding: int = 0, bigendian: bool = False
            ) -> Image:
    """An rclpy Image of ``bgr`` as a camera sending ``encoding`` would publish it."""
    if encoding in BAYER:
        raw = mosaic(bgr, BAYER[encoding])
        raw = to16(raw) if encoding.endswith('16') else raw
    elif encoding in YUV422:
        raw = pack_422(*bt601_video(bgr), YUV422[encoding])
    else:
        order = COLOUR16[encoding]
        bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
        raw = to16(np.stack([bgra[..., 'BGRA'.index(c)] for c in order], axis=-1))
    msg = cv.numpy_to_image(raw, encoding, 1_000, 'camera', step_padding=padding,
                            is_bigendian=bigendian)
    assert isinstance(msg, Image)
    return msg


def hand_made(encoding: str, height: int, width: int, step: int, data: bytes,
              bigendian: bool = False) -> Image:
    msg = Image(height=height, width=width, encoding=encoding, step=step,
                is_bigendian=bigendian)
    msg.data = array.array('B', data)
    return msg


# -------------------------------------------------------------------------- Bayer

@pytest.mark.parametrize('encoding', sorted(BAYER))
@pytest.mark.parametrize('name', sorted(FLAT))
def test_bayer_flat_colour_comes_back(encoding, name):
    """The pattern check: a flat red (green, blue, ...) scene decodes to that colour."""
    bgr = flat_bgr(FLAT[name])
    msg = message(encoding, bgr)
    np.testing.assert_array_equal(decode_image(IMAGE, msg), bgr)
    gray = decode_image(IMAGE, msg, gray=True)
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    assert np.abs(gray.astype(int) - expected).max() <= 1


@pytest.mark.parametrize('encoding', sorted(BAYER))
@pytest.mark.parametrize('padding', [0, 3])
@pytest.mark.parametrize('bigendian', [False, True])
def test_bayer_texture(encoding, padding, bigendian):
    """Demosaicing is exact to 1-2 grey levels on smooth texture, away from the 1-pixel rim
    (OpenCV's border handling); the grey matches the colour image's BT.601 grey."""
    bgr = textured_bgr()
    msg = message(encoding, bgr, padding=padding, bigendian=bigendian)
    assert msg.step == bgr.shape[1] * (2 if encoding.endswith('16') else 1) + padding
    gray = decode_image(IMAGE, msg, gray=True)
    colour = decode_image(IMAGE, msg)
    assert gray.shape == bgr.shape[:2] and gray.dtype == np.uint8
    assert colour.shape == bgr.shape and colour.dtype == np.uint8
    d_gray = np.abs(gray.astype(int) - cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    d_colour = np.abs(colour.astype(int) - bgr)
    assert d_gray[1:-1, 1:-1].max() <= 2 and d_gray.mean() < 1.0
    assert d_colour[1:-1, 1:-1].max() <= 2 and d_colour.mean() < 1.0


def test_bayer16_bigendian_bytes():
    """Hand-made bytes: the flag decides which byte is the high one."""
    data = b'\xab\x01' * 16  # 4x4 pixels, each 0xab01 big-endian, 0x01ab little-endian
    big = hand_made('bayer_rggb16', 4, 4, 8, data, bigendian=True)
    little = hand_made('bayer_rggb16', 4, 4, 8, data, bigendian=False)
    assert (cv.image_to_numpy(big) == 0xAB01).all()
    assert (decode_image(IMAGE, big, gray=True) == 0xAB).all()
    assert (decode_image(IMAGE, big) == 0xAB).all()
    assert (decode_image(IMAGE, little, gray=True) == 0x01).all()


# ------------------------------------------------------------------------------- YUV 4:2:2

@pytest.mark.parametrize('encoding', sorted(YUV422))
@pytest.mark.parametrize('name', sorted(FLAT))
def test_yuv422_flat_colour_comes_back(encoding, name):
    """The byte-order check: U and V swapped would turn red into blue."""
    bgr = flat_bgr(FLAT[name])
    msg = message(encoding, bgr)
    colour = decode_image(IMAGE, msg)
    assert np.abs(colour.astype(int) - bgr).max() <= 3


@pytest.mark.parametrize('encoding', sorted(YUV422))
@pytest.mark.parametrize('padding', [0, 3])
def test_yuv422_texture(encoding, padding):
    """Grey is the luma Y as sent (exactly); colour is within the chroma subsampling's error
    on smooth texture."""
    bgr = textured_bgr()
    y = bt601_video(bgr)[0]
    msg = message(encoding, bgr, padding=padding)
    assert msg.step == 2 * bgr.shape[1] + padding
    gray = decode_image(IMAGE, msg, gray=True)
    np.testing.assert_array_equal(gray, np.round(y).astype(np.uint8))
    colour = decode_image(IMAGE, msg)
    assert colour.shape == bgr.shape and colour.dtype == np.uint8
    d_colour = np.abs(colour.astype(int) - bgr)
    assert d_colour.max() <= 10 and d_colour.mean() < 2.5


@pytest.mark.parametrize('encoding', sorted(YUV422))
def test_yuv422_raw_view_is_the_packing(encoding):
    """image_to_numpy keeps the bytes as packed: (H, W, 2), luma in its slot of each pixel."""
    bgr = textured_bgr(6, 8)
    msg = message(encoding, bgr, padding=2)
    raw = cv.image_to_numpy(msg)
    assert raw.shape == (6, 8, 2) and raw.dtype == np.uint8
    luma = raw[..., 1] if YUV422[encoding] == 'UYVY' else raw[..., 0]
    np.testing.assert_array_equal(luma, np.round(bt601_video(bgr)[0]).astype(np.uint8))


@pytest.mark.parametrize('encoding', sorted(YUV422))
def test_yuv422_odd_width_rejected(encoding):
    msg = hand_made(encoding, 2, 5, 10, bytes(20))
    for decode in (cv.image_to_numpy, lambda m: decode_image(IMAGE, m),
                   lambda m: decode_image(IMAGE, m, gray=True)):
        with pytest.raises(ConversionError, match=rf'^Image: width=5 is odd; {encoding} '):
            decode(msg)
    with pytest.raises(ConversionError, match='width=5 is odd'):
        cv.numpy_to_image(np.zeros((2, 5, 2), np.uint8), encoding, 0, 'camera')


# ---------------------------------------------------------------------------- 16-bit colour

@pytest.mark.parametrize('encoding', sorted(COLOUR16))
@pytest.mark.parametrize('padding', [0, 3])
@pytest.mark.parametrize('bigendian', [False, True])
def test_colour16(encoding, padding, bigendian):
    """The high byte of each channel, in the encoding's channel order, like mono16."""
    bgr = textured_bgr()
    msg = message(encoding, bgr, padding=padding, bigendian=bigendian)
    np.testing.assert_array_equal(decode_image(IMAGE, msg), bgr)
    np.testing.assert_array_equal(decode_image(IMAGE, msg, gray=True),
                                  cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    for colour in FLAT.values():
        assert tuple(decode_image(IMAGE, message(encoding, flat_bgr(colour)))[0, 0]) == colour


# ----------------------------------------------------------------- every new encoding

@pytest.mark.parametrize('encoding', NEW)
@pytest.mark.parametrize('padding', [0, 1, 4])
@pytest.mark.parametrize('bigendian', [False, True])
def test_raw_round_trip(encoding, padding, bigendian):
    """numpy_to_image then image_to_numpy gives the array back: Bayer (H, W), YUV 4:2:2
    (H, W, 2), 16-bit colour (H, W, C) uint16; padded rows and byte order honoured."""
    kind, channels = cv.IMAGE_ENCODINGS[encoding]
    dtype = np.uint8 if kind == 'u1' else np.uint16
    shape = (5, 6) if channels == 1 else (5, 6, channels)
    img = np.random.default_rng(1).integers(0, np.iinfo(dtype).max, shape, dtype=dtype,
                                            endpoint=True)
    msg = cv.numpy_to_image(img, encoding, 7, 'camera', step_padding=padding,
                            is_bigendian=bigendian)
    assert msg.step == 6 * channels * img.itemsize + padding
    assert bool(msg.is_bigendian) == (bigendian and img.itemsize == 2)
    out = cv.image_to_numpy(msg)
    assert out.dtype == dtype and out.dtype.isnative
    np.testing.assert_array_equal(out, img)
    assert decode_image(IMAGE, msg, gray=True).shape == (5, 6)
    assert decode_image(IMAGE, msg).shape == (5, 6, 3)


@pytest.mark.parametrize('encoding', NEW)
def test_truncated_buffer_rejected(encoding):
    msg = message(encoding, textured_bgr(4, 6), padding=2)
    msg.data = msg.data[:-1]
    for decode in (cv.image_to_numpy, lambda m: decode_image(IMAGE, m),
                   lambda m: decode_image(IMAGE, m, gray=True)):
        with pytest.raises(ConversionError, match=r'^Image: data has \d+ bytes, expected'):
            decode(msg)


def test_nv21_nv24_still_rejected():
    for encoding in ('nv21', 'nv24'):
        with pytest.raises(ConversionError, match=f"unsupported encoding '{encoding}'"):
            decode_image(IMAGE, hand_made(encoding, 2, 2, 4, bytes(8)), gray=True)


# --------------------------------------------------------- end to end: a real demo frame

@pytest.fixture(scope='module')
def demo_grays() -> list[np.ndarray]:
    """The first frames of bags/demo as the pipeline sees them (mono8 JPEG, decoded grey)."""
    camera = select_camera_topics(bag_topics(demo_bag()))
    frames = islice(iter_bag(demo_bag(), [camera.image]), 3)
    return [decode_image(msgtype, msg, gray=True) for _, msgtype, _, msg in frames]


def test_demo_frames_through_bayer_and_yuyv(demo_grays):
    """The grey a Bayer (rggb) or a YUYV camera would give vo_node for a real frame is the
    mono8 grey: exactly for YUYV (its luma, here full range), to demosaicing's error for Bayer
    (real texture, edges included)."""
    assert demo_grays and demo_grays[0].shape == (480, 640)
    for gray in demo_grays:
        h, w = gray.shape
        # a grey scene: R = G = B = grey, so the rggb mosaic is the grey itself
        bayer = cv.numpy_to_image(gray, 'bayer_rggb8', 0, 'camera')
        from_bayer = decode_image(IMAGE, bayer, gray=True)
        diff = np.abs(from_bayer.astype(int) - gray)
        assert from_bayer.shape == (h, w)
        assert diff.mean() < 1.5 and np.percentile(diff, 99) <= 10
        packed = np.stack([gray, np.full_like(gray, 128)], axis=-1)  # Y0 U Y1 V, U = V = 128
        yuyv = cv.numpy_to_image(packed, 'yuyv', 0, 'camera', step_padding=4)
        np.testing.assert_array_equal(decode_image(IMAGE, yuyv, gray=True), gray)
