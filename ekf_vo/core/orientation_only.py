"""Orientation before the map: the camera's rotation from its tracks alone
(docs/method.md §15.9).

Until the bootstrap finds the parallax to triangulate (a camera turning in place, a robot
standing still) there is no map and no position, but the tracks still fix the rotation:
under a pure rotation a ray seen along the unit bearing b in the reference frame is seen
along R_cur_ref b now, whatever its depth. The rotation is the orthogonal Procrustes
(Kabsch) solution over the tracks the two frames share, with a two-point RANSAC against
outliers. Its noise covariance, in the current camera frame, is

    sigma^2 (sum_i (I - c_i c_i^T))^-1,   c_i = R_cur_ref b_i,

(each bearing residual constrains the rotation across its ray), sigma the pixel noise of
the two frames (sqrt 2 sigma_px) over the focal length, or the fit's residual if larger.

A translation is not noise: it is absorbed into the rotation (t/d for a translation t
across the view at depth d), and when the points lie at about one depth no residual shows
it. The two-view bootstrap refuses pairs whose parallax is below its gate, so a
translation whose parallax is below the gate goes undetected; the rotation it can pass
for is a prior, `orientation_only_translation_sigma_deg` (isotropic, `model_sigma_rad`),
added to each reference's covariance as the chain hands over and to each published
frame. (Measured on the rendered hand-held camera, 3 cm at 3 m: the chain is off by
0.1-0.9 deg. The median parallax the bootstrap triangulates from such pairs says
0.05-0.7 deg, with single pairs at 9-28 deg: under a near-pure rotation the essential
matrix's translation is arbitrary, and so is that parallax; it is not used.)

The rotation is taken against the bootstrap's reference frame, so the absorbed
translation is bounded by that pair's, not summed frame after frame; when the reference's
tracks have gone, or it has no orientation, against the last frame that has one. A new
reference inherits the orientation and the covariance of the frame it is taken at: the
chain's covariance grows with each reference, as a gyro's would. The world frame is the
first frame's camera (or the pose a re-bootstrap attaches at), so the map the bootstrap
builds later is attached at the chain's orientation of its reference frame
(core/initialisation.py).

A frame whose fit against the reference fails while the step from the last frame with an
orientation is a rotation is published from that step (`carried`), with a second
translation prior; the chain itself keeps no orientation for it, so its failed fit stays
the evidence of a translation it is. A camera that stood still and then moves is told
from one that turns (`judge_pair`): a translation across the view passes for a rotation of
about t/d and gives the bootstrap pair a parallax of about t/d, while a turn's pair has
next to none; and a robot driving off forward leaves its frames unexplained for longer
than a turn's edge does. Once seen, the chain's orientation is not published any more
and the bootstrap is not held to it (docs/method.md §15.9), unless failed fits alone
declared it and the bootstrap then refuses every pair as a rotation for a second
(`reconsider`, §15.13).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry as geo
from .camera import PinholeCamera

#: two-point hypotheses tried per fit (a Kabsch solution each; 64 leave a 1e-8 chance
#: of missing a 50 % inlier set: 0.75^64)
_HYPOTHESES = 64
#: share of the common tracks a rotation must explain: a translating camera with depth in
#: view (a car) leaves the near points' flow unexplained, and is not a rotation
MIN_INLIER_SHARE = 0.7
#: fewest inliers for a fit (the rotation has 3 dof; a few tens make it robust)
MIN_INLIERS = 20
#: below this many tracks shared with the reference, the last frame with an orientation is fitted
_HANDOVER_TRACKS = 2 * MIN_INLIERS
#: a translation across the view at depth d passes for a rotation of about t/d, and gives
#: the bootstrap pair a parallax of about t/d: a pair whose median parallax is within
#: this ratio of the chain's rotation since the reference shows that rotation to be a
#: translation. Under a turn the pair's parallax is noise, far below the rotation
#: (measured on the rendered hand-held camera, 8 seeds: 0.00-0.1 of it), or, on the few
#: pairs whose essential matrix is arbitrary, far above it (2-5x)
TRANSLATION_PARALLAX_RATIO = (0.5, 1.5)
#: ... and at least this parallax [deg]: below it the pair's parallax is noise
TRANSLATION_MIN_PARALLAX_DEG = 0.5
#: a camera whose frames no rotation from the reference explains for this long [s]
#: translates (a robot that drives off forward: its flow is no rotation, and its
#: parallax is not one either). A turn's failures at the image's edge are brief:
#: at most 0.1 s on the rendered hand-held camera (8 seeds)
TRANSLATION_FAILED_FOR_S = 0.3
#: ... unless the bootstrap does not confirm it: a translation declared from failed fits
#: alone, after which the bootstrap made no map for this long [s] and refused every pair
#: as a rotation (a homography explains it at little parallax), was a turn whose fits the
#: few centimetres of a hand-held camera broke at the image's edges (a wide lens, near
#: objects): the chain goes on from the orientation stepped on frame by frame. A robot
#: that drives off shows parallax to the bootstrap (its map came 1-45 frames after the
#: rule, on the rendered walk, orbit and ground robot that stand first, and the drone)
TRANSLATION_UNCONFIRMED_S = 1.0


def kabsch(b_from: np.ndarray, b_to: np.ndarray) -> np.ndarray:
    """Rotations R (..., 3, 3) that best map b_from onto b_to (..., n, 3) in least
    squares: b_to ~ R b_from."""
    M = np.swapaxes(b_to, -1, -2) @ b_from                  # sum b_to b_from^T
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


@dataclass
class RotationFit:
    """A rotation between two frames from their shared bearings."""

    R_cur_ref: np.ndarray      #: 3x3, b_cur ~ R_cur_ref b_ref
    cov_cur: np.ndarray        #: 3x3 noise covariance, rotation vector in the current frame
    n_inliers: int
    inlier_share: float
    rms_rad: float             #: the inliers' residual per component (noise and parallax)


def fit_rotation(b_ref: np.ndarray, b_cur: np.ndarray, sigma_rad: float, max_rad: float,
                 rng: np.random.Generator) -> RotationFit | None:
    """The rotation from matched unit bearings (n,3) of two frames, or None when fewer
    than MIN_INLIERS of them (or under MIN_INLIER_SHARE) agree with one rotation within
    max_rad. sigma_rad: the bearings' noise (pixel sigma / focal length)."""
    n = len(b_ref)
    if n < MIN_INLIERS:
        return None
    pairs = rng.integers(0, n, (_HYPOTHESES, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    R = kabsch(b_ref[pairs], b_cur[pairs])                            # (h,3,3)
    resid = np.linalg.norm(b_cur[None] - b_ref @ np.swapaxes(R, -1, -2), axis=2)
    inliers = resid[int(np.argmax(np.count_nonzero(resid < max_rad, axis=1)))] < max_rad
    for _ in range(2):                     # refine on the inliers, then take them again
        if np.count_nonzero(inliers) < MIN_INLIERS:
            return None
        R_best = kabsch(b_ref[inliers], b_cur[inliers])
        r = np.linalg.norm(b_cur - b_ref @ R_best.T, axis=1)
        inliers = r < max_rad
    m = int(np.count_nonzero(inliers))
    if m < MIN_INLIERS or m < MIN_INLIER_SHARE * n:
        return None
    c = b_ref[inliers] @ R_best.T
    info = m * np.eye(3) - c.T @ c                  # sum (I - c c^T)
    # two residual components per bearing, three parameters fitted
    s2 = max(sigma_rad ** 2, float(np.sum(r[inliers] ** 2)) / max(2 * m - 3, 1))
    try:
        cov = s2 * np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    rms = float(np.sqrt(np.sum(r[inliers] ** 2) / (2 * m)))
    return RotationFit(R_best, 0.5 * (cov + cov.T), m, m / n, rms)


@dataclass
class Orientation:
    """The chain's estimate for one frame."""

    R_world_cam: np.ndarray
    cov_world: np.ndarray      #: 3x3, world rotation vector: the reference's + this fit's
    noise_cov_world: np.ndarray  #: 3x3, this frame's fit alone (for the angular rate)
    stamp_ns: int


@dataclass
class _Frame:
    ids: np.ndarray
    b: np.ndarray              # unit bearings
    est: Orientation | None
    #: est, or, when the fit against the reference failed, the last frame's stepped
    #: orientation and the step from it, with a translation prior per step (None: a
    #: step no rotation explains broke it)
    stepped: Orientation | None = None


class OrientationChain:
    """The orientation of the frames before a map (module docstring)."""

    def __init__(self, camera: PinholeCamera, sigma_px: float, max_px: float,
                 translation_sigma_deg: float, rng: np.random.Generator,
                 max_deg: float = 0.0) -> None:
        self.unproject = camera.unproject        # ideal pixels -> unit bearings
        self.focal = 0.5 * float(camera.fx + camera.fy)
        # a residual holds the pixel noise of both frames
        self.sigma_rad = np.sqrt(2.0) * float(sigma_px) / self.focal
        # a track agrees with a rotation within max_px of pixel noise, or within max_deg
        # of the ray angle a hand-held camera's few centimetres leave: in pixels alone,
        # a long focal length would take that angle for a translation (§15.9)
        self.max_rad = max(float(max_px) / self.focal, float(np.radians(max_deg)))
        #: the rotation an undetected translation can pass for (module docstring)
        self.model_sigma_rad = float(np.radians(translation_sigma_deg))
        self.rng = rng
        self.restart(np.eye(3), np.zeros((3, 3)))

    def restart(self, R_world_cam: np.ndarray, cov_world: np.ndarray) -> None:
        """Start at a known orientation (the world frame, or where a re-bootstrap
        attaches) with its covariance."""
        self._start = (np.asarray(R_world_cam, float).copy(), np.asarray(cov_world).copy())
        self._ref: _Frame | None = None
        self._known_ref: _Frame | None = None      # the last reference with an orientation
        self._prev: _Frame | None = None
        #: the orientation of the frame tracked before the last one (for the angular rate)
        self.previous: Orientation | None = None
        self._last_good: _Frame | None = None      # the last frame with an orientation
        self.translating = False       #: the last frame tracked moved by more than a turn
        self.started_ns: int | None = None
        self._carry_from: _Frame | None = None
        self._carried: tuple[int | None, Orientation | None] = (None, None)
        self.n_references = 0          #: references taken after the first
        #: a bootstrap pair has shown the chain's rotation to be a translation (sticky
        #: until the next restart: a camera seen to translate is not turning in place),
        #: or failed fits have (taken back by `reconsider` if the bootstrap never agrees)
        self.translation_seen = False
        #: stamp at which failed fits alone declared translation_seen, while no bootstrap
        #: pair has confirmed it (None: not so declared, or confirmed)
        self._unconfirmed_since_ns: int | None = None
        #: stamp of the first of the frames just tracked that no fit explained
        self.failing_since_ns: int | None = None

    def track(self, stamp_ns: int, ids: np.ndarray, px_ideal: np.ndarray
              ) -> Orientation | None:
        """This frame's orientation (None: no rotation explains its tracks)."""
        b = self.unproject(px_ideal)
        if self.started_ns is None:
            self.started_ns = int(stamp_ns)
            R0, cov0 = self._start
            est = Orientation(R0, cov0, np.zeros((3, 3)), int(stamp_ns))
        else:
            # against the reference while it shares enough tracks: a failed fit there
            # means the motion is not a rotation (the frame is not published); the last
            # frame with an orientation only hands over when the reference's tracks have
            # gone, or when the reference itself has none (its fit failed)
            base = self._ref
            if base is None or base.est is None or \
                    np.count_nonzero(np.isin(ids, base.ids)) < _HANDOVER_TRACKS:
                base = self._last_good
            est = None if base is None else self._chain(base, ids, b, stamp_ns)
            # what carried() may try: the step from the last frame with an orientation,
            # when that is not the fit that just failed
            self._carry_from = self._last_good if est is None and base is self._ref \
                and self._last_good is not None and self._last_good is not base else None
        # translating: not even the step from the previous frame is a rotation (a car's
        # near points); a fit against the reference can also fail on a few tracks at the
        # image's edge while the camera turns, and then the step is one
        step = None if est is not None or self._prev is None else \
            self._fit(self._prev, ids, b)
        self.translating = est is None and step is None
        stepped = est
        if step is not None and self._prev.stepped is not None:
            stepped = self._compose(self._prev.stepped, step, stamp_ns)
            stepped.cov_world = stepped.cov_world + self.model_sigma_rad ** 2 * np.eye(3)
        self.previous = None if self._prev is None else self._prev.est
        self._prev = _Frame(ids, b, est, stepped)
        self._prev_stamp_ns = int(stamp_ns)
        if est is not None:
            self._last_good = self._prev
            self.failing_since_ns = None
        elif self.failing_since_ns is None:
            self.failing_since_ns = int(stamp_ns)
        return est

    def _fit(self, base: _Frame, ids: np.ndarray, b: np.ndarray) -> RotationFit | None:
        """The rotation from `base` to the tracks (ids, bearings b) they share."""
        _, i_base, i_cur = np.intersect1d(base.ids, ids, assume_unique=True,
                                          return_indices=True)
        return fit_rotation(base.b[i_base], b[i_cur], self.sigma_rad, self.max_rad,
                            self.rng)

    def _chain(self, base: _Frame, ids: np.ndarray, b: np.ndarray, stamp_ns: int
               ) -> Orientation | None:
        fit = self._fit(base, ids, b)
        return None if fit is None else self._compose(base.est, fit, stamp_ns)

    @staticmethod
    def _compose(base: Orientation, fit: RotationFit, stamp_ns: int) -> Orientation:
        """The orientation `fit` leads to from `base`, with both errors."""
        R = base.R_world_cam @ fit.R_cur_ref.T
        # the fit's error, a rotation vector in the current frame, seen from the world
        noise = R @ fit.cov_cur @ R.T
        return Orientation(R, base.cov_world + noise, noise, int(stamp_ns))

    def judge_pair(self, est: Orientation | None, parallax_deg: float) -> None:
        """Note in translation_seen whether the bootstrap pair of the reference and the
        frame of `est` (its median parallax, deg) shows the chain's rotation between them
        to be a translation passing for one (TRANSLATION_PARALLAX_RATIO): a camera that
        stood still, then walked or flew over a floor; or whether no fit has explained
        the frames for TRANSLATION_FAILED_FOR_S (a robot that drove off)."""
        if est is None and self.failing_since_ns is not None and self._prev is not None \
                and (self._prev_stamp_ns - self.failing_since_ns) * 1e-9 >= \
                TRANSLATION_FAILED_FOR_S:
            if not self.translation_seen:
                self._unconfirmed_since_ns = self._prev_stamp_ns
            self.translation_seen = True
            return
        ref = self.reference
        if est is None:        # the step since the last frame with one, if a rotation
            est = self.carried()
        if est is None or ref is None or not parallax_deg >= TRANSLATION_MIN_PARALLAX_DEG:
            return
        R = est.R_world_cam.T @ ref.R_world_cam
        turn = np.degrees(np.linalg.norm(geo.quat_to_rotvec(geo.matrix_to_quat(R))))
        lo, hi = TRANSLATION_PARALLAX_RATIO
        if lo * turn <= parallax_deg <= hi * turn:
            self.translation_seen = True
            self._unconfirmed_since_ns = None       # a pair confirms it: not taken back

    def reconsider(self, rotation_like: bool) -> Orientation | None:
        """After a bootstrap pair was refused: a translation that failed fits alone
        declared, and that the bootstrap has not confirmed for TRANSLATION_UNCONFIRMED_S
        (no map, every pair refused as a rotation: `rotation_like`), is taken back. The
        frame just tracked becomes the chain's reference at its stepped orientation
        (each step a rotation fit with a translation prior), which is returned, to be
        published; None when nothing is taken back (docs/method.md §15.13)."""
        if self._unconfirmed_since_ns is None:
            return None
        if not rotation_like:
            self._unconfirmed_since_ns = None       # parallax: the translation is real
            return None
        cur = self._prev
        if (self._prev_stamp_ns - self._unconfirmed_since_ns) * 1e-9 < \
                TRANSLATION_UNCONFIRMED_S or cur is None or cur.stepped is None:
            return None
        self._prev = _Frame(cur.ids, cur.b, cur.stepped, cur.stepped)
        self._ref = self._last_good = self._known_ref = self._prev
        self.translation_seen = False
        self._unconfirmed_since_ns = self.failing_since_ns = None
        return cur.stepped

    def carried(self) -> Orientation | None:
        """For publishing only: the orientation of the frame just tracked when its fit
        against the reference failed, from the step since the last frame that has one
        (a rotation fit of its own, a second translation prior in its covariance); None
        when that step is no rotation either. The chain itself does not use it: the
        failed fit stays its evidence of a translation (docs/method.md §15.9)."""
        base, cur = self._carry_from, self._prev
        if base is None or cur is None:
            return None
        if self._carried[0] != self._prev_stamp_ns:       # once a frame
            est = self._chain(base, cur.ids, cur.b, self._prev_stamp_ns)
            if est is not None:
                est.cov_world = est.cov_world + self.model_sigma_rad ** 2 * np.eye(3)
            self._carried = (self._prev_stamp_ns, est)
        return self._carried[1]

    def new_reference(self, est: Orientation | None) -> None:
        """The bootstrap took the last tracked frame as its reference: later frames are
        fitted against it. Its covariance keeps the translation term of its own pair."""
        if self._prev is None:
            return
        if est is not None and self._ref is not None:
            est.cov_world = est.cov_world + self.model_sigma_rad ** 2 * np.eye(3)
            self.n_references += 1
        self._ref = self._prev
        if self._ref.est is not None:
            self._known_ref = self._ref

    def resectable(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Frames whose orientation a map made later can be attached through, by
        resecting them against it: (track ids, unit bearings, R_world_cam, 3x3 world
        covariance) of the last reference frame that had an orientation (its own
        covariance: what its fit absorbed is in it) and of the last frame tracked with
        one (its published covariance: with the translation its fit may have absorbed)."""
        out = []
        ref = self._known_ref
        if ref is not None:
            out.append((ref.ids, ref.b, ref.est.R_world_cam, ref.est.cov_world))
        last = self._last_good
        if last is not None and last is not ref:
            out.append((last.ids, last.b, last.est.R_world_cam,
                        self.published_covariance(last.est)))
        return out

    @property
    def start_covariance(self) -> np.ndarray:
        """The rotation covariance the chain started with."""
        return self._start[1]

    @property
    def reference(self) -> Orientation | None:
        """The current reference frame's orientation (None: unknown)."""
        return None if self._ref is None else self._ref.est

    def reference_or_last(self, stamp_ns: int, rate_sigma: float
                          ) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_cam, 3x3 world covariance) of the reference frame taken at
        `stamp_ns`: its own orientation; or, when its fit failed (the camera was
        translating), the orientation stepped on to it frame by frame, each step a
        rotation fit with a translation prior; or, when a step was no rotation either,
        the last orientation known before it, uncertain by a turn at `rate_sigma`
        [rad/s] over the time between."""
        if self._ref is not None and self._ref.est is not None:
            return self._ref.est.R_world_cam, self._ref.est.cov_world
        if self._ref is not None and self._ref.stepped is not None:
            # stepped on from the last frame with an orientation (a robot driving off)
            return self._ref.stepped.R_world_cam, self._ref.stepped.cov_world
        last = self._last_good.est
        dt = max(stamp_ns - last.stamp_ns, 0) * 1e-9
        return last.R_world_cam, last.cov_world + (rate_sigma * dt) ** 2 * np.eye(3)

    def published_covariance(self, est: Orientation) -> np.ndarray:
        """The 3x3 world rotation covariance to publish for `est`: the chain's plus the
        current pair's translation term."""
        return est.cov_world + self.model_sigma_rad ** 2 * np.eye(3)

    @staticmethod
    def angular_rate(prev: Orientation, cur: Orientation, model_var: float
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Angular velocity (camera frame, rad/s) between two chained frames and its 3x3
        covariance."""
        dt = max((cur.stamp_ns - prev.stamp_ns) * 1e-9, 1e-6)
        R_rel = prev.R_world_cam.T @ cur.R_world_cam
        w = geo.quat_to_rotvec(geo.matrix_to_quat(R_rel)) / dt
        Rc = cur.R_world_cam.T
        var = Rc @ (prev.noise_cov_world + cur.noise_cov_world) @ Rc.T + \
            model_var * np.eye(3)
        return w, var / dt ** 2
