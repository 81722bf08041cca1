"""Readers of the public monocular datasets that ``ekf-vo-convert`` turns into bags.

Each reader returns a :class:`SourceSequence` (camera, image stamps and paths, ground truth of
the camera optical frame); :func:`load_source` picks one by format. Writing the bag and the
CLI are in :mod:`ekf_vo.tools.convert`.

Formats (what is read, and the frame conventions of its ground truth):

``kitti``
    KITTI odometry sequence folder (``dataset/sequences/NN``): ``image_0/*.png`` (left grey
    camera, rectified), ``times.txt`` (seconds from the sequence start), ``calib.txt``
    (``P0: p00 .. p23``, the 3x4 rectified projection of camera 0; ``K = P0[:, :3]``, no
    distortion). Ground truth, optional: ``--poses FILE``, else ``SRC/poses.txt``, else
    ``SRC/../poses/NN.txt`` or ``SRC/../../poses/NN.txt``; 12 numbers per line, the row-major
    3x4 ``T_world_cam`` of camera 0 (optical frame; world = camera 0 at frame 0).
``tum``
    TUM RGB-D folder: ``rgb.txt`` (``t rgb/xxx.png``), ``groundtruth.txt``
    (``t tx ty tz qx qy qz qw``). The TUM ground truth is the pose of the optical centre of
    the colour camera in the motion-capture world frame, with the optical axes (z forward,
    x right, y down): it is ``T_world_cam`` as is. Ground truth (100 Hz) is interpolated to
    the image stamps (position linear, rotation slerp) between samples at most 50 ms apart,
    else the nearest sample within 20 ms is used, else the frame has no ground truth.
    Intrinsics: ``--camera fx fy cx cy [d0..d4]`` or, from a folder name containing
    ``freiburg1/2/3``, the calibration published on the TUM website (:data:`TUM_CAMERAS`).
    Colour images are converted to grey (OpenCV BT.601 weights).
``euroc``
    EuRoC MAV (ASL) folder: ``mav0/cam0/data.csv`` (``timestamp_ns,filename``) with
    ``mav0/cam0/data/*.png``, ``mav0/cam0/sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``,
    ``distortion_model: radial-tangential`` ``[k1, k2, p1, p2]`` -> plumb_bob with k3 = 0,
    or ``equidistant``; ``T_BS``: the camera sensor frame in the body frame, i.e.
    ``T_body_cam``) and ``mav0/state_groundtruth_estimate0/data.csv`` (body pose
    ``p_RS_R``, ``q_RS_w, q_RS_x, q_RS_y, q_RS_z`` = ``T_world_body``). The camera optical
    frame pose is ``T_world_cam = T_world_body @ T_body_cam``, interpolated as for TUM.
``folder``
    The image-folder layout (``camera.json``, ``groundtruth_tum.txt`` of the optical
    frame, images with ``times.txt`` or ``frames.txt``), read by
    :func:`ekf_vo.io.dataset.load_folder`.

Stamps keep the dataset's clock (KITTI: seconds from the sequence start, so frame 0 is at
t = 0; TUM and EuRoC: Unix time).
"""
from __future__ import annotations

import logging
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

logger = logging.getLogger(__name__)

FORMATS = ('kitti', 'tum', 'euroc', 'folder')

