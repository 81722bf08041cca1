"""Convert public monocular datasets into rosbag2 (MCAP) bags that ekf_vo replays.

Console script::

    ekf-vo-convert FORMAT SRC OUT_BAG [--compressed] [--jpeg-quality Q] [--info-after-image]
                   [--limit N] [--camera-topic /camera] [--poses FILE]
                   [--camera FX FY CX CY [D0..D4]] [--overwrite] [--quiet]

Formats ``kitti``, ``tum``, ``euroc`` and ``folder``: what is read, and the frame conventions
of its ground truth, are described in :mod:`ekf_vo.tools.convert_sources` (the readers).

Output bag (every message stamped with the image time, header stamp = log time, except the
CameraInfo log time with ``--info-after-image``):

* ``<camera-topic>/image_raw`` ``sensor_msgs/msg/Image`` mono8, or with ``--compressed``
  ``<camera-topic>/image_raw/compressed`` ``sensor_msgs/msg/CompressedImage`` PNG (lossless),
  or with ``--jpeg-quality Q`` the same topic as JPEG at quality Q (lossy, what a camera's
  image_transport ``compressed`` publisher records); frame_id ``camera_optical``;
* ``<camera-topic>/camera_info`` ``sensor_msgs/msg/CameraInfo`` (R = I, P = [K | 0]), written
  before its image (same log time); with ``--info-after-image`` its log time is
  :data:`INFO_AFTER_NS` after the image (at most half-way to the next image), the order a
  live image_transport camera publisher gives, so a reader sees the first image before any
  CameraInfo; the header stamp stays the image stamp;
* ``/ground_truth/pose`` ``geometry_msgs/msg/PoseStamped``: ``T_world_cam`` of the camera
  optical frame, frame_id ``world``, for the frames that have ground truth.

Stamps keep the dataset's clock (KITTI: seconds from the sequence start, so frame 0 is at
t = 0; TUM and EuRoC: Unix time).
"""
from __future__ import annotations

import argparse
import logging
import shutil
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..bridge.topics import transport_topic
from ..cli import UsageError, check_writable, entry_point
from ..io.trajectory import GT_TOPIC
from .convert_sources import (FORMATS, ConvertError, SourceSequence, interpolate_poses,
                              load_source, tum_camera_from_name)

logger = logging.getLogger(__name__)

__all__ = ['FORMATS', 'ConvertError', 'SourceSequence', 'ConvertSummary', 'interpolate_poses',
           'load_source', 'tum_camera_from_name', 'INFO_AFTER_NS', 'check_jpeg_quality',
           'write_sequence', 'convert', 'build_parser', 'main']

CAMERA_FRAME = 'camera_optical'
WORLD_FRAME = 'world'
#: log-time delay of a CameraInfo after its image with ``info_after_image`` [ns] (1 ms)
INFO_AFTER_NS = 1_000_000


@dataclass
class ConvertSummary:
    """What :func:`convert` wrote."""

    out_bag: Path
    frames: int
    frames_with_gt: int
    counts: dict[str, int]
    camera: dict
    notes: list[str]


def check_jpeg_quality(jpeg_quality: int | None) -> None:
    """ConvertError unless ``jpeg_quality`` is None or an int in 1..100 (OpenCV would
    silently clamp anything else, hiding a typo in a benchmark's settings)."""
    if jpeg_quality is None:
        return
    if isinstance(jpeg_quality, bool) or not isinstance(jpeg_quality, (int, np.integer)) \
            or not 1 <= jpeg_quality <= 100:
        raise ConvertError(f'--jpeg-quality must be in 1..100, got {jpeg_quality}')


