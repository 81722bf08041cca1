"""Errors a user can provoke in the console scripts: one line on stderr naming what is wrong,
a non-zero exit, no traceback, and before any long work. Also: ROS 1 bags (EuRoC, TUM RGB-D
ship them) read like their rosbag2 twins."""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.typesys import Stores, get_typestore

from ekf_vo.io import bag as bagio
from ekf_vo.io.trajectory import write_tum
from ekf_vo.ros.harness import domain_id_for, ros_env
from ekf_vo.tools import synth
from ekf_vo.tools.run import run_bag

BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]


def _run(tool: str, *args: str, cwd: Path = REPO, env: dict | None = None
         ) -> subprocess.CompletedProcess:
    """The installed console script ``tool`` with ``args``."""
    return subprocess.run([str(BIN / tool), *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env=env)


def _fails_with(result: subprocess.CompletedProcess, line: str) -> None:
    """Non-zero exit, exactly ``line`` on stderr, nothing else there."""
    assert result.returncode != 0, result
    assert 'Traceback' not in result.stderr, result.stderr
    assert result.stderr.strip() == line, result.stderr


@pytest.fixture(scope='module')
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """40 frames, raw and JPEG-compressed images, CameraInfo and ground truth."""
    path = tmp_path_factory.mktemp('cli') / 'walk40'
    synth.write_bag(synth.SynthConfig(frames=40, seed=2), path, compressed=True)
    return path


@pytest.fixture(scope='module')
def tum_pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A ground-truth and an estimated TUM trajectory (the estimate at half scale)."""
    folder = tmp_path_factory.mktemp('tum')
    t = np.arange(50) * 0.1
    T = np.tile(np.eye(4), (50, 1, 1))
    T[:, 0, 3], T[:, 1, 3] = np.cos(t), np.sin(2 * t)
    write_tum(folder / 'gt.tum', t, T)
    T[:, :3, 3] *= 0.5
    write_tum(folder / 'est.tum', t, T)
    return folder / 'gt.tum', folder / 'est.tum'


# ------------------------------------------------------------------ 1. broken params YAML
def test_run_params_invalid_yaml(small_bag: Path, tmp_path: Path) -> None:
    params = tmp_path / 'broken.yaml'
    params.write_text('vo_node:\n  ros__parameters:\n\tmax_features: 300\n')
    r = _run('ekf-vo-run', small_bag, '-o', tmp_path / 'e.tum', '-q', '--params', params)
    _fails_with(r, f"ekf-vo-run: error: {params}:3: invalid YAML: found character '\\t' "
                "that cannot start any token")


# ------------------------------------------------------------------ 2. not a bag
NOT_A_BAG = ('cannot open bag {}: not a bag (a rosbag2 bag is a directory with a '
             'metadata.yaml, a ROS 1 bag a .bag file)')


def test_play_empty_directory(tmp_path: Path) -> None:
    (tmp_path / 'emptydir').mkdir()
    r = _run('ekf-vo-play', 'emptydir', cwd=tmp_path, env=ros_env(domain_id_for(__name__)))
    _fails_with(r, 'ekf-vo-play: error: ' + NOT_A_BAG.format('emptydir'))


def test_run_empty_directory(tmp_path: Path) -> None:
    (tmp_path / 'emptydir').mkdir()
    r = _run('ekf-vo-run', 'emptydir', '-o', 'e.tum', '-q', cwd=tmp_path)
    _fails_with(r, 'ekf-vo-run: error: ' + NOT_A_BAG.format('emptydir'))


# ------------------------------------------------------------------ 3. unwritable outputs
@pytest.mark.parametrize('option', ['-o', '--stats', '--json'])
def test_run_unwritable_output_checked_first(small_bag: Path, tmp_path: Path,
                                             option: str) -> None:
    outputs = {'-o': tmp_path / 'e.tum', '--stats': None, '--json': None}
    outputs[option] = Path('/proc/nope/x.out')
    args = [a for k, v in outputs.items() if v is not None for a in (k, v)]
    t0 = time.monotonic()
    r = _run('ekf-vo-run', small_bag, '-q', *args)
    _fails_with(r, f'ekf-vo-run: error: cannot write {option} /proc/nope/x.out: /proc is '
                'not writable (No such file or directory)')
    assert not (tmp_path / 'e.tum').exists()     # nothing was run
    assert time.monotonic() - t0 < 30.0


def test_eval_unwritable_plot(tum_pair: tuple[Path, Path]) -> None:
    r = _run('ekf-vo-eval', *tum_pair, '--plot', '/proc/x.png')
    _fails_with(r, 'ekf-vo-eval: error: cannot write --plot /proc/x.png: /proc is not '
                'writable (No such file or directory)')
    r = _run('ekf-vo-eval', *tum_pair, '--plot', 'x.nosuchformat')
    assert r.returncode == 2 and "unsupported image format 'nosuchformat'" in r.stderr


# ------------------------------------------------------------------ 4. closed stdout
@pytest.mark.parametrize('command', [['ekf-vo-params'], ['ekf-vo-params', '--yaml'],
                                     ['ekf-vo-eval', 'GT', 'EST', '--json', '--json-arrays']])
def test_closed_stdout_exits_quietly(command: list[str],
                                     tum_pair: tuple[Path, Path]) -> None:
    """`tool | head -1`: the reader is gone before the tool writes."""
    files = {'GT': str(tum_pair[0]), 'EST': str(tum_pair[1])}
    argv = [str(BIN / command[0]), *(files.get(a, a) for a in command[1:])]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (0, 141), err
    assert err.decode() == ''


# ------------------------------------------------------------------ 5. synth with no frames
def test_synth_rejects_too_few_frames(tmp_path: Path) -> None:
    r = _run('ekf-vo-synth', tmp_path / 'out', '--frames', '0', '-q')
    _fails_with(r, 'ekf-vo-synth: error: --frames must be at least 2, got 0')
    assert not (tmp_path / 'out').exists()


# ------------------------------------------------------------------ 6. values naming what
def test_run_set_wrong_type(small_bag: Path, tmp_path: Path) -> None:
    r = _run('ekf-vo-run', small_bag, '-o', tmp_path / 'e.tum', '-q',
             '--set', 'max_features=abc')
    _fails_with(r, "ekf-vo-run: error: --set max_features: expected an integer, got 'abc'")
    r = _run('ekf-vo-run', small_bag, '-o', tmp_path / 'e.tum', '-q',
             '--set', 'one_point_ransac=maybe')
    _fails_with(r, "ekf-vo-run: error: --set one_point_ransac: expected a boolean "
                "(true/false), got 'maybe'")


def test_eval_zero_quaternion_names_file_and_line(tum_pair: tuple[Path, Path],
                                                  tmp_path: Path) -> None:
    lines = tum_pair[1].read_text().splitlines()
    lines[3] = ' '.join(lines[3].split()[:4] + ['0', '0', '0', '0'])
    est = tmp_path / 'zero_quat.tum'
    est.write_text('\n'.join(lines) + '\n')
    r = _run('ekf-vo-eval', tum_pair[0], est)
    _fails_with(r, f'ekf-vo-eval: error: {est}:4: quaternion qx qy qz qw has zero norm')


# ------------------------------------------------------------------ 7. --help
def test_synth_help_lists_defaults_and_trajectories() -> None:
    r = _run('ekf-vo-synth', '--help')
    assert r.returncode == 0
    text = ' '.join(r.stdout.split())
    for needle in ('(default: 300)', '(default: 640)', '(default: 480)', '(default: mono8)',
                   'seed of the room texture'):
        assert needle in text, needle
    lines = r.stdout.splitlines()
    for name in synth.TRAJECTORIES:
        assert sum(line.split()[:1] == [name] for line in lines) == 1, name


def _parsers() -> dict[str, argparse.ArgumentParser]:
    from ekf_vo.ros import player
    from ekf_vo.tools import convert, demo, evaluate, run
    return {'synth': synth.build_parser(), 'run': run.build_parser(),
            'eval': evaluate._build_parser(), 'convert': convert.build_parser(),
            'play': player.build_parser(), 'demo': demo.build_parser()}


def test_every_option_has_help() -> None:
    missing = [f'{tool} {action.dest}' for tool, parser in _parsers().items()
               for action in parser._actions if not action.help]
    assert missing == []


# ------------------------------------------------------------------ 8. ROS 1 bags
def _ros1_message(ts1, msgtype: str, msg, seq: int):
    """The ROS 1 (Noetic) twin of a ROS 2 message of the synthetic bag."""
    T = ts1.types
    stamp = T['builtin_interfaces/msg/Time'](sec=msg.header.stamp.sec,
                                             nanosec=msg.header.stamp.nanosec)
    header = T['std_msgs/msg/Header'](seq=seq, stamp=stamp, frame_id=msg.header.frame_id)
    if msgtype == bagio.IMAGE:
        return T[msgtype](header=header, height=msg.height, width=msg.width,
                          encoding=msg.encoding, is_bigendian=msg.is_bigendian,
                          step=msg.step, data=msg.data)
    if msgtype == bagio.COMPRESSED_IMAGE:
        return T[msgtype](header=header, format=msg.format, data=msg.data)
    if msgtype == bagio.CAMERA_INFO:
        roi = T['sensor_msgs/msg/RegionOfInterest'](
            x_offset=msg.roi.x_offset, y_offset=msg.roi.y_offset, height=msg.roi.height,
            width=msg.roi.width, do_rectify=msg.roi.do_rectify)
        return T[msgtype](header=header, height=msg.height, width=msg.width,
                          distortion_model=msg.distortion_model, D=msg.d, K=msg.k, R=msg.r,
                          P=msg.p, binning_x=msg.binning_x, binning_y=msg.binning_y, roi=roi)
    assert msgtype == bagio.POSE_STAMPED
    p, q = msg.pose.position, msg.pose.orientation
    pose = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=p.x, y=p.y, z=p.z),
        orientation=T['geometry_msgs/msg/Quaternion'](x=q.x, y=q.y, z=q.z, w=q.w))
    return T[msgtype](header=header, pose=pose)


def _write_ros1_twin(src: Path, dst: Path) -> None:
    """Every message of the rosbag2 ``src`` into the ROS 1 bag ``dst``, same log times."""
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    seqs: dict[str, int] = {}
    with Ros1Writer(dst) as writer:
        conns = {}
        for topic, msgtype, log_ns, msg in bagio.iter_bag(src):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts1)
            seqs[topic] = seqs.get(topic, -1) + 1
            ros1 = _ros1_message(ts1, msgtype, msg, seqs[topic])
            writer.write(conns[topic], log_ns, ts1.serialize_ros1(ros1, msgtype))


def test_ros1_bag_gives_the_same_trajectory(small_bag: Path, tmp_path: Path) -> None:
    ros1 = tmp_path / 'walk40.bag'
    _write_ros1_twin(small_bag, ros1)
    assert bagio.is_ros1_bag(ros1)
    assert bagio.topic_counts(ros1) == bagio.topic_counts(small_bag)
    # the messages come out as their ROS 2 selves (header.seq dropped, d k r p fields)
    assert [r[:3] for r in bagio.read_raw(ros1)] == [r[:3] for r in bagio.read_raw(small_bag)]
    assert list(bagio.read_raw(ros1)) == list(bagio.read_raw(small_bag))
    for image_topic in ('/camera/image_raw', '/camera/image_raw/compressed'):
        a = run_bag(small_bag, image_topic=image_topic)
        b = run_bag(ros1, image_topic=image_topic)
        assert a.frames == b.frames == 40 and a.frames_ok > 20
        assert np.array_equal(a.est_stamps_s, b.est_stamps_s)
        assert np.array_equal(a.est_T_world_cam, b.est_T_world_cam)
        assert b.eval is not None and b.eval.n_matched == b.frames_ok
    gt_a, gt_b = bagio.read_ground_truth(small_bag), bagio.read_ground_truth(ros1)
    assert np.array_equal(gt_a[0], gt_b[0]) and np.array_equal(gt_a[1], gt_b[1])


def test_ros1_bag_through_the_tools(small_bag: Path, tmp_path: Path) -> None:
    ros1 = tmp_path / 'walk40.bag'
    _write_ros1_twin(small_bag, ros1)
    r = _run('ekf-vo-run', ros1, '-o', tmp_path / 'e.tum', '-q')
    assert r.returncode == 0 and 'Traceback' not in r.stderr, r.stderr
    r = _run('ekf-vo-eval', ros1, tmp_path / 'e.tum')
    assert r.returncode == 0, r.stderr
    assert 'Poses gt / est / matched' in r.stdout
    r = _run('ekf-vo-convert', 'euroc', ros1, tmp_path / 'out')
    _fails_with(r, f'ekf-vo-convert: error: {ros1} is a ROS 1 bag: no conversion needed, '
                'ekf-vo-run, ekf-vo-play and ekf-vo-eval read it as it is (ekf-vo-convert '
                'reads dataset folders)')


@pytest.mark.parametrize('node', ['vo_node', 'map_node', 'ekf_vo_nodes'])
@pytest.mark.parametrize('content', [None, 'vo_node:\n  ros__parameters:\n    x: [1,\n'],
                         ids=['missing', 'broken'])
def test_node_with_a_bad_params_file(tmp_path, node, content):
    params = tmp_path / 'params.yaml'
    if content is not None:
        params.write_text(content)
    r = _run(node, '--ros-args', '--params-file', params,
             env=ros_env(domain_id_for('test_cli_errors')))
    assert r.returncode == 2, r
    assert 'Traceback' not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'{node}: error: '), r.stderr
    assert "Couldn't parse params file" in lines[0] and str(params) in lines[0]


def test_player_with_a_bad_params_file(tmp_path):
    r = _run('ekf-vo-play', REPO / 'bags' / 'demo', '--ros-args', '--params-file',
             tmp_path / 'nope.yaml', env=ros_env(domain_id_for('test_cli_errors')))
    assert r.returncode == 2 and 'Traceback' not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('ekf-vo-play: error: '), r.stderr
