"""Run the estimation core offline on a rosbag2 bag (no DDS, no rclpy) and evaluate it.

Console script::

    ekf-vo-run BAG -o EST.tum [--params config/ekf_vo.yaml] [--set name=value ...]
               [--image-topic T] [--info-topic T] [--gt-topic T] [--stats stats.csv]
               [--json summary.json] [--limit N] [--gt-bootstrap] [--quiet]
               [--scale-odom-topic T]

What it does, per image message of the bag (in log-time order):

1. topics: :func:`ekf_vo.bridge.topics.select_camera_topics` (the first
   ``sensor_msgs/msg/Image`` topic of the bag, else the first ``CompressedImage`` topic; the
   CameraInfo topic in the image topic's namespace, ``/cam/image_raw[/compressed]`` ->
   ``/cam/camera_info``, else the first CameraInfo topic); ground truth is
   ``/ground_truth/pose`` when present. All overridable.
2. parameters: the core (:class:`ekf_vo.config.VoConfig`) fields of the ``vo_node:
   ros__parameters:`` section of ``--params`` (run_params.py; of the node-only fields, only
   the extrinsic ``T_base_cam_xyz`` / ``_xyzw`` is used: the metric scale's gravity and
   lever arm), then ``--set name=value`` overrides, typed by the field type. With
   ``scale_source: odometry`` the bag's nav_msgs/Odometry topic (``--scale-odom-topic``,
   default ``/scale_odom``) is read in log order with the images.
3. images are decoded to grey with :func:`ekf_vo.bridge.image.decode_image` (as in vo_node);
   the stamp is the header stamp. Images before the first valid CameraInfo are skipped; a
   CameraInfo that changes the calibration re-creates the :class:`VisualOdometry` (its new
   trajectory starts at the identity again, as a restarted node would).
4. ``VisualOdometry.process`` runs on each image; with ``--gt-bootstrap`` the ground-truth
   pose at the image stamp is passed as ``known_T_world_cam`` while the pipeline state is
   ``initialising``; the pipeline reads it for its first map only (the EKFPnP paper's
   protocol: ground truth fixes the bootstrap scale; after a loss it bootstraps from the
   images).
5. output: ``T_world_cam`` of the camera optical frame of the frames with ``result.ok`` (the
   online trajectory a node would publish; in metres with a scale source) as TUM text; per-frame statistics as CSV; a
   summary (frames, % tracked, frames/s, mean per-stage ms) and, when the bag has ground
   truth, :func:`ekf_vo.tools.evaluate.evaluate` (ATE after Sim(3), rotation error, %
   tracked) printed and written to ``--json``. Orientation-only poses (before a map,
   docs/method.md §15.9) are in the TUM file, at the attach point, and in ``--cov`` with
   the position's unknown variance; the evaluation leaves them out.

Exit codes: 0 success; 2 bad input (missing bag, no image/CameraInfo topic, unknown or
invalid parameter). A failed evaluation (e.g. fewer than 3 tracked frames) is reported and
does not change the exit code.

Library use (tests, benchmarks)::

    summary = run_bag('bags/demo', overrides={'estimator': 'iekf'})
    print(summary.pct_tracked, summary.eval.ate_sim3_pct_of_path)
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..bridge.topics import TopicError, select_camera_topics, topic_listing
from ..cli import HelpFormatter, UsageError, check_writable, entry_point
from ..config import ConfigError, VoConfig
from ..core.pipeline import TrackingState
from ..core.stream import VoStream
from ..io.bag import BagError
from ..io.bag import topic_counts as _topic_counts
from ..io.trajectory import GT_TOPIC
from .run_params import base_extrinsic, make_config, parse_overrides
from .run_summary import FrameStats, RunSummary, format_summary, write_stats_csv

#: default nav_msgs/Odometry topic of scale_source odometry (vo_node subscribes scale_odom)
SCALE_ODOM_TOPIC = '/scale_odom'

logger = logging.getLogger(__name__)




class RunError(RuntimeError):
    """The bag cannot be run (missing, no image or CameraInfo topic, bad parameters)."""





# ============================================================================ topics
def select_topics(topics: Mapping[str, str], image_topic: str | None = None,
                  info_topic: str | None = None, gt_topic: str | None = None
                  ) -> tuple[str, str, str | None]:
    """(image topic, CameraInfo topic, ground-truth topic or None) of a bag's
    ``{topic: msgtype}``; explicit choices are checked.

    Raises:
        RunError: no (or a wrongly typed) image or CameraInfo topic, missing --gt-topic.
    """
    try:
        camera = select_camera_topics(topics, image_topic, info_topic)
    except TopicError as exc:
        raise RunError(str(exc)) from None
    if gt_topic is None:
        gt_topic = GT_TOPIC if GT_TOPIC in topics else None
    elif gt_topic not in topics:
        raise RunError(f'--gt-topic {gt_topic}: not in the bag '
                       f'(topics: {topic_listing(topics)})')
    return camera.image, camera.info, gt_topic


# ============================================================================ run
def _pose_at(gt_ns: np.ndarray, gt_T: np.ndarray, stamp_ns: int,
             tol_ns: int) -> np.ndarray | None:
    if gt_ns.size == 0:
        return None
    j = int(np.argmin(np.abs(gt_ns - stamp_ns)))
    return gt_T[j] if abs(int(gt_ns[j]) - stamp_ns) <= tol_ns else None


def run_bag(bag: str | Path,
            params: str | Path | Mapping[str, Any] | VoConfig | None = None,
            overrides: Mapping[str, Any] | None = None, *,
            image_topic: str | None = None, info_topic: str | None = None,
            gt_topic: str | None = None, limit: int | None = None,
            gt_bootstrap: bool = False, out_tum: str | Path | None = None,
            stats_csv: str | Path | None = None, progress: bool = False,
            out_cov: str | Path | None = None,
            max_time_diff_s: float = 0.01, seed: int = 0,
            scale_odom_topic: str | None = None) -> RunSummary:
    """Run :class:`ekf_vo.core.pipeline.VisualOdometry` on a bag (see the module docstring).

    Args:
        bag: rosbag2 directory (or its .mcap/.db3 file) or ROS 1 .bag file.
        params: params YAML path, flat vo_node parameter mapping, VoConfig or None.
        overrides: core parameter -> value, applied last.
        image_topic, info_topic, gt_topic: override the automatic topic choice.
        limit: feed at most this many images to the core.
        gt_bootstrap: pass the ground truth at the image stamp as ``known_T_world_cam``
            while the state is ``initialising`` (read for the first map only).
        out_tum: write the trajectory (ok frames) here, TUM format.
        out_cov: write each of those poses' 6x6 covariance here (io.trajectory.
            write_covariances: the stamp and 36 numbers per line).
        stats_csv: write per-frame statistics here.
        progress: tqdm progress bar on stderr.
        max_time_diff_s: association tolerance of the evaluation and of the ground-truth
            lookup for ``gt_bootstrap`` [s].
        seed: RNG seed of the core.
        scale_odom_topic: nav_msgs/Odometry topic for ``scale_source: odometry``
            (default SCALE_ODOM_TOPIC).

    Returns:
        :class:`RunSummary`.

    Raises:
        RunError: missing bag or topics, ``gt_bootstrap`` without ground truth.
        ConfigError: bad parameters.
    """
    bag = Path(bag)
    if not bag.exists():
        raise RunError(f'bag not found: {bag}')
    cfg = make_config(params, overrides)
    try:
        counts = _topic_counts(bag)
    except BagError as exc:
        raise RunError(str(exc)) from None
    image_topic, info_topic, gt_topic = select_topics(
        {t: m for t, (m, _) in counts.items()}, image_topic, info_topic, gt_topic)
    odom_topic = _scale_odom_topic(cfg, counts, scale_odom_topic)
    gt_ns, gt_T = _ground_truth(bag, gt_topic, gt_bootstrap)
    summary = RunSummary(str(bag), image_topic, info_topic, gt_topic, cfg,
                         gt_bootstrap=gt_bootstrap)
    n_images = counts[image_topic][1]
    total = n_images if limit is None else min(n_images, int(limit))
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, unit='frame', desc=f'ekf-vo-run {bag.name}', file=sys.stderr)
    known_poses = (gt_ns, gt_T, int(round(max_time_diff_s * 1e9))) if gt_bootstrap else None
    try:
        stream, stamps_s, poses = _feed_stream(bag, cfg, seed, summary, limit, bar,
                                               known_poses, base_extrinsic(params),
                                               odom_topic)
    finally:
        if bar is not None:
            bar.close()
    if summary.frames == 0:
        why = ('no CameraInfo before/among the images' if stream.camera is None
               else 'no decodable image')
        raise RunError(f'{bag}: no image was processed ({why}; image topic {image_topic} '
                       f'[{counts[image_topic][0]}], CameraInfo topic {info_topic})')
    _summarise(summary, stamps_s, poses)
    _write_outputs(summary, out_tum, out_cov, stats_csv)
    if gt_topic is not None:
        _evaluate_into(summary, gt_ns, gt_T, max_time_diff_s)
    return summary


def _write_outputs(summary: RunSummary, out_tum: str | Path | None,
                   out_cov: str | Path | None, stats_csv: str | Path | None) -> None:
    """The trajectory (TUM), its covariances and the per-frame CSV, where asked."""
    if out_tum is not None:
        from ..io.trajectory import write_tum
        write_tum(out_tum, summary.est_stamps_s, summary.est_T_world_cam)
    if out_cov is not None:
        from ..io.trajectory import write_covariances
        write_covariances(out_cov, summary.est_stamps_s,
                          np.array(summary.est_pose_cov).reshape(-1, 6, 6))
    if stats_csv is not None:
        write_stats_csv(stats_csv, summary.frame_stats)


def _scale_odom_topic(cfg: VoConfig, counts: Mapping[str, tuple[str, int]],
                      given: str | None) -> str | None:
    """The nav_msgs/Odometry topic scale_source odometry reads (None for other sources);
    RunError when the bag lacks it."""
    if cfg.scale_source != 'odometry':
        return None
    topic = given or SCALE_ODOM_TOPIC
    if counts.get(topic, ('', 0))[0] != 'nav_msgs/msg/Odometry':
        raise RunError(f'scale_source odometry: the bag has no nav_msgs/Odometry topic '
                       f'{topic} (give --scale-odom-topic)')
    return topic


def _ground_truth(bag: Path, gt_topic: str | None, gt_bootstrap: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(stamps ns, T_world_cam) of ``gt_topic`` (empty for None); RunError when it is
    unusable or missing for ``gt_bootstrap``."""
    from ..io.bag import read_ground_truth
    if gt_bootstrap and gt_topic is None:
        raise RunError('--gt-bootstrap needs ground truth: the bag has no '
                       f'{GT_TOPIC} (give --gt-topic)')
    if gt_topic is None:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    try:
        return read_ground_truth(bag, gt_topic)
    except ValueError as exc:     # unsupported type, broken message
        raise RunError(str(exc)) from None


