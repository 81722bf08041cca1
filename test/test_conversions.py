"""Tests for ekf_vo.bridge with real rclpy and real rosbags message classes (no mocks)."""
from __future__ import annotations

import array
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField

from ekf_vo import bridge as cv
from ekf_vo.bridge import ConversionError

TS = get_typestore(Stores.ROS2_JAZZY)
BACKENDS = {'rclpy': None, 'rosbags': TS}
K = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])
#: packed YUV 4:2:2: the width must be even. Bayer and 4:2:2 grey: test_image_encodings.py.
YUV422 = ('uyvy', 'yuv422', 'yuyv', 'yuv422_yuy2')
PER_PIXEL = sorted(e for e in cv.IMAGE_ENCODINGS
                   if not e.startswith('bayer_') and e not in YUV422)


@pytest.fixture(params=sorted(BACKENDS))
def typestore(request):
    return BACKENDS[request.param]


def random_image(encoding: str, h: int = 7, w: int = 5, seed: int = 0) -> np.ndarray:
    kind, ch = cv.IMAGE_ENCODINGS[encoding]
    rng = np.random.default_rng(seed)
    if encoding in YUV422:
        w += w % 2
    dtype = np.uint8 if kind == 'u1' else np.uint16
    shape = (h, w) if ch == 1 else (h, w, ch)
    return rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)


def to_rclpy(msg, rclpy_cls):
    """Serialize a rosbags message to CDR and deserialize it with rclpy."""
    raw = TS.serialize_cdr(msg, msg.__msgtype__)
    return deserialize_message(bytes(raw), rclpy_cls)


def to_rosbags(msg, msgtype: str):
    """Serialize an rclpy message to CDR and deserialize it with rosbags."""
    return TS.deserialize_cdr(serialize_message(msg), msgtype)


# ------------------------------------------------------------------------------------------ images

@pytest.mark.parametrize('encoding', sorted(cv.IMAGE_ENCODINGS))
@pytest.mark.parametrize('padding', [0, 3])
@pytest.mark.parametrize('bigendian', [False, True])
def test_image_round_trip(encoding, padding, bigendian, typestore):
    img = random_image(encoding)
    msg = cv.numpy_to_image(img, encoding, 1_500_000_000, 'cam', step_padding=padding,
                            typestore=typestore, is_bigendian=bigendian)
    kind, ch = cv.IMAGE_ENCODINGS[encoding]
    itemsize = int(kind[1])
    assert msg.step == img.shape[1] * ch * itemsize + padding
    assert msg.height == img.shape[0] and msg.width == img.shape[1]
    assert msg.encoding == encoding
    assert bool(msg.is_bigendian) == (bigendian and itemsize == 2)
    out = cv.image_to_numpy(msg)
    assert out.dtype == img.dtype and out.dtype.isnative
    assert out.shape == img.shape
    np.testing.assert_array_equal(out, img)
    assert out.flags.c_contiguous and out.flags.writeable
    assert cv.stamp_to_ns(msg.header.stamp) == 1_500_000_000
    assert msg.header.frame_id == 'cam'


def test_image_mono16_bigendian_bytes_layout():
    img = np.array([[0x0102, 0xA0B0]], dtype=np.uint16)
    big = cv.numpy_to_image(img, 'mono16', 0, 'c', is_bigendian=True)
    little = cv.numpy_to_image(img, 'mono16', 0, 'c', is_bigendian=False)
    assert bytes(big.data) == b'\x01\x02\xa0\xb0'
    assert bytes(little.data) == b'\x02\x01\xb0\xa0'
    # the same bytes, flagged differently, must decode differently
    big.is_bigendian = 0
    np.testing.assert_array_equal(cv.image_to_numpy(big), [[0x0201, 0xB0A0]])


@pytest.mark.parametrize('container', ['bytes', 'array', 'list', 'numpy', 'bytearray'])
def test_image_data_containers(container):
    img = random_image('rgb8', 4, 3)
    msg = cv.numpy_to_image(img, 'rgb8', 0, 'c', step_padding=2, typestore=TS)
    raw = np.asarray(msg.data, dtype=np.uint8)
    data = {'bytes': raw.tobytes(), 'array': array.array('B', raw.tobytes()),
            'list': raw.tolist(), 'numpy': raw, 'bytearray': bytearray(raw.tobytes())}[container]
    msg.data = data
    np.testing.assert_array_equal(cv.image_to_numpy(msg), img)


def test_image_no_copy_is_view_and_copy_is_independent():
    img = random_image('mono8', 6, 4)
    msg = cv.numpy_to_image(img, 'mono8', 0, 'c', typestore=TS)
    view = cv.image_to_numpy(msg, copy=False)
    assert np.shares_memory(view, msg.data)
    copied = cv.image_to_numpy(msg)
    assert not np.shares_memory(copied, msg.data)


