"""Tests of the synthetic sequence generator (ekf_vo.tools.synth) and rosbag2 I/O (bagio)."""
from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from ekf_vo.bridge.image import decode_image
from ekf_vo.io import bag as bagio
from ekf_vo.tools import synth

SEED = 3


@pytest.fixture(scope='module')
def scene() -> synth.Scene:
    return synth.make_scene(SEED)


def _cfg(**kw) -> synth.SynthConfig:
    base = dict(frames=6, seed=SEED, noise_px=0.0)
    base.update(kw)
    return synth.SynthConfig(**base)


def test_deterministic(scene: synth.Scene) -> None:
    cfg = _cfg(frames=3, noise_px=2.0)
    a = list(synth.render_sequence(cfg, scene))
    b = list(synth.render_sequence(cfg, synth.make_scene.__wrapped__(SEED)))  # fresh scene
    for (sa, ia, Ta), (sb, ib, Tb) in zip(a, b):
        assert sa == sb
        assert np.array_equal(ia, ib)
        assert np.array_equal(Ta, Tb)
    c = list(synth.render_sequence(_cfg(frames=1, noise_px=2.0, seed=SEED + 1)))
    assert not np.array_equal(a[0][1], c[0][1])


def test_image_properties(scene: synth.Scene) -> None:
    stamp, img, T = next(synth.render_sequence(_cfg(frames=1, noise_px=2.0), scene))
    assert img.shape == (480, 640) and img.dtype == np.uint8
    assert stamp == synth.EPOCH_NS
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    corners = cv2.goodFeaturesToTrack(img, 400, 0.01, 10)
    assert corners is not None and len(corners) >= 250
    # well spread: every cell of a 3x3 grid has corners
    cells = set(map(tuple, (corners.reshape(-1, 2) // [640 / 3, 480 / 3]).astype(int)))
    assert len(cells) == 9
    assert 40 < img.mean() < 215 and img.std() > 25


@pytest.mark.parametrize('name', ['walk', 'orbit', 'figure8'])
def test_trajectory_realistic(name: str) -> None:
    st = synth.trajectory_stats(name, 20.0, SEED)
    assert 0.3 < st['speed_max'] < 1.1
    assert 10.0 < st['rot_max_deg_s'] < 45.0


def test_ground_robot_drives_stops_and_turns_in_place() -> None:
    """Four 90 deg turns per loop, each made standing still (the camera, 0.1 m ahead of
    the axis, moves on a 0.1 m arc), at a constant height with no roll or pitch."""
    from scipy.spatial.transform import Rotation
    rate = 30.0
    ts = np.arange(0, 25.1, 1 / rate)          # one period
    Ts = np.stack([synth.trajectory_pose('ground_robot', float(t)) for t in ts])
    assert np.allclose(Ts[:, 2, 3], 0.4)
    assert np.allclose(Ts[:, 2, 1], -1.0)     # optical y points down: no roll, no pitch
    dR = np.einsum('nji,njk->nik', Ts[:-1, :3, :3], Ts[1:, :3, :3])
    ang = np.degrees(Rotation.from_matrix(dR).magnitude()) * rate
    speed = np.linalg.norm(np.diff(Ts[:, :3, 3], axis=0), axis=1) * rate
    turning = ang > 1.0
    # turning, the camera only swings on the 0.1 m lever: v = 0.1 m x the turn rate
    assert np.all(speed[turning] <= 0.1 * np.radians(ang[turning]) * 1.05 + 1e-6)
    total = np.sum(ang[turning]) / rate
    assert total == pytest.approx(360.0, abs=5.0)
    st = synth.trajectory_stats('ground_robot', 20.0)
    assert 0.8 < st['speed_max'] < 1.0 and 80 < st['rot_max_deg_s'] < 100


def test_ground_robot_arcs_turns_while_driving() -> None:
    """The rounded rectangle: a constant 0.5 m/s, 360 deg per 18.3 s loop, never in
    place; and the synthetic wheel odometry follows its base within the noise."""
    from ekf_vo.tools.synth_scene import robot_base
    from ekf_vo.tools.wheel_odometry import WheelNoise, wheel_odometry
    rate = 30.0
    ts = np.arange(0, 18.28, 1 / rate)
    Ts = np.stack([synth.trajectory_pose('ground_robot_arcs', float(t)) for t in ts])
    assert np.allclose(Ts[:, 2, 3], 0.4)
    base = np.array([robot_base('ground_robot_arcs', float(t))[:2] for t in ts])
    speed = np.linalg.norm(np.diff(base, axis=0), axis=1) * rate
    assert np.allclose(speed, 0.5, atol=0.01)
    heading = np.array([robot_base('ground_robot_arcs', float(t))[2] for t in ts])
    assert heading[-1] - heading[0] == pytest.approx(2 * np.pi, abs=0.05)
    odom, slipping = wheel_odometry('ground_robot_arcs', ts, WheelNoise(slip_share=0.0))
    assert not slipping.any()
    steps = np.linalg.norm(np.diff(odom[:, :2], axis=0), axis=1) * rate
    assert abs(np.mean(steps) - 0.5) < 0.01           # 2 % white noise per step
    odom_slip, slipping = wheel_odometry('ground_robot_arcs', ts, WheelNoise(slip_share=0.2))
    assert 0.1 < slipping.mean() < 0.3
    steps = np.linalg.norm(np.diff(odom_slip[:, :2], axis=0), axis=1) * rate
    assert np.mean(steps[slipping[1:]]) == pytest.approx(0.65, rel=0.05)   # +30 %


def test_handheld_rotation_mostly_rotates() -> None:
    st = synth.trajectory_stats('handheld_rotation', 20.0, SEED)
    assert st['speed_max'] < 0.15 and 80 < st['rot_max_deg_s'] < 120


def test_drone_nadir_looks_down_at_the_floor_while_it_flies() -> None:
    ts = np.arange(0.0, 20.0, 0.1)
    Ts = np.stack([synth.trajectory_pose('drone_nadir', float(t), SEED) for t in ts])
    # the optical axis (third column of R_world_cam) points down, within 10 deg
    assert np.all(Ts[:, 2, 2] < -np.cos(np.radians(10.0)))
    assert np.all((1.9 < Ts[:, 2, 3]) & (Ts[:, 2, 3] < 2.3))
    st = synth.trajectory_stats('drone_nadir', 20.0, SEED)
    assert 0.3 < st['speed_mean'] < 0.8 and st['rot_max_deg_s'] < 30


def test_depth_matches_raycast(scene: synth.Scene) -> None:
    """The renderer's z-buffer equals exact ray/rectangle intersection (away from edges)."""
    cfg = _cfg()
    seq = synth.SequenceRenderer(cfg, scene)
    K = cfg.K()
    rng = np.random.default_rng(0)
    for k in (0, 5):
        T = seq.pose(k)
        _, invz = seq.renderer.render(T)
        uv = np.stack([rng.integers(0, 640, 300), rng.integers(0, 480, 300)], 1)
        rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T  # z = 1
        s, qi = scene.raycast(T[:3, 3], rays @ T[:3, :3].T)
        assert np.all(qi >= 0)
        z_render = 1.0 / invz[uv[:, 1], uv[:, 0]]
        err = np.abs(z_render - s) / s
        assert np.median(err) < 1e-4
        assert np.mean(err < 1e-3) > 0.97  # a few pixels on occlusion edges may differ


@pytest.mark.parametrize('kw', [{}, {'distortion': (-0.25, 0.08, 0.0005, -0.0003, 0.0)}],
                         ids=['pinhole', 'plumb_bob'])
def test_ground_truth_consistent_with_images(scene: synth.Scene, kw: dict) -> None:
    """Corners tracked by KLT land where GT poses + ray-cast 3-D points predict (< 0.5 px)."""
    cfg = _cfg(frames=2, **kw)
    seq = synth.SequenceRenderer(cfg, scene)
    K, D = cfg.K(), cfg.D()
    for k in (0, 40):
        _, im0, T0 = seq.frame(k)
        _, im1, T1 = seq.frame(k + 1)
        p0 = cv2.goodFeaturesToTrack(im0, 300, 0.01, 10).reshape(-1, 2)
        # 3-D points: undistort, back-project, intersect the scene
        und = synth.undistort_pixels(p0, K, D)
        rays = np.c_[und.reshape(-1, 2), np.ones(len(p0))] @ T0[:3, :3].T
        s, qi = scene.raycast(T0[:3, 3], rays)
        ok = qi >= 0
        X_world = T0[:3, 3] + s[ok, None] * rays[ok]
        T_c1_w = np.linalg.inv(T1)
        rvec, _ = cv2.Rodrigues(T_c1_w[:3, :3])
        pred, _ = cv2.projectPoints(X_world, rvec, T_c1_w[:3, 3], K, D)
        pred = pred.reshape(-1, 2)
        trk, st, _ = cv2.calcOpticalFlowPyrLK(
            im0, im1, p0[ok].astype(np.float32).reshape(-1, 1, 2), None, winSize=(21, 21),
            maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-3))
        good = (st.ravel() == 1) & np.all((pred > 5) & (pred < [635, 475]), axis=1)
        err = np.linalg.norm(trk.reshape(-1, 2)[good] - pred[good], axis=1)
        flow = np.linalg.norm(pred[good] - p0[ok][good], axis=1)
        assert good.sum() > 150
        assert np.median(flow) > 1.0  # the camera really moved
        assert np.median(err) < 0.2, (k, np.median(err))  # measured ~0.04 px
        assert np.mean(err < 1.0) > 0.8


def test_bag_round_trip(tmp_path: Path) -> None:
    cfg = _cfg(frames=10, noise_px=2.0)
    out = tmp_path / 'bag'
    tum = tmp_path / 'gt.txt'
    synth.write_bag(cfg, out, compressed=True, tum=tum)
    frames = list(synth.render_sequence(cfg))
    assert bagio.bag_topics(out) == {
        '/camera/camera_info': bagio.CAMERA_INFO, '/camera/image_raw': bagio.IMAGE,
        '/camera/image_raw/compressed': bagio.COMPRESSED_IMAGE,
        '/ground_truth/pose': bagio.POSE_STAMPED}
    by_topic: dict[str, list] = {}
    last = -1
    for topic, msgtype, stamp, msg in bagio.iter_bag(out):
        assert stamp >= last
        last = stamp
        assert bagio.time_to_ns(msg.header.stamp) == stamp
        by_topic.setdefault(topic, []).append((stamp, msgtype, msg))
    stamps = [f[0] for f in frames]
    for topic, msgs in by_topic.items():
        assert [m[0] for m in msgs] == stamps, topic
    for (stamp, img, T), (_, mt, im_msg), (_, _, cz), (_, _, ci), (_, _, ps) in zip(
            frames, by_topic['/camera/image_raw'], by_topic['/camera/image_raw/compressed'],
            by_topic['/camera/camera_info'], by_topic['/ground_truth/pose']):
        assert im_msg.encoding == 'mono8' and im_msg.header.frame_id == 'camera_optical'
        assert np.array_equal(decode_image(mt, im_msg), img)
        jpg = decode_image(bagio.COMPRESSED_IMAGE, cz)
        assert jpg.shape == img.shape and np.abs(jpg.astype(int) - img).mean() < 4
        assert np.allclose(np.asarray(ci.k).reshape(3, 3), cfg.K())
        assert np.allclose(np.asarray(ci.p).reshape(3, 4)[:, :3], cfg.K())
        assert (ci.width, ci.height, ci.distortion_model) == (640, 480, 'plumb_bob')
        assert ps.header.frame_id == 'world'
        assert np.allclose(bagio.pose_to_matrix(ps.pose), T, atol=1e-12)
    st, Ts = bagio.read_ground_truth(out)
    assert list(st) == stamps and np.allclose(Ts, np.stack([f[2] for f in frames]))
    raw = list(bagio.read_raw(out, ['/ground_truth/pose']))
    assert len(raw) == 10 and isinstance(raw[0][3], bytes)
    rows = np.loadtxt(tum)
    assert rows.shape == (10, 8) and np.allclose(rows[:, 1:4], Ts[:, :3, 3], atol=1e-8)
    assert abs(rows[1, 0] - rows[0, 0] - 1 / 30) < 1e-6
    # same args -> same bytes
    out2 = tmp_path / 'again' / 'bag'  # same bag name (the .mcap file is named after it)
    synth.write_bag(cfg, out2, compressed=True)

    def digest(p: Path) -> dict[str, str]:
        return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(p.iterdir())}
    assert digest(out) == digest(out2)


def test_cli_compressed_only_bgr(tmp_path: Path) -> None:
    out = tmp_path / 'cli_bag'
    rc = synth.main([str(out), '--frames', '3', '--compressed-only', '--encoding', 'bgr8',
                     '--width', '320', '--height', '240', '--fx', '262.5', '--blur', '5',
                     '--supersample', '2', '-q'])
    assert rc == 0
    topics = bagio.bag_topics(out)
    assert '/camera/image_raw' not in topics
    assert topics['/camera/image_raw/compressed'] == bagio.COMPRESSED_IMAGE
    imgs = [decode_image(mt, m) for _, mt, _, m in
            bagio.iter_bag(out, ['/camera/image_raw/compressed'])]
    assert len(imgs) == 3 and imgs[0].shape == (240, 320, 3)
