"""The front door of the core: camera calibrations and frames in, one estimate per frame out.

`VoStream` is what every user of the estimator talks to — `vo_node`, `ekf-vo-run`, the
demo and the benchmarks — so the rules about inputs are written once:
- camera: the first valid calibration starts the estimator; a different one (intrinsics,
  distortion or size; camera.PinholeCamera.same_as) restarts it on the next frame;
  stamped CameraInfo (`add_camera_info`) is paired with the image of its stamp, whichever
  comes first (pairing.py): an image whose own CameraInfo was invalid is rejected with
  it, and a changed calibration applies from the image of its stamp;
- stamps, in arrival order (`admit`): a duplicate, a slightly older stamp (out of order)
  or a jump of more than FUTURE_JUMP_S ahead is rejected; a stamp far behind the last one
  (TIME_RESET_S: a looping bag, a simulator reset) resets the estimator when that frame
  is processed;
- frames: an image whose size is not the calibration's is rejected; an image identical
  to the one processed before it is skipped, up to `repeated_image_max_skip` in a row (a
  driver repeating a frame under a new stamp: no new measurement, and processed it would
  say the camera stopped); a reset requested from outside happens before the next frame.
Rejections come back as `Rejection(key, text)` and are counted in `counters[key]`, so a
node can throttle its log per kind and publish the counts. Speaks numpy arrays, integer
nanosecond stamps and plain mappings; no ROS types.
"""
from __future__ import annotations

import collections
import logging
import threading
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from ..config import VoConfig
from .camera import PinholeCamera
from .metric_scale import MetricScale, ScaleStatus
from .pairing import CalibrationBook, Pairing
from .pipeline import FrameResult, TrackingState, VisualOdometry

logger = logging.getLogger(__name__)

#: a stamp this far behind the last one means time restarted (looping bag, sim reset) [s]
TIME_RESET_S = 1.0
#: stamps further than this ahead of the last one are treated as corrupt [s]
FUTURE_JUMP_S = 3600.0


@dataclass(frozen=True)
class Rejection:
    """Why an input was not used: `key` names the kind (a counter), `text` says it."""

    key: str
    text: str

    @property
    def ok(self) -> bool:
        """False: a rejected frame has no pose (as FrameResult.ok), so a caller that only
        wants the published poses reads `ok` of either."""
        return False