@pytest.mark.parametrize('encoding', PER_PIXEL)
def test_image_to_gray(encoding, typestore):
    img = random_image(encoding, 9, 11, seed=3)
    msg = cv.numpy_to_image(img, encoding, 0, 'c', step_padding=1, typestore=typestore)
    gray = cv.image_to_gray(msg)
    assert gray.dtype == np.uint8 and gray.shape == (9, 11)
    code = {'rgb8': cv2.COLOR_RGB2GRAY, 'bgr8': cv2.COLOR_BGR2GRAY, '8UC3': cv2.COLOR_BGR2GRAY,
            'rgba8': cv2.COLOR_RGBA2GRAY, 'bgra8': cv2.COLOR_BGRA2GRAY,
            '8UC4': cv2.COLOR_BGRA2GRAY, 'rgb16': cv2.COLOR_RGB2GRAY,
            'bgr16': cv2.COLOR_BGR2GRAY, '16UC3': cv2.COLOR_BGR2GRAY,
            'rgba16': cv2.COLOR_RGBA2GRAY, 'bgra16': cv2.COLOR_BGRA2GRAY,
            '16UC4': cv2.COLOR_BGRA2GRAY}.get(encoding)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if code is None:
        expected = img
    else:
        expected = cv2.cvtColor(img, code)
    np.testing.assert_array_equal(gray, expected)


def test_image_rgb_vs_bgr_channel_order():
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 0] = 255  # pure red
    g_rgb = cv.image_to_gray(cv.numpy_to_image(rgb, 'rgb8', 0, 'c'))
    g_bgr = cv.image_to_gray(cv.numpy_to_image(rgb[..., ::-1].copy(), 'bgr8', 0, 'c'))
    np.testing.assert_array_equal(g_rgb, g_bgr)
    assert int(g_rgb[0, 0]) == 76  # 0.299 * 255


def test_image_rosbags_to_rclpy_via_cdr():
    for encoding in sorted(cv.IMAGE_ENCODINGS):
        img = random_image(encoding, 5, 6, seed=7)
        bag_msg = cv.numpy_to_image(img, encoding, 1_234_567_891, 'cam', step_padding=2,
                                    typestore=TS, is_bigendian=True)
        ros_msg = to_rclpy(bag_msg, Image)
        assert isinstance(ros_msg, Image)
        np.testing.assert_array_equal(cv.image_to_numpy(ros_msg), img)
        np.testing.assert_array_equal(cv.image_to_numpy(ros_msg), cv.image_to_numpy(bag_msg))
        assert cv.stamp_to_ns(ros_msg.header.stamp) == 1_234_567_891


def test_image_rclpy_to_rosbags_via_cdr():
    img = random_image('bgr8', 5, 6, seed=8)
    ros_msg = cv.numpy_to_image(img, 'bgr8', 42, 'cam', step_padding=1)
    bag_msg = to_rosbags(ros_msg, 'sensor_msgs/msg/Image')
    assert isinstance(bag_msg.data, np.ndarray)
    np.testing.assert_array_equal(cv.image_to_numpy(bag_msg), img)


def _raw_image(typestore=None, **kw):
    fields = dict(height=480, width=640, encoding='mono8', is_bigendian=0, step=640,
                  data=np.zeros(480 * 640, np.uint8))
    fields.update(kw)
    header = (TS.types['std_msgs/msg/Header'](stamp=TS.types['builtin_interfaces/msg/Time'](0, 0),
                                              frame_id='c'))
    return TS.types['sensor_msgs/msg/Image'](header=header, **fields)


@pytest.mark.parametrize('kw, match', [
    (dict(data=np.zeros(100, np.uint8)),
     r'Image: data has 100 bytes, expected at least 480\*640=307200 \(step\*height\)'),
    (dict(step=639), r'step=639 is smaller than width\*channels\*bytes=640\*1\*1=640'),
    (dict(encoding='mono16'), r'step=640 is smaller than .*=1280 for mono16'),
    (dict(encoding='nv21'), r"unsupported encoding 'nv21'"),
    (dict(encoding='32FC1'), r"unsupported encoding '32FC1'"),
    (dict(height=0, data=np.zeros(0, np.uint8)), r'empty image \(0x640\)'),
    (dict(width=0, step=0), r'empty image \(480x0\)'),
    (dict(data=np.full(480 * 640, 300, np.int32)), r'data values span \[300, 300\]'),
    (dict(data=np.zeros(480 * 640, np.float32)), r'dtype float32'),
    (dict(data='abc'), r'data is a str'),
])
def test_image_errors(kw, match):
    msg = _raw_image(**kw)
    with pytest.raises(ConversionError, match=match):
        cv.image_to_numpy(msg)
    with pytest.raises(ConversionError):
        cv.image_to_gray(msg)


def test_image_error_is_valueerror_and_one_line():
    with pytest.raises(ValueError) as exc_info:
        cv.image_to_numpy(_raw_image(data=b'\x00' * 10))
    assert '\n' not in str(exc_info.value)