def _feed_stream(bag: Path, cfg: VoConfig, seed: int, summary: RunSummary,
                 limit: int | None, bar, known_poses, T_base_cam: np.ndarray,
                 odom_topic: str | None
                 ) -> tuple[VoStream, list[float], list[np.ndarray]]:
    """Every image and CameraInfo (and scale odometry) of the bag, in log order, through
    the core's front door (core.stream.VoStream); fills the counters and per-frame rows
    of `summary`. `known_poses`: (gt stamps ns, gt poses, tolerance ns) for the
    ground-truth bootstrap, or None. Returns the stream and the (stamp s, T_world_cam)
    of ok frames."""
    from ..bridge import ConversionError
    from ..core.stream import Rejection
    from ..io.prefetch import prefetched

    stream = VoStream(cfg, seed=seed, T_base_cam=T_base_cam)
    stamps_s: list[float] = []
    poses: list[np.ndarray] = []
    #: images waiting for the CameraInfo of their stamp (core/pairing.py): until it comes
    #: or the next image does; before the first CameraInfo, until it comes (as vo_node's
    #: queue_policy all)
    held: list[tuple[int, int, np.ndarray]] = []
    warned_info = False

    def process(log_ns: int, stamp_ns: int, gray: np.ndarray) -> None:
        known = None
        if known_poses is not None and stream.state == TrackingState.INITIALISING:
            known = _pose_at(*known_poses[:2], stamp_ns, known_poses[2])
        res = stream.process(gray, stamp_ns, known)
        if isinstance(res, Rejection):
            logger.warning('skipping image at %d ns: %s', log_ns, res.text)
            summary.frames_skipped += 1
            return
        summary.frames += 1
        summary.frame_stats.append(FrameStats.of(stamp_ns, res))
        if res.ok and res.T_world_cam is not None:
            stamps_s.append(stamp_ns * 1e-9)
            poses.append(np.asarray(res.T_world_cam, dtype=np.float64))
            summary.est_pose_cov.append(np.asarray(res.pose_cov, dtype=np.float64))
            summary.est_twist.append(np.asarray(res.twist_cam, dtype=np.float64))
            summary.est_twist_cov.append(np.asarray(res.twist_cov, dtype=np.float64))
            summary.est_located.append(not res.orientation_only)

    def flush(force: bool) -> None:
        """Process the held images whose CameraInfo has come (force: the next image
        came, the bound) once any calibration is known."""
        while held:
            pair = stream.pairing(held[0][1])
            if pair is None or (pair.camera is None and not pair.invalid) or \
                    (pair.wait and not force):
                return                   # an invalid one goes on: the stream rejects it
            process(*held.pop(0))

    t0 = time.perf_counter()
    topics = [summary.image_topic, summary.info_topic] + ([odom_topic] if odom_topic else [])
    for topic, msgtype, log_ns, msg, decoded in prefetched(
            _read_bag(bag, topics, summary.image_topic)):
        if topic == odom_topic:
            _add_scale_odometry(stream, topic, log_ns, msg)
            continue
        if topic == summary.info_topic:
            problem = _add_camera_info(stream, msg)
            if problem and not warned_info:
                logger.warning('unusable CameraInfo on %s: %s', topic, problem)
                warned_info = True
            flush(force=False)
            continue
        if limit is not None and summary.frames + len(held) >= limit:
            break
        if bar is not None:
            bar.update(1)
        if isinstance(decoded, ConversionError):
            logger.warning('skipping image at %d ns: %s', log_ns, decoded)
            summary.frames_skipped += 1
            continue
        gray, stamp_ns = decoded
        rejected = stream.admit(stamp_ns)
        if rejected is not None:
            logger.warning('skipping image at %d ns: %s', log_ns, rejected.text)
            summary.frames_skipped += 1
            continue
        flush(force=True)
        held.append((log_ns, stamp_ns, gray))
        flush(force=False)
    flush(force=True)
    summary.frames_skipped += len(held)        # no CameraInfo ever came for these
    summary.wall_s = time.perf_counter() - t0
    summary.n_resets = stream.n_resets
    summary.n_camera_changes = stream.n_camera_changes
    summary.local_map = stream.local_map_stats()
    summary.scale = stream.scale_status().as_status()
    return stream, stamps_s, poses


