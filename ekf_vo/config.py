"""The one typed source of truth for every ekf_vo parameter.

Each parameter is a dataclass field with a default, a unit, a description and a valid
range (or a set of choices). The core reads `VoConfig`; the ROS nodes declare exactly
these fields as ROS parameters (with the description and range in the descriptor); the
CLI tools load the same fields from the shipped YAML; `config/ekf_vo.yaml` is generated
from here (`ekf-vo-params --yaml`), and a test checks that it is up to date.

Deliberately free of rclpy: the core imports it.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from dataclasses import dataclass, field, fields
from typing import Any, Iterable, Mapping

from .cli import entry_point


class ConfigError(ValueError):
    """A parameter value is missing, of the wrong type or out of range."""


def param(default: Any, doc: str, unit: str = '', lo: float | None = None,
          hi: float | None = None, choices: Iterable[str] | None = None,
          group: str = '', read_only: bool = False) -> Any:
    """A dataclass field carrying its documentation, unit and valid range. `read_only`:
    fixed when a node starts (e.g. its subscriptions depend on it); a node refuses to
    change it at run time."""
    return field(default=default, metadata={
        'doc': doc, 'unit': unit, 'lo': lo, 'hi': hi,
        'choices': tuple(choices) if choices else None, 'group': group,
        'read_only': read_only})


class _Params:
    """Shared behaviour of the parameter dataclasses: validation and construction."""

    def validate(self):
        """Check types and ranges; raise ConfigError naming the parameter."""
        validate_dataclass(self)
        return self

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], strict: bool = True):
        """Build from a dict (e.g. the `ros__parameters` of the YAML) and validate."""
        return from_mapping(cls, values, strict).validate()


@dataclass
class VoConfig(_Params):
    """Parameters of the estimation core (camera-agnostic; units are SI or pixels).

    Monocular scale is arbitrary: "m" below means map units, which are metres only when
    `bootstrap_baseline_m` is the true distance between the two bootstrap frames.
    """

    # ---- front end (ekf_vo/core/features.py) ----
    max_features: int = param(300, 'Target number of tracked corners.', 'count', 20, 5000,
                              group='front end')
    grid_rows: int = param(4, 'Bucketing grid rows: new corners are spread over the grid.',
                           'count', 1, 32, group='front end')
    grid_cols: int = param(6, 'Bucketing grid columns.', 'count', 1, 64, group='front end')
    min_feature_distance_px: float = param(
        10.0, 'Minimum distance between corners.', 'px', 1.0, 200.0, group='front end')
    corner_quality: float = param(
        0.005, 'Shi-Tomasi quality level relative to the best corner.', '', 1e-5, 0.5,
        group='front end')
    repeated_image_max_skip: int = param(
        2, 'An image identical, pixel for pixel, to the one processed before it is skipped '
        '(counted as repeated_image), up to this many in a row: a driver or relay that '
        'repeats a frame under a new stamp would tell the filter the camera stopped for '
        'that time and jerk its velocity. Further repeats are processed: a noise-free '
        'simulated camera standing still. 0: never skip (docs/ros.md).', 'count', 0, 1000,
        group='front end')
    rolling_shutter_s: float = param(
        0.0, 'Rolling shutter: the time the sensor takes from its first row to its last '
        '(the stamp taken as the middle row\'s). Tracked pixels are moved to the stamp\'s '
        'time by the predicted motion: the rotation, and the translation at the map\'s '
        'depths (docs/method.md §15.14). Set it from the sensor\'s datasheet: a wrong '
        'value is as bad as none. 0: a global shutter. With rolling_shutter_estimate, '
        'the value used until the estimate is significant.',
        's', 0.0, 1.0, group='front end')
    rolling_shutter_estimate: bool = param(
        True, 'Estimate the rolling shutter\'s readout while tracking, from the map '
        'points\' residuals after each update (the part no pose change explains that '
        'grows with the row\'s time and the image motion; docs/method.md §15.17), and '
        'correct the pixels with it once it is significant, after 60 tracked frames. A '
        'global-shutter camera keeps rolling_shutter_s. False: rolling_shutter_s only.',
        group='front end')
    rolling_shutter_max_s: float = param(
        0.05, 'The largest readout the estimate may apply (a webcam\'s is 10-33 ms).',
        's', 0.0, 1.0, group='front end')
    klt_window_px: int = param(
        13, 'KLT window side while the light is steady. A small window is more precise (its '
        'flow is that of fewer pixels) and faster, but alone it loses tracks in fast '
        'motion; the tracks it loses are tracked again with klt_flicker_window_px '
        '(docs/method.md §6.1).', 'px', 5, 101, group='front end')
    klt_flicker_window_px: int = param(
        21, 'KLT window side while the brightness changes from frame to frame (a flicker, '
        'a hunting auto-exposure) and for the first frames, before it is measured: a '
        'larger window loses fewer tracks then; and, while the light is steady, for the '
        'tracks the klt_window_px window lost (its KLT or forward-backward check failed) '
        '(docs/method.md §6.1). 0: always klt_window_px, no second window.', 'px', 0, 101,
        group='front end')
    klt_flicker_log_gain: float = param(
        0.04, 'The light counts as changing when the root mean square, over the last 10 '
        'frame pairs, of the log brightness ratio at the tracks exceeds this (or one pair '
        'exceeds twice it); it counts as steady again 30 frames after the last such pair. '
        'While it changes, KLT uses klt_flicker_window_px and, with '
        'klt_gain_compensation, the gain is divided out before KLT.',
        '', 0.0, 1.0, group='front end')
    klt_gain_compensation: bool = param(
        True, 'While the light changes (klt_flicker_log_gain: a flicker, an auto-exposure '
        'answering a jump of the light) or on a single jump, measure the brightness '
        'change from the previous frame before KLT (31x31 grey means around the tracks '
        'and where KLT starts them) and divide it out of the frame KLT sees, as long as '
        'it is a gain of the whole frame and not each patch changing on its own: KLT has '
        'no gain in its model, and a 10 % change moves a tenth of the tracks by 7-33 px '
        '(docs/method.md §6.1: under a flicker or a hunting auto-exposure, runs more than '
        '2 deg off fall from 17 of 38 to 1). Under steady light it costs one measure after '
        'KLT (~0.2 ms a frame) and changes nothing. False: frames are tracked as they '
        'come.',
        group='front end')
    klt_pyramid_levels: int = param(
        4, 'KLT pyramid levels (more levels follow faster motion).', 'count', 0, 8,
        group='front end')
    klt_fb_max_px: float = param(
        1.0, 'Forward-backward KLT check: drop tracks whose round trip misses by more.',
        'px', 0.05, 20.0, group='front end')
    clahe_clip_limit: float = param(
        0.0, 'CLAHE contrast limit applied before detection and tracking (0 disables); '
        'helps dark or low-contrast video.', '', 0.0, 40.0, group='front end')
    redetect_ratio: float = param(
        0.8, 'Detect new corners when fewer than this fraction of max_features survive.',
        '', 0.0, 1.0, group='front end')
    lens_falloff: bool = param(
        True, 'Estimate the lens\'s fall-off of brightness towards the corners '
        '(vignetting) from the tracks, and divide it out of every image before tracking '
        'once the image is found darker by more than 15 % as far out as the tracks reach '
        '(docs/method.md §6.11). '
        'False: images are tracked as they come.', group='front end')
    denoise_min_noise_grey: float = param(
        0.0, 'Smooth the frames KLT and the detector see (a Gaussian of denoise_sigma_px) '
        'while the sensor noise estimated from the images (Immerkaer 1996) is at least '
        'this: a dim sensor at a high gain, e.g. 12 (docs/method.md §6.12: better on 38 of 51 '
        'rendered runs at 12-20 grey levels, but it left one of them confidently wrong, so '
        'it is off). 0 = never.',
        'grey levels',
        0.0, 255.0, group='front end')
    denoise_sigma_px: float = param(
        1.0, 'Standard deviation of that smoothing.', 'px', 0.1, 10.0, group='front end')
    camera_fixed_frames: int = param(
        10, 'Image regions that move with the camera (the vehicle\'s body in view, a '
        'clock burned into the image) are found by comparing each frame with the one this '
        'many frames before: textured blocks at the image\'s border that stayed identical '
        'while the rest of the image moved get no tracks (docs/method.md §6.10). 0: off.',
        'frames', 0, 1000, group='front end')

    # ---- bootstrap (ekf_vo/core/bootstrap.py) ----
    bootstrap_min_parallax_deg: float = param(
        2.0, 'Median parallax angle the bootstrap pair must reach.', 'deg', 0.1, 45.0,
        group='bootstrap')
    bootstrap_relief_h_over_e: float = param(
        0.5, 'A pair whose homography explains less than this share of the essential '
        'matrix\'s inliers sees depth relief (a street): its relative pose is unique and '
        'well conditioned at less parallax, so when its tracks will not last another '
        'frame (a fast car) it is judged by bootstrap_relief_parallax_deg instead of '
        'waiting for bootstrap_min_parallax_deg (docs/method.md §2.2.1). Flat or far '
        'scenes and rotations (H/E 0.5-1.3) keep the full gate. 0 disables.', '', 0.0,
        1.0, group='bootstrap')
    bootstrap_relief_parallax_deg: float = param(
        1.0, 'Median parallax a pair with depth relief (bootstrap_relief_h_over_e) whose '
        'tracks will not last must reach.', 'deg', 0.1, 45.0, group='bootstrap')
    bootstrap_point_min_parallax_deg: float = param(
        1.0, 'A point of the first map (two-view or multi-view start) is kept only if its '
        'rays differ by this angle; the pair\'s pose comes from the same rays, so only the '
        'pixel noise limits it.', 'deg', 0.01, 45.0, group='bootstrap')
    bootstrap_min_inliers: int = param(
        60, 'Essential-matrix inliers (with valid triangulation) the pair must have.',
        'count', 8, 10000, group='bootstrap')
    bootstrap_ransac_px: float = param(
        1.0, 'Essential-matrix RANSAC threshold.', 'px', 0.1, 20.0, group='bootstrap')
    bootstrap_max_frames: int = param(
        60, 'Give up on the reference frame after this many frames and take a new one.',
        'frames', 2, 10000, group='bootstrap')
    bootstrap_baseline_m: float = param(
        1.0, 'Distance assigned to the bootstrap baseline (sets the map scale).', 'm',
        1e-6, 1e6, group='bootstrap')
    orientation_before_map: bool = param(
        True, 'Before the two-view bootstrap has a map (a camera turning in place, a robot '
        'standing), publish the orientation from the tracks alone, with the position '
        'unknown (unknown_position_sigma) and ~/status DEGRADED (docs/method.md §15.9).',
        group='bootstrap')
    orientation_only_after_s: float = param(
        0.5, 'Publish orientation-only poses once the bootstrap has waited this long (a '
        'camera that moves bootstraps sooner, and its position is then known).', 's', 0.0,
        3600.0, group='bootstrap')
    orientation_only_translation_sigma_deg: float = param(
        0.5, 'The rotation an undetected translation (parallax below the bootstrap\'s gate) '
        'can pass for in an orientation-only pose: added per reference frame and per pose '
        '(docs/method.md §15.9).', 'deg', 0.0, 45.0, group='bootstrap')
    orientation_only_bootstrap_parallax_deg: float = param(
        4.0, 'Once orientation-only poses are published, the bootstrap waits for this median '
        'parallax (instead of bootstrap_min_parallax_deg): nothing is lost by waiting, and '
        'the rotation of a pair at the smaller gate can be degrees off (§15.9).', 'deg',
        0.1, 45.0, group='bootstrap')
    orientation_only_max_px: float = param(
        3.0, 'A track agrees with a rotation-only fit within this distance (or within '
        'orientation_only_max_deg, whichever is larger).', 'px', 0.1, 50.0,
        group='bootstrap')
    orientation_only_max_deg: float = param(
        0.32, 'A track agrees with a rotation-only fit within this angle (or within '
        'orientation_only_max_px, whichever is larger): the few centimetres a hand-held '
        'camera moves while it turns leave an angle between the rays whatever the '
        'resolution; 0.32 deg is 2.9 px at a 525 px focal length, 5.0 px at 900 px '
        '(docs/method.md §15.9).',
        'deg', 0.0, 10.0, group='bootstrap')
    unknown_position_sigma: float = param(
        1000.0, 'Std published for a position (and linear velocity, per second) that '
        'nothing measures: orientation-only poses.', 'm', 1.0, 1e9, group='bootstrap')
    bootstrap: str = param(
        'two_view', 'Map bootstrap: two_view (essential matrix, docs/method.md §2.1) or '
        'multi_view (two-view start, PnP + triangulation over the first '
        'multiview_keyframes keyframes, then a sparse bundle adjustment; docs/method.md §2.4).',
        choices=('two_view', 'multi_view'), group='bootstrap')
    multiview_keyframes: int = param(
        5, 'Keyframes reconstructed together by the multi_view bootstrap.', 'count', 2, 30,
        group='bootstrap')
    multiview_keyframe_parallax_deg: float = param(
        2.0, 'multi_view: a frame becomes a keyframe when the median parallax of the map '
        'points against the last keyframe exceeds this.', 'deg', 0.1, 45.0,
        group='bootstrap')
    multiview_ba_huber_px: float = param(
        1.0, 'multi_view: width of the Huber loss of the bundle adjustment (residuals '
        'beyond it are down-weighted as outliers).', 'px', 0.01, 50.0, group='bootstrap')
    multiview_ba_max_evaluations: int = param(
        200, 'multi_view: residual evaluations allowed to the bundle adjustment.', 'count',
        1, 10000, group='bootstrap')

    # ---- EKF (ekf_vo/core/ekf.py) ----
    estimator: str = param('ekf', 'Pose tracker: ekf (hybrid EKF), iekf (iterated EKF) or '
                           'epnp (per-frame EPnP + refinement, the paper baseline).',
                           choices=('ekf', 'iekf', 'epnp'), group='ekf')
    iekf_iterations: int = param(2, 'Iterations of the iterated EKF update.', 'count', 1, 20,
                                 group='ekf')
    pixel_sigma_px: float = param(
        1.0, 'Standard deviation of a feature measurement: the R of the EKF update and '
        'the noise of the EPnP baseline\'s covariance.', 'px', 0.01, 50.0, group='ekf')
    accel_sigma: float = param(
        5.0, 'Linear acceleration impulse std: velocity noise a*dt per step (docs/method.md §3).',
        'm/s^2', 1e-6, 1e4, group='ekf')
    accel_sigma_per_speed: float = param(
        0.0, 'Linear acceleration impulse std per unit of the speed over the bootstrap '
        'pair: the noise is max(accel_sigma, this x that speed). The map\'s unit is the '
        'bootstrap baseline, so an acceleration in m/s^2 means a different motion in '
        'each map: a camera three times as fast bootstraps over a third of the time, at '
        'three times the speed in map units, and turns its velocity nine times as fast '
        '(docs/method.md §3.2). 0: accel_sigma alone.', '1/s', 0.0, 1e3, group='ekf')
    angular_accel_sigma: float = param(
        5.0, 'Angular acceleration impulse std: angular velocity noise alpha*dt per step.', 'rad/s^2', 1e-6, 1e4,
        group='ekf')
    stamp_sigma_s: float = param(
        0.0, 'Standard deviation of an image stamp\'s error (a driver that stamps on '
        'arrival: 1-5 ms); the prediction is uncertain by the motion over that time. '
        'Off by default: it helps jittered stamps and hurts fast motion (docs/method.md '
        '§3.5).', 's', 0.0, 1.0, group='ekf')
    init_velocity_sigma: float = param(
        0.5, 'Initial standard deviation of the linear velocity.', 'm/s', 1e-6, 1e4,
        group='ekf')
    init_angular_velocity_sigma: float = param(
        0.5, 'Initial standard deviation of the angular velocity.', 'rad/s', 1e-6, 1e4,
        group='ekf')
    init_pose_sigma: float = param(
        1e-3, 'Initial standard deviation of position (m) and orientation (rad).', '',
        1e-9, 10.0, group='ekf')
    fading_memory: float = param(
        1.0, 'Fading-memory factor lambda: P(k|k-1) = lambda F P F^T + G Q G^T '
        '(1 disables; docs/method.md §3.4).', '',
        1.0, 1.5, group='ekf')
    default_dt_s: float = param(
        0.1, 'Time step used when stamps are unusable (first frames, equal stamps).', 's',
        1e-4, 10.0, group='ekf')
    max_dt_s: float = param(
        1.0, 'Reset tracking when the gap between two frames is longer.', 's', 1e-3, 1e3,
        group='ekf')

    # ---- robust update (ekf_vo/core/robust_update.py) ----
    one_point_ransac: bool = param(True, 'Use 1-point RANSAC (Civera 2010) in the update.',
                                   group='ransac')
    ransac_inlier_px: float = param(
        2.0, 'Support threshold of a 1-point hypothesis (low-innovation inliers).', 'px',
        0.1, 50.0, group='ransac')
    ransac_probability: float = param(
        0.99, 'Probability that at least one hypothesis is outlier-free.', '', 0.5, 0.99999,
        group='ransac')
    ransac_max_hypotheses: int = param(
        50, 'Upper bound on 1-point hypotheses per frame.', 'count', 1, 10000,
        group='ransac')
    gate_probability: float = param(
        0.99, 'Chi-square gate (2 dof) for the high-innovation rescue.', '', 0.5, 0.99999,
        group='ransac')
    max_update_points: int = param(
        400, 'At most this many map points enter one update (spread over the image).',
        'count', 6, 100000, group='ransac')

    # ---- tracks without depth (ekf_vo/core/bearing.py) ----
    bearing_max_map_points: int = param(
        40, 'In a frame with fewer map matches than this (a turn in place leaves the map '
        'behind), tracks without a map point are measured too, as rays of unknown depth '
        '(docs/method.md §15.8); 0 = never.', 'count', 0, 100000, group='map')
    bearing_max_points: int = param(
        60, 'At most this many rays without depth in one update (the oldest tracks).',
        'count', 1, 100000, group='map')
    bearing_max_baseline_ratio: float = param(
        0.1, 'A ray is measured only while the camera is within this share of the median '
        'depth of the map from where the ray was first seen: with a baseline its unknown '
        'depth trades the rotation against the translation, and the linearised depth '
        'spread no longer holds (docs/method.md §15.8).', '', 0.0, 10.0, group='map')
    bearing_depth_rel_sigma: float = param(
        1.0, 'Std of a ray\'s unknown inverse depth relative to the inverse of the median '
        'depth of the map in view (1: from a third of that depth to infinity at 2 sigma).',
        '', 0.01, 100.0, group='map')

    # ---- map (ekf_vo/core/map.py, triangulation.py) ----
    triangulation_min_parallax_deg: float = param(
        1.0, 'A new point is triangulated once its rays differ by this angle.', 'deg',
        0.01, 45.0, group='map')
    triangulation_max_reproj_px: float = param(
        2.0, 'Reject a triangulated point whose reprojection error is larger.', 'px', 0.1,
        50.0, group='map')
    triangulation_depth_debias: bool = param(
        False, 'Move each new point towards its first camera by its depth\'s second-order '
        'bias, var(depth) / depth, at the pixel noise its neighbours\' triangulation '
        'residuals show: a depth from a small parallax is too long on average, and a map '
        'whose every new point is too long grows its scale (docs/method.md §7.2.1). Off by '
        'default: it lowers a forward-driving car\'s scale drift (KITTI 06) but made the '
        'rendered ground robot worse on 4 of 5 seeds.', group='map')
    max_map_points: int = param(5000, 'Bound on the map size; oldest unseen culled first.',
                                'count', 50, 1000000, group='map')
    cull_after_misses: int = param(
        3, 'Remove a map point after this many consecutive outlier verdicts.', 'count', 1,
        1000, group='map')

    # ---- local map: keyframes, windowed adjustment (ekf_vo/core/local_map.py) ----
    local_map: bool = param(
        True, 'Keyframes and a windowed bundle adjustment that refines the map points and '
        'the keyframe poses in a worker process (docs/method.md §12); off = points are '
        'triangulated once and never refined.', group='local_map')
    keyframe_min_covisibility: float = param(
        0.7, 'A frame becomes a keyframe when fewer than this share of the last keyframe\'s '
        'map points are still tracked.', '', 0.0, 1.0, group='local_map')
    keyframe_max_baseline_ratio: float = param(
        0.1, 'A frame becomes a keyframe when its distance to the last keyframe exceeds '
        'this share of the median depth of the map points it tracks.', '', 1e-3, 10.0,
        group='local_map')
    keyframe_max_rotation_deg: float = param(
        10.0, 'A frame becomes a keyframe when it has turned this much since the last one.',
        'deg', 0.1, 180.0, group='local_map')
    ba_window_keyframes: int = param(
        6, 'Keyframes in the adjusted window (the newest ones). 8-10 for a car on a road '
        '(KITTI 06, raw and JPEG: every seed at or below 0.084 % of the path, against up '
        'to 0.120 %) at 2.5-3x the adjustment\'s time; not the default, since a longer '
        'window loses on a fast junction, the rendered walk and drone (docs/method.md '
        '§12.4, ninth round).',
        'count', 3, 50,
        group='local_map')
    ba_fixed_keyframes: int = param(
        2, 'Oldest keyframes of the window held fixed: they fix position, orientation and '
        'scale (a monocular gauge needs two).', 'count', 2, 10, group='local_map')
    ba_min_keyframe_points: int = param(
        10, 'A keyframe fixes the adjustment\'s gauge, or is adjusted, only if it sees this '
        'many of the window\'s points; one that sees fewer is held fixed, and a window '
        'without ba_fixed_keyframes + 1 such keyframes is not adjusted (docs/method.md '
        '§12.2).', 'count', 3, 10000, group='local_map')
    ba_min_parallax_deg: float = param(
        1.0, 'Only points whose rays from the window\'s keyframes span this angle are '
        'adjusted (1 deg, the triangulation gate: the young points that made a camera '
        'circling a scene drift are refined too; docs/method.md §15.8).', 'deg', 0.0, 45.0,
        group='local_map')
    ba_max_iterations: int = param(
        10, 'Levenberg-Marquardt iterations per adjustment.', 'count', 1, 100,
        group='local_map')
    ba_huber_px: float = param(
        2.0, 'Width of the Huber loss of the adjustment (larger errors weigh linearly).',
        'px', 0.1, 50.0, group='local_map')
    ba_outlier_px: float = param(
        3.0, 'After an adjustment, a point whose median reprojection error over its '
        'keyframes exceeds this is culled.', 'px', 0.1, 50.0, group='local_map')
    ba_apply_after_frames: int = param(
        2, 'An adjustment started at a keyframe is applied before the update of the frame '
        'this many frames later (waiting for it if it is not done: results do not depend '
        'on timing).', 'frames', 1, 100, group='local_map')
    ba_pose_prior_weight: float = param(
        1.0, 'Share of an adjustment\'s information about a keyframe pose (the inverse of '
        'its marginal covariance, from its observations) kept as a prior on that pose in '
        'the next adjustment (0: none, each window starts afresh from its fixed '
        'keyframes; 1: all of it, which counts those observations twice, the price of not '
        'marginalising). It holds the scale of a window whose gauge keyframes are a short '
        'baseline apart (docs/method.md §12.2, §15.8).', '', 0.0, 1.0, group='local_map')
    ba_pose_feedback: bool = param(
        False, 'Feed an adjustment\'s pose of its newest keyframe back to the filter, as a '
        'measurement of the current pose (the keyframe\'s correction carried along the '
        'filter\'s motion since), when it disagrees with the filter beyond '
        'ba_pose_feedback_min_nis: the filter has drifted from the map its window refined, '
        'and its fresh points would carry the drift into the map. The mean moves; the '
        'covariance stays, since the pose rests on pixels the filter has used '
        '(docs/method.md §12.2).', group='local_map')
    ba_pose_feedback_min_nis: float = param(
        16.81, 'The NIS (6 dof) of the adjusted pose against the filter\'s own covariance '
        'above which ba_pose_feedback corrects the filter (16.81: the chi-square 99 % '
        'quantile; 0: every adjustment).', '', 0.0, 1e6, group='local_map')
    refind_map_points: bool = param(
        False, 'Search map points whose track has ended around their predicted pixel by '
        'ORB descriptor; a match becomes a measurement and a track again '
        '(docs/method.md §12.5). Needs local_map (descriptors come from keyframes). Off: '
        'not yet a win on every sequence (docs/method.md §12.4).',
        group='local_map')
    refind_max_hamming: int = param(
        50, 'Largest Hamming distance (of 256 bits) of a match found again.', 'bits', 1,
        256, group='local_map')
    refind_search_sigmas: float = param(
        3.0, 'Search radius in standard deviations of the innovation (prior + pixel '
        'noise).', '', 0.5, 20.0, group='local_map')
    refind_min_radius_px: float = param(
        4.0, 'Smallest search radius.', 'px', 0.5, 200.0, group='local_map')
    refind_max_radius_px: float = param(
        20.0, 'Largest search radius (a wider prior is not searched: too ambiguous).',
        'px', 1.0, 500.0, group='local_map')
    refind_max_points: int = param(
        150, 'At most this many map points are searched for per frame.', 'count', 1,
        100000, group='local_map')
    map_point_uncertainty: bool = param(
        False, 'Add each map point\'s covariance (triangulation or adjustment), projected '
        'into the image, to its measurement noise (docs/method.md §12.3). Off by default: '
        'per-point independent noise ignores the error the points share (bench.local_map).',
        group='local_map')

    # ---- the map's error in the published covariance (ekf_vo/core/map_uncertainty.py) ----
    map_in_covariance: bool = param(
        True, 'Add the map\'s own error to the published pose covariance: each point\'s '
        'triangulation noise and the common error points inherit from the poses they were '
        'made from (docs/method.md §14). Off: the covariance is relative to the map only '
        '(honest for the papers\' exact-map experiments, far too small on real data).',
        group='consistency')

    # ---- metric scale (ekf_vo/core/metric_scale.py, docs/method.md §16) ----
    scale_source: str = param(
        'none', 'none: odometry in map units (the bootstrap baseline is one unit, or '
        'bootstrap_baseline_m); camera_height: metres from the camera\'s height above '
        'the ground plane fitted to the map (camera_height_m); odometry: metres from an '
        'external odometry\'s travelled distance (vo_node topic scale_odom, '
        'nav_msgs/Odometry; ekf-vo-run --scale-odom-topic).',
        choices=('none', 'camera_height', 'odometry'), group='scale')
    camera_height_m: float = param(
        0.0, 'camera_height: the camera centre\'s height above the ground (KITTI: 1.65); '
        'required (> 0) with that source.', 'm', 0.0, 1000.0, group='scale')
    camera_height_sigma_m: float = param(
        0.05, 'camera_height: uncertainty of camera_height_m (mounting, load, '
        'suspension); a bias no averaging removes, kept in the published covariance.',
        'm', 0.0, 100.0, group='scale')
    ground_max_tilt_deg: float = param(
        15.0, 'camera_height: largest angle between the fitted ground plane\'s normal and '
        'gravity (from the base extrinsic T_base_cam_xyzw).', 'deg', 0.5, 60.0,
        group='scale')
    scale_drift_per_sqrt_m: float = param(
        0.003, 'Growth of the scale\'s log-uncertainty with the distance travelled '
        '(monocular scale drift): its variance grows by this squared per metre (0.003: '
        '3 % after 100 m; KITTI 06\'s map drifts 1.7 % in 50 m).',
        '1/sqrt(m)', 0.0, 10.0, group='scale')
    scale_drift_per_sqrt_rad: float = param(
        0.05, 'Growth of the scale\'s log-uncertainty with the angle turned (a turn, even '
        'in place, renews the map): its variance grows by this squared per radian (0.05: '
        '6 % per 90 deg; the rendered ground robot\'s map changed by up to 7 % per turn).',
        '1/sqrt(rad)', 0.0, 10.0, group='scale')
    scale_drift_per_sqrt_depth: float = param(
        0.02, 'scale_source none: growth of the map scale\'s log-uncertainty with the '
        'distance travelled in units of the median depth of the map points in front of the '
        'camera (the unit is the bootstrap baseline, so metres mean nothing): its variance '
        'grows by this squared per depth travelled, and the published position and '
        'velocity covariances carry the error it makes (docs/method.md §16.7). KITTI 06: '
        '1-3 % in 2.4 depths.', '1/sqrt(depth)', 0.0, 10.0, group='scale')
    scale_odom_window_s: float = param(
        1.0, 'odometry: one scale measurement per window of this length (the median of '
        'its sub-segments\' distance ratios).', 's', 0.1, 600.0, group='scale')
    scale_odom_min_distance_m: float = param(
        0.3, 'odometry: a window counts only when the odometry travelled this far in it '
        '(no scale while standing still).', 'm', 0.0, 1000.0, group='scale')
    scale_odom_sigma: float = param(
        0.03, 'odometry: relative error of the odometry\'s distance over one window.', '',
        0.0, 10.0, group='scale')

    # ---- measurement noise (ekf_vo/core/noise_model.py) ----
    measurement_noise: str = param(
        'fixed', 'fixed: every map point has pixel_sigma_px; adaptive: each landmark\'s '
        'sigma is pixel_sigma_px times a factor learned from its own residuals '
        '(docs/method.md §13).', choices=('fixed', 'adaptive'), group='noise')
    noise_prior_dof: float = param(
        2.0, 'adaptive: weight of the nominal sigma, in residual components (a young '
        'landmark is shrunk toward it).', 'count', 0.1, 1000.0, group='noise')
    noise_min_scale: float = param(
        0.1, 'adaptive: floor of a landmark\'s sigma / pixel_sigma_px.', '', 0.01, 1.0,
        group='noise')
    noise_max_scale: float = param(
        10.0, 'adaptive: cap of a landmark\'s sigma / pixel_sigma_px.', '', 1.0, 1000.0,
        group='noise')

    # ---- in-filter map refinement (ekf_vo/core/point_filter.py) ----
    map_refinement: str = param(
        'none', 'none: new points are triangulated once (hybrid, docs/method.md §1); '
        'filter: new tracks enter the EKF state as anchored inverse depths and are frozen '
        'into the map once accurate (docs/method.md §8); ignored by estimator epnp.',
        choices=('none', 'filter'), group='refinement')
    filter_max_points: int = param(
        40, 'N: most points in the EKF state (state dimension 13 + N).', 'count', 1, 1000,
        group='refinement')
    filter_retire_count: int = param(
        4, 'm: the m oldest in-filter points are examined for freezing every frame '
        '(N/m >= 10 is required).', 'count', 1, 100, group='refinement')
    filter_max_rel_depth_std: float = param(
        0.05, 'Freeze a point once its depth std / depth is below this.', '', 1e-4, 1.0,
        group='refinement')
    filter_min_observations: int = param(
        10, 'Freeze a point only after this many inlier observations.', 'count', 1, 10000,
        group='refinement')
    filter_max_observations: int = param(
        100, 'Drop a point still not accurate after this many observations (too little '
        'parallax; it returns to triangulation).', 'count', 2, 100000, group='refinement')
    filter_init_rho_rel_sigma: float = param(
        1.0, 'Initial inverse-depth std relative to 1/d_guess (>= 0.51 puts rho = 0, '
        'infinity, inside the 95% region).', '', 0.01, 100.0, group='refinement')
    filter_ray_sigma_px: float = param(
        1.0, 'Pixel std of the first observation that fixes a filter point\'s anchor ray; '
        'its angular error bounds how accurate the point can become (freezing test).',
        'px', 0.01, 50.0, group='refinement')

    # ---- tracking quality (ekf_vo/core/pipeline.py) ----
    min_tracking_inliers: int = param(
        12, 'Fewer update inliers than this counts as a failed frame.', 'count', 4, 10000,
        group='quality')
    max_failed_frames: int = param(
        3, 'Declare tracking lost (and re-bootstrap) after this many failed frames.',
        'frames', 1, 1000, group='quality')
    max_nis_per_dof: float = param(
        100.0, 'A frame fails when the update NIS per degree of freedom exceeds this '
        '(innovations inconsistent with the covariance; 1 is expected).', '', 1.0, 1e6,
        group='quality')
    health_window_frames: int = param(
        10, 'Updates whose NIS is summed for the consistency check (docs/method.md §15).',
        'frames', 1, 1000, group='quality')
    health_max_variance_factor: float = param(
        4.0, 'DEGRADED when the windowed NIS per dof exceeds this (and its chi-square '
        'bound); the published covariance is inflated by that factor whenever it exceeds '
        'the bound.', '', 1.0, 1e6, group='quality')
    health_min_found_share: float = param(
        0.2, 'DEGRADED when fewer of the map points the prior puts in the image are '
        'found (used as inliers).', '', 0.0, 1.0, group='quality')
    rotation_check: bool = param(
        True, 'At each keyframe, compare the filter\'s rotation since the last one with the '
        'essential matrix of their shared tracks (docs/method.md §15.2).', group='quality')
    rotation_check_max_nees: float = param(
        16.27, 'A keyframe pair whose rotation NEES against the two-view covariance exceeds '
        'this (chi-square 3 dof, 99.9 %) adds its discrepancy to the published covariance '
        'and is DEGRADED.', '', 1.0, 1e6, group='quality')
    rotation_drift_window: int = param(
        10, 'The discrepancies of up to this many consecutive judged keyframe pairs are '
        'summed and judged against their summed covariance, so that a steady drift whose '
        'every pair is within rotation_check_max_nees is found (docs/method.md §15.11); '
        '1: pairs are judged one by one only.', 'keyframe pairs', 1, 1000, group='quality')
    rotation_drift_lost_deg: float = param(
        0.0, 'A drift (rotation_drift_window) larger than this means the map no longer '
        'holds the camera: tracking is lost and the map dropped, not relocalised in '
        '(docs/method.md §15.11). 0: never (the default: on the Middlebury dino the '
        'two-view geometry itself is degrees off, and the map was dropped 5-7 times).',
        'deg', 0.0, 180.0, group='quality')
    rotation_check_min_parallax_deg: float = param(
        1.0, 'Keyframe pairs with less median parallax are not judged (the essential '
        'matrix needs a baseline).', 'deg', 0.0, 90.0, group='quality')
    relocalise: bool = param(
        True, 'After a loss, keep the map and find the camera in it by ORB descriptors and '
        'PnP (docs/method.md §15.6) before re-bootstrapping (needs local_map).',
        group='quality')
    relocalise_timeout_s: float = param(
        1.0, 'Re-bootstrap when relocalisation has failed on this much time of textured '
        'images (frames without features, e.g. a covered lens, do not count).', 's', 0.0,
        3600.0, group='quality')
    relocalise_min_inliers: int = param(
        25, 'PnP inliers needed to accept a relocalisation.', 'count', 6, 10000,
        group='quality')
    relocalise_max_hamming: int = param(
        50, 'Largest Hamming distance (of 256 bits) of a relocalisation match.', 'bits', 1,
        256, group='quality')
    max_position_sigma_m: float = param(
        10.0, 'Declare tracking lost when the position std exceeds this.', 'm', 1e-3, 1e6,
        group='quality')

    def validate(self) -> 'VoConfig':
        validate_dataclass(self)
        # Li et al. 2016: N/m >= 10, so every point is observed ~10 times before freezing
        if self.filter_max_points < 10 * self.filter_retire_count:
            raise ConfigError(
                f'filter_max_points / filter_retire_count must be >= 10, got '
                f'{self.filter_max_points}/{self.filter_retire_count}')
        if self.filter_max_observations <= self.filter_min_observations:
            raise ConfigError('filter_max_observations must exceed filter_min_observations')
        if self.scale_source == 'camera_height' and not self.camera_height_m > 0:
            raise ConfigError('scale_source camera_height needs camera_height_m > 0 (the '
                              'camera centre\'s height above the ground, metres)')
        return self


@dataclass
class NodeConfig(_Params):
    """Parameters of the ROS edge (vo_node); the core never sees these."""

    image_transport: str = param('raw', 'Subscribe `image` (raw) or `image/compressed`.',
                                 choices=('raw', 'compressed'), group='ros', read_only=True)
    reliable_qos: bool = param(
        False, 'Subscribe with reliable QoS instead of sensor-data (best effort) QoS.',
        group='ros', read_only=True)
    odom_frame: str = param('odom', 'frame_id of the published odometry and map.',
                            group='ros')
    base_frame: str = param('base_link', 'child_frame_id of the odometry (the robot body).',
                            group='ros')
    T_base_cam_xyz: tuple = param(
        (0.0, 0.0, 0.0), 'Camera optical frame origin in the base frame.', 'm', group='ros')
    T_base_cam_xyzw: tuple = param(
        (-0.5, 0.5, -0.5, 0.5), 'Camera optical frame orientation in the base frame, '
        'quaternion x y z w (default: REP-103 optical -> body rotation).', group='ros')
    queue_policy: str = param(
        'latest', 'latest: a live robot; at most queue_size frames wait for the estimator, '
        'the oldest is dropped when it is behind (counted in ~/status as dropped_behind). '
        'all: replay; every frame is processed in arrival order, nothing is dropped '
        '(reliable keep-all subscription, images before the first CameraInfo wait for '
        'it); pace the player (ekf-vo-play --rate) so the queue stays short.',
        choices=('latest', 'all'), group='ros', read_only=True)
    queue_size: int = param(
        2, 'queue_policy latest: frames waiting for the estimator; older ones are dropped '
        'and counted.', 'count', 1, 100, group='ros')
    camera_info_wait_s: float = param(
        0.05, 'An image waits at most this long for the CameraInfo of its stamp '
        '(image_transport\'s pairing, whichever comes first); once CameraInfo stops '
        'matching image stamps, images go on with the last valid one at once.', 's', 0.0,
        5.0, group='ros')
    publish_path: bool = param(True, 'Publish ~/path (nav_msgs/Path) for RViz.', group='ros')
    max_path_length: int = param(5000, 'Poses kept in ~/path.', 'count', 1, 1000000,
                                 group='ros')
    path_rate_hz: float = param(2.0, 'Rate at which ~/path is republished.', 'Hz', 0.01,
                                100.0, group='ros')
    landmarks_every_n_frames: int = param(
        5, 'Publish the landmark update for map_node every n frames.', 'frames', 1, 1000,
        group='ros')

    def validate(self) -> 'NodeConfig':
        validate_dataclass(self)
        if len(self.T_base_cam_xyz) != 3 or len(self.T_base_cam_xyzw) != 4:
            raise ConfigError('T_base_cam_xyz needs 3 values and T_base_cam_xyzw 4')
        norm = math.sqrt(sum(float(v) ** 2 for v in self.T_base_cam_xyzw))
        if not 0.9 < norm < 1.1:
            raise ConfigError(f'T_base_cam_xyzw must be a unit quaternion (norm {norm:.3f})')
        return self


@dataclass
class MapNodeConfig(_Params):
    """Parameters of map_node."""

    publish_rate_hz: float = param(1.0, 'Rate of `map_points` (PointCloud2).', 'Hz', 0.01,
                                   100.0, group='map_node')
    odom_frame: str = param('odom', 'frame_id of the published cloud.', group='map_node')


# ---------------------------------------------------------------- generic helpers

def validate_dataclass(obj: Any) -> None:
    """Type and range check of every field against its metadata."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        default = f.default if f.default is not dataclasses.MISSING else None
        meta = f.metadata
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f'{f.name} must be a bool, got {value!r}')
            continue
        if isinstance(default, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f'{f.name} must be a number, got {value!r}')
            if isinstance(default, int) and not isinstance(default, bool) \
                    and float(value) != int(value):
                raise ConfigError(f'{f.name} must be an integer, got {value!r}')
            if not math.isfinite(float(value)):
                raise ConfigError(f'{f.name} must be finite, got {value!r}')
            if meta.get('lo') is not None and value < meta['lo']:
                raise ConfigError(f'{f.name}={value} is below its minimum {meta["lo"]}')
            if meta.get('hi') is not None and value > meta['hi']:
                raise ConfigError(f'{f.name}={value} is above its maximum {meta["hi"]}')
        if meta.get('choices') and value not in meta['choices']:
            raise ConfigError(f'{f.name}={value!r} is not one of {meta["choices"]}')