class VoStream:
    """One camera's stream of calibrations and frames into the estimator.

    Attributes: camera (the current PinholeCamera or None), vo (the VisualOdometry, None
    until a calibration arrived), counters (collections.Counter of rejections and
    events), n_camera_changes, n_resets (over every estimator this stream ran)."""

    def __init__(self, cfg: VoConfig, seed: int = 0,
                 T_base_cam: np.ndarray | None = None) -> None:
        """`T_base_cam`: the camera's pose on the robot (4x4, metres: vo_node's
        T_base_cam_xyz / _xyzw); gives the metric scale its gravity direction and lever
        arm (metric_scale.py); None: those parameters' defaults."""
        self.cfg = cfg.validate()
        self.seed = int(seed)
        self._T_base_cam = T_base_cam
        #: the map's metric scale (scale_source); converts results to metres
        self.scale = MetricScale(self.cfg, T_base_cam)
        self.camera: PinholeCamera | None = None
        self.vo: VisualOdometry | None = None
        self.counters: collections.Counter = collections.Counter()
        self.n_camera_changes = 0
        #: resets asked from outside the estimator (request_reset, time going back)
        self.n_requested_resets = 0
        self._resets_before = 0          # resets of estimators this stream replaced
        self._last_stamp_ns: int | None = None        # last admitted (arrival order)
        self._last_processed_ns: int | None = None    # last run through the estimator
        self._pending_reset: str | None = None
        self._last_image: np.ndarray | None = None    # a copy of the last one processed
        self._repeats = 0                             # images identical to it, in a row
        self._book = CalibrationBook()             # stamped CameraInfo (pairing.py)
        #: the last processed image had a CameraInfo of its own stamp (None: none yet)
        self.last_pair_exact: bool | None = None
        #: guards the inputs (calibration, stamps, resets) so a node's callbacks may call
        #: in while its worker is inside the estimator, which runs outside this lock
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ inputs
    def set_camera(self, info: Mapping[str, Any] | PinholeCamera) -> bool:
        """A calibration: a PinholeCamera or the mapping PinholeCamera.from_camera_info
        reads. Returns True when it is new or changed (the estimator restarts); raises
        CameraModelError or ValueError when unusable (the current camera stays)."""
        camera = info if isinstance(info, PinholeCamera) else \
            PinholeCamera.from_camera_info(info)
        with self._lock:
            if camera.same_as(self.camera):
                return False
            self._switch_camera(camera)
            return True

    def _switch_camera(self, camera: PinholeCamera) -> None:
        if self.camera is not None:
            self.n_camera_changes += 1
            logger.info('calibration changed: restarting the estimator')
        self.camera = camera
        self._replace_estimator(VisualOdometry(self.cfg, camera, seed=self.seed))

    def add_camera_info(self, stamp_ns: int, info: Mapping[str, Any] | PinholeCamera
                        ) -> bool:
        """A CameraInfo stamped `stamp_ns`, for the image of that stamp (pairing.py).
        Returns True when it started the estimator (the first valid one). Raises
        CameraModelError or ValueError when unusable: its stamp is then recorded as
        invalid, so that its image is rejected with it."""
        try:
            camera = info if isinstance(info, PinholeCamera) else \
                PinholeCamera.from_camera_info(info)
        except Exception:
            self.reject_camera_info(stamp_ns)
            raise
        with self._lock:
            self._book.add(stamp_ns, camera)
            first = self.camera is None
        return self.set_camera(camera) if first else False

    def reject_camera_info(self, stamp_ns: int) -> None:
        """A CameraInfo stamped `stamp_ns` that could not be used (the caller's check
        failed): its image will be rejected with it."""
        with self._lock:
            self._book.add(stamp_ns, None)

    def pairing(self, stamp_ns: int) -> Pairing | None:
        """The calibration an image of this stamp would get now (None: no stamped
        CameraInfo has come yet)."""
        with self._lock:
            return self._book.pair(stamp_ns) if len(self._book) else None

    def set_config(self, cfg: VoConfig) -> None:
        """New estimator parameters: the estimator restarts with them."""
        with self._lock:
            self.cfg = cfg.validate()
            self.scale = MetricScale(self.cfg, self._T_base_cam)
            if self.camera is not None:
                self._replace_estimator(VisualOdometry(self.cfg, self.camera,
                                                       seed=self.seed))

    def admit(self, stamp_ns: int) -> Rejection | None:
        """Check a frame's stamp in ARRIVAL order (before any queue may drop frames).
        None = accepted. A jump far back is accepted and counted (time_resets); the
        estimator resets when the first frame older than its last one is processed,
        whichever frames a caller's queue drops in between."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            last = self._last_stamp_ns
            if last is not None:
                if stamp_ns == last:
                    return self._reject('duplicate_stamp', 'duplicate image stamp: dropped')
                if stamp_ns < last:
                    if (last - stamp_ns) * 1e-9 <= TIME_RESET_S:
                        return self._reject('out_of_order',
                                            'out-of-order image stamp: dropped')
                    self.counters['time_resets'] += 1
                elif (stamp_ns - last) * 1e-9 > FUTURE_JUMP_S:
                    return self._reject('future_stamp',
                                        'image stamp jumps more than 1 h ahead: dropped')
            self._last_stamp_ns = stamp_ns
            return None

    def request_reset(self, reason: str) -> None:
        """Drop the map and re-bootstrap before the next frame."""
        with self._lock:
            self._pending_reset = reason

    def process(self, gray: np.ndarray, stamp_ns: int,
                known_T_world_cam: np.ndarray | None = None,
                on_pose: Callable[[FrameResult], None] | None = None
                ) -> FrameResult | Rejection:
        """Run one admitted frame (grey uint8 HxW) through the estimator.

        `known_T_world_cam`: only for the papers' ground-truth bootstrap (benchmarks).
        `on_pose`: called with the result (in the published frame: metres with a scale
        source) as soon as a tracked frame's pose and covariance are final, before the
        estimator's map work (pipeline.VisualOdometry.process); a node publishes its
        odometry from there. The result returned is the same object, completed.
        Only one thread may call this (a node's worker); the others may call the rest."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            if len(self._book):
                pair = self._book.pair(stamp_ns)
                if pair.invalid:
                    return self._reject('bad_camera_info_image', 'image dropped with its '
                                        'invalid CameraInfo (same stamp)')
                self.last_pair_exact = pair.exact
                if pair.camera is not None and not pair.camera.same_as(self.camera):
                    self._switch_camera(pair.camera)
            vo, camera = self.vo, self.camera
            if vo is None:
                return self._reject('no_camera_info', 'image before any valid CameraInfo: '
                                    'skipped')
            if gray.shape[:2] != (camera.height, camera.width):
                return self._reject('size_mismatch', (
                    f'image {gray.shape[1]}x{gray.shape[0]} does not match the CameraInfo '
                    f'{camera.width}x{camera.height}: dropped'))
            if self._repeated(gray):
                return self._reject('repeated_image', 'image identical to the previous one '
                                    '(a frame repeated under a new stamp): skipped')
            reasons = []
            if self._last_processed_ns is not None and stamp_ns < self._last_processed_ns:
                reasons.append('time went backwards (looping bag or sim reset)')
            if self._pending_reset is not None:
                reasons.append(self._pending_reset)
                self._pending_reset = None
            for reason in reasons[:1]:
                vo.reset(reason)
                self.n_requested_resets += 1
            self._last_processed_ns = stamp_ns
        # the estimator runs outside the lock: calibration, stamps and reset requests keep
        # coming in; a calibration change replaces the estimator for the next frame
        scaled: list[FrameResult] = []

        def pose_ready(res: FrameResult) -> None:
            # the scale sees the map the pose was estimated from, in every run (a node's
            # or an offline one): the same figures whether on_pose is given or not
            self._apply_scale(vo, res)
            scaled.append(res)
            if on_pose is not None:
                on_pose(res)

        result = vo.process(gray, stamp_ns, known_T_world_cam, on_pose=pose_ready,
                            pose_first=on_pose is not None)
        if not scaled:                     # a frame that did not track
            self._apply_scale(vo, result)
        return result

    def _repeated(self, gray: np.ndarray) -> bool:
        """True for an image identical to the last one processed, for the first
        repeated_image_max_skip of such images in a row. Real sensor noise makes two
        exposures differ; equal pixels are the same exposure sent twice."""
        if self.cfg.repeated_image_max_skip == 0:      # off: no copy, no comparison
            return False
        last = self._last_image
        if last is None or last.shape != gray.shape or not np.array_equal(last, gray):
            self._last_image = np.array(gray, copy=True)
            self._repeats = 0
            return False
        self._repeats += 1
        return self._repeats <= self.cfg.repeated_image_max_skip

    def _apply_scale(self, vo: VisualOdometry, result: FrameResult) -> None:
        with self._lock:
            if vo is self.vo:
                self.scale.apply(result, vo.map.X_world, vo.map.n_obs)

    def add_scale_odometry(self, stamp_ns: int, xyz: np.ndarray) -> Rejection | None:
        """An external odometry's position (metres, its own frame) at `stamp_ns`, for
        scale_source odometry (metric_scale.py). None = used; a non-finite position or a
        stamp not after the last one is rejected (and counted)."""
        xyz = np.asarray(xyz, float)
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            return self._reject('bad_scale_odom', 'scale_odom with a non-finite position: '
                                'ignored')
        with self._lock:
            used = self.scale.add_odometry(int(stamp_ns), xyz)
        if not used:
            return self._reject('scale_odom_out_of_order', 'scale_odom stamp not after the '
                                'last one: ignored')
        return None

    def scale_status(self) -> ScaleStatus:
        return self.scale.status()

    def map_points(self, X_world: np.ndarray) -> np.ndarray:
        """Map points in the frame of the published poses (metres with a scale source)."""
        return self.scale.points(X_world) if self.scale.active else X_world

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> TrackingState:
        return self.vo.state if self.vo is not None else TrackingState.INITIALISING

    @property
    def n_resets(self) -> int:
        return self._resets_before + (self.vo.n_resets if self.vo is not None else 0)

    def local_map_stats(self) -> dict:
        """The local map's keyframe and adjustment figures ({} when it is off)."""
        vo = self.vo
        if vo is None or vo.local_map is None:
            return {}
        return vo.local_map.stats.as_status()

    def restart(self) -> None:
        """Throw the estimator away (after an internal error); the next frame starts a
        fresh one with the current camera and parameters."""
        with self._lock:
            if self.camera is not None:
                self._replace_estimator(VisualOdometry(self.cfg, self.camera,
                                                       seed=self.seed))

    def _replace_estimator(self, vo: VisualOdometry) -> None:
        if self.vo is not None:
            self._resets_before += self.vo.n_resets
            self.vo.close()
        self.vo = vo
        self.scale.reset()                      # a new world: its scale is unknown
        self._pending_reset = None
        self._last_processed_ns = None          # a new estimator has no past

    def _reject(self, key: str, text: str) -> Rejection:
        self.counters[key] += 1
        return Rejection(key, text)