def _read_bag(bag: Path, topics: list[str], image_topic: str) -> Iterator[tuple]:
    """The bag's messages on `topics` in log order as (topic, msgtype, log ns, msg,
    decoded): for an image, decoded is (grey image, header stamp ns) or the
    ConversionError that says why not (decode_image, as in vo_node); else None. Runs in
    the prefetch thread (io/prefetch.py)."""
    from ..bridge import ConversionError, stamp_to_ns
    from ..bridge.image import decode_image
    from ..io.bag import iter_bag
    for topic, msgtype, log_ns, msg in iter_bag(bag, topics):
        decoded = None
        if topic == image_topic:
            try:
                decoded = (decode_image(msgtype, msg, gray=True),
                           stamp_to_ns(msg.header.stamp))
            except ConversionError as exc:
                decoded = exc
        yield topic, msgtype, log_ns, msg, decoded


def _add_camera_info(stream: VoStream, msg: Any) -> str:
    """A CameraInfo message into the stream; '' or why it was unusable (its stamp then
    rejects its image, core/pairing.py)."""
    from ..bridge import (ConversionError, camera_info_to_dict, stamp_to_ns,
                          validate_camera_info)
    from ..core.camera import CameraModelError
    info_stamp = None
    try:
        info_stamp = stamp_to_ns(msg.header.stamp)
        info = camera_info_to_dict(msg)
        validate_camera_info(info)
        stream.add_camera_info(info_stamp, info)
    except (ConversionError, CameraModelError, ValueError) as exc:
        if info_stamp is not None:
            stream.reject_camera_info(info_stamp)
        return str(exc)
    return ''