@pytest.mark.parametrize('args, match', [
    ((np.zeros((4, 4), np.uint16), 'mono8'), r'dtype uint16 does not fit mono8'),
    ((np.zeros((4, 4), np.uint8), 'rgb8'), r'does not fit rgb8, expected \(H, W, 3\)'),
    ((np.zeros((0, 4), np.uint8), 'mono8'), r'empty array'),
    ((np.zeros((4, 4), np.uint8), 'jpeg'), r"unsupported encoding 'jpeg'"),
])
def test_numpy_to_image_errors(args, match):
    with pytest.raises(ConversionError, match=match):
        cv.numpy_to_image(*args, stamp_ns=0, frame_id='c')


def test_numpy_to_image_accepts_hw1():
    img = random_image('mono8', 3, 4)
    msg = cv.numpy_to_image(img[:, :, None], 'mono8', 0, 'c')
    np.testing.assert_array_equal(cv.image_to_numpy(msg), img)


# ------------------------------------------------------------------------------------- compressed

def smooth_image(h=48, w=64, color=False):
    v, u = np.mgrid[0:h, 0:w]
    gray = (128 + 60 * np.sin(u / 9.0) * np.cos(v / 7.0)).astype(np.uint8)
    if not color:
        return gray
    return np.dstack([gray, np.roll(gray, 5, axis=1), 255 - gray]).astype(np.uint8)


