"""Tests of ekf-vo-convert (ekf_vo.tools.convert): one fixture per dataset format, built here
from rendered synthetic frames, converted and read back with bagio; then convert -> run.

Each fixture lays out the same rendered frames (known T_world_cam per frame) the way the
dataset does, including its own ground-truth convention (EuRoC: body poses and T_BS; TUM:
ground truth at 100 Hz, not at the image stamps), so the bag's /ground_truth/pose must come
back as the optical-frame pose of the renderer.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ekf_vo.bridge.image import decode_image
from ekf_vo.io import bag as bagio
from ekf_vo.tools import convert, synth
from ekf_vo.tools.run import run_bag

from .support.data import need_shared_data

SEED = 5
N = 20
TUM_GT_RATE = 100.0
EUROC_GT_RATE = 200.0

#: EuRoC-like T_BS (camera sensor frame in the body/IMU frame), deliberately non-identity
T_BS = np.eye(4)
T_BS[:3, :3] = Rotation.from_euler('xyz', [92.0, -1.5, 89.0], degrees=True).as_matrix()
T_BS[:3, 3] = [-0.0216, -0.0647, 0.0098]


def _small_cfg(**kw) -> synth.SynthConfig:
    base = dict(frames=N, width=320, height=240, fx=262.5, seed=SEED, noise_px=1.0)
    base.update(kw)
    return synth.SynthConfig(**base)


@pytest.fixture(scope='module')
def frames() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """N rendered (stamp_ns, grey image, T_world_cam) of the 'walk' trajectory."""
    return list(synth.render_sequence(_small_cfg()))


def _fmt_T(T: np.ndarray) -> str:
    return ' '.join(f'{v:.12e}' for v in T[:3, :].reshape(-1))


def _tum_line(t: float, T: np.ndarray) -> str:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return f'{t:.6f} ' + ' '.join(f'{v:.10f}' for v in (*T[:3, 3], *q))


def _read_back(bag: Path) -> dict:
    """topics, per-topic stamps, images, camera infos and ground truth of a bag."""
    out: dict = {'topics': bagio.bag_topics(bag), 'stamps': {}, 'images': [], 'infos': []}
    for topic, msgtype, log_ns, msg in bagio.iter_bag(bag):
        out['stamps'].setdefault(topic, []).append(bagio.time_to_ns(msg.header.stamp))
        assert bagio.time_to_ns(msg.header.stamp) == log_ns
        if msgtype in (bagio.IMAGE, bagio.COMPRESSED_IMAGE):
            out['images'].append(decode_image(msgtype, msg))
            assert msg.header.frame_id == 'camera_optical'
        elif msgtype == bagio.CAMERA_INFO:
            out['infos'].append(msg)
        else:
            assert msg.header.frame_id == 'world'
    out['gt_ns'], out['gt_T'] = bagio.read_ground_truth(bag)
    return out


def _assert_pose_close(A: np.ndarray, B: np.ndarray, pos_tol: float, deg_tol: float) -> None:
    assert np.linalg.norm(A[:3, 3] - B[:3, 3]) < pos_tol
    ang = np.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude())
    assert ang < deg_tol


# ============================================================================ fixtures
def make_kitti(root: Path, frames, with_labels: bool = True) -> Path:
    seq = root / 'sequences' / '07'
    (seq / 'image_0').mkdir(parents=True)
    K = _small_cfg().K()
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -0.54 * K[0, 0]
    lines = []
    for i, P in enumerate((P0, P1, P0, P1)):
        vals = ' '.join(f'{v:.12e}' for v in P.reshape(-1))
        lines.append(f'P{i}: {vals}' if with_labels else vals)
    (seq / 'calib.txt').write_text('\n'.join(lines) + '\n')
    times, poses = [], []
    t0 = frames[0][0]
    for k, (stamp, img, T) in enumerate(frames):
        cv2.imwrite(str(seq / 'image_0' / f'{k:06d}.png'), img)
        times.append(f'{(stamp - t0) * 1e-9:.6e}')
        poses.append(_fmt_T(T))
    (seq / 'times.txt').write_text('\n'.join(times) + '\n')
    (root / 'poses').mkdir()
    (root / 'poses' / '07.txt').write_text('\n'.join(poses) + '\n')   # ../../poses/NN.txt
    return seq


def make_tum(root: Path, frames, name: str = 'rgbd_dataset_freiburg2_synth') -> Path:
    """TUM layout; colour PNGs; ground truth at 100 Hz starting 63.7 ms after the first image."""
    src = root / name
    (src / 'rgb').mkdir(parents=True)
    rgb = ['# color images', '# timestamp filename']
    for stamp, img, _ in frames:
        t = stamp * 1e-9
        cv2.imwrite(str(src / 'rgb' / f'{t:.6f}.png'), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        rgb.append(f'{t:.6f} rgb/{t:.6f}.png')
    (src / 'rgb.txt').write_text('\n'.join(rgb) + '\n')
    cfg = _small_cfg()
    t_first = frames[0][0] * 1e-9
    gt = ['# ground truth trajectory', '# timestamp tx ty tz qx qy qz qw']
    k = 0
    while True:
        t_rel = 0.06 + 0.0037 + k / TUM_GT_RATE   # offset: never on an image stamp
        if t_rel > (frames[-1][0] - frames[0][0]) * 1e-9 + 0.02:
            break
        gt.append(_tum_line(t_first + t_rel, synth.trajectory_pose(cfg.trajectory, t_rel,
                                                                   cfg.seed)))
        k += 1
    (src / 'groundtruth.txt').write_text('\n'.join(gt) + '\n')
    return src


def make_euroc(root: Path, frames, cfg: synth.SynthConfig,
               distortion=(-0.28, 0.07, 0.0002, 1.8e-05)) -> Path:
    """EuRoC layout: ground truth = body pose T_world_body = T_world_cam * T_BS^-1, 200 Hz,
    sampled off the image stamps (starts 12.5 ms before the first image)."""
    src = root / 'MH_99_synth'
    cam = src / 'mav0' / 'cam0'
    (cam / 'data').mkdir(parents=True)
    rows = ['#timestamp [ns],filename']
    for stamp, img, _ in frames:
        cv2.imwrite(str(cam / 'data' / f'{stamp}.png'), img)
        rows.append(f'{stamp},{stamp}.png')
    (cam / 'data.csv').write_text('\n'.join(rows) + '\n')
    K = cfg.K()
    tbs = ', '.join(f'{v:.15g}' for v in T_BS.reshape(-1))
    (cam / 'sensor.yaml').write_text(
        '# General sensor definitions.\nsensor_type: camera\ncomment: synthetic cam0\n\n'
        f'T_BS:\n  cols: 4\n  rows: 4\n  data: [{tbs}]\n\n'
        f'rate_hz: 30\nresolution: [{cfg.width}, {cfg.height}]\ncamera_model: pinhole\n'
        f'intrinsics: [{K[0, 0]}, {K[1, 1]}, {K[0, 2]}, {K[1, 2]}] #fu, fv, cu, cv\n'
        f'distortion_model: radial-tangential\n'
        f'distortion_coefficients: [{", ".join(str(d) for d in distortion)}]\n')
    gt_dir = src / 'mav0' / 'state_groundtruth_estimate0'
    gt_dir.mkdir(parents=True)
    gt = ['#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], '
          'q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], '
          'b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], '
          'b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]']
    t0 = frames[0][0]
    span = (frames[-1][0] - t0) * 1e-9
    inv_T_BS = np.linalg.inv(T_BS)
    k = 0
    while (t_rel := -0.0125 + k / EUROC_GT_RATE) <= span + 0.01:
        T_wb = synth.trajectory_pose(cfg.trajectory, t_rel, cfg.seed) @ inv_T_BS
        qx, qy, qz, qw = Rotation.from_matrix(T_wb[:3, :3]).as_quat()
        vals = [*T_wb[:3, 3], qw, qx, qy, qz] + [0.0] * 9
        gt.append(f'{t0 + int(round(t_rel * 1e9))},' + ','.join(f'{v:.12f}' for v in vals))
        k += 1
    (gt_dir / 'data.csv').write_text('\n'.join(gt) + '\n')
    return src


def make_folder(root: Path, frames) -> Path:
    """../shared/data layout: camera.json, frames.txt (t name), groundtruth_tum.txt."""
    src = root / 'synth_folder'
    (src / 'images').mkdir(parents=True)
    cfg = _small_cfg()
    K = cfg.K()
    (src / 'camera.json').write_text(json.dumps(
        {'model': 'pinhole', 'fx': K[0, 0], 'fy': K[1, 1], 'cx': K[0, 2], 'cy': K[1, 2],
         'dist': [0, 0, 0, 0, 0], 'width': cfg.width, 'height': cfg.height}))
    rows, gt = [], ['# timestamp tx ty tz qx qy qz qw']
    for k, (stamp, img, T) in enumerate(frames):
        cv2.imwrite(str(src / 'images' / f'{k:04d}.png'), img)
        rows.append(f'{stamp * 1e-9:.6f} images/{k:04d}.png')
        gt.append(_tum_line(stamp * 1e-9, T))
    (src / 'frames.txt').write_text('\n'.join(rows) + '\n')
    (src / 'groundtruth_tum.txt').write_text('\n'.join(gt) + '\n')
    return src


# ============================================================================ per format
def test_kitti(tmp_path: Path, frames) -> None:
    src = make_kitti(tmp_path, frames)
    res = convert.convert('kitti', src, tmp_path / 'bag')
    assert (res.frames, res.frames_with_gt) == (N, N)
    bag = _read_back(tmp_path / 'bag')
    assert bag['topics'] == {'/camera/camera_info': bagio.CAMERA_INFO,
                             '/camera/image_raw': bagio.IMAGE,
                             '/ground_truth/pose': bagio.POSE_STAMPED}
    t0 = frames[0][0]
    expected = [int(round(float(f'{(s - t0) * 1e-9:.6e}') * 1e9)) for s, _, _ in frames]
    for topic in bag['topics']:
        assert bag['stamps'][topic] == expected, topic
    assert expected[0] == 0   # KITTI times start at 0
    K = _small_cfg().K()
    for info in bag['infos']:
        assert np.allclose(np.asarray(info.k).reshape(3, 3), K)
        assert (info.width, info.height) == (320, 240)
        assert not np.any(info.d)
    for img, (_, ref, _) in zip(bag['images'], frames):
        assert np.array_equal(img, ref)
    for T, (_, _, ref) in zip(bag['gt_T'], frames):
        _assert_pose_close(T, ref, 1e-9, 1e-6)


def test_kitti_unlabelled_calib_explicit_poses_and_limit(tmp_path: Path, frames) -> None:
    src = make_kitti(tmp_path, frames, with_labels=False)
    poses = tmp_path / 'poses' / '07.txt'
    moved = tmp_path / 'gt.txt'
    poses.rename(moved)
    res = convert.convert('kitti', src, tmp_path / 'nogt')
    assert res.frames_with_gt == 0 and any('no ground truth' in n for n in res.notes)
    assert '/ground_truth/pose' not in bagio.bag_topics(tmp_path / 'nogt')
    res = convert.convert('kitti', src, tmp_path / 'bag', poses=moved, limit=5,
                          compressed=True, camera_topic='/cam0')
    bag = _read_back(tmp_path / 'bag')
    assert set(bag['topics']) == {'/cam0/camera_info', '/cam0/image_raw/compressed',
                                  '/ground_truth/pose'}
    assert len(bag['images']) == 5 and len(bag['gt_T']) == 5
    for img, (_, ref, _) in zip(bag['images'], frames):
        assert np.array_equal(img, ref)   # PNG: lossless


def test_tum(tmp_path: Path, frames) -> None:
    src = make_tum(tmp_path, frames)
    res = convert.convert('tum', src, tmp_path / 'bag')
    bag = _read_back(tmp_path / 'bag')
    assert len(bag['images']) == N
    # freiburg2 from the folder name: the TUM website calibration
    info = bag['infos'][0]
    assert np.allclose(np.asarray(info.k).reshape(3, 3),
                       [[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]])
    assert np.allclose(info.d, [0.2312, -0.7849, -0.0033, -0.0001, 0.9172])
    assert info.distortion_model == 'plumb_bob'
    for img, (_, ref, _) in zip(bag['images'], frames):   # colour -> grey exactly
        assert np.array_equal(img, ref)
    image_ns = np.array(bag['stamps']['/camera/image_raw'])
    assert np.all(np.abs(image_ns - [s for s, _, _ in frames]) < 1000)   # 6-decimal file
    # ground truth starts 63.7 ms after the first image: frames 0 and 1 (> 20 ms from the
    # first sample) have none, the rest is interpolated from the 100 Hz samples
    assert res.frames_with_gt == N - 2
    assert list(bag['gt_ns']) == list(image_ns[2:])
    by_stamp = {s: T for s, _, T in frames}
    for t, T in zip(bag['gt_ns'], bag['gt_T']):
        ref = min(by_stamp.items(), key=lambda kv: abs(kv[0] - t))[1]
        _assert_pose_close(T, ref, 1e-3, 0.05)


def test_tum_explicit_camera_and_errors(tmp_path: Path, frames) -> None:
    src = make_tum(tmp_path, frames[:4], name='my_sequence')
    with pytest.raises(convert.ConvertError, match='--camera'):
        convert.convert('tum', src, tmp_path / 'a')
    K = _small_cfg().K()
    convert.convert('tum', src, tmp_path / 'b', camera=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    info = _read_back(tmp_path / 'b')['infos'][0]
    assert np.allclose(np.asarray(info.k).reshape(3, 3), K)
    assert not np.any(info.d)
    assert convert.tum_camera_from_name('rgbd_dataset_freiburg3_long_office_household')[0] \
        == 'freiburg3'
    assert convert.tum_camera_from_name('fr1_desk')[0] == 'freiburg1'
    assert convert.tum_camera_from_name('sequence_10') is None


def test_euroc_composes_T_BS(tmp_path: Path, frames) -> None:
    src = make_euroc(tmp_path, frames, _small_cfg())
    res = convert.convert('euroc', src, tmp_path / 'bag')
    assert (res.frames, res.frames_with_gt) == (N, N)
    bag = _read_back(tmp_path / 'bag')
    assert bag['stamps']['/camera/image_raw'] == [s for s, _, _ in frames]
    info = bag['infos'][0]
    assert np.allclose(np.asarray(info.k).reshape(3, 3), _small_cfg().K())
    assert info.distortion_model == 'plumb_bob'
    assert np.allclose(info.d, [-0.28, 0.07, 0.0002, 1.8e-05, 0.0])
    assert list(bag['gt_ns']) == [s for s, _, _ in frames]
    for T, (_, _, ref) in zip(bag['gt_T'], frames):
        _assert_pose_close(T, ref, 1e-4, 0.01)
    # without T_BS the body pose would be far from the camera pose: the check has teeth
    body = bag['gt_T'][0] @ np.linalg.inv(T_BS)
    assert np.degrees(Rotation.from_matrix(body[:3, :3].T @ frames[0][2][:3, :3])
                      .magnitude()) > 45


def test_folder(tmp_path: Path, frames) -> None:
    src = make_folder(tmp_path, frames)
    res = convert.convert('folder', src, tmp_path / 'bag', compressed=True)
    assert res.frames_with_gt == N
    bag = _read_back(tmp_path / 'bag')
    assert set(bag['topics']) == {'/camera/camera_info', '/camera/image_raw/compressed',
                                  '/ground_truth/pose'}
    assert np.allclose(np.asarray(bag['infos'][0].k).reshape(3, 3), _small_cfg().K())
    for img, (_, ref, _) in zip(bag['images'], frames):
        assert np.array_equal(img, ref)
    for T, (_, _, ref) in zip(bag['gt_T'], frames):
        _assert_pose_close(T, ref, 1e-8, 1e-5)


def test_cli_errors(tmp_path: Path, frames, capsys) -> None:
    assert convert.main(['euroc', str(tmp_path / 'absent'), str(tmp_path / 'x')]) == 2
    assert 'source folder not found' in capsys.readouterr().err
    src = make_folder(tmp_path, frames[:3])
    (src / 'images' / '0001.png').unlink()
    assert convert.main(['folder', str(src), str(tmp_path / 'y'), '-q']) == 2
    assert '0001.png' in capsys.readouterr().err
    assert not (tmp_path / 'y').exists()     # the partly written bag was removed
    assert convert.main(['kitti', str(src), str(tmp_path / 'z'), '-q']) == 2
    assert 'image_0' in capsys.readouterr().err
    (tmp_path / 'exists').mkdir()
    assert convert.main(['folder', str(src), str(tmp_path / 'exists'), '-q']) == 2
    assert 'exists' in capsys.readouterr().err


def test_interpolate_poses() -> None:
    t = np.array([0.0, 0.01, 0.02, 0.2])
    T = np.stack([synth.trajectory_pose('walk', x) for x in t])
    out = convert.interpolate_poses(t, T, np.array([0.0, 0.005, 0.03, 0.19, 0.5, -0.5]))
    assert np.allclose(out[0], T[0])
    mid = synth.trajectory_pose('walk', 0.005)
    _assert_pose_close(out[1], mid, 1e-4, 0.01)
    assert np.allclose(out[2], T[2])      # gap 0.18 s > 50 ms: nearest within 20 ms
    assert np.allclose(out[3], T[3])
    assert out[4] is None and out[5] is None


# ============================================================================ options
def test_jpeg_quality_is_lossy_but_close(tmp_path: Path, frames) -> None:
    """--jpeg-quality: JPEG CompressedImage on .../compressed that decodes near the source
    (not equal: the check would pass for PNG too if the data were not JPEG)."""
    src = make_kitti(tmp_path, frames)
    res = convert.convert('kitti', src, tmp_path / 'bag', jpeg_quality=75)
    assert res.counts['/camera/image_raw/compressed'] == N
    bag = _read_back(tmp_path / 'bag')
    assert set(bag['topics']) == {'/camera/camera_info', '/camera/image_raw/compressed',
                                  '/ground_truth/pose'}
    fmts = {msg.format for _, _, _, msg in bagio.iter_bag(tmp_path / 'bag',
                                                          ['/camera/image_raw/compressed'])}
    assert fmts == {'mono8; jpeg compressed '}
    assert len(bag['images']) == N
    diffs = [float(np.mean(np.abs(img.astype(float) - ref.astype(float))))
             for img, (_, ref, _) in zip(bag['images'], frames)]
    assert all(0.0 < d < 3.0 for d in diffs), diffs
    # a lower quality loses more: the option reaches the encoder
    convert.convert('kitti', src, tmp_path / 'q10', jpeg_quality=10)
    low = _read_back(tmp_path / 'q10')['images'][0]
    assert np.mean(np.abs(low.astype(float) - frames[0][1])) > diffs[0]


def test_info_after_image_order(tmp_path: Path, frames) -> None:
    """--info-after-image: a reader sees each image before its CameraInfo (the first message
    is an image), the info keeps the image's header stamp and precedes the next image; the
    default keeps CameraInfo first; both run the same frames."""
    src = make_kitti(tmp_path, frames)
    convert.convert('kitti', src, tmp_path / 'before')
    convert.convert('kitti', src, tmp_path / 'after', info_after_image=True)
    first = next(bagio.iter_bag(tmp_path / 'before'))
    assert first[1] == bagio.CAMERA_INFO
    msgs = list(bagio.iter_bag(tmp_path / 'after'))
    assert msgs[0][1] == bagio.IMAGE
    camera = [(msgtype, log_ns, bagio.time_to_ns(msg.header.stamp))
              for _, msgtype, log_ns, msg in msgs if msgtype != bagio.POSE_STAMPED]
    assert [m for m, _, _ in camera] == [bagio.IMAGE, bagio.CAMERA_INFO] * N
    images, infos = camera[0::2], camera[1::2]
    for k, ((_, img_log, img_stamp), (_, info_log, info_stamp)) in \
            enumerate(zip(images, infos)):
        assert info_stamp == img_stamp == img_log < info_log
        if k + 1 < N:
            assert info_log < images[k + 1][1]
    for name in ('before', 'after'):
        summary = run_bag(tmp_path / name)
        assert (summary.frames, summary.frames_skipped) == (N, 0), name


def test_cli_jpeg_and_info_after(tmp_path: Path, frames, capsys) -> None:
    src = make_folder(tmp_path, frames[:3])
    assert convert.main(['folder', str(src), str(tmp_path / 'x'), '-q',
                         '--jpeg-quality', '101']) == 2
    err = capsys.readouterr().err
    assert err.strip() == 'ekf-vo-convert: error: --jpeg-quality must be in 1..100, got 101'
    assert not (tmp_path / 'x').exists()
    assert convert.main(['folder', str(src), str(tmp_path / 'y'), '-q', '--jpeg-quality',
                         '90', '--info-after-image']) == 0
    topic, msgtype, _, msg = next(bagio.iter_bag(tmp_path / 'y'))
    assert (topic, msgtype) == ('/camera/image_raw/compressed', bagio.COMPRESSED_IMAGE)
    assert 'jpeg' in msg.format
    with pytest.raises(convert.ConvertError, match='1..100'):
        convert.convert('folder', src, tmp_path / 'z', jpeg_quality=True)

# ============================================================================ convert -> run
def test_convert_then_run_euroc_walk(tmp_path: Path) -> None:
    """60 frames of 'walk' at 30 Hz, 640x480, laid out as EuRoC (body poses + T_BS),
    converted, then run offline: tracks and is accurate after Sim(3)."""
    cfg = synth.SynthConfig(frames=60, seed=0)
    seq = list(synth.render_sequence(cfg))
    src = make_euroc(tmp_path, seq, cfg, distortion=(0.0, 0.0, 0.0, 0.0))
    convert.convert('euroc', src, tmp_path / 'bag')
    summary = run_bag(tmp_path / 'bag', out_tum=tmp_path / 'est.tum')
    assert summary.frames == 60
    assert summary.pct_tracked >= 80.0, summary.frame_stats[:5]
    assert summary.eval is not None, summary.eval_error
    assert summary.eval.ate_sim3_pct_of_path < 5.0
    assert (tmp_path / 'est.tum').is_file()


@pytest.mark.data
def test_convert_then_run_kitti06(tmp_path: Path) -> None:
    src = need_shared_data('kitti06_f0-50', 'convert + run on real KITTI data')
    res = convert.convert('folder', src, tmp_path / 'bag')
    assert res.frames == 51 and res.frames_with_gt == 51
    summary = run_bag(tmp_path / 'bag')
    assert summary.pct_tracked >= 95.0
    assert summary.eval is not None, summary.eval_error
    assert summary.eval.ate_sim3_pct_of_path <= 2.0


@pytest.mark.parametrize('fmt', ['kitti', 'tum', 'folder'])
def test_convert_then_run_each_format(tmp_path: Path, fmt: str) -> None:
    """Every format's small fixture (120 frames, 320x240) converts and then tracks
    (the bootstrap needs ~20 frames of parallax at this size)."""
    cfg = _small_cfg(frames=120)
    seq = list(synth.render_sequence(cfg))
    kwargs = {}
    if fmt == 'kitti':
        src = make_kitti(tmp_path, seq)
    elif fmt == 'tum':
        src = make_tum(tmp_path, seq)
        K = cfg.K()
        kwargs['camera'] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    else:
        src = make_folder(tmp_path, seq)
    convert.convert(fmt, src, tmp_path / 'bag', **kwargs)
    summary = run_bag(tmp_path / 'bag')
    assert summary.frames == 120
    assert summary.pct_tracked >= 80.0
    assert summary.eval is not None, summary.eval_error
    assert summary.eval.ate_sim3_pct_of_path < 5.0
