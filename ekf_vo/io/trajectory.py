"""Trajectory file I/O: TUM text files and ground truth from rosbag2 bags.

Conventions
-----------
* Poses are ``T_world_cam`` (4x4 homogeneous, float64): they map points from the camera
  optical frame into the world frame, i.e. ``p_world = T_world_cam @ p_cam``.  The
  translation column is therefore the camera centre expressed in the world frame.
* Timestamps are float64 seconds (for ROS data: ``header.stamp.sec + 1e-9 * nanosec``).
* Quaternions are Hamilton, scalar-last, named ``*_xyzw`` (TUM and ROS order).

TUM format (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    # timestamp tx ty tz qx qy qz qw
    1700000000.033333 0.1 0.0 0.0 0.0 0.0 0.0 1.0

One pose per line, whitespace separated, lines starting with ``#`` are comments.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Union

import numpy as np
from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)

PathLike = Union[str, Path]

#: Default ground-truth topic (geometry_msgs/msg/PoseStamped) in the project's bags.
GT_TOPIC = '/ground_truth/pose'

_TUM_HEADER = '# timestamp tx ty tz qx qy qz qw'
_BAG_SUFFIXES = ('.mcap', '.db3', '.bag')


def poses_from_tum_rows(t_xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Build homogeneous poses from positions and quaternions.

    Args:
        t_xyz: (N, 3) translations (camera centre in world frame, metres).
        quat_xyzw: (N, 4) unit quaternions, scalar last; re-normalised here.

    Returns:
        (N, 4, 4) float64 ``T_world_cam``.

    Raises:
        ValueError: a quaternion has (near) zero norm or shapes mismatch.
    """
    t_xyz = np.asarray(t_xyz, dtype=np.float64).reshape(-1, 3)
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64).reshape(-1, 4)
    if t_xyz.shape[0] != quat_xyzw.shape[0]:
        raise ValueError(f'{t_xyz.shape[0]} translations but {quat_xyzw.shape[0]} quaternions')
    n = t_xyz.shape[0]
    T = np.tile(np.eye(4), (n, 1, 1))
    if n == 0:
        return T
    norms = np.linalg.norm(quat_xyzw, axis=1)
    if np.any(norms < 1e-9):
        bad = int(np.argmax(norms < 1e-9))
        raise ValueError(f'quaternion {bad} has zero norm: {quat_xyzw[bad]}')
    T[:, :3, :3] = Rotation.from_quat(quat_xyzw / norms[:, None]).as_matrix()
    T[:, :3, 3] = t_xyz
    return T


def tum_rows_from_poses(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split poses into positions and quaternions.

    Args:
        T_world_cam: (N, 4, 4) poses (rotation block must be a rotation matrix).

    Returns:
        ``(t_xyz (N, 3), quat_xyzw (N, 4))``; quaternion sign chosen with ``qw >= 0``.
    """
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    if T.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    quat_xyzw = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    quat_xyzw[quat_xyzw[:, 3] < 0] *= -1.0
    return T[:, :3, 3].copy(), quat_xyzw


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Args:
        path: text file with lines ``timestamp tx ty tz qx qy qz qw``; ``#`` comments and
            blank lines are ignored.

    Returns:
        ``(stamps_s (N,), T_world_cam (N, 4, 4))`` in file order (not re-sorted).

    Raises:
        FileNotFoundError: missing file.
        ValueError: a data line does not have exactly 8 finite numeric columns or has a
            zero quaternion (the message names the file and line).
    """
    path = Path(path)
    stamps: list[float] = []
    rows: list[list[float]] = []
    try:
        text = path.read_bytes().decode('utf-8')
    except UnicodeDecodeError:
        raise ValueError(f'{path}: not a text file (expected a TUM trajectory)') from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        parts = line.replace(',', ' ').split()
        if len(parts) != 8:
            raise ValueError(
                f'{path}:{lineno}: expected 8 columns '
                f'(timestamp tx ty tz qx qy qz qw), got {len(parts)}')
        try:
            vals = [float(p) for p in parts]
        except ValueError as exc:
            raise ValueError(f'{path}:{lineno}: non-numeric value: {exc}') from exc
        _check_tum_row(vals, f'{path}:{lineno}')
        stamps.append(vals[0])
        rows.append(vals[1:])
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    T = poses_from_tum_rows(data[:, :3], data[:, 3:7])
    logger.debug('read %d poses from %s', len(stamps), path)
    return np.asarray(stamps, dtype=np.float64), T


def _check_tum_row(vals: list[float], where: str) -> None:
    """ValueError naming ``where`` (file:line) for a non-finite value or a zero quaternion."""
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f'{where}: non-finite value (nan or inf)')
    if sum(v * v for v in vals[4:8]) < 1e-18:
        raise ValueError(f'{where}: quaternion qx qy qz qw has zero norm')