def test_compressed_png_exact(typestore):
    gray = random_image('mono8', 13, 17, seed=5)
    msg = cv.numpy_to_compressed(gray, 'png', 99, 'cam', typestore=typestore)
    assert msg.format == 'mono8; png compressed mono8'
    np.testing.assert_array_equal(cv.compressed_to_gray(msg), gray)
    bgr = random_image('bgr8', 13, 17, seed=6)
    msg = cv.numpy_to_compressed(bgr, 'png', 99, 'cam', typestore=typestore)
    assert msg.format == 'bgr8; png compressed bgr8'
    np.testing.assert_array_equal(cv.compressed_to_gray(msg),
                                  cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


def test_compressed_png16_to_gray_high_byte():
    img = random_image('mono16', 6, 5, seed=9)
    msg = cv.numpy_to_compressed(img, 'png', 0, 'c')
    assert msg.format.startswith('mono16')
    np.testing.assert_array_equal(cv.compressed_to_gray(msg), (img >> 8).astype(np.uint8))


@pytest.mark.parametrize('color', [False, True])
def test_compressed_jpeg_tolerance(color, typestore):
    img = smooth_image(color=color)
    msg = cv.numpy_to_compressed(img, 'jpg', 5, 'cam', typestore=typestore, jpeg_quality=95)
    assert 'jpeg compressed' in msg.format
    gray = cv.compressed_to_gray(msg)
    ref = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if color else img
    assert gray.shape == ref.shape and gray.dtype == np.uint8
    assert np.abs(gray.astype(int) - ref.astype(int)).mean() < 2.0
    assert np.abs(gray.astype(int) - ref.astype(int)).max() < 20


def test_compressed_rosbags_to_rclpy_via_cdr():
    img = smooth_image()
    bag_msg = cv.numpy_to_compressed(img, 'png', 7, 'cam', typestore=TS)
    ros_msg = to_rclpy(bag_msg, CompressedImage)
    np.testing.assert_array_equal(cv.compressed_to_gray(ros_msg), img)


@pytest.mark.parametrize('data, fmt, match', [
    (b'', 'jpeg', r'data is empty'),
    (b'not an image at all', 'jpeg', r'could not decode 19 bytes'),
    (b'\x89PNG\r\n\x1a\n\x00\x00', 'png', r'could not decode|failed to decode'),
    (b'\xff\xd8\xff', '16UC1; compressedDepth png', r'compressedDepth'),
])
def test_compressed_errors(data, fmt, match):
    msg = CompressedImage(format=fmt)
    msg.data = array.array('B', data)
    with pytest.raises(ConversionError, match=match):
        cv.compressed_to_gray(msg)


@pytest.mark.parametrize('image, fmt, match', [
    (np.zeros((4, 4), np.uint8), 'webp', r"format 'webp' not supported"),
    (np.zeros((4, 4), np.uint16), 'jpeg', r'dtype uint16 not supported for jpeg'),
    (np.zeros((4, 4, 2), np.uint8), 'png', r'not \(H, W\) or \(H, W, 3\)'),
    (np.zeros((0, 4), np.uint8), 'png', r'not \(H, W\)'),
])
def test_numpy_to_compressed_errors(image, fmt, match):
    with pytest.raises(ConversionError, match=match):
        cv.numpy_to_compressed(image, fmt, 0, 'c')


# ------------------------------------------------------------------------------------------ stamps

@pytest.mark.parametrize('ns', [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789,
                                (2**31 - 1) * 10**9 + 999_999_999])
def test_stamp_round_trip(ns, typestore):
    stamp = cv.ns_to_stamp(ns, typestore)
    assert stamp.sec == ns // 10**9 and stamp.nanosec == ns % 10**9
    assert cv.stamp_to_ns(stamp) == ns


def test_stamp_numpy_integer():
    assert cv.stamp_to_ns(cv.ns_to_stamp(np.int64(5_000_000_001))) == 5_000_000_001


@pytest.mark.parametrize('ns, match', [
    (-1, r'negative'),
    (2**31 * 10**9, r'overflows builtin_interfaces/Time.sec'),
    (1.5, r'must be an integer'),
    (True, r'must be an integer'),
    ('1', r'must be an integer'),
])
def test_ns_to_stamp_errors(ns, match):
    with pytest.raises(ConversionError, match=match):
        cv.ns_to_stamp(ns)


def test_stamp_to_ns_errors():
    T = TS.types['builtin_interfaces/msg/Time']
    with pytest.raises(ConversionError, match=r'nanosec=1000000000 must be < 1e9'):
        cv.stamp_to_ns(T(sec=1, nanosec=10**9))
    with pytest.raises(ConversionError, match=r'sec=-1 must be >= 0'):
        cv.stamp_to_ns(Time(sec=-1, nanosec=0))
    with pytest.raises(ConversionError, match=r"no field 'sec'"):
        cv.stamp_to_ns(object())


# ------------------------------------------------------------------------------------- pointcloud

def test_pointcloud_round_trip_with_extras(typestore):
    rng = np.random.default_rng(1)
    n = 50
    xyz = rng.normal(size=(n, 3))
    extras = {
        'id': np.arange(n, dtype=np.uint32) + 4_000_000_000,
        'score': rng.random(n).astype(np.float32),
        'depth_var': rng.random(n),  # float64 kept
        'level': rng.integers(-5, 5, n).astype(np.int16),
        'inlier': rng.random(n) > 0.5,  # bool -> uint8
        'track': np.arange(n),  # int64 -> uint32
        'signed': -np.arange(n),  # int64 negative -> int32
    }
    msg = cv.points_to_pointcloud2(xyz, 7, 'map', extras, typestore=typestore)
    assert msg.height == 1 and msg.width == n and not msg.is_bigendian and msg.is_dense
    assert msg.row_step == msg.point_step * n and len(msg.data) == msg.row_step
    types = {f.name: (f.datatype, f.offset) for f in msg.fields}
    assert types['x'] == (PointField.FLOAT32, 0) and types['y'] == (7, 4) and types['z'] == (7, 8)
    assert types['id'][0] == PointField.UINT32 and types['score'][0] == PointField.FLOAT32
    assert types['depth_var'][0] == PointField.FLOAT64 and types['depth_var'][1] % 8 == 0
    assert types['level'][0] == PointField.INT16 and types['inlier'][0] == PointField.UINT8
    assert types['track'][0] == PointField.UINT32 and types['signed'][0] == PointField.INT32
    out = cv.pointcloud2_to_numpy(msg)
    np.testing.assert_array_equal(out['x'], xyz[:, 0].astype(np.float32))
    np.testing.assert_array_equal(np.stack([out['x'], out['y'], out['z']], 1),
                                  xyz.astype(np.float32))
    np.testing.assert_array_equal(out['id'], extras['id'])
    np.testing.assert_array_equal(out['score'], extras['score'])
    np.testing.assert_array_equal(out['depth_var'], extras['depth_var'])
    np.testing.assert_array_equal(out['level'], extras['level'])
    np.testing.assert_array_equal(out['inlier'], extras['inlier'].astype(np.uint8))
    np.testing.assert_array_equal(out['track'], extras['track'])
    np.testing.assert_array_equal(out['signed'], extras['signed'])
    np.testing.assert_allclose(cv.pointcloud2_to_xyz(msg), xyz, atol=1e-6)


def test_pointcloud_zero_copy_view():
    msg = cv.points_to_pointcloud2(np.ones((4, 3)), 0, 'm', typestore=TS)
    x = cv.pointcloud2_to_numpy(msg)['x']
    assert np.shares_memory(x, msg.data)
    assert not np.shares_memory(cv.pointcloud2_to_numpy(msg, copy=True)['x'], msg.data)


def test_pointcloud_empty(typestore):
    msg = cv.points_to_pointcloud2(np.zeros((0, 3)), 0, 'map', {'id': np.zeros(0, np.uint32)},
                                   typestore=typestore)
    assert msg.width == 0 and len(msg.data) == 0 and msg.is_dense
    out = cv.pointcloud2_to_numpy(msg)
    assert set(out) == {'x', 'y', 'z', 'id'}
    assert out['x'].shape == (0,) and out['id'].dtype == np.uint32
    assert cv.pointcloud2_to_xyz(msg).shape == (0, 3)
    bag_msg = cv.points_to_pointcloud2(np.zeros((0, 3)), 0, 'm', typestore=TS)
    ros_msg = to_rclpy(bag_msg, PointCloud2)
    assert cv.pointcloud2_to_xyz(ros_msg).shape == (0, 3)


def test_pointcloud_nan_not_dense():
    xyz = np.ones((3, 3))
    xyz[1, 2] = np.nan
    msg = cv.points_to_pointcloud2(xyz, 0, 'map')
    assert msg.is_dense is False
    assert np.isnan(cv.pointcloud2_to_numpy(msg)['z'][1])
    assert cv.pointcloud2_to_xyz(msg, drop_invalid=True).shape == (2, 3)


def test_pointcloud_point_step_padding(typestore):
    xyz = np.arange(15, dtype=float).reshape(5, 3)
    msg = cv.points_to_pointcloud2(xyz, 0, 'map', {'w': np.ones(5, np.float32)},
                                   typestore=typestore, point_step_padding=7)
    assert msg.point_step == 16 + 7
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(msg), xyz)
    np.testing.assert_array_equal(cv.pointcloud2_to_numpy(msg)['w'], np.ones(5))