#: TUM RGB-D colour camera calibrations (fx, fy, cx, cy, d0..d4 plumb_bob), from
#: https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats
#: (section "Intrinsic Camera Calibration of the Kinect", colour camera, ROS default model)
TUM_CAMERAS: dict[str, tuple[float, ...]] = {
    'freiburg1': (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    'freiburg2': (520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    'freiburg3': (535.4, 539.2, 320.1, 247.6, 0.0, 0.0, 0.0, 0.0, 0.0),
}

#: ground truth to image stamps: interpolate between samples at most this far apart [s]
INTERP_MAX_GAP_S = 0.05
#: otherwise take the nearest sample if it is at most this far from the image [s]
NEAREST_MAX_DIFF_S = 0.02


class ConvertError(RuntimeError):
    """The source dataset is missing files or is malformed (message says which)."""


@dataclass
class SourceSequence:
    """A dataset read into memory (image paths, not pixels).

    Attributes:
        camera: CameraInfo as a dict: width, height (int), K (3x3), D (1-D),
            distortion_model ('plumb_bob', 'equidistant' or '').
        stamps_ns: (N,) int64 image stamps, strictly increasing.
        images: N image paths, same order.
        gt_T_world_cam: N entries, the 4x4 T_world_cam of the camera optical frame at each
            image stamp, or None where there is no ground truth; None when the dataset has
            no ground truth at all.
        notes: human-readable remarks (source of intrinsics, ground-truth coverage).
    """

    camera: dict
    stamps_ns: np.ndarray
    images: list[Path]
    gt_T_world_cam: list[np.ndarray | None] | None = None
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    def check(self) -> None:
        """Raise ConvertError on inconsistent lengths or non-increasing stamps."""
        n = len(self.images)
        if n == 0:
            raise ConvertError('no images found')
        if len(self.stamps_ns) != n:
            raise ConvertError(f'{n} images but {len(self.stamps_ns)} stamps')
        if self.gt_T_world_cam is not None and len(self.gt_T_world_cam) != n:
            raise ConvertError(f'{n} images but {len(self.gt_T_world_cam)} poses')
        bad = np.flatnonzero(np.diff(self.stamps_ns) <= 0)
        if bad.size:
            k = int(bad[0])
            raise ConvertError(f'image stamps not strictly increasing at frame {k + 1} '
                               f'({self.stamps_ns[k]} -> {self.stamps_ns[k + 1]} ns)')
        if np.any(self.stamps_ns < 0):
            raise ConvertError('negative image stamps')


# ============================================================================ helpers
def _need(path: Path, what: str) -> Path:
    if not path.exists():
        raise ConvertError(f'missing {what}: {path}')
    return path


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, whitespace/comma separated fields) of non-comment, non-blank lines."""
    with path.open('r', encoding='utf-8') as f:
        for lineno, line in enumerate(f, start=1):
            line = line.split('#', 1)[0].strip()
            if line:
                yield lineno, line.replace(',', ' ').split()


def _floats(path: Path, parts: Sequence[str], lineno: int) -> list[float]:
    try:
        return [float(p) for p in parts]
    except ValueError as exc:
        raise ConvertError(f'{path}:{lineno}: non-numeric value ({exc})') from None


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ConvertError(f'cannot read image {path}')
    return int(img.shape[1]), int(img.shape[0])


def _pinhole(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
             D: Sequence[float] = (), model: str = 'plumb_bob') -> dict:
    D = np.asarray(D, dtype=np.float64).reshape(-1)
    if model == 'plumb_bob':
        D = np.concatenate([D, np.zeros(max(0, 5 - D.size))])[:5] if D.size <= 5 else D
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return {'width': int(width), 'height': int(height), 'K': K, 'D': D,
            'distortion_model': model}


def interpolate_poses(gt_stamps_s: np.ndarray, gt_T: np.ndarray, query_s: np.ndarray,
                      max_gap_s: float = INTERP_MAX_GAP_S,
                      nearest_max_diff_s: float = NEAREST_MAX_DIFF_S
                      ) -> list[np.ndarray | None]:
    """Poses at the ``query_s`` times from a time-sorted pose sequence.

    Between two samples at most ``max_gap_s`` apart: position interpolated linearly,
    rotation by slerp. Otherwise the nearest sample within ``nearest_max_diff_s``, else None.

    Args:
        gt_stamps_s: (M,) increasing times [s].
        gt_T: (M, 4, 4) poses.
        query_s: (N,) times [s].

    Returns:
        N poses (4x4) or None.
    """
    t = np.asarray(gt_stamps_s, dtype=np.float64)
    T = np.asarray(gt_T, dtype=np.float64)
    out: list[np.ndarray | None] = []
    if t.size == 0:
        return [None] * len(query_s)
    for q in np.asarray(query_s, dtype=np.float64):
        i1 = int(np.searchsorted(t, q, side='left'))
        if i1 < t.size and t[i1] == q:
            out.append(T[i1].copy())
            continue
        i0 = i1 - 1
        if 0 <= i0 and i1 < t.size and t[i1] - t[i0] <= max_gap_s:
            a = (q - t[i0]) / (t[i1] - t[i0])
            pose = np.eye(4)
            pose[:3, 3] = (1 - a) * T[i0, :3, 3] + a * T[i1, :3, 3]
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix(T[[i0, i1], :3, :3]))
            pose[:3, :3] = slerp([a]).as_matrix()[0]
            out.append(pose)
            continue
        cands = [i for i in (i0, i1) if 0 <= i < t.size]
        j = min(cands, key=lambda i: abs(t[i] - q))
        out.append(T[j].copy() if abs(t[j] - q) <= nearest_max_diff_s else None)
    return out


def _se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ============================================================================ KITTI
def read_kitti_calib(path: Path, camera: str = 'P0') -> np.ndarray:
    """3x4 projection matrix ``camera`` ('P0'..'P3') of a KITTI ``calib.txt``.

    Lines are ``P0: 12 numbers``; a file without the ``Pn:`` labels is read by line order.
    """
    _need(path, 'KITTI calib.txt')
    index = int(camera[1:])
    unlabelled = []
    for lineno, parts in _data_lines(path):
        if parts[0].endswith(':'):
            if parts[0][:-1] == camera:
                vals = _floats(path, parts[1:], lineno)
                if len(vals) != 12:
                    raise ConvertError(f'{path}:{lineno}: {camera} needs 12 numbers, '
                                       f'got {len(vals)}')
                return np.asarray(vals).reshape(3, 4)
        elif len(parts) == 12:
            unlabelled.append(np.asarray(_floats(path, parts, lineno)).reshape(3, 4))
    if len(unlabelled) > index:
        return unlabelled[index]
    raise ConvertError(f'{path}: no {camera} line')


def read_kitti_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) poses of a KITTI poses file (12 numbers per line, row-major 3x4)."""
    poses = []
    for lineno, parts in _data_lines(_need(path, 'KITTI poses file')):
        vals = _floats(path, parts, lineno)
        if len(vals) != 12:
            raise ConvertError(f'{path}:{lineno}: expected 12 numbers, got {len(vals)}')
        T = np.eye(4)
        T[:3, :] = np.asarray(vals).reshape(3, 4)
        poses.append(T)
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def load_kitti(src: Path, poses: Path | None = None) -> SourceSequence:
    """Read a KITTI odometry sequence folder (see the module docstring)."""
    src = Path(src)
    folder = _need(src / 'image_0', 'KITTI image_0 folder')
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() == '.png')
    if not images:
        raise ConvertError(f'no .png images in {folder}')
    times_path = _need(src / 'times.txt', 'KITTI times.txt')
    times = [_floats(times_path, parts[:1], n)[0] for n, parts in _data_lines(times_path)]
    if len(times) < len(images):
        raise ConvertError(f'{times_path}: {len(times)} times for {len(images)} images')
    if len(times) > len(images):
        logger.warning('%s: %d times for %d images; extra times ignored', times_path,
                       len(times), len(images))
    P0 = read_kitti_calib(src / 'calib.txt', 'P0')
    width, height = _image_size(images[0])
    K = P0[:, :3] / P0[2, 2]
    camera = _pinhole(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(5))
    seq = SourceSequence(camera, np.round(np.asarray(times[:len(images)]) * 1e9)
                         .astype(np.int64), images)
    seq.notes.append('intrinsics: calib.txt P0[:, :3] (rectified, no distortion)')
    if poses is not None:
        pose_file: Path | None = _need(Path(poses), 'poses file (--poses)')
    else:
        pose_file = next((p for p in (src / 'poses.txt',
                                      src.parent / 'poses' / f'{src.name}.txt',
                                      src.parent.parent / 'poses' / f'{src.name}.txt')
                          if p.is_file()), None)
    if pose_file is None:
        seq.notes.append('no ground truth (no poses.txt / ../poses/NN.txt; use --poses)')
        return seq
    T = read_kitti_poses(pose_file)
    if len(T) < len(images):
        raise ConvertError(f'{pose_file}: {len(T)} poses for {len(images)} images')
    seq.gt_T_world_cam = list(T[:len(images)])
    seq.notes.append(f'ground truth: {pose_file} (T_world_cam of camera 0)')
    return seq


