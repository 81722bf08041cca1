"""rosbag2 reading and writing with the pure-Python ``rosbags`` library (no ROS install needed);
ROS 1 ``.bag`` files (EuRoC, TUM RGB-D) are read too, their messages converted to ROS 2.

Messages are built from, and deserialized into, the ``rosbags`` typestore classes of ROS 2
Jazzy (``Stores.ROS2_JAZZY``) and (de)serialized as CDR.  Bags are written with the MCAP
storage plugin (rosbag2 format version 9) by default, the Jazzy default.

Conventions: stamps are integer nanoseconds; ``T_world_cam`` is the 4x4 pose of the camera
frame in the world frame (maps camera-frame points to world-frame points); quaternions are
``*_xyzw`` (scalar last, ROS order). Messages are built and read by :mod:`ekf_vo.bridge`;
images read from a bag are decoded with the bridge's one decoder, :func:`decode_image`
(re-exported here).
"""
from __future__ import annotations

import functools
import logging
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from rosbags.convert.converter import is_same_wireformat, migrate_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.reader import Connection
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from ..bridge.camera_info import camera_info_from_params
from ..bridge.common import (CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, POSE_STAMPED, ns_to_stamp,
                             stamp_to_ns)
from ..bridge.image import numpy_to_image
from ..bridge.odometry import matrix_to_pose_stamped, pose_msg_to_matrix, quat_xyzw_to_matrix

logger = logging.getLogger(__name__)

#: message types (from the bridge), writers and readers
__all__ = ['IMAGE', 'COMPRESSED_IMAGE', 'CAMERA_INFO', 'POSE_STAMPED',
           'typestore', 'ns_to_time', 'time_to_ns', 'make_header', 'image_msg',
           'compressed_msg', 'camera_info_msg', 'pose_stamped_msg', 'pose_to_matrix',
           'BagWriter', 'BagError', 'is_ros1_bag', 'bag_topics', 'topic_counts', 'read_raw',
           'iter_bag', 'read_ground_truth']

_TYPESTORE: Typestore | None = None


def typestore() -> Typestore:
    """Return the shared ROS 2 Jazzy typestore (created on first use)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


# --------------------------------------------------------------------------- message helpers
def ns_to_time(stamp_ns: int) -> Any:
    """builtin_interfaces/Time for an integer nanosecond stamp."""
    return ns_to_stamp(stamp_ns, typestore())


def time_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time (rosbags or rclpy object)."""
    return stamp_to_ns(stamp)


def make_header(stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the given stamp and frame."""
    return typestore().types['std_msgs/msg/Header'](stamp=ns_to_time(stamp_ns), frame_id=frame_id)


def image_msg(image: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/Image from a uint8 array: (H, W) -> mono8, (H, W, 3) BGR -> bgr8."""
    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f'image must be uint8, got {img.dtype}')
    if img.ndim == 2:
        encoding = 'mono8'
    elif img.ndim == 3 and img.shape[2] == 3:
        encoding = 'bgr8'
    else:
        raise ValueError(f'unsupported image shape {img.shape}')
    return numpy_to_image(img, encoding, stamp_ns, frame_id, typestore=typestore())