def test_pointcloud_rosbags_to_rclpy_via_cdr():
    xyz = np.random.default_rng(2).normal(size=(20, 3))
    bag_msg = cv.points_to_pointcloud2(xyz, 11, 'map', {'id': np.arange(20, dtype=np.uint32)},
                                       typestore=TS)
    ros_msg = to_rclpy(bag_msg, PointCloud2)
    a, b = cv.pointcloud2_to_numpy(bag_msg), cv.pointcloud2_to_numpy(ros_msg)
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def _cloud(fields, height, width, point_step, row_step, data, bigendian=False, typestore=TS):
    f = TS.types if typestore is TS else None
    if f is None:
        pfs = [PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields]
        msg = PointCloud2(height=height, width=width, fields=pfs, is_bigendian=bigendian,
                          point_step=point_step, row_step=row_step, is_dense=True)
        msg.data = array.array('B', bytes(data))
        return msg
    pfs = [f['sensor_msgs/msg/PointField'](name=n, offset=o, datatype=d, count=c)
           for n, o, d, c in fields]
    header = f['std_msgs/msg/Header'](stamp=f['builtin_interfaces/msg/Time'](0, 0), frame_id='m')
    return f['sensor_msgs/msg/PointCloud2'](header=header, height=height, width=width, fields=pfs,
                                            is_bigendian=bigendian, point_step=point_step,
                                            row_step=row_step,
                                            data=np.frombuffer(bytes(data), np.uint8).copy(),
                                            is_dense=True)


def test_pointcloud_organized_bigendian_rowpad_count(typestore):
    """Hand-made H=3, W=4 cloud: big-endian, row padding, a count-3 field and a uint16 field."""
    h, w, point_step, row_step = 3, 4, 20, 4 * 20 + 6
    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(h, w, 3)).astype('>f4')
    ring = rng.integers(0, 60000, size=(h, w)).astype('>u2')
    buf = np.zeros(h * row_step, np.uint8)
    for r in range(h):
        for c in range(w):
            base = r * row_step + c * point_step
            buf[base:base + 12] = np.frombuffer(xyz[r, c].tobytes(), np.uint8)
            buf[base + 14:base + 16] = np.frombuffer(ring[r, c:c + 1].tobytes(), np.uint8)
    fields = [('xyz', 0, PointField.FLOAT32, 3), ('ring', 14, PointField.UINT16, 1)]
    msg = _cloud(fields, h, w, point_step, row_step, buf, bigendian=True, typestore=typestore)
    out = cv.pointcloud2_to_numpy(msg)
    assert out['xyz'].shape == (h * w, 3) and out['xyz'].dtype == np.float32
    assert out['xyz'].dtype.isnative and out['ring'].dtype.isnative
    np.testing.assert_array_equal(out['xyz'], xyz.reshape(-1, 3).astype(np.float32))
    np.testing.assert_array_equal(out['ring'], ring.reshape(-1).astype(np.uint16))
    org = cv.pointcloud2_to_numpy(msg, organized=True)
    assert org['xyz'].shape == (h, w, 3) and org['ring'].shape == (h, w)
    np.testing.assert_array_equal(org['ring'], ring)
    with pytest.raises(ConversionError, match=r"missing field\(s\) \['x', 'y', 'z'\]"):
        cv.pointcloud2_to_xyz(msg)


@pytest.mark.parametrize('fields, h, w, ps, rs, n, match', [
    ([('x', 0, 7, 1)], 1, 4, 4, 16, 15, r'data has 15 bytes, expected at least 1\*16=16'),
    ([('x', 0, 9, 1)], 1, 1, 4, 4, 4, r"field 'x' has unknown datatype 9"),
    ([('x', 0, 7, 1), ('x', 4, 7, 1)], 1, 1, 8, 8, 8, r"duplicate field 'x'"),
    ([('x', 2, 7, 1)], 1, 1, 4, 4, 4, r"spans bytes \[2, 6\) beyond point_step=4"),
    ([('x', 0, 7, 1)], 2, 2, 4, 7, 16, r'row_step=7 is smaller than width\*point_step=2\*4'),
    ([('', 0, 7, 1)], 1, 1, 4, 4, 4, r'field name .* non-empty'),
    ([('x', 0, 7, 0)], 1, 1, 4, 4, 4, r'count=0 must be >= 1'),
])
def test_pointcloud_errors(fields, h, w, ps, rs, n, match):
    with pytest.raises(ConversionError, match=match):
        cv.pointcloud2_to_numpy(_cloud(fields, h, w, ps, rs, bytes(n)))