# ============================================================================ TUM RGB-D
def tum_camera_from_name(name: str) -> tuple[str, tuple[float, ...]] | None:
    """(key, calibration) of the TUM camera named in a folder name, e.g. ``..._freiburg2_xyz``
    or ``fr3_office``; None when no freiburg camera is named."""
    m = re.search(r'(?:freiburg|fr)([123])(?![0-9])', name.lower())
    if not m:
        return None
    key = f'freiburg{m.group(1)}'
    return key, TUM_CAMERAS[key]


def load_tum(src: Path, camera: Sequence[float] | None = None) -> SourceSequence:
    """Read a TUM RGB-D sequence folder (see the module docstring)."""
    src = Path(src)
    rgb_txt = _need(src / 'rgb.txt', 'TUM rgb.txt')
    stamps, images = [], []
    for lineno, parts in _data_lines(rgb_txt):
        if len(parts) < 2:
            raise ConvertError(f'{rgb_txt}:{lineno}: expected "timestamp filename"')
        stamps.append(_floats(rgb_txt, parts[:1], lineno)[0])
        images.append(src / parts[1])
    if not images:
        raise ConvertError(f'{rgb_txt}: no images listed')
    _need(images[0], 'TUM image listed in rgb.txt')
    width, height = _image_size(images[0])
    if camera is not None:
        cal = tuple(float(c) for c in camera)
        if len(cal) not in (4, 9):
            raise ConvertError(f'--camera needs fx fy cx cy [d0 d1 d2 d3 d4] (4 or 9 numbers), '
                               f'got {len(cal)}')
        source = '--camera'
    else:
        found = tum_camera_from_name(src.resolve().name)
        if found is None:
            raise ConvertError(f'cannot tell the TUM camera from the folder name '
                               f'{src.resolve().name!r} (no freiburg1/2/3): give '
                               f'--camera fx fy cx cy [d0..d4]')
        source = f'TUM website defaults for {found[0]}'
        cal = found[1]
    D = cal[4:] if len(cal) == 9 else (0.0,) * 5
    cam = _pinhole(width, height, *cal[:4], D)
    seq = SourceSequence(cam, np.round(np.asarray(stamps) * 1e9).astype(np.int64), images)
    seq.notes.append(f'intrinsics: {source}')
    gt_path = src / 'groundtruth.txt'
    if not gt_path.is_file():
        seq.notes.append('no ground truth (no groundtruth.txt)')
        return seq
    from ..io.trajectory import read_tum
    try:
        gt_s, gt_T = read_tum(gt_path)
    except ValueError as exc:
        raise ConvertError(str(exc)) from None
    order = np.argsort(gt_s, kind='stable')
    seq.gt_T_world_cam = interpolate_poses(gt_s[order], gt_T[order], np.asarray(stamps))
    seq.notes.append(f'ground truth: {gt_path} (optical centre of the colour camera), '
                     f'interpolated to image stamps')
    return seq


