"""Property tests: malformed messages give a correct array or ConversionError, never another error.

Messages are real rclpy and rosbags classes, filled with hypothesis-chosen layouts and data.
"""
from __future__ import annotations

import array

import cv2
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header

from ekf_vo import bridge as cv
from ekf_vo.bridge import ConversionError

TS = get_typestore(Stores.ROS2_JAZZY)
FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
ENCODINGS = sorted(cv.IMAGE_ENCODINGS) + ['mono 8', '32FC1', 'yuv422', '', 'MONO8']


@pytest.fixture(autouse=True, scope='module')
def quiet_opencv():
    """OpenCV logs decoder complaints about garbage input to stderr; silence it here only."""
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    yield
    cv2.utils.logging.setLogLevel(previous)


def bag_header():
    return TS.types['std_msgs/msg/Header'](stamp=TS.types['builtin_interfaces/msg/Time'](1, 0),
                                           frame_id='c')


def wrap_data(raw: bytes, container: str, backend: str):
    if container == 'bytes':
        return raw
    if container == 'list':
        return list(raw)
    if container == 'numpy' or backend == 'rosbags':
        return np.frombuffer(raw, np.uint8).copy()
    return array.array('B', raw)


@st.composite
def image_messages(draw):
    encoding = draw(st.one_of(st.sampled_from(sorted(cv.IMAGE_ENCODINGS)),
                              st.sampled_from(ENCODINGS)))
    height = draw(st.sampled_from(range(13)))
    width = draw(st.sampled_from(range(13)))
    kind, ch = cv.IMAGE_ENCODINGS.get(encoding, ('u1', 1))
    row_bytes = width * ch * int(kind[1])
    step = max(0, row_bytes + draw(st.sampled_from([0, 0, 0, 1, 2, 3, 5, -1, -3])))
    n = max(0, step * height + draw(st.sampled_from([0, 0, 0, 1, 4, -1, -8])))
    raw = draw(st.binary(min_size=n, max_size=n))
    bigendian = draw(st.booleans())
    backend = draw(st.sampled_from(['rclpy', 'rosbags']))
    data = wrap_data(raw, draw(st.sampled_from(['bytes', 'list', 'numpy', 'array'])), backend)
    fields = dict(height=height, width=width, encoding=encoding, is_bigendian=int(bigendian),
                  step=step)
    if backend == 'rclpy':
        msg = Image(**fields)
        msg.data = data if not isinstance(data, np.ndarray) else array.array('B', data.tobytes())
    else:
        header = bag_header()
        msg = TS.types['sensor_msgs/msg/Image'](header=header, data=data, **fields)
    return msg, raw


@FUZZ
@given(image_messages())
def test_fuzz_image(sample):
    msg, raw = sample
    encoding = msg.encoding.strip()
    try:
        img = cv.image_to_numpy(msg)
    except ConversionError as exc:
        event('Image rejected')
        assert str(exc).startswith('Image:') and '\n' not in str(exc)
        with pytest.raises(ConversionError):
            cv.image_to_gray(msg)
        return
    event('Image converted')
    kind, ch = cv.IMAGE_ENCODINGS[encoding]
    assert img.shape == ((msg.height, msg.width) if ch == 1 else (msg.height, msg.width, ch))
    assert img.dtype == (np.uint8 if kind == 'u1' else np.uint16) and img.dtype.isnative
    # independent reference: pick each row out of the raw bytes
    dt = np.dtype(('>' if msg.is_bigendian else '<') + kind)
    row_bytes = msg.width * ch * dt.itemsize
    for v in range(msg.height):
        row = np.frombuffer(raw[v * msg.step:v * msg.step + row_bytes], dtype=dt)
        np.testing.assert_array_equal(img[v].reshape(-1), row)
    gray = cv.image_to_gray(msg)
    assert gray.shape == (msg.height, msg.width) and gray.dtype == np.uint8


def _valid_codec_bytes(seed: int, fmt: str) -> bytes:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, size=(rng.integers(1, 24), rng.integers(1, 24), 3), dtype=np.uint8)
    return cv2.imencode('.' + fmt, img)[1].tobytes()


