"""Tests of the offline runner ekf-vo-run (ekf_vo.tools.run): synth -> run -> evaluate round
trip, the CLI (files written, exit codes), parameters, topic selection and CameraInfo
handling."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ekf_vo.config import ConfigError, VoConfig
from ekf_vo.io import bag as bagio
from ekf_vo.tools import synth
from ekf_vo.tools.run import (RunError, make_config, parse_overrides, run_bag,
                              select_topics)
from ekf_vo.io.trajectory import read_tum

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def synth_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """90 frames of the 'walk' trajectory, 640x480 at 30 Hz, raw images + ground truth."""
    path = tmp_path_factory.mktemp('run') / 'walk90'
    synth.write_bag(synth.SynthConfig(frames=90), path)
    return path


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'ekf_vo.tools.run', *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_round_trip(synth_bag: Path, tmp_path: Path) -> None:
    s = run_bag(synth_bag, out_tum=tmp_path / 'est.tum', stats_csv=tmp_path / 'stats.csv')
    assert (s.image_topic, s.info_topic, s.gt_topic) == (
        '/camera/image_raw', '/camera/camera_info', '/ground_truth/pose')
    assert s.frames == 90 and s.frames_skipped == 0
    assert s.pct_tracked >= 85.0
    assert s.eval is not None, s.eval_error
    assert s.eval.ate_sim3_pct_of_path < 3.0
    assert s.eval.n_matched == s.frames_ok
    assert {'total', 'track'} <= set(s.stage_ms)
    # the TUM file is the online trajectory: ok frames only, same poses
    stamps, T = read_tum(tmp_path / 'est.tum')
    assert len(stamps) == s.frames_ok
    assert np.allclose(T[:, :3, 3], s.est_T_world_cam[:, :3, 3], atol=1e-8)
    with (tmp_path / 'stats.csv').open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 90
    assert sum(int(r['ok']) for r in rows) == s.frames_ok
    assert rows[0]['state'] == 'initialising' and rows[-1]['state'] == 'tracking'
    assert 'ms_total' in rows[0] and float(rows[-1]['ms_update']) > 0
    # the online checks' verdict per frame, as ~/status has it: none before the map
    assert rows[0]['health'] == '' and rows[-1]['health'] in ('ok', 'degraded')
    assert all(r['health'] in ('ok', 'degraded', 'lost') for r in rows if int(r['ok']))


def test_gt_bootstrap_fixes_scale(synth_bag: Path) -> None:
    s = run_bag(synth_bag, gt_bootstrap=True, limit=45)
    assert s.frames == 45 and s.gt_bootstrap
    assert s.eval is not None, s.eval_error
    # the ground-truth bootstrap pair gives metric scale and the world frame
    assert abs(s.eval.sim3_scale - 1.0) < 0.1
    assert s.eval.ate_se3_rmse < 0.05


def test_cli_writes_files(synth_bag: Path, tmp_path: Path) -> None:
    est, stats, summary = tmp_path / 'est.tum', tmp_path / 'stats.csv', tmp_path / 's.json'
    r = _cli(str(synth_bag), '-o', str(est), '--stats', str(stats), '--json', str(summary),
             '--params', str(REPO / 'config' / 'ekf_vo.yaml'), '--set', 'max_features=250',
             '--set', 'one_point_ransac=true', '--limit', '60', '--quiet')
    assert r.returncode == 0, r.stderr
    assert est.is_file() and stats.is_file()
    data = json.loads(summary.read_text())
    assert data['frames'] == 60 and data['config']['max_features'] == 250
    assert data['eval']['ate_sim3_pct_of_path'] < 5.0
    assert 0 < data['pct_tracked'] <= 100 and data['fps'] > 0
    assert len(read_tum(est)[0]) == data['frames_ok']
    r = _cli(str(synth_bag), '-o', str(est), '--limit', '40')   # report on stdout
    assert r.returncode == 0, r.stderr
    assert 'ATE Sim(3) RMSE' in r.stdout and 'frames/s' in r.stdout


def test_cli_bag_without_images(tmp_path: Path) -> None:
    bag = tmp_path / 'poses_only'
    with bagio.BagWriter(bag) as w:
        for k in range(3):
            w.add_pose('/ground_truth/pose', np.eye(4), 1_000_000_000 + k, 'world')
    r = _cli(str(bag), '-o', str(tmp_path / 'e.tum'), '--quiet')
    assert r.returncode == 2
    assert 'no sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage topic' in r.stderr
    assert 'Traceback' not in r.stderr
    r = _cli(str(tmp_path / 'absent'), '-o', str(tmp_path / 'e.tum'), '--quiet')
    assert r.returncode == 2 and 'bag not found' in r.stderr


def test_cli_unknown_parameter(synth_bag: Path, tmp_path: Path) -> None:
    r = _cli(str(synth_bag), '-o', str(tmp_path / 'e.tum'), '--set', 'no_such_param=3')
    assert r.returncode == 2
    assert 'no_such_param' in r.stderr and 'unknown parameter' in r.stderr
    assert 'Traceback' not in r.stderr
    r = _cli(str(synth_bag), '-o', str(tmp_path / 'e.tum'), '--set', 'max_features=lots')
    assert r.returncode == 2 and 'max_features' in r.stderr


def test_parse_overrides_types() -> None:
    got = parse_overrides(['max_features=200', 'one_point_ransac=false',
                           'pixel_sigma_px=2', 'estimator=iekf', 'max_dt_s=0.5'])
    assert got == {'max_features': 200, 'one_point_ransac': False, 'pixel_sigma_px': 2.0,
                   'estimator': 'iekf', 'max_dt_s': 0.5}
    assert isinstance(got['pixel_sigma_px'], float) and isinstance(got['max_features'], int)
    for bad in (['max_features=1.5'], ['one_point_ransac=maybe'], ['max_features'],
                ['odom_frame=odom'], ['nope=1']):
        with pytest.raises(ConfigError):
            parse_overrides(bad)
    with pytest.raises(ConfigError, match='estimator'):
        make_config(None, {'estimator': 'magic'})     # validated against the choices
    with pytest.raises(ConfigError, match='max_features'):
        make_config(None, {'max_features': 1})        # below the range
    cfg = make_config(REPO / 'config' / 'ekf_vo.yaml', {'max_features': 123})
    assert cfg.max_features == 123 and cfg.pixel_sigma_px == VoConfig().pixel_sigma_px
    assert make_config({'max_features': 99, 'odom_frame': 'odom'}).max_features == 99


def test_select_topics() -> None:
    topics = {'/ground_truth/pose': bagio.POSE_STAMPED,
              '/left/camera_info': bagio.CAMERA_INFO,
              '/right/camera_info': bagio.CAMERA_INFO,
              '/right/image_raw/compressed': bagio.COMPRESSED_IMAGE}
    assert select_topics(topics) == ('/right/image_raw/compressed', '/right/camera_info',
                                     '/ground_truth/pose')
    topics['/left/image_raw'] = bagio.IMAGE        # raw preferred over compressed
    assert select_topics(topics)[:2] == ('/left/image_raw', '/left/camera_info')
    with pytest.raises(RunError, match='not an Image'):
        select_topics(topics, image_topic='/left/camera_info')
    with pytest.raises(RunError, match='CameraInfo'):
        select_topics({'/img': bagio.IMAGE})


def test_camera_info_handling(tmp_path: Path) -> None:
    """Images before the first CameraInfo wait for it (the rule of vo_node's queue_policy
    all, so node and runner see the same frames); a calibration change restarts the VO;
    the compressed topic is decoded."""
    cfg = synth.SynthConfig(frames=24, width=320, height=240, fx=262.5, seed=2)
    K2 = cfg.K().copy()
    K2[0, 0] = K2[1, 1] = 270.0
    bag = tmp_path / 'infos'
    with bagio.BagWriter(bag) as w:
        for k, (stamp, img, _) in enumerate(synth.render_sequence(cfg)):
            if k >= 2:
                w.add_camera_info('/cam/camera_info', cfg.width, cfg.height,
                                  cfg.K() if k < 12 else K2, np.zeros(5), 'plumb_bob', stamp,
                                  'cam')
            w.add_compressed('/cam/image_raw/compressed', img, stamp, 'cam', fmt='png')
    s = run_bag(bag)
    assert s.image_topic == '/cam/image_raw/compressed' and s.gt_topic is None
    assert s.frames_skipped == 0 and s.frames == 24
    assert s.n_camera_changes == 1
    assert s.eval is None and s.eval_error is None
    with pytest.raises(RunError, match='ground truth'):
        run_bag(bag, gt_bootstrap=True)