@pytest.mark.parametrize('xyz, extras, match', [
    (np.zeros((3, 2)), None, r'expected \(N, 3\)'),
    (np.zeros((3, 3)), {'x': np.zeros(3)}, r"'x' clashes"),
    (np.zeros((3, 3)), {'id': np.zeros(4)}, r"'id' has shape \(4,\), expected \(3,\)"),
    (np.zeros((3, 3)), {'c': np.zeros(3, complex)}, r'unsupported dtype complex128'),
    (np.zeros((3, 3)), {'big': np.array([0, 1, 2**40])}, r'do not fit 32 bits'),
])
def test_points_to_pointcloud2_errors(xyz, extras, match):
    with pytest.raises(ConversionError, match=match):
        cv.points_to_pointcloud2(xyz, 0, 'm', extras)


# ------------------------------------------------------------------------------------ camera info

def test_camera_info_round_trip(typestore):
    D = [0.1, -0.2, 0.001, 0.002, 0.05]
    msg = cv.camera_info_from_params(640, 480, K, D, 'plumb_bob', 77, 'cam', typestore=typestore)
    info = cv.camera_info_to_dict(msg)
    cv.validate_camera_info(info)
    assert info['width'] == 640 and info['height'] == 480
    assert info['distortion_model'] == 'plumb_bob' and info['frame_id'] == 'cam'
    assert info['stamp_ns'] == 77
    np.testing.assert_array_equal(info['K'], K)
    np.testing.assert_array_equal(info['D'], D)
    np.testing.assert_array_equal(info['R'], np.eye(3))
    np.testing.assert_array_equal(info['P'], np.hstack([K, np.zeros((3, 1))]))
    assert info['roi'] == {'x_offset': 0, 'y_offset': 0, 'width': 0, 'height': 0,
                           'do_rectify': False}
    assert info['binning_x'] == 0 and info['binning_y'] == 0


def test_camera_info_rosbags_to_rclpy_via_cdr():
    bag_msg = cv.camera_info_from_params(320, 240, K, np.zeros(8), 'rational_polynomial', 3,
                                         'cam', typestore=TS)
    ros_msg = to_rclpy(bag_msg, CameraInfo)
    a, b = cv.camera_info_to_dict(bag_msg), cv.camera_info_to_dict(ros_msg)
    for key in ('K', 'D', 'R', 'P'):
        np.testing.assert_array_equal(a[key], b[key])
    assert a['distortion_model'] == b['distortion_model'] == 'rational_polynomial'
    cv.validate_camera_info(b)


def test_camera_info_uppercase_fields_fallback():
    """ROS 1 style upper-case fields are read too (duck typing)."""
    ros1_info = SimpleNamespace(  # a plain record with ROS 1 field names
        width=10, height=8, distortion_model='plumb_bob', K=K.reshape(-1).tolist(), D=[0.0] * 5,
        R=np.eye(3).reshape(-1).tolist(), P=np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist())
    info = cv.camera_info_to_dict(ros1_info)
    np.testing.assert_array_equal(info['K'], K)
    assert info['P'].shape == (3, 4)


def good_info(**kw):
    info = {'width': 640, 'height': 480, 'K': K.copy(), 'D': np.zeros(5),
            'distortion_model': 'plumb_bob', 'R': np.eye(3), 'P': np.hstack([K, np.zeros((3, 1))])}
    info.update(kw)
    return info


def _with(arr, idx, value):
    arr = np.array(arr, dtype=float)
    arr[idx] = value
    return arr


@pytest.mark.parametrize('kw, match', [
    (dict(width=0), r'width=0 must be a positive integer'),
    (dict(height=0), r'height=0 must be a positive integer'),
    (dict(K=np.zeros((3, 3))), r'K\[0\] \(fx\) is 0, the camera is uncalibrated'),
    (dict(K=_with(K, (0, 2), np.nan)), r'K contains NaN or inf'),
    (dict(K=_with(K, (1, 1), np.inf)), r'K contains NaN or inf'),
    (dict(D=[0, 0, np.nan, 0, 0]), r'D contains NaN or inf'),
    (dict(P=_with(np.hstack([K, np.zeros((3, 1))]), (2, 3), np.inf)), r'P contains NaN or inf'),
    (dict(K=_with(K, (0, 0), -500.0)), r'focal lengths must be positive, got fx=-500'),
    (dict(K=_with(K, (1, 1), 0.0)), r'focal lengths must be positive, got fx=500.0, fy=0.0'),
    (dict(K=_with(K, (2, 2), 0.0)), r'last row \(0, 0, 1\)'),
    (dict(K=np.eye(2)), r'K has shape \(2, 2\), expected \(3, 3\)'),
    (dict(distortion_model='fisheye'), r"unknown distortion_model 'fisheye' \(allowed: plumb_bob"),
    (dict(D=np.zeros(4)), r"'plumb_bob' needs 5 coefficients in D, got 4"),
    (dict(distortion_model='rational_polynomial', D=np.zeros(6)),
     r"'rational_polynomial' needs 8 or 5 coefficients in D, got 6"),
    (dict(distortion_model='equidistant', D=np.zeros(5)), r"'equidistant' needs 4 coefficients"),
    (dict(distortion_model='', D=[0.1, 0, 0, 0, 0]),
     r"distortion_model '' requires D to be all zero"),
    (dict(distortion_model='none', D=[0, 0.3]), r"'none' requires D to be all zero"),
])
def test_validate_camera_info_rejects(kw, match):
    with pytest.raises(ConversionError, match=match):
        cv.validate_camera_info(good_info(**kw))