def _add_scale_odometry(stream: VoStream, topic: str, log_ns: int, msg: Any) -> None:
    """An external odometry message's position into the stream (scale_source odometry)."""
    from ..bridge import ConversionError, odometry_to_pose, stamp_to_ns
    try:
        rejected = stream.add_scale_odometry(stamp_to_ns(msg.header.stamp),
                                             odometry_to_pose(msg)[0][:3, 3])
    except ConversionError as exc:
        logger.warning('skipping %s message at %d ns: %s', topic, log_ns, exc)
        return
    if rejected is not None:
        logger.warning('skipping %s message at %d ns: %s', topic, log_ns, rejected.text)


def _summarise(summary: RunSummary, stamps_s: list[float], poses: list[np.ndarray]
               ) -> None:
    """Tracked %, frames/s, mean stage times and the trajectory into `summary`."""
    summary.frames_ok = len(poses)
    summary.frames_orientation_only = summary.frames_ok - int(sum(summary.est_located))
    summary.pct_tracked = 100.0 * summary.frames_ok / summary.frames
    summary.fps = summary.frames / max(summary.wall_s, 1e-9)
    stages: dict[str, list[float]] = {}
    for row in summary.frame_stats:
        for key, ms in row.timings_ms.items():
            stages.setdefault(key, []).append(float(ms))
    summary.stage_ms = {k: float(np.mean(v)) for k, v in stages.items()}
    core_s = 1e-3 * sum(stages.get('total', []))
    summary.core_fps = summary.frames / core_s if core_s > 0 else math.nan
    summary.est_stamps_s = np.asarray(stamps_s, dtype=np.float64)
    summary.est_T_world_cam = (np.stack(poses) if poses else np.zeros((0, 4, 4)))