def from_mapping(cls: type, values: Mapping[str, Any], strict: bool = True) -> Any:
    """Instantiate `cls` from a mapping; unknown keys raise when `strict`."""
    names = {f.name: f for f in fields(cls)}
    unknown = [k for k in values if k not in names]
    if strict and unknown:
        raise ConfigError(f'unknown parameter(s) for {cls.__name__}: {sorted(unknown)}')
    kwargs = {}
    for key, value in values.items():
        if key not in names:
            continue
        default = names[key].default
        if isinstance(default, float) and isinstance(value, int) \
                and not isinstance(value, bool):
            value = float(value)   # YAML "2" for a float parameter
        if isinstance(default, int) and not isinstance(default, bool) \
                and isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(default, tuple) and isinstance(value, (list, tuple)):
            value = tuple(float(v) for v in value)   # ROS double arrays arrive as lists
        kwargs[key] = value
    return cls(**kwargs)


def _parse_bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ('1', 'true', 'yes', 'on'):
        return True
    if low in ('0', 'false', 'no', 'off'):
        return False
    raise ValueError(text)


def _parse_int(text: str) -> int:
    value = float(text)          # '300', '3e2' and '300.0' alike
    if not value.is_integer():
        raise ValueError(text)
    return int(value)


def _parse_floats(text: str) -> tuple:
    return tuple(float(v) for v in text.split(',') if v.strip())