def write_sequence(seq: SourceSequence, out_bag: str | Path, *, compressed: bool = False,
                   jpeg_quality: int | None = None, info_after_image: bool = False,
                   limit: int | None = None, camera_topic: str = '/camera',
                   overwrite: bool = False, progress: bool = False) -> ConvertSummary:
    """Write ``seq`` as a rosbag2 (MCAP) bag (topics in the module docstring); a partly
    written bag is removed when an error interrupts the conversion.

    ``compressed``: PNG CompressedImage; ``jpeg_quality`` (1..100): JPEG CompressedImage at
    that quality (implies compressed); ``info_after_image``: each CameraInfo logged after
    its image (image_transport's order) instead of before it.
    """
    check_jpeg_quality(jpeg_quality)
    out_bag = Path(out_bag)
    if out_bag.exists() and not overwrite:
        raise ConvertError(f'{out_bag} exists (use --overwrite)')
    ns = '/' + camera_topic.strip('/') if camera_topic.strip('/') else ''
    compressed = compressed or jpeg_quality is not None
    image_topic = transport_topic(f'{ns}/image_raw', 'compressed' if compressed else 'raw')
    info_topic = f'{ns}/camera_info'
    n = len(seq) if limit is None else max(0, min(int(limit), len(seq)))
    cam = seq.camera
    it: Sequence[int] | Iterator[int] = range(n)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, unit='frame', desc=f'convert -> {out_bag.name}', file=sys.stderr)
    opts = _WriteOptions(compressed, jpeg_quality, info_after_image)
    try:
        counts = _write_frames(seq, out_bag, it, image_topic, info_topic, opts, overwrite)
    except BaseException:
        # no half-written bag left behind (a later run would refuse to overwrite it)
        if out_bag.exists():
            shutil.rmtree(out_bag, ignore_errors=True)
        raise
    n_gt = counts.get(GT_TOPIC, 0)
    notes = list(seq.notes)
    if seq.gt_T_world_cam is not None and n_gt < n:
        notes.append(f'{n - n_gt} of {n} frames have no ground truth')
    return ConvertSummary(out_bag, n, n_gt, counts, cam, notes)


@dataclass(frozen=True)
class _WriteOptions:
    """How :func:`_write_frames` writes each image and where its CameraInfo goes."""

    compressed: bool                 #: CompressedImage (else raw Image)
    jpeg_quality: int | None         #: JPEG at this quality, None: PNG (when compressed)
    info_after_image: bool           #: CameraInfo logged after its image