@st.composite
def compressed_payloads(draw):
    mode = draw(st.sampled_from(['random', 'truncated', 'corrupted', 'prefixed']))
    if mode == 'random':
        return draw(st.binary(max_size=256))
    valid = _valid_codec_bytes(draw(st.integers(0, 2**16)), draw(st.sampled_from(['jpg', 'png'])))
    if mode == 'truncated':
        return valid[:draw(st.integers(0, len(valid)))]
    if mode == 'prefixed':  # a real magic number followed by garbage
        return valid[:draw(st.integers(2, 24))] + draw(st.binary(max_size=128))
    data = bytearray(valid)  # corrupt bytes after the headers (keeps image sizes bounded)
    for _ in range(draw(st.integers(1, 8))):
        pos = draw(st.integers(len(data) // 2, len(data) - 1))
        data[pos] = draw(st.integers(0, 255))
    return bytes(data)


@FUZZ
@given(compressed_payloads(), st.sampled_from(['jpeg', 'png', 'bgr8; jpeg compressed bgr8', '']),
       st.sampled_from(['rclpy', 'rosbags']))
def test_fuzz_compressed(payload, fmt, backend):
    if backend == 'rclpy':
        msg = CompressedImage(format=fmt)
        msg.data = array.array('B', payload)
    else:
        header = bag_header()
        msg = TS.types['sensor_msgs/msg/CompressedImage'](
            header=header, format=fmt, data=np.frombuffer(payload, np.uint8).copy())
    try:
        gray = cv.compressed_to_gray(msg)
    except ConversionError as exc:
        event('CompressedImage rejected')
        assert str(exc).startswith('CompressedImage:')
        return
    event('CompressedImage decoded')
    assert gray.dtype == np.uint8 and gray.ndim == 2 and gray.size > 0


@st.composite
def pointcloud_messages(draw):
    """Half consistent layouts (overlapping fields allowed), half arbitrary ones."""
    height = draw(st.integers(0, 4))
    width = draw(st.integers(0, 6))
    fields = []
    if draw(st.booleans()):  # consistent layout
        names = draw(st.lists(st.sampled_from(['x', 'y', 'z', 'id', 'rgb', 'ring']), unique=True,
                              min_size=1, max_size=4))
        for name in names:
            datatype = draw(st.integers(1, 8))
            fields.append((name, draw(st.integers(0, 16)), datatype, draw(st.integers(1, 3))))
        ends = [o + cv.POINTFIELD_DTYPES[d].itemsize * c for _, o, d, c in fields]
        point_step = max(ends, default=0) + draw(st.integers(0, 6))
        row_step = width * point_step + draw(st.integers(0, 7))
        n = row_step * height + draw(st.integers(0, 5))
    else:  # arbitrary layout
        for i in range(draw(st.integers(0, 5))):
            name = draw(st.sampled_from(['x', 'y', 'z', 'id', f'f{i}', '']))
            fields.append((name, draw(st.integers(0, 40)), draw(st.integers(0, 9)),
                           draw(st.integers(0, 3))))
        point_step = draw(st.integers(0, 48))
        row_step = max(0, width * point_step + draw(st.integers(-4, 8)))
        n = max(0, row_step * height + draw(st.integers(-6, 3)))
    raw = draw(st.binary(min_size=n, max_size=n))
    bigendian = draw(st.booleans())
    if draw(st.booleans()):
        msg = PointCloud2(header=Header(stamp=Time(sec=1), frame_id='m'), height=height,
                          width=width, is_bigendian=bigendian, point_step=point_step,
                          row_step=row_step, is_dense=False,
                          fields=[PointField(name=a, offset=b, datatype=c, count=d)
                                  for a, b, c, d in fields])
        msg.data = array.array('B', raw)
    else:
        T = TS.types
        msg = T['sensor_msgs/msg/PointCloud2'](
            header=bag_header(),
            height=height, width=width,
            fields=[T['sensor_msgs/msg/PointField'](name=a, offset=b, datatype=c, count=d)
                    for a, b, c, d in fields],
            is_bigendian=bigendian, point_step=point_step, row_step=row_step,
            data=np.frombuffer(raw, np.uint8).copy(), is_dense=False)
    return msg, raw


@FUZZ
@given(pointcloud_messages(), st.booleans())
def test_fuzz_pointcloud(sample, organized):
    msg, raw = sample
    try:
        out = cv.pointcloud2_to_numpy(msg, organized=organized)
    except ConversionError as exc:
        event('PointCloud2 rejected')
        assert str(exc).startswith(('PointCloud2', 'PointField')) and '\n' not in str(exc)
        return
    event('PointCloud2 converted' + (' (non-empty)' if out and msg.height * msg.width else ''))
    assert list(out) == [f.name for f in msg.fields]
    h, w = msg.height, msg.width
    for f in msg.fields:
        col = out[f.name]
        base = (h, w) if organized else (h * w,)
        assert col.shape == base + (() if f.count == 1 else (f.count,))
        assert col.dtype.isnative
        if h * w:  # compare the last point with a direct decode of its bytes
            dt = np.dtype(cv.POINTFIELD_DTYPES[f.datatype])
            dt = dt.newbyteorder('>' if msg.is_bigendian else '<')
            start = (h - 1) * msg.row_step + (w - 1) * msg.point_step + f.offset
            ref = np.frombuffer(raw[start:start + dt.itemsize * f.count], dtype=dt)
            last = col[-1, -1] if organized else col[-1]
            np.testing.assert_array_equal(np.asarray(last).reshape(-1), ref)


@FUZZ
@given(st.integers(0, 2**16), st.integers(0, 30), st.dictionaries(
    st.text(alphabet='abcdefgh', min_size=1, max_size=4),
    st.sampled_from(['float32', 'float64', 'uint32', 'int16', 'uint8', 'int8', 'bool', 'int64']),
    max_size=4), st.integers(0, 9), st.booleans())
def test_fuzz_pointcloud_round_trip(seed, n, extra_types, padding, use_rosbags):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * 10
    if n and rng.random() < 0.3:
        xyz[rng.integers(n), rng.integers(3)] = np.nan
    extras = {name: (rng.random(n) * 100).astype(dt) for name, dt in extra_types.items()
              if name not in ('x', 'y', 'z')}
    msg = cv.points_to_pointcloud2(xyz, 0, 'map', extras, typestore=TS if use_rosbags else None,
                                   point_step_padding=padding)
    assert msg.is_dense == bool(np.isfinite(xyz).all())
    out = cv.pointcloud2_to_numpy(msg)
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(msg), xyz.astype(np.float32).astype(float))
    for name, values in extras.items():
        np.testing.assert_array_equal(out[name], values)


@FUZZ
@given(st.integers(-2**64, 2**64))
def test_fuzz_stamps(ns):
    try:
        stamp = cv.ns_to_stamp(ns)
    except ConversionError:
        assert ns < 0 or ns >= 2**31 * 10**9
        return
    assert cv.stamp_to_ns(stamp) == ns