def parse_value(name: str, text: str, default: Any, prefix: str = '') -> Any:
    """Command-line ``text`` as the type of parameter ``name`` (that of its ``default``:
    bool, int, float, str; a tuple takes comma-separated numbers). ConfigError naming
    ``prefix + name`` and the expected type, e.g. "max_features: expected an integer,
    got 'abc'". Ranges are checked by :func:`validate_dataclass`, not here."""
    if isinstance(default, bool):
        expected, convert = 'a boolean (true/false)', _parse_bool
    elif isinstance(default, int):
        expected, convert = 'an integer', _parse_int
    elif isinstance(default, float):
        expected, convert = 'a number', float
    elif isinstance(default, tuple):
        expected, convert = 'comma-separated numbers', _parse_floats
    else:
        return text
    try:
        return convert(text)
    except ValueError:
        raise ConfigError(f'{prefix}{name}: expected {expected}, got {text!r}') from None


def describe(f: dataclasses.Field) -> str:
    """One-line description with unit and range, used in YAML and ROS descriptors."""
    meta = f.metadata
    text = meta['doc']
    extras = []
    if meta.get('unit'):
        extras.append(f'unit: {meta["unit"]}')
    if meta.get('lo') is not None:
        extras.append(f'range: [{meta["lo"]}, {meta["hi"]}]')
    if meta.get('choices'):
        extras.append('choices: ' + ', '.join(meta['choices']))
    if meta.get('read_only'):
        extras.append('read-only: set at start')
    if extras:
        text += ' (' + '; '.join(extras) + ')'
    return text