def compressed_msg(image: np.ndarray, stamp_ns: int, frame_id: str, fmt: str = 'jpeg',
                   quality: int = 90) -> Any:
    """sensor_msgs/CompressedImage (jpeg or png) from a mono8 / bgr8 uint8 array.

    ``format`` follows compressed_image_transport: ``"mono8; jpeg compressed "`` for mono,
    ``"bgr8; jpeg compressed bgr8"`` for colour.
    """
    img = np.ascontiguousarray(image)
    encoding = 'mono8' if img.ndim == 2 else 'bgr8'
    fmt = fmt.lower()
    if fmt in ('jpeg', 'jpg'):
        ok, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        fmt = 'jpeg'
    elif fmt == 'png':
        ok, buf = cv2.imencode('.png', img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    else:
        raise ValueError(f'unsupported compressed format {fmt!r}')
    if not ok:
        raise RuntimeError(f'cv2.imencode failed for {fmt}')
    target = 'bgr8' if encoding == 'bgr8' else ''
    return typestore().types[COMPRESSED_IMAGE](
        header=make_header(stamp_ns, frame_id), format=f'{encoding}; {fmt} compressed {target}',
        data=np.asarray(buf, dtype=np.uint8).reshape(-1))


def camera_info_msg(width: int, height: int, K: np.ndarray, D: Sequence[float],
                    distortion_model: str, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/CameraInfo with R = I and P = [K | 0]."""
    return camera_info_from_params(width, height, K, D, distortion_model, stamp_ns, frame_id,
                                   typestore())


def pose_stamped_msg(T_world_cam: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """geometry_msgs/PoseStamped of a 4x4 pose (``frame_id`` is the parent/world frame)."""
    return matrix_to_pose_stamped(T_world_cam, stamp_ns, frame_id, typestore())


def pose_to_matrix(pose: Any) -> np.ndarray:
    """4x4 matrix of a geometry_msgs/Pose (rosbags object)."""
    return pose_msg_to_matrix(pose)


# --------------------------------------------------------------------------- writing
class BagWriter:
    """Context manager writing a rosbag2 (MCAP storage by default) from numpy data.

    Example::

        with BagWriter('out_bag') as bag:
            bag.add_image('/camera/image_raw', img, stamp_ns, 'camera_optical')
    """

    def __init__(self, path: str | Path, *, storage: str = 'mcap', version: int = 9,
                 overwrite: bool = False) -> None:
        """Prepare a writer for the new bag directory ``path``.

        Args:
            path: Bag directory to create (must not exist unless ``overwrite``).
            storage: ``'mcap'`` (default) or ``'sqlite3'``.
            version: rosbag2 metadata version (8 or 9).
            overwrite: Delete an existing ``path`` first.
        """
        self.path = Path(path)
        if self.path.exists() and overwrite:
            shutil.rmtree(self.path)
        plugin = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}[storage]
        self._writer = Writer(self.path, version=version,  # type: ignore[arg-type]
                              storage_plugin=plugin)
        self._connections: dict[tuple[str, str], Connection] = {}
        self._open = False
        self.counts: dict[str, int] = {}

    def open(self) -> BagWriter:
        """Open the bag for writing (also done by ``with``)."""
        if not self._open:
            self._writer.open()
            self._open = True
        return self

    def close(self) -> None:
        """Finish the bag (writes metadata.yaml)."""
        if self._open:
            self._writer.close()
            self._open = False
            logger.info('wrote %s: %s', self.path, self.counts)

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _connection(self, topic: str, msgtype: str) -> Connection:
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is None:
            if any(t == topic for t, _ in self._connections):
                raise ValueError(f'topic {topic} already written with another type')
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore())
            self._connections[key] = conn
        return conn

    def write_raw(self, topic: str, msgtype: str, data: bytes | memoryview, stamp_ns: int) -> None:
        """Write already CDR-serialized ``data`` with log time ``stamp_ns``."""
        self.open()
        self._writer.write(self._connection(topic, msgtype), int(stamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        """Serialize a typestore message object and write it with log time ``stamp_ns``."""
        self.write_raw(topic, msgtype, typestore().serialize_cdr(msg, msgtype), stamp_ns)

    def add_image(self, topic: str, image: np.ndarray, stamp_ns: int, frame_id: str) -> None:
        """sensor_msgs/Image: (H, W) uint8 -> mono8, (H, W, 3) BGR uint8 -> bgr8."""
        self.write(topic, IMAGE, image_msg(image, stamp_ns, frame_id), stamp_ns)

    def add_compressed(self, topic: str, image: np.ndarray, stamp_ns: int, frame_id: str,
                       fmt: str = 'jpeg', quality: int = 90) -> None:
        """sensor_msgs/CompressedImage (``fmt`` 'jpeg' or 'png')."""
        msg = compressed_msg(image, stamp_ns, frame_id, fmt, quality)
        self.write(topic, COMPRESSED_IMAGE, msg, stamp_ns)

    def add_camera_info(self, topic: str, width: int, height: int, K: np.ndarray,
                        D: Sequence[float], distortion_model: str, stamp_ns: int,
                        frame_id: str) -> None:
        """sensor_msgs/CameraInfo with R = I, P = [K | 0]."""
        msg = camera_info_msg(width, height, K, D, distortion_model, stamp_ns, frame_id)
        self.write(topic, CAMERA_INFO, msg, stamp_ns)

    def add_odometry(self, topic: str, T_odom_base: np.ndarray, stamp_ns: int, frame_id: str,
                     child_frame_id: str, position_sigma_m: float = 0.01) -> None:
        """nav_msgs/Odometry of a pose only (twist zero, its covariance large)."""
        from ..bridge.odometry import pose_to_odometry
        cov = np.eye(6) * position_sigma_m ** 2
        msg = pose_to_odometry(T_odom_base, cov, np.zeros(3), np.zeros(3), np.eye(6) * 1e3,
                               stamp_ns, frame_id, child_frame_id, typestore())
        self.write(topic, 'nav_msgs/msg/Odometry', msg, stamp_ns)

    def add_pose(self, topic: str, T_world_cam: np.ndarray, stamp_ns: int, frame_id: str) -> None:
        """geometry_msgs/PoseStamped of ``T_world_cam``; ``frame_id`` is the world frame."""
        msg = pose_stamped_msg(T_world_cam, stamp_ns, frame_id)
        self.write(topic, POSE_STAMPED, msg, stamp_ns)


# --------------------------------------------------------------------------- reading
class BagError(ValueError):
    """A path that cannot be read as a bag (missing, not a bag, damaged); one-line message."""


def is_ros1_bag(path: str | Path) -> bool:
    """True for a ROS 1 bag file (``*.bag``); anything else is read as a rosbag2 bag."""
    path = Path(path)
    return path.suffix.lower() == '.bag' and not path.is_dir()


@contextmanager
def _open_bag(path: str | Path) -> Iterator[Reader | AnyReader]:
    """An open reader (``.connections``, ``.messages(connections=...)``) of a rosbag2
    directory (or a storage file in one) or a ROS 1 ``.bag`` file; BagError otherwise."""
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if path.is_file() and path.suffix in ('.mcap', '.db3') and \
            (path.parent / 'metadata.yaml').is_file():
        path = path.parent
    if not is_ros1_bag(path) and not (path / 'metadata.yaml').is_file():
        raise BagError(f'cannot open bag {path}: not a bag (a rosbag2 bag is a directory '
                       f'with a metadata.yaml, a ROS 1 bag a .bag file)')
    try:
        reader = AnyReader([path]) if is_ros1_bag(path) else Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for a bad bag
        raise BagError(f'cannot open bag {path}: {exc}') from None
    try:
        yield reader
    finally:
        reader.close()


def _register_unknown(connections: Iterable[Connection]) -> None:
    """Add message types found in the bag but missing from the Jazzy typestore."""
    ts = typestore()
    for conn in connections:
        if conn.msgtype in ts.types or not conn.msgdef.data:
            continue
        try:
            ts.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        except Exception as exc:  # noqa: BLE001 - IDL or broken definitions: skip, warn
            logger.warning('cannot register %s from bag definition: %s', conn.msgtype, exc)


def _ros1_to_cdr(bag_ts: Typestore, msgtypes: Iterable[str]
                 ) -> dict[str, Callable[[bytes | memoryview], bytes]]:
    """Per ROS 1 message type of a bag (typestore ``bag_ts`` from its definitions): a
    converter of its ROS 1 bytes into the CDR bytes of the same ROS 2 (Jazzy) type, byte
    for byte when the layouts match (``header.seq`` is dropped), else field by field as
    ``rosbags-convert`` does. Types missing from Jazzy are registered from the bag."""
    ts = typestore()
    out: dict[str, Callable[[bytes | memoryview], bytes]] = {}
    for msgtype in sorted(set(msgtypes)):
        try:
            if msgtype not in ts.fielddefs:
                text = bag_ts.generate_msgdef(msgtype, ros_version=2)[0]
                ts.register({k: v for k, v in get_types_from_msg(text, msgtype).items()
                             if k not in ts.fielddefs})
            if is_same_wireformat(bag_ts, ts, msgtype, msgtype):
                out[msgtype] = functools.partial(_ros1_bytes_to_cdr, ts, msgtype)
            else:
                out[msgtype] = functools.partial(_ros1_migrate_to_cdr, bag_ts, ts, msgtype, {})
        except Exception as exc:  # noqa: BLE001 - an unusual type: skip it, keep the rest
            logger.warning('skipping %s of the ROS 1 bag: %s', msgtype, exc)
    return out


def _ros1_bytes_to_cdr(ts: Typestore, msgtype: str, raw: bytes | memoryview) -> bytes:
    return bytes(ts.ros1_to_cdr(raw, msgtype))


def _ros1_migrate_to_cdr(bag_ts: Typestore, ts: Typestore, msgtype: str, cache: dict,
                         raw: bytes | memoryview) -> bytes:
    msg = migrate_message(bag_ts, ts, msgtype, msgtype, cache,
                          bag_ts.deserialize_ros1(raw, msgtype))
    return bytes(ts.serialize_cdr(msg, msgtype))


def _messages(reader: Reader | AnyReader, topics: Iterable[str] | None
              ) -> Iterator[tuple[Connection, int, bytes | memoryview]]:
    """``(connection, log time ns, CDR bytes)`` of ``topics`` (None: all) in log-time
    order; the messages of a ROS 1 bag come converted to ROS 2 CDR."""
    wanted = set(topics) if topics is not None else None
    conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
    convert: dict[str, Callable[[bytes | memoryview], bytes]] = {}
    if isinstance(reader, AnyReader):
        convert = _ros1_to_cdr(reader.typestore, (c.msgtype for c in conns))
        conns = [c for c in conns if c.msgtype in convert]
    else:
        _register_unknown(conns)
    if not conns:          # (no connections would mean "all" to rosbags)
        return
    for conn, stamp_ns, raw in reader.messages(connections=conns):
        yield conn, int(stamp_ns), convert[conn.msgtype](raw) if convert else raw


def bag_topics(path: str | Path) -> dict[str, str]:
    """Map topic -> message type of a rosbag2 bag or a ROS 1 .bag file."""
    with _open_bag(path) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def topic_counts(path: str | Path) -> dict[str, tuple[str, int]]:
    """Map topic -> (message type, message count) of a rosbag2 bag or a ROS 1 .bag file."""
    out: dict[str, tuple[str, int]] = {}
    with _open_bag(path) as reader:
        for c in reader.connections:
            typ, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (typ, n + int(c.msgcount))
    return out


def read_raw(path: str | Path, topics: Iterable[str] | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """Yield ``(topic, msgtype, stamp_ns, cdr_bytes)`` in log-time order (ROS 2 CDR, also
    for a ROS 1 bag, whose messages are converted)."""
    with _open_bag(path) as reader:
        for conn, stamp_ns, raw in _messages(reader, topics):
            yield conn.topic, conn.msgtype, stamp_ns, bytes(raw)


def iter_bag(path: str | Path, topics: Iterable[str] | None = None
             ) -> Iterator[tuple[str, str, int, Any]]:
    """Yield ``(topic, msgtype, stamp_ns, msg)`` in log-time order, msg deserialized
    into rosbags typestore classes of ROS 2 Jazzy (also for a ROS 1 bag: same fields as
    from its rosbag2 twin); ``topics=None`` reads all topics."""
    ts = typestore()
    with _open_bag(path) as reader:
        for conn, stamp_ns, raw in _messages(reader, topics):
            yield conn.topic, conn.msgtype, stamp_ns, ts.deserialize_cdr(raw, conn.msgtype)


def read_ground_truth(path: str | Path, topic: str = '/ground_truth/pose'
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses of a bag: ``(stamps_ns (N,) int64, T_world_cam (N, 4, 4))``.

    The one ground-truth reader of the project. Stamps are the header stamps (the bag time
    where a header stamp is zero), sorted. Accepts PoseStamped, PoseWithCovarianceStamped,
    Odometry and TransformStamped; an absent topic gives empty arrays.
    """
    stamps: list[int] = []
    poses: list[np.ndarray] = []
    n_fallback = 0
    for _, msgtype, log_ns, msg in iter_bag(path, [topic]):
        if msgtype == POSE_STAMPED:
            T = pose_to_matrix(msg.pose)
        elif msgtype in ('nav_msgs/msg/Odometry',
                         'geometry_msgs/msg/PoseWithCovarianceStamped'):
            T = pose_to_matrix(msg.pose.pose)
        elif msgtype == 'geometry_msgs/msg/TransformStamped':
            tr, q = msg.transform.translation, msg.transform.rotation
            T = np.eye(4)
            T[:3, :3] = quat_xyzw_to_matrix([q.x, q.y, q.z, q.w])
            T[:3, 3] = [tr.x, tr.y, tr.z]
        else:
            raise ValueError(f'{topic}: unsupported ground-truth type {msgtype}')
        stamp_ns = time_to_ns(msg.header.stamp)
        if stamp_ns == 0:
            n_fallback += 1
            stamp_ns = log_ns
        stamps.append(stamp_ns)
        poses.append(T)
    if not poses:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))
    if n_fallback:
        logger.warning('%d/%d ground-truth messages had a zero header stamp; used bag time',
                       n_fallback, len(stamps))
    stamps_arr = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(stamps_arr, kind='stable')
    return stamps_arr[order], np.stack(poses)[order]