# ============================================================================ EuRoC
def _load_yaml(path: Path) -> dict:
    import yaml
    text = _need(path, 'EuRoC sensor.yaml').read_text(encoding='utf-8')
    text = re.sub(r'^%YAML:?[0-9.]*\s*\n', '', text)   # OpenCV-style header
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConvertError(f'{path}: invalid YAML: {exc}') from None
    if not isinstance(data, dict):
        raise ConvertError(f'{path}: not a YAML mapping')
    return data


def read_euroc_camera(path: Path) -> tuple[dict, np.ndarray]:
    """(CameraInfo dict, T_body_cam 4x4) of a EuRoC ``sensor.yaml`` (pinhole camera)."""
    data = _load_yaml(path)
    try:
        fu, fv, cu, cv = (float(v) for v in data['intrinsics'])
        width, height = (int(v) for v in data['resolution'])
        T_BS = data['T_BS']
        T = np.asarray(T_BS['data'] if isinstance(T_BS, dict) else T_BS,
                       dtype=np.float64).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConvertError(f'{path}: needs intrinsics [fu, fv, cu, cv], resolution [w, h] '
                           f'and T_BS (4x4): {exc!r}') from None
    if data.get('camera_model', 'pinhole') != 'pinhole':
        raise ConvertError(f'{path}: camera_model {data.get("camera_model")!r} unsupported '
                           f'(pinhole only)')
    model = str(data.get('distortion_model', 'radial-tangential'))
    D = np.asarray(data.get('distortion_coefficients', []), dtype=np.float64).reshape(-1)
    if model in ('radial-tangential', 'radtan', 'plumb_bob'):
        if D.size not in (0, 4, 5):
            raise ConvertError(f'{path}: radial-tangential needs 4 coefficients, got {D.size}')
        cam = _pinhole(width, height, fu, fv, cu, cv, D, 'plumb_bob')
    elif model in ('equidistant', 'fisheye'):
        if D.size != 4:
            raise ConvertError(f'{path}: equidistant needs 4 coefficients, got {D.size}')
        cam = _pinhole(width, height, fu, fv, cu, cv, D, 'equidistant')
    else:
        raise ConvertError(f'{path}: unsupported distortion_model {model!r}')
    if not np.allclose(T[3], (0, 0, 0, 1)) or \
            not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise ConvertError(f'{path}: T_BS is not a rigid transform')
    # re-orthonormalise the rotation (the files give ~1e-6 precision)
    T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()
    return cam, T