def _evaluate_into(summary: RunSummary, gt_ns: np.ndarray, gt_T: np.ndarray,
                   max_time_diff_s: float) -> None:
    from .evaluate import EvaluationError, evaluate
    if gt_ns.size == 0:
        summary.eval_error = f'ground-truth topic {summary.gt_topic} has no messages'
        return
    if summary.frames_ok == 0:
        summary.eval_error = 'no tracked frame to evaluate'
        return
    # the poses with a position: an orientation-only one (docs/method.md §15.9) has none
    located = np.asarray(summary.est_located, bool)
    if not located.any():
        summary.eval_error = (f'no pose with a position to evaluate: all '
                              f'{summary.frames_ok} are orientation only (no map yet)')
        return
    try:
        summary.eval = evaluate(gt_ns * 1e-9, gt_T, summary.est_stamps_s[located],
                                summary.est_T_world_cam[located],
                                max_time_diff_s=max_time_diff_s,
                                n_frames_total=summary.frames)
    except EvaluationError as exc:
        summary.eval_error = str(exc)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='ekf-vo-run', description='Run ekf_vo offline on a rosbag2 bag (no ROS needed), '
        'write the trajectory (TUM) and evaluate it against the ground truth in the bag.',
        formatter_class=HelpFormatter)
    p.add_argument('bag', type=Path, help='rosbag2 directory (MCAP or sqlite3) or ROS 1 '
                   '.bag file')
    p.add_argument('-o', '--output', type=Path, required=True, metavar='EST.tum',
                   help='estimated trajectory (camera optical frame, ok frames), TUM format')
    p.add_argument('--params', type=Path, default=None,
                   help='ROS params YAML with a "vo_node: ros__parameters:" section '
                   '(default: the built-in defaults = config/ekf_vo.yaml)')
    p.add_argument('--set', dest='overrides', action='append', default=[],
                   metavar='NAME=VALUE', nargs='+',
                   help='override core parameters (list them with ekf-vo-params)')
    p.add_argument('--image-topic', default=None, help='Image or CompressedImage topic '
                   '(default: the first Image topic, else the first CompressedImage one)')
    p.add_argument('--info-topic', default=None, help='CameraInfo topic (default: the one '
                   'in the image topic\'s namespace, else the first one)')
    p.add_argument('--gt-topic', default=None,
                   help=f'ground-truth PoseStamped topic (default {GT_TOPIC} when present)')
    p.add_argument('--cov', type=Path, default=None, metavar='EST.cov',
                   help='each pose\'s 6x6 covariance (stamp + 36 numbers, row-major, '
                   'position then rotation about the world axes), for ekf-vo-eval --cov')
    p.add_argument('--stats', type=Path, default=None, metavar='stats.csv',
                   help='per-frame statistics CSV')
    p.add_argument('--json', type=Path, default=None, metavar='summary.json',
                   help='summary and evaluation as JSON')
    p.add_argument('--limit', type=int, default=None, metavar='N',
                   help='process at most N images')
    p.add_argument('--gt-bootstrap', action='store_true',
                   help='give the ground-truth pose to the first bootstrap (papers\' protocol)')
    p.add_argument('--max-time-diff', type=float, default=0.01, metavar='S',
                   help='stamp association tolerance for the evaluation [s]')
    p.add_argument('--seed', type=int, default=0, help='RNG seed of the core')
    p.add_argument('--scale-odom-topic', default=None, metavar='TOPIC',
                   help=f'nav_msgs/Odometry topic for scale_source odometry (default '
                   f'{SCALE_ODOM_TOPIC})')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar, no report')
    return p