def check_poses(stamps_s: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps (N,), T (N, 4, 4))`` as float64 arrays; ValueError if the shapes do not fit."""
    stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f'poses must have shape (N, 4, 4), got {T.shape}')
    if T.shape[0] != stamps.shape[0]:
        raise ValueError(f'{stamps.shape[0]} stamps but {T.shape[0]} poses')
    return stamps, T


def write_tum(path: PathLike, stamps_s: np.ndarray, T_world_cam: np.ndarray) -> None:
    """Write a TUM trajectory file (with a ``#`` header line).

    Timestamps are written with the shortest representation that round-trips the float64
    exactly (positional notation, no exponent); translations and quaternions with 9 decimals.

    Args:
        path: output file; parent directories are created.
        stamps_s: (N,) timestamps in seconds.
        T_world_cam: (N, 4, 4) poses, camera optical frame -> world.

    Raises:
        ValueError: shapes do not match.
    """
    stamps, T = check_poses(stamps_s, T_world_cam)
    t_xyz, q_xyzw = tum_rows_from_poses(T)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [_TUM_HEADER]
    for s, t, q in zip(stamps, t_xyz, q_xyzw):
        stamp = np.format_float_positional(s, unique=True, trim='-')
        lines.append(stamp + ' ' + ' '.join(f'{v:.9f}' for v in (*t, *q)))
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    logger.debug('wrote %d poses to %s', stamps.shape[0], path)


def is_bag_path(path: PathLike) -> bool:
    """True if ``path`` looks like a bag: rosbag2 (directory, ``.mcap`` or ``.db3`` file)
    or ROS 1 (``.bag`` file)."""
    path = Path(path)
    return path.is_dir() or path.suffix.lower() in _BAG_SUFFIXES


def read_gt_from_bag(path: PathLike, topic: str = GT_TOPIC) -> tuple[np.ndarray, np.ndarray]:
    """Read a ground-truth trajectory from a rosbag2 bag (via :func:`.bag.read_ground_truth`).

    The topic should carry ``geometry_msgs/msg/PoseStamped`` whose pose is ``T_world_cam``
    (``PoseWithCovarianceStamped``, ``nav_msgs/msg/Odometry`` and ``TransformStamped`` are
    accepted too). Time is ``header.stamp``; messages with a zero stamp fall back to the bag
    receive time.

    Args:
        path: bag directory (with metadata.yaml), a ``.mcap`` / ``.db3`` file in one, or a
            ROS 1 ``.bag`` file.
        topic: ground-truth topic name.

    Returns:
        ``(stamps_s (N,), T_world_cam (N, 4, 4))`` sorted by time.

    Raises:
        FileNotFoundError: missing bag.
        ValueError: topic absent, of an unsupported type, or without messages.
    """
    from .bag import bag_topics, read_ground_truth

    topics = bag_topics(path)
    if topic not in topics:
        available = sorted(f'{t} [{m}]' for t, m in topics.items())
        raise ValueError(f'topic {topic!r} not in bag {path}; available: {available}')
    stamps_ns, T = read_ground_truth(path, topic)
    if not len(stamps_ns):
        raise ValueError(f'topic {topic!r} in bag {path} has no messages')
    logger.debug('read %d ground-truth poses from %s %s', len(stamps_ns), path, topic)
    return stamps_ns * 1e-9, T


def read_trajectory(path: PathLike, topic: str = GT_TOPIC) -> tuple[np.ndarray, np.ndarray]:
    """Read a trajectory from a TUM file or (if :func:`is_bag_path`) a rosbag2 bag topic.

    Returns:
        ``(stamps_s (N,), T_world_cam (N, 4, 4))``.
    """
    if is_bag_path(path):
        return read_gt_from_bag(path, topic)
    return read_tum(path)


_COV_HEADER = ('# stamp c00 c01 ... c55: 6x6 pose covariance, row-major, (x y z, rotation '
               'about the world x y z axes) of the TUM poses with the same stamps')


def write_covariances(path: PathLike, stamps_s: np.ndarray, cov: np.ndarray) -> None:
    """Write each pose's 6x6 covariance beside a TUM file: one line per stamp, `stamp`
    then 36 numbers row-major, in the convention of nav_msgs/Odometry's pose covariance
    (position, then rotation vector about the parent frame's fixed axes)."""
    stamps = np.asarray(stamps_s, np.float64).reshape(-1)
    cov = np.asarray(cov, np.float64).reshape(-1, 6, 6)
    if len(stamps) != len(cov):
        raise ValueError(f'{len(stamps)} stamps but {len(cov)} covariances')
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [_COV_HEADER]
    for s, c in zip(stamps, cov):
        stamp = np.format_float_positional(s, unique=True, trim='-')
        lines.append(stamp + ' ' + ' '.join(f'{v:.9e}' for v in c.ravel()))
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')


def read_covariances(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,), covariances (N,6,6)) of a file written by `write_covariances`.
    Raises ValueError on a malformed line (its number in the message)."""
    stamps, covs = [], []
    for k, line in enumerate(Path(path).read_text(encoding='utf-8').splitlines(), 1):
        line = line.strip()
        if not line or line.startswith('#'):
            continue
        vals = line.split()
        if len(vals) != 37:
            raise ValueError(f'{path}:{k}: expected a stamp and 36 numbers, got {len(vals)}')
        row = np.array([float(v) for v in vals])
        if not np.all(np.isfinite(row)):
            raise ValueError(f'{path}:{k}: non-finite value')
        stamps.append(row[0])
        covs.append(row[1:].reshape(6, 6))
    if not stamps:
        raise ValueError(f'{path}: no covariance')
    return np.array(stamps), np.array(covs)