@pytest.mark.parametrize('kw', [
    dict(),
    dict(distortion_model='rational_polynomial', D=np.zeros(8)),
    dict(distortion_model='rational_polynomial', D=np.zeros(5)),
    dict(distortion_model='equidistant', D=[0.1, 0.01, 0.0, 0.0]),
    dict(distortion_model='', D=[]),
    dict(distortion_model='none', D=np.zeros(5)),
])
def test_validate_camera_info_accepts(kw):
    cv.validate_camera_info(good_info(**kw))


def test_uncalibrated_camera_info_message_rejected():
    """A default CameraInfo (what an uncalibrated driver publishes) fails validation."""
    info = cv.camera_info_to_dict(CameraInfo(width=640, height=480))
    with pytest.raises(ConversionError, match='uncalibrated'):
        cv.validate_camera_info(info)


def test_camera_info_from_params_validates():
    with pytest.raises(ConversionError, match='needs 5 coefficients'):
        cv.camera_info_from_params(640, 480, K, [0.1, 0.2], 'plumb_bob', 0, 'cam')


# ----------------------------------------------------------------------------- rotations/odometry

def test_quaternions_against_scipy():
    rots = Rotation.random(200, random_state=np.random.default_rng(0))
    special = Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi],
                                    [np.pi / np.sqrt(2), np.pi / np.sqrt(2), 0],
                                    [0, 0, 0], [1e-9, 0, 0], [0, 0, np.pi - 1e-7]])
    for rot in list(rots) + list(special):
        R = rot.as_matrix()
        q = cv.matrix_to_quat_xyzw(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        q_ref = rot.as_quat(canonical=True)
        np.testing.assert_allclose(q, q_ref, atol=1e-9)
        np.testing.assert_allclose(cv.quat_xyzw_to_matrix(q), R, atol=1e-12)
        np.testing.assert_allclose(cv.quat_xyzw_to_matrix(rot.as_quat()), R, atol=1e-12)


def test_quat_to_matrix_normalises_and_rejects():
    np.testing.assert_allclose(cv.quat_xyzw_to_matrix([0, 0, 0, 5.0]), np.eye(3))
    with pytest.raises(ConversionError, match='zero norm'):
        cv.quat_xyzw_to_matrix([0, 0, 0, 0])
    with pytest.raises(ConversionError, match='NaN or inf'):
        cv.quat_xyzw_to_matrix([np.nan, 0, 0, 1])
    with pytest.raises(ConversionError, match='not a rotation matrix'):
        cv.matrix_to_quat_xyzw(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ConversionError, match='not a rotation matrix'):
        cv.matrix_to_quat_xyzw(2 * np.eye(3))


def random_pose(seed=0):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def random_cov(seed=0, scale=1e-3):
    A = np.random.default_rng(seed).normal(size=(6, 6))
    return scale * (A @ A.T + 0.1 * np.eye(6))


def test_odometry_round_trip(typestore):
    T, Cp, Ct = random_pose(1), random_cov(2), random_cov(3, 1e-2)
    v, w = np.array([0.5, -0.1, 0.02]), np.array([0.0, 0.01, -0.3])
    msg = cv.pose_to_odometry(T, Cp, v, w, Ct, 1_000_000_123, 'odom', 'base_link', typestore)
    assert msg.header.frame_id == 'odom' and msg.child_frame_id == 'base_link'
    assert msg.pose.pose.orientation.w >= 0
    np.testing.assert_array_equal(np.asarray(msg.pose.covariance), Cp.reshape(-1))  # row-major
    T2, Cp2, tw, Ct2 = cv.odometry_to_pose(msg)
    np.testing.assert_allclose(T2, T, atol=1e-12)
    np.testing.assert_array_equal(Cp2, Cp)
    np.testing.assert_array_equal(Ct2, Ct)
    np.testing.assert_array_equal(tw, np.concatenate([v, w]))


def test_odometry_covariance_row_major_order():
    C = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    C[0, 5] = C[5, 0] = 0.5
    msg = cv.pose_to_odometry(np.eye(4), C, np.zeros(3), np.zeros(3), np.eye(6), 0, 'o', 'b')
    assert msg.pose.covariance[5] == 0.5 and msg.pose.covariance[30] == 0.5
    assert msg.pose.covariance[7] == 2.0 and msg.pose.covariance[35] == 6.0


def test_odometry_rosbags_to_rclpy_via_cdr():
    T, Cp, Ct = random_pose(5), random_cov(6), random_cov(7)
    bag_msg = cv.pose_to_odometry(T, Cp, [1, 2, 3], [4, 5, 6], Ct, 9, 'odom', 'base', TS)
    ros_msg = to_rclpy(bag_msg, Odometry)
    for a, b in zip(cv.odometry_to_pose(bag_msg), cv.odometry_to_pose(ros_msg)):
        np.testing.assert_array_equal(a, b)


def _nan_at(M, idx):
    M = M.copy()
    M[idx] = np.nan
    return M


@pytest.mark.parametrize('case, match', [
    ('pose_nan', r'pose covariance contains NaN or inf'),
    ('pose_zero', r'pose covariance has a non-positive diagonal'),
    ('twist_zero', r'twist covariance has a non-positive diagonal'),
    ('twist_inf', r'twist covariance contains NaN or inf'),
    ('neg_diag', r'non-positive diagonal'),
    ('asym', r'pose covariance is not symmetric'),
    ('not_psd', r'not positive semi-definite'),
    ('T_nan', r'T contains NaN or inf'),
    ('T_bad_rot', r'not a rotation matrix'),
    ('T_bad_row', r'last row of T'),
    ('v_nan', r'twist_lin contains NaN or inf'),
    ('w_shape', r'twist_ang has shape'),
    ('stamp', r'negative'),
])
def test_odometry_refuses(case, match):
    T, Cp, Ct = random_pose(), random_cov(1), random_cov(2)
    v, w, stamp = np.zeros(3), np.zeros(3), 0
    if case == 'pose_nan':
        Cp = _nan_at(Cp, (2, 2))
    elif case == 'pose_zero':
        Cp = np.zeros((6, 6))
    elif case == 'twist_zero':
        Ct = np.zeros((6, 6))
    elif case == 'twist_inf':
        Ct = Ct.copy()
        Ct[0, 1] = Ct[1, 0] = np.inf
    elif case == 'neg_diag':
        Cp = np.diag([1.0, 1, 1, 1, 1, -1e-6])
    elif case == 'asym':
        Cp = Cp.copy()
        Cp[0, 3] += 1e-3
    elif case == 'not_psd':
        Cp = np.eye(6)
        Cp[0, 1] = Cp[1, 0] = 2.0
    elif case == 'T_nan':
        T = _nan_at(T, (0, 3))
    elif case == 'T_bad_rot':
        T = T.copy()
        T[:3, :3] *= 1.1
    elif case == 'T_bad_row':
        T = T.copy()
        T[3, 0] = 1.0
    elif case == 'v_nan':
        v = np.array([0.0, np.nan, 0.0])
    elif case == 'w_shape':
        w = np.zeros(4)
    elif case == 'stamp':
        stamp = -5
    with pytest.raises(ConversionError, match=match):
        cv.pose_to_odometry(T, Cp, v, w, Ct, stamp, 'odom', 'base')


def test_pose_stamped_round_trip(typestore):
    T = random_pose(9)
    msg = cv.matrix_to_pose_stamped(T, 5, 'world', typestore)
    assert msg.header.frame_id == 'world'
    np.testing.assert_allclose(cv.pose_stamped_to_matrix(msg), T, atol=1e-12)
    if typestore is TS:
        ros_msg = to_rclpy(msg, PoseStamped)
        np.testing.assert_allclose(cv.pose_stamped_to_matrix(ros_msg), T, atol=1e-12)


def test_transform_pose_covariance():
    C = random_cov(4)
    R = Rotation.random(random_state=np.random.default_rng(5)).as_matrix()
    out = cv.transform_pose_covariance(C, R)
    J = np.zeros((6, 6))
    J[:3, :3] = J[3:, 3:] = R
    np.testing.assert_allclose(out, J @ C @ J.T, atol=1e-15)
    np.testing.assert_allclose(out, out.T, atol=0)
    np.testing.assert_allclose(cv.transform_pose_covariance(out, R.T), C, atol=1e-14)
    iso = np.diag([2.0, 2, 2, 3, 3, 3])
    np.testing.assert_allclose(cv.transform_pose_covariance(iso, R), iso, atol=1e-14)
    # empirical check: samples rotated by blockdiag(R, R) have covariance J C J^T
    rng = np.random.default_rng(6)
    samples = rng.multivariate_normal(np.zeros(6), C, size=20_000) @ J.T
    np.testing.assert_allclose(np.cov(samples.T), out, atol=0.1 * np.abs(out).max())
    with pytest.raises(ConversionError, match='not a rotation matrix'):
        cv.transform_pose_covariance(C, np.ones((3, 3)))
