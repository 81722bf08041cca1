"""Synthetic monocular sequences: a procedurally textured room seen by a moving pinhole camera.

Console script ``ekf-vo-synth OUT_BAG [options]`` writes a rosbag2 (MCAP) with
``/camera/image_raw`` (or ``/camera/image_raw/compressed``), ``/camera/camera_info`` and
``/ground_truth/pose`` (T_world_cam of the optical frame, frame_id ``world``), all with the
same stamps.  Library use (no bag)::

    cfg = SynthConfig(frames=100, seed=3)
    for stamp_ns, image, T_world_cam in render_sequence(cfg):
        ...

Conventions: world frame z up; camera optical frame z forward, x right, y down;
``T_a_b`` maps b-frame points into frame a; pixel (0, 0) is the centre of the top-left
pixel (OpenCV); quaternions are ``*_xyzw``.

Scene, renderer and trajectories: :mod:`ekf_vo.tools.synth_scene`; here the frames of a
sequence (supersampling, plumb_bob distortion, motion blur, noise), the bag writer and the CLI.
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..bridge.topics import transport_topic
from ..cli import HelpFormatter, UsageError, check_writable, entry_point
from .wheel_odometry import WheelNoise, wheel_odometry
from .synth_scene import (TRAJECTORIES, Renderer, Scene, make_scene, scene_for,
                          trajectory_pose, trajectory_stats, undistort_pixels)

logger = logging.getLogger(__name__)

__all__ = ['EPOCH_NS', 'TRAJECTORIES', 'Scene', 'make_scene', 'scene_for', 'undistort_pixels',
           'trajectory_pose', 'trajectory_stats', 'SynthConfig', 'SequenceRenderer',
           'render_sequence', 'write_bag', 'build_parser', 'main']

EPOCH_NS = 1_700_000_000 * 1_000_000_000
"""Stamp of frame 0 (fixed so output is reproducible)."""
ROLLING_SHUTTER_BANDS = 32
"""Bands of rows a rolling-shutter frame is rendered in (SynthConfig.rolling_shutter_s)."""


# =========================================================================== sequences
@dataclass
class SynthConfig:
    """All options of a synthetic sequence (defaults = the CLI defaults)."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float | None = None          # default: fx
    cx: float | None = None          # default: (width - 1) / 2
    cy: float | None = None          # default: (height - 1) / 2
    rate: float = 30.0
    frames: int = 300
    seed: int = 0
    trajectory: str = 'walk'
    noise_px: float = 2.0            # Gaussian intensity noise sigma (grey levels)
    blur: float = 0.0                # linear motion-blur kernel length (px)
    distortion: tuple[float, ...] | None = None  # plumb_bob k1 k2 p1 p2 k3
    supersample: int = 1
    encoding: str = 'mono8'          # or 'bgr8'
    start_ns: int = EPOCH_NS
    ppm: float = 256.0               # texture texels per metre
    #: rolling shutter: the time from the first row's exposure to the last's [s]; the
    #: stamp (and the ground truth) is the middle row's. 0: a global shutter
    rolling_shutter_s: float = 0.0

    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        fy = self.fx if self.fy is None else self.fy
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        return np.array([[self.fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def D(self) -> np.ndarray:
        """plumb_bob distortion (5,), zeros when undistorted."""
        if self.distortion is None:
            return np.zeros(5)
        return np.asarray(self.distortion, float).reshape(5)

    def stamp_ns(self, k: int) -> int:
        """Stamp of frame ``k`` (exact integer nanoseconds)."""
        return int(self.start_ns + round(k * 1e9 / self.rate))


class SequenceRenderer:
    """Frames of a :class:`SynthConfig` (supersampling, distortion, blur and noise included)."""

    def __init__(self, config: SynthConfig, scene: Scene | None = None) -> None:
        self.cfg = config
        self.scene = scene if scene is not None else \
            scene_for(config.trajectory, config.seed, config.ppm)
        ss = max(1, int(config.supersample))
        K = config.K()
        W, H = config.width, config.height
        self._map: tuple[np.ndarray, np.ndarray] | None = None
        mx = my = 0
        if config.distortion is not None and np.any(config.D() != 0):
            # for each distorted pixel: where is it in the ideal (undistorted) image?
            uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            pts = np.stack([uu.ravel(), vv.ravel()], 1)
            und = undistort_pixels(pts, K, config.D(), K).reshape(H, W, 2)
            mx = int(min(max(0.0, -und[..., 0].min(), und[..., 0].max() - (W - 1)), W)) + 2
            my = int(min(max(0.0, -und[..., 1].min(), und[..., 1].max() - (H - 1)), H)) + 2
            self._map = ((und[..., 0] + mx).astype(np.float32),
                         (und[..., 1] + my).astype(np.float32))
        self._margin = (mx, my)
        Wc, Hc = W + 2 * mx, H + 2 * my
        Kc = K.copy()
        Kc[0, 2] += mx
        Kc[1, 2] += my
        Kss = Kc.copy()
        Kss[:2, :2] *= ss
        Kss[0, 2] = (Kc[0, 2] + 0.5) * ss - 0.5
        Kss[1, 2] = (Kc[1, 2] + 0.5) * ss - 0.5
        self._ss = ss
        self._canvas = (Wc, Hc)
        self.renderer = Renderer(self.scene, Kss, Wc * ss, Hc * ss,
                                 color=config.encoding == 'bgr8',
                                 lod_bias=math.log2(ss) if ss > 1 else 0.0)

    def pose(self, k: int) -> np.ndarray:
        """T_world_cam of frame ``k``."""
        return trajectory_pose(self.cfg.trajectory, k / self.cfg.rate, self.cfg.seed)

    def render_clean(self, T_world_cam: np.ndarray, k: int | None = None) -> np.ndarray:
        """Noise- and blur-free (but distorted, if configured) image at a pose; with a
        rolling shutter and the frame index `k`, each band of rows at its own time."""
        if k is not None and self.cfg.rolling_shutter_s > 0:
            img = self._render_rolling(k)
        else:
            img, _ = self.renderer.render(T_world_cam)
        if self._ss > 1:
            img = cv2.resize(img, self._canvas, interpolation=cv2.INTER_AREA)
        if self._map is not None:
            img = cv2.remap(img, self._map[0], self._map[1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        return img

    def _render_rolling(self, k: int) -> np.ndarray:
        """Frame k through a rolling shutter: ROLLING_SHUTTER_BANDS bands of rows of the
        ideal image, each rendered at the pose of its middle row's time (the stamp is the
        middle row's). Between bands the image jumps by the motion over one band's
        readout (at 100 deg/s and 30 ms, 0.1 deg); with lens distortion, a row of the
        ideal image stands for the sensor row it lands on."""
        rows = self.renderer.height
        bands = np.linspace(0, rows, ROLLING_SHUTTER_BANDS + 1).round().astype(int)
        img = None
        for b0, b1 in zip(bands[:-1], bands[1:]):
            dt = ((b0 + b1) / 2.0 / rows - 0.5) * self.cfg.rolling_shutter_s
            T = trajectory_pose(self.cfg.trajectory, k / self.cfg.rate + dt, self.cfg.seed)
            band, _ = self.renderer.render(T, rows=(int(b0), int(b1)))
            if img is None:
                img = band
            else:
                img[b0:b1] = band[b0:b1]
        return img

    def _blur_kernel(self, k: int) -> np.ndarray | None:
        L = float(self.cfg.blur)
        if L < 1.0:
            return None
        # direction of the image motion of the point 3 m ahead of the image centre
        K = self.cfg.K()
        half = 0.5 / self.cfg.rate
        Ta = trajectory_pose(self.cfg.trajectory, k / self.cfg.rate - half, self.cfg.seed)
        Tb = trajectory_pose(self.cfg.trajectory, k / self.cfg.rate + half, self.cfg.seed)
        X = Ta @ np.array([0.0, 0.0, 3.0, 1.0])
        pb = np.linalg.inv(Tb) @ X
        uv_b = (K @ pb[:3])[:2] / pb[2]
        d = uv_b - K[:2, 2]
        ang = math.atan2(d[1], d[0]) if np.linalg.norm(d) > 1e-6 else 0.0
        n = int(math.ceil(L)) | 1
        ker = np.zeros((n, n), np.float32)
        c = n // 2
        p0 = (c - 0.5 * (L - 1) * math.cos(ang), c - 0.5 * (L - 1) * math.sin(ang))
        p1 = (c + 0.5 * (L - 1) * math.cos(ang), c + 0.5 * (L - 1) * math.sin(ang))
        cv2.line(ker, (int(round(p0[0] * 16)), int(round(p0[1] * 16))),
                 (int(round(p1[0] * 16)), int(round(p1[1] * 16))), 1.0, 1, cv2.LINE_AA, shift=4)
        return ker / ker.sum()

    def frame(self, k: int) -> tuple[int, np.ndarray, np.ndarray]:
        """``(stamp_ns, image uint8, T_world_cam)`` of frame ``k``."""
        T = self.pose(k)
        img = self.render_clean(T, k)
        ker = self._blur_kernel(k)
        if ker is not None:
            img = cv2.filter2D(img, -1, ker, borderType=cv2.BORDER_REPLICATE)
        if self.cfg.noise_px > 0:
            rng = np.random.default_rng([int(self.cfg.seed), int(k), 99])
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            # img + sigma * noise, rounded and saturated to uint8
            noisy = cv2.scaleAdd(noise, float(self.cfg.noise_px), img.astype(np.float32))
            np.rint(noisy, out=noisy)
            np.clip(noisy, 0, 255, out=noisy)
            img = noisy.astype(np.uint8)
        return self.cfg.stamp_ns(k), img, T


def render_sequence(config: SynthConfig, scene: Scene | None = None
                    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield ``(stamp_ns, image, T_world_cam)`` for frames 0..config.frames-1."""
    seq = SequenceRenderer(config, scene)
    for k in range(config.frames):
        yield seq.frame(k)


def write_bag(config: SynthConfig, out: str | Path, *, raw: bool = True, compressed: bool = False,
              compressed_format: str = 'jpeg', jpeg_quality: int = 90, overwrite: bool = False,
              tum: str | Path | None = None, progress: bool = False,
              wheel_odom: WheelNoise | None = None) -> dict[str, float]:
    """Render ``config`` into the rosbag2 ``out`` (MCAP); returns timing statistics.
    `wheel_odom` (the ground_robot trajectories): also write a synthetic wheel odometry
    (wheel_odometry.py) on /scale_odom, frame odom -> base_link."""
    from ..io.bag import BagWriter  # local: keeps the renderer importable without rosbags
    from ..io.trajectory import write_tum

    cam_frame, world_frame = 'camera_optical', 'world'
    seq = SequenceRenderer(config)
    K, D = config.K(), config.D()
    stamps, poses = [], []
    t_render = 0.0
    t0 = time.perf_counter()
    it = range(config.frames)
    if progress:
        try:
            from tqdm import tqdm
            it = tqdm(it, unit='frame', desc='synth')
        except ImportError:  # pragma: no cover
            pass
    odom_xyz = None
    if wheel_odom is not None:
        # the trajectory's own time (SequenceRenderer.pose), one sample per frame
        odom_xyz = wheel_odometry(config.trajectory, np.arange(config.frames) / config.rate,
                                  wheel_odom, config.seed)[0]
    with BagWriter(out, overwrite=overwrite) as bag:
        for k in it:
            tr = time.perf_counter()
            stamp, img, T = seq.frame(k)
            t_render += time.perf_counter() - tr
            if odom_xyz is not None:    # a wheel odometry's message precedes the image's
                T_odom_base = np.eye(4)
                T_odom_base[:3, 3] = odom_xyz[k]
                bag.add_odometry('/scale_odom', T_odom_base, stamp, 'odom', 'base_link')
            bag.add_camera_info('/camera/camera_info', config.width, config.height, K, D,
                                'plumb_bob', stamp, cam_frame)
            if raw:
                bag.add_image('/camera/image_raw', img, stamp, cam_frame)
            if compressed:
                bag.add_compressed(transport_topic('/camera/image_raw', 'compressed'), img,
                                   stamp, cam_frame, compressed_format, jpeg_quality)
            bag.add_pose('/ground_truth/pose', T, stamp, world_frame)
            stamps.append(stamp)
            poses.append(T)
    total = time.perf_counter() - t0
    if tum is not None:
        write_tum(tum, np.asarray(stamps, dtype=np.int64) * 1e-9, np.asarray(poses))
    return {'frames': config.frames, 'render_s': t_render, 'total_s': total,
            'render_fps': config.frames / max(t_render, 1e-9)}


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


#: one line per trajectory of :data:`TRAJECTORIES`, for ``--help``
TRAJECTORY_HELP = {
    'walk': 'hand-held wander through the room: smooth in all 6 DoF, turning slowly',
    'orbit': 'circle of radius 1.3 m at 1.5 m height, looking outward-forward at the walls',
    'figure8': 'lemniscate 3 m x 2 m at 1.4 m height, heading loosely following the path',
    'ground_robot': 'camera 0.4 m up on a robot driving a 3 m x 2 m rectangle, stopping and '
                    'turning 90 deg in place at each corner',
    'ground_robot_arcs': 'the same robot and rectangle, corners rounded to 0.5 m, driven at '
                         'a constant 0.5 m/s (turning while driving)',
    'handheld_rotation': 'hand-held at 1.5 m, mostly rotating: yaw +-30, pitch +-20, '
                         'roll +-15 deg at up to ~100 deg/s, a few cm of translation',
    'drone_nadir': 'about 2.1 m up, looking straight down at the floor (a planar scene), '
                   'flying a 2.8 m x 1.8 m figure of eight at up to ~0.5 m/s',
    'car': 'a car 1.65 m up driving down a street of facades at 8-11 m/s (not the room; '
           'KITTI\'s camera is --width 1226 --height 370 --fx 707 --rate 10)',
    'car_turn': 'the car slowing to 4.5 m/s and turning left into a side street on a 10 m '
                'radius (26 deg/s), then driving up it',
}
#: fewest frames of a usable bag (the bootstrap needs two views)
MIN_FRAMES = 2


def build_parser() -> argparse.ArgumentParser:
    """argparse parser of ``ekf-vo-synth``."""
    epilog = 'trajectories (--trajectory):\n' + '\n'.join(
        f'  {name:<8} {TRAJECTORY_HELP[name]}' for name in TRAJECTORIES)
    p = argparse.ArgumentParser(prog='ekf-vo-synth', description=__doc__.split('\n')[0],
                                formatter_class=HelpFormatter, epilog=epilog)
    p.add_argument('out_bag', type=Path, help='output rosbag2 directory (must not exist)')
    p.add_argument('--width', type=int, default=640, help='image width (px)')
    p.add_argument('--height', type=int, default=480, help='image height (px)')
    p.add_argument('--fx', type=float, default=525.0,
                   help='focal length (px); fy = fx unless --fy')
    p.add_argument('--fy', type=float, default=None, help='vertical focal length (px); default: --fx')
    p.add_argument('--rate', type=float, default=30.0, help='frame rate (Hz)')
    p.add_argument('--frames', type=int, default=300,
                   help=f'number of frames (at least {MIN_FRAMES})')
    p.add_argument('--seed', type=int, default=0,
                   help='seed of the room texture, trajectory phases and noise')
    p.add_argument('--trajectory', choices=TRAJECTORIES, default='walk',
                   help='camera path (listed below)')
    p.add_argument('--noise-px', type=float, default=2.0,
                   help='Gaussian intensity noise sigma (grey levels)')
    p.add_argument('--blur', type=float, default=0.0, help='motion-blur kernel length (px)')
    p.add_argument('--rolling-shutter-ms', type=float, default=0.0,
                   help='rolling shutter: readout time from the first row to the last (ms; '
                   'the stamp is the middle row\'s); 0: a global shutter')
    p.add_argument('--distortion', type=float, nargs=5, metavar=('K1', 'K2', 'P1', 'P2', 'K3'),
                   default=None, help='plumb_bob distortion applied to the images')
    p.add_argument('--supersample', type=int, default=1, help='anti-aliasing factor')
    p.add_argument('--encoding', choices=('mono8', 'bgr8'), default='mono8',
                   help='image encoding: grey or colour')
    p.add_argument('--compressed', action='store_true',
                   help='also write /camera/image_raw/compressed')
    p.add_argument('--compressed-only', action='store_true',
                   help='write /camera/image_raw/compressed instead of /camera/image_raw')
    p.add_argument('--compressed-format', choices=('jpeg', 'png'), default='jpeg',
                   help='format of the compressed images')
    p.add_argument('--jpeg-quality', type=int, default=90, help='JPEG quality (1-100)')
    p.add_argument('--wheel-odom', action='store_true',
                   help='ground_robot(_arcs): also write a synthetic wheel odometry on /scale_odom '
                   '(noise and slip episodes, docs/method.md §16.4)')
    p.add_argument('--wheel-slip', type=float, default=WheelNoise.slip,
                   help='extra distance the wheels read in a slip episode (0.3 = +30 %%)')
    p.add_argument('--wheel-slip-share', type=float, default=WheelNoise.slip_share,
                   help='share of the time in slip episodes')
    p.add_argument('--tum', type=Path, default=None, help='also write ground truth as TUM text')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUT_BAG')
    p.add_argument('--stats', action='store_true', help='print trajectory speed statistics')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar or summary')
    return p


def check_args(args: argparse.Namespace) -> None:
    """UsageError for options that cannot make a usable bag, before anything is written."""
    if args.frames < MIN_FRAMES:
        raise UsageError(f'--frames must be at least {MIN_FRAMES}, got {args.frames}')
    for option, value in (('--width', args.width), ('--height', args.height),
                          ('--fx', args.fx), ('--fy', args.fy), ('--rate', args.rate),
                          ('--supersample', args.supersample)):
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise UsageError(f'{option} must be positive, got {value}')
    for option, value in (('--noise-px', args.noise_px), ('--blur', args.blur),
                          ('--rolling-shutter-ms', args.rolling_shutter_ms)):
        if not (value >= 0 and math.isfinite(value)):
            raise UsageError(f'{option} must be >= 0, got {value}')
    if not 1 <= args.jpeg_quality <= 100:
        raise UsageError(f'--jpeg-quality must be in 1..100, got {args.jpeg_quality}')
    if args.out_bag.exists() and not args.overwrite:
        raise UsageError(f'{args.out_bag} exists (use --overwrite)')
    if args.out_bag.exists() and not args.out_bag.is_dir():
        raise UsageError(f'{args.out_bag} is a file, not a bag directory')
    if not args.out_bag.exists():
        check_writable(args.out_bag / 'metadata.yaml', 'OUT_BAG')
    if args.tum is not None:
        check_writable(args.tum, '--tum')
    if args.wheel_odom and not args.trajectory.startswith('ground_robot'):
        raise UsageError('--wheel-odom needs --trajectory ground_robot(_arcs)')
    if not (0.0 <= args.wheel_slip_share <= 1.0 and args.wheel_slip >= 0.0):
        raise UsageError('--wheel-slip must be >= 0 and --wheel-slip-share in [0, 1]')


@entry_point
def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``ekf-vo-synth``."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format='%(levelname)s %(name)s: %(message)s')
    try:
        check_args(args)
    except UsageError as exc:
        print(f'ekf-vo-synth: error: {exc}', file=sys.stderr)
        return 2
    cfg = SynthConfig(width=args.width, height=args.height, fx=args.fx, fy=args.fy,
                      rate=args.rate, frames=args.frames, seed=args.seed,
                      trajectory=args.trajectory, noise_px=args.noise_px, blur=args.blur,
                      distortion=tuple(args.distortion) if args.distortion else None,
                      supersample=args.supersample, encoding=args.encoding,
                      rolling_shutter_s=args.rolling_shutter_ms * 1e-3)
    if args.stats:
        print(trajectory_stats(cfg.trajectory, cfg.frames / cfg.rate, cfg.seed))
    res = write_bag(cfg, args.out_bag, raw=not args.compressed_only,
                    compressed=args.compressed or args.compressed_only,
                    compressed_format=args.compressed_format, jpeg_quality=args.jpeg_quality,
                    overwrite=args.overwrite, tum=args.tum, progress=not args.quiet,
                    wheel_odom=WheelNoise(slip=args.wheel_slip,
                                          slip_share=args.wheel_slip_share)
                    if args.wheel_odom else None)
    size = _dir_size(args.out_bag)
    logger.info('%d frames, render %.1f frames/s, total %.1f s, bag %.2f MB',
                res['frames'], res['render_fps'], res['total_s'], size / 1e6)
    if not args.quiet:
        print(f'{args.out_bag}: {res["frames"]} frames, {size / 1e6:.2f} MB, '
              f'render {res["render_fps"]:.1f} frames/s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