@entry_point
def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``ekf-vo-run``; exit 0 ok, 2 bad input."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    if args.limit is not None and args.limit <= 0:
        print(f'ekf-vo-run: error: --limit must be positive, got {args.limit}',
              file=sys.stderr)
        return 2
    try:
        overrides = parse_overrides([item for group in args.overrides for item in group])
        for option, path in (('-o', args.output), ('--stats', args.stats),
                             ('--json', args.json), ('--cov', args.cov)):
            if path is not None:
                check_writable(path, option)    # before the bag, not after it
        summary = run_bag(args.bag, args.params, overrides, image_topic=args.image_topic,
                          info_topic=args.info_topic, gt_topic=args.gt_topic,
                          limit=args.limit, gt_bootstrap=args.gt_bootstrap,
                          out_tum=args.output, stats_csv=args.stats, out_cov=args.cov,
                          progress=not args.quiet, max_time_diff_s=args.max_time_diff,
                          seed=args.seed, scale_odom_topic=args.scale_odom_topic)
    except (RunError, ConfigError, UsageError) as exc:
        print(f'ekf-vo-run: error: {exc}', file=sys.stderr)
        return 2
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary.to_dict(), indent=1) + '\n', encoding='utf-8')
    if not args.quiet:
        print(format_summary(summary))
    elif summary.eval_error:
        print(f'ekf-vo-run: evaluation failed: {summary.eval_error}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