def load_yaml_params(path: str, node_name: str = 'vo_node') -> dict[str, Any]:
    """The `ros__parameters` of `node_name` in a ROS params YAML file."""
    import yaml   # PyYAML comes with rclpy; imported lazily to keep the core light
    try:
        with open(path, 'r', encoding='utf-8') as stream:
            data = yaml.safe_load(stream) or {}
    except OSError as exc:
        raise ConfigError(f'cannot read params file {path}: {exc.strerror or exc}') from None
    except UnicodeDecodeError:
        raise ConfigError(f'{path}: not a text (UTF-8) YAML file') from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f'{path}:{mark.line + 1}' if mark is not None else str(path)
        what = getattr(exc, 'problem', None) or str(exc).splitlines()[0]
        raise ConfigError(f'{where}: invalid YAML: {what}') from None
    for key in (node_name, '/' + node_name, '/**'):
        section = data.get(key) if isinstance(data, dict) else None
        if isinstance(section, dict) and 'ros__parameters' in section:
            params = section['ros__parameters'] or {}
            if not isinstance(params, dict):
                raise ConfigError(f'{path}: {key}: ros__parameters must be a mapping')
            return dict(params)
    raise ConfigError(f'{path}: no "{node_name}: ros__parameters:" section')


def split_params(values: Mapping[str, Any]) -> tuple[VoConfig, NodeConfig]:
    """Split a flat vo_node parameter dict into the core and the node configs."""
    core_names = {f.name for f in fields(VoConfig)}
    node_names = {f.name for f in fields(NodeConfig)}
    unknown = set(values) - core_names - node_names - {'use_sim_time'}
    if unknown:
        raise ConfigError(f'unknown vo_node parameter(s): {sorted(unknown)}')
    core = VoConfig.from_mapping({k: v for k, v in values.items() if k in core_names})
    node = NodeConfig.from_mapping({k: v for k, v in values.items() if k in node_names})
    return core, node


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    return repr(value)


