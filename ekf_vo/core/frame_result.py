"""What the pipeline says about one frame, and its tracking states (core/pipeline.py)."""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .rotation_check import KeyframePairCheck

#: smallest variance (m^2, rad^2) of a published pose: a zero covariance would read as
#: infinite confidence to robot_localization (docs/ros.md)
MIN_VARIANCE = 1e-9


class TrackingState(enum.Enum):
    INITIALISING = 'initialising'
    TRACKING = 'tracking'
    LOST = 'lost'


@dataclass
class FrameResult:
    """What the pipeline says about one frame. Pose fields are None unless `ok`."""

    stamp_ns: int
    state: TrackingState
    ok: bool = False                        #: a pose worth publishing
    T_world_cam: np.ndarray | None = None   #: 4x4 camera optical frame -> world
    pose_cov: np.ndarray | None = None      #: 6x6 (position, world rotation vector)
    twist_cam: np.ndarray | None = None     #: (6,) v^C [m/s], w^C [rad/s], camera frame
    twist_cov: np.ndarray | None = None     #: 6x6
    n_tracks: int = 0       #: live tracks, new corners included (at on_pose: KLT's so far)
    n_matches: int = 0                      #: tracks with a landmark used in the update
    n_inliers: int = 0
    n_new_points: int = 0
    n_found_again: int = 0                  #: map points found again (tracks from now)
    n_rays: int = 0                         #: of the inliers, rays without depth (bearing.py)
    nis_per_dof: float = 0.0               #: normalised innovation squared / (2 n)
    map_size: int = 0
    #: before the map: a pose whose orientation alone is measured (orientation_only.py)
    orientation_only: bool = False
    bootstrapped: bool = False              #: this frame completed a (re-)bootstrap
    #: with bootstrapped: the index (images processed, from 0) of the bootstrap's first
    #: frame, the pose the map's gauge was fixed at (docs/method.md §12.7)
    reference_frame_index: int = -1
    #: online checks of a tracked frame (health.py): 'ok', 'degraded' or 'lost', and why
    health: str = ''
    health_reason: str = ''
    variance_factor: float = 1.0            #: windowed NIS / dof
    found_share: float = 1.0                #: inliers / map points the prior put in view
    #: share of the image fixed to the camera, whose corners are not used (camera_fixed.py)
    camera_fixed_share: float = 0.0
    #: the corners' loss of brightness of the lens fall-off divided out of the images, 0
    #: while none is (vignetting.py)
    lens_falloff_drop: float = 0.0
    #: the KLT window side [px] the next frame is tracked with, and the log brightness
    #: change divided out of this frame before KLT, 0 when none was (features.py)
    klt_window_px: int = 0
    klt_log_gain: float = 0.0
    #: tracks the steady light's small KLT window lost in this frame and the large one
    #: kept (features.py `_track_wide`): many in fast motion
    klt_wide_kept: int = 0
    #: the sensor's noise estimated from the frames [grey levels], nan before any, and
    #: whether the frames were smoothed for it before KLT (sensor_noise.py)
    sensor_noise_grey: float = float('nan')
    denoised: bool = False
    #: the rolling shutter's readout [s] the next frame's pixels are corrected with, and
    #: its estimate from the tracked frames so far, nan before any (readout.py)
    readout_s: float = 0.0
    readout_estimate_s: float = float('nan')
    message: str = ''                       #: why not ok / what happened
    #: the keyframe pair whose rotation check this frame took, as it was judged
    #: (rotation_check.KeyframePairCheck; None in most frames, and for a check taken
    #: at a reset or a loss): the benchmarks' record of the checks (§15.2)
    keyframe_pair_check: 'KeyframePairCheck | None' = None
    #: wall-clock ms of the stages this frame ran: predict, track (KLT; before the first
    #: map also the detection), update, to_pose (the start of a tracked frame to its
    #: final pose), top_up (a tracked frame's new corners, after the pose), detect (the
    #: detection alone, a part of top_up or track), map, local_map, refind, bootstrap,
    #: and total (the whole frame, measured on its own)
    timings_ms: dict = field(default_factory=dict)
    track_ids: np.ndarray | None = None     #: (n,) for debug drawing
    track_px: np.ndarray | None = None      #: (n,2) raw pixels
    track_inlier: np.ndarray | None = None  #: (n,) bool, used as an inlier this frame
    track_has_point: np.ndarray | None = None
