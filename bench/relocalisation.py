"""Relocalisation after a loss: the demo with the lens covered, offline and over DDS.

Offline (VoStream, as ekf-vo-run): the demo bag's frames 150-169 replaced by black
frames, per seed: the frames from the first good one to the first published pose, the
resets, the ATE (Sim(3)) against the clean run's, and the scale after the loss against the
clean run's (estimated / true distance travelled over frames 171-220).
Over DDS: a fresh vo_node (live queue policy) fed the demo frames at 30 Hz with 3 s (90
frames) of black frames in the middle; the frames to the first odometry after them and
the resets on ~/status.

    python -m bench.relocalisation [--seeds 0 1 2] [--no-dds] [--json OUT]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from .common import machine, write_json

BLACK = range(150, 170)
SCALE_SPAN = (171, 220)


def _offline(frames, info, gt_ns, gt_T, black, seed):
    from ekf_vo.config import VoConfig
    from ekf_vo.core.camera import PinholeCamera
    from ekf_vo.core.stream import VoStream
    from ekf_vo.tools.evaluate import evaluate
    stream = VoStream(VoConfig(), seed=seed)
    stream.set_camera(PinholeCamera.from_camera_info(info))
    oks, est = [], {}
    for k, (t, g) in enumerate(frames):
        r = stream.process(np.zeros_like(g) if k in black else g, t)
        oks.append(bool(r.ok))      # a skipped repeat of a black frame: a Rejection, not ok
        if r.ok:
            est[k] = r.T_world_cam
    stream.vo.local_map.close()
    ks = sorted(est)
    ev = evaluate(np.asarray(gt_ns) * 1e-9, gt_T, np.array([frames[k][0] * 1e-9 for k in ks]),
                  np.array([est[k] for k in ks]), max_time_diff_s=1e-3)
    a, b = SCALE_SPAN
    gt_at = {int(t): T for t, T in zip(gt_ns, gt_T)}
    scale = np.nan
    if a in est and b in est:
        d_gt = np.linalg.norm(gt_at[frames[b][0]][:3, 3] - gt_at[frames[a][0]][:3, 3])
        scale = np.linalg.norm(est[b][:3, 3] - est[a][:3, 3]) / d_gt
    back = next((k - black.stop for k in range(black.stop, len(oks)) if oks[k]), None) \
        if len(black) else None
    return {'ate_m': ev.ate_sim3_rmse, 'resets': stream.n_resets, 'scale': scale,
            'frames_to_pose': back}


def _over_dds(info, frames, n_black: int) -> dict:
    from ekf_vo import bridge as conv
    from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
    domain = domain_id_for(__name__)
    with tempfile.TemporaryDirectory() as tmp:
        node = NodeProcess('ekf_vo.ros.vo_node', [
            '-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
            '-r', 'odom:=/odom', '-p', 'reliable_qos:=true'], domain, Path(tmp) / 'vo.log')
        node.wait_for_output('vo_node ready')
        h = Harness(domain)
        try:
            feed = Feeder(h, info)
            feed.wait_connected()
            image = lambda k, s, g: conv.numpy_to_image(g, 'mono8', s, 'camera_optical')  # noqa
            dt = frames[1][0] - frames[0][0]
            before = feed.publish(frames[:150], image, 30.0)
            t0 = frames[149][0]
            covered = [(t0 + (j + 1) * dt, np.zeros_like(frames[0][1])) for j in range(n_black)]
            feed.publish(covered, image, 30.0)
            shift = covered[-1][0] - frames[149][0]
            after = feed.publish([(t + shift, g) for t, g in frames[150:]], image, 30.0)
            feed.wait_last(after[-1])
            h.spin_for(0.6)
        finally:
            h.close()
            node.stop()
    got = set(feed.odom_wall)
    back = next((j for j, s in enumerate(after) if s in got), None)
    values = {kv.key: kv.value for kv in feed.status[-1].status[0].values} if feed.status \
        else {}
    return {'black_frames': n_black, 'frames_to_odometry': back,
            'resets': int(values.get('resets', -1)), 'odometry_before': len(
                [s for s in before if s in got]), 'odometry_after': len(
                [s for s in after if s in got]), 'frames_after': len(after)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--seeds', nargs='+', type=int, default=[0, 1, 2])
    p.add_argument('--no-dds', action='store_true')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    from ekf_vo.io.bag import read_ground_truth
    from ekf_vo.tools.demo import demo_bag, load_demo_frames
    info, frames = load_demo_frames()
    gt_ns, gt_T = read_ground_truth(demo_bag())
    print(f'# relocalisation, demo bag ({machine()})')
    print('| seed | frames to a pose after the black frames | resets | ATE / clean | '
          'scale after / clean |')
    print('|---|---|---|---|---|')
    rows = []
    for seed in args.seeds:
        clean = _offline(frames, info, gt_ns, gt_T, range(0), seed)
        lost = _offline(frames, info, gt_ns, gt_T, BLACK, seed)
        row = {'seed': seed, 'clean': clean, 'covered': lost,
               'ate_ratio': lost['ate_m'] / clean['ate_m'],
               'scale_ratio': lost['scale'] / clean['scale']}
        rows.append(row)
        print(f"| {seed} | {lost['frames_to_pose']} | {lost['resets']} | "
              f"{row['ate_ratio']:.2f} | {row['scale_ratio']:.3f} |", flush=True)
    out = {'machine': machine(), 'offline': rows}
    if not args.no_dds:
        dds = _over_dds(info, frames, 90)
        out['dds'] = dds
        print(f"over DDS, 3 s (90 frames) covered: odometry {dds['frames_to_odometry']} "
              f"frames after the lens is uncovered, {dds['resets']} resets, odometry for "
              f"{dds['odometry_after']} of the {dds['frames_after']} frames after it")
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