def _yaml_section(node_name: str, classes: Iterable[type]) -> list[str]:
    lines = [f'{node_name}:', '  ros__parameters:']
    group = None
    for cls in classes:
        for f in fields(cls):
            if f.metadata['group'] != group:
                group = f.metadata['group']
                lines += ['', f'    # ---- {group} ----']
            lines.append(f'    # {describe(f)}')
            lines.append(f'    {f.name}: {_yaml_value(f.default)}')
    return lines


def to_yaml() -> str:
    """The shipped params file, generated so it can never disagree with the code."""
    lines = ['# ekf_vo parameters. GENERATED from ekf_vo/config.py by `make params`;',
             '# edit the code, not this file. Every parameter: meaning (unit; range).',
             '# Use: vo_node --ros-args --params-file config/ekf_vo.yaml', '']
    lines += _yaml_section('vo_node', (VoConfig, NodeConfig))
    lines += [''] + _yaml_section('map_node', (MapNodeConfig,))
    return '\n'.join(lines) + '\n'


@entry_point
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='ekf-vo-params',
                                     description='Print the ekf_vo parameters.')
    parser.add_argument('--yaml', action='store_true', help='print the shipped YAML')
    args = parser.parse_args(argv)
    if args.yaml:
        sys.stdout.write(to_yaml())
        return 0
    for cls in (VoConfig, NodeConfig, MapNodeConfig):
        print(f'[{cls.__name__}]')
        for f in fields(cls):
            print(f'  {f.name} = {f.default!r}: {describe(f)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