def _info_log_ns(seq: SourceSequence, k: int) -> int:
    """Log time of frame ``k``'s CameraInfo when it follows its image: INFO_AFTER_NS after
    the image, but at most half-way to the next image so it still precedes that one."""
    stamp = int(seq.stamps_ns[k])
    if k + 1 < len(seq):
        return stamp + min(INFO_AFTER_NS, (int(seq.stamps_ns[k + 1]) - stamp) // 2)
    return stamp + INFO_AFTER_NS


def _write_frames(seq: SourceSequence, out_bag: Path, frames: Iterable[int], image_topic: str,
                  info_topic: str, opts: _WriteOptions, overwrite: bool
                  ) -> dict[str, int]:
    """Write the frames ``frames`` of ``seq``; returns the message count per topic."""
    from ..io.bag import CAMERA_INFO, BagWriter, camera_info_msg

    cam = seq.camera
    with BagWriter(out_bag, overwrite=overwrite) as bag:
        for k in frames:
            stamp = int(seq.stamps_ns[k])
            gray = cv2.imread(str(seq.images[k]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise ConvertError(f'cannot read image {seq.images[k]}')
            if gray.shape != (cam['height'], cam['width']):
                raise ConvertError(f'{seq.images[k]}: {gray.shape[1]}x{gray.shape[0]} differs '
                                   f'from the camera {cam["width"]}x{cam["height"]}')
            # header stamp = image stamp either way (how a camera publisher pairs them)
            info = camera_info_msg(cam['width'], cam['height'], cam['K'], cam['D'],
                                   cam['distortion_model'], stamp, CAMERA_FRAME)
            if not opts.info_after_image:
                bag.write(info_topic, CAMERA_INFO, info, stamp)
            if opts.jpeg_quality is not None:
                bag.add_compressed(image_topic, gray, stamp, CAMERA_FRAME, fmt='jpeg',
                                   quality=opts.jpeg_quality)
            elif opts.compressed:
                bag.add_compressed(image_topic, gray, stamp, CAMERA_FRAME, fmt='png')
            else:
                bag.add_image(image_topic, gray, stamp, CAMERA_FRAME)
            T = seq.gt_T_world_cam[k] if seq.gt_T_world_cam is not None else None
            if T is not None:
                bag.add_pose(GT_TOPIC, T, stamp, WORLD_FRAME)
            if opts.info_after_image:
                bag.write(info_topic, CAMERA_INFO, info, _info_log_ns(seq, k))
        return dict(bag.counts)


def convert(fmt: str, src: str | Path, out_bag: str | Path, *, compressed: bool = False,
            jpeg_quality: int | None = None, info_after_image: bool = False,
            limit: int | None = None, camera_topic: str = '/camera',
            poses: str | Path | None = None, camera: Sequence[float] | None = None,
            overwrite: bool = False, progress: bool = False) -> ConvertSummary:
    """Read dataset ``src`` (format ``fmt``) and write the bag ``out_bag``
    (``compressed``, ``jpeg_quality``, ``info_after_image``: see :func:`write_sequence`).

    Raises:
        ConvertError: missing or malformed input, or ``out_bag`` exists without ``overwrite``.
    """
    if limit is not None and limit <= 0:
        raise ConvertError(f'--limit must be positive, got {limit}')
    check_jpeg_quality(jpeg_quality)
    if Path(out_bag).exists() and not overwrite:
        raise ConvertError(f'{out_bag} exists (use --overwrite)')
    if not Path(out_bag).exists():
        try:
            check_writable(Path(out_bag) / 'metadata.yaml', 'OUT_BAG')
        except UsageError as exc:
            raise ConvertError(str(exc)) from None
    if Path(src).suffix.lower() == '.bag' and Path(src).is_file():
        raise ConvertError(f'{src} is a ROS 1 bag: no conversion needed, ekf-vo-run, '
                           'ekf-vo-play and ekf-vo-eval read it as it is (ekf-vo-convert '
                           'reads dataset folders)')
    seq = load_source(fmt, src, poses=poses, camera=camera)
    return write_sequence(seq, out_bag, compressed=compressed, jpeg_quality=jpeg_quality,
                          info_after_image=info_after_image, limit=limit,
                          camera_topic=camera_topic, overwrite=overwrite, progress=progress)


# ============================================================================ CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='ekf-vo-convert', description='Convert a KITTI / TUM RGB-D / EuRoC / image-folder '
        'sequence into a rosbag2 (MCAP) with images, camera_info and ground truth.',
        epilog='Frame conventions and file layouts: see the docstring of '
        'ekf_vo/tools/convert.py.')
    p.add_argument('format', choices=FORMATS, help='dataset layout')
    p.add_argument('src', type=Path, help='dataset folder')
    p.add_argument('out_bag', type=Path, help='output bag directory (must not exist)')
    p.add_argument('--compressed', action='store_true',
                   help='write PNG CompressedImage on <camera-topic>/image_raw/compressed '
                   'instead of raw mono8 Image')
    p.add_argument('--jpeg-quality', type=int, default=None, metavar='Q',
                   help='write JPEG CompressedImage at quality Q (1-100) on '
                   '<camera-topic>/image_raw/compressed (lossy, as a camera driver records; '
                   'implies --compressed, JPEG instead of PNG)')
    p.add_argument('--info-after-image', action='store_true',
                   help='log each CameraInfo 1 ms after its image (image_transport order) '
                   'instead of before it')
    p.add_argument('--limit', type=int, default=None, metavar='N', help='first N frames only')
    p.add_argument('--camera-topic', default='/camera',
                   help='topic namespace of the camera (default: /camera)')
    p.add_argument('--poses', type=Path, default=None,
                   help='kitti: ground-truth poses file (default SRC/poses.txt or '
                   '../poses/NN.txt)')
    p.add_argument('--camera', type=float, nargs='+', default=None,
                   metavar='V', help='tum: fx fy cx cy [d0 d1 d2 d3 d4] (default: from the '
                   'freiburg1/2/3 in the folder name)')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUT_BAG')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar or summary')
    return p


@entry_point
def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``ekf-vo-convert``; exit 0 ok, 2 bad input."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    try:
        res = convert(args.format, args.src, args.out_bag, compressed=args.compressed,
                      jpeg_quality=args.jpeg_quality, info_after_image=args.info_after_image,
                      limit=args.limit, camera_topic=args.camera_topic, poses=args.poses,
                      camera=args.camera, overwrite=args.overwrite, progress=not args.quiet)
    except ConvertError as exc:
        print(f'ekf-vo-convert: error: {exc}', file=sys.stderr)
        return 2
    if not args.quiet:
        K = res.camera['K']
        print(f'{res.out_bag}: {res.frames} frames, {res.frames_with_gt} with ground truth')
        print(f'  camera {res.camera["width"]}x{res.camera["height"]} fx {K[0, 0]:.3f} '
              f'fy {K[1, 1]:.3f} cx {K[0, 2]:.3f} cy {K[1, 2]:.3f} '
              f'{res.camera["distortion_model"] or "none"} '
              f'D {np.round(res.camera["D"], 6).tolist()}')
        for topic, count in res.counts.items():
            print(f'  {topic}: {count}')
        for note in res.notes:
            print(f'  note: {note}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