def read_euroc_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (M,), T_world_body (M, 4, 4)) of ``state_groundtruth_estimate0/data.csv``
    (columns: timestamp [ns], p_RS_R xyz [m], q_RS w x y z, ...)."""
    stamps, poses = [], []
    for lineno, parts in _data_lines(_need(path, 'EuRoC ground truth')):
        if len(parts) < 8:
            raise ConvertError(f'{path}:{lineno}: expected >= 8 columns, got {len(parts)}')
        try:
            t_ns = int(parts[0])
        except ValueError:
            raise ConvertError(f'{path}:{lineno}: timestamp {parts[0]!r} is not an integer '
                               f'[ns]') from None
        p = _floats(path, parts[1:4], lineno)
        qw, qx, qy, qz = _floats(path, parts[4:8], lineno)
        stamps.append(t_ns)
        poses.append(_se3(Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), np.asarray(p)))
    if not poses:
        return np.zeros(0), np.zeros((0, 4, 4))
    s = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(s, kind='stable')
    return s[order] * 1e-9, np.stack(poses)[order]


def load_euroc(src: Path) -> SourceSequence:
    """Read a EuRoC MAV sequence folder (the one holding ``mav0``, or ``mav0`` itself)."""
    src = Path(src)
    mav0 = src / 'mav0' if (src / 'mav0').is_dir() else src
    cam_dir = _need(mav0 / 'cam0', 'EuRoC mav0/cam0 folder')
    csv = _need(cam_dir / 'data.csv', 'EuRoC cam0/data.csv')
    stamps, images = [], []
    for lineno, parts in _data_lines(csv):
        if len(parts) < 2:
            raise ConvertError(f'{csv}:{lineno}: expected "timestamp_ns,filename"')
        try:
            stamps.append(int(parts[0]))
        except ValueError:
            raise ConvertError(f'{csv}:{lineno}: timestamp {parts[0]!r} is not an integer '
                               f'[ns]') from None
        images.append(cam_dir / 'data' / parts[1])
    if not images:
        raise ConvertError(f'{csv}: no images listed')
    _need(images[0], 'EuRoC image listed in cam0/data.csv')
    camera, T_body_cam = read_euroc_camera(cam_dir / 'sensor.yaml')
    seq = SourceSequence(camera, np.asarray(stamps, dtype=np.int64), images)
    seq.notes.append(f'intrinsics: {cam_dir / "sensor.yaml"} ({camera["distortion_model"]})')
    gt_path = mav0 / 'state_groundtruth_estimate0' / 'data.csv'
    if not gt_path.is_file():
        seq.notes.append('no ground truth (no state_groundtruth_estimate0/data.csv)')
        return seq
    gt_s, T_world_body = read_euroc_groundtruth(gt_path)
    # camera optical frame in the world: T_world_cam = T_world_body * T_body_cam (T_BS)
    T_world_cam = T_world_body @ T_body_cam
    seq.gt_T_world_cam = interpolate_poses(gt_s, T_world_cam,
                                           np.asarray(stamps, dtype=np.int64) * 1e-9)
    seq.notes.append(f'ground truth: {gt_path} composed with T_BS, interpolated to image '
                     f'stamps')
    return seq


# ============================================================================ folder
def load_folder_sequence(src: Path) -> SourceSequence:
    """Read the image-folder layout (camera.json, images, TUM ground truth) through :func:`ekf_vo.io.dataset.load_folder`."""
    from ..io.dataset import load_folder
    src = Path(src)
    _need(src / 'camera.json', 'camera.json')
    try:
        data = load_folder(src)
    except (OSError, KeyError, ValueError) as exc:
        raise ConvertError(f'{src}: {exc!r}') from None
    cam = dict(data.camera)
    if cam['distortion_model'] == '':
        cam['D'] = np.zeros(5)
        cam['distortion_model'] = 'plumb_bob'
    seq = SourceSequence(cam, np.asarray(data.stamps_ns, dtype=np.int64), list(data.images))
    seq.notes.append('intrinsics: camera.json')
    if data.gt_T_world_cam is not None:
        seq.gt_T_world_cam = [data.gt_at(k) for k in range(len(data))]
        seq.notes.append('ground truth: groundtruth_tum.txt (T_world_cam, stamps within 1 ms)')
    return seq


# ============================================================================ any format
def load_source(fmt: str, src: str | Path, *, poses: str | Path | None = None,
                camera: Sequence[float] | None = None) -> SourceSequence:
    """Read dataset ``src`` of format ``fmt`` (one of :data:`FORMATS`)."""
    src = Path(src)
    if fmt not in FORMATS:
        raise ConvertError(f'unknown format {fmt!r}; choose from {FORMATS}')
    if fmt != 'kitti' and poses is not None:
        raise ConvertError('--poses is only for the kitti format')
    if fmt != 'tum' and camera is not None:
        raise ConvertError('--camera is only for the tum format')
    if not src.is_dir():
        raise ConvertError(f'source folder not found: {src}')
    if fmt == 'kitti':
        seq = load_kitti(src, Path(poses) if poses else None)
    elif fmt == 'tum':
        seq = load_tum(src, camera)
    elif fmt == 'euroc':
        seq = load_euroc(src)
    else:
        seq = load_folder_sequence(src)
    seq.check()
    return seq
