"""How much the map's own error adds to a pose estimated against it (docs/method.md §14).

The hybrid EKF treats the map points as exact inputs, so its covariance is the camera's
uncertainty RELATIVE TO THE MAP. A navigation stack needs it relative to the world, and
the map is not exact: every point has its own triangulation noise, and every point made
from an EKF pose inherits that pose's error — a common mode that no amount of averaging
over points or frames removes (the map frame drifts). Two consider terms (Schmidt, 1966:
parameters whose uncertainty is accounted for but which are not estimated) are added to
the published covariance; the filter's own state and gain are left as they are.

Pose parameters here: camera position r and a world-frame (left) rotation vector theta,
R_world_cam = exp(theta) R0 — the published covariance's convention (ekf.pose_covariance).

1. Independent point errors (`point_consider_covariance`). With the pose's linearised
   least-squares sensitivity to the measurements, A = sum J_i^T R_i^-1 J_i, a point error
   dX_i moves the pixel by J_X,i dX_i and the pose by A^-1 J_i^T R_i^-1 J_X,i dX_i:
       Sigma_points = A^-1 (sum J_i^T R_i^-1 J_X,i Sigma_X,i J_X,i^T R_i^-1 J_i) A^-1.
2. The common mode (`anchor_covariance`). Each point remembers the world covariance of
   the pose it was made from (its anchor: covariance C_a at camera centre c_a). A world
   error (dp, dtheta) of that anchor shifts the point as the anchor moves; a camera at r
   that tracks such points inherits dtheta and dp + dtheta x (r - c_a). The frame's
   common-mode covariance is the mean of its inliers' anchors carried to r: for nested
   anchors (each generation's error = the last one's plus an increment), the mean of the
   covariances bounds the covariance of any weighted mean of the errors, i.e. it is
   conservative.
3. The bootstrap map's anchor (`relative_pose_covariance`): the second view's covariance
   relative to the first with the scale held (two-view bundle adjustment information,
   points eliminated by the Schur complement, the translation along the baseline
   projected out).
"""
from __future__ import annotations

import numpy as np

from . import geometry as geo
from .observation import world_point_jacobian
from .psd import nearest_psd

#: regulariser of 3x3 point information blocks (one view or none: singular)
_INFO_REGULARISER = 1e-9


def pose_point_jacobians(K: np.ndarray, T_world_cam: np.ndarray, X_world: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians of the ideal pixels of points X_world (n,3) seen from T_world_cam:
    (J_pose (n,2,6) w.r.t. (r, theta), J_X (n,2,3), in_front (n,) bool)."""
    d = np.asarray(X_world, float).reshape(-1, 3) - T_world_cam[:3, 3]
    J_X, front = world_point_jacobian(X_world, T_world_cam, K)        # J_pi R_cw
    # dp/dr = -J_X, dp/dtheta = J_X [d]x (left perturbation of R_world_cam)
    J_pose = np.concatenate((-J_X, J_X @ geo.skew_batch(d)), axis=2)
    return J_pose, J_X, front


def point_consider_covariance(J_pose: np.ndarray, J_X: np.ndarray, sigma_px: np.ndarray,
                              X_cov: np.ndarray) -> np.ndarray:
    """6x6 pose covariance caused by independent point errors X_cov (n,3,3) (item 1 of
    the module docstring); sigma_px (n,) the pixel noise of each measurement."""
    if len(J_pose) < 3:
        return np.zeros((6, 6))
    w = 1.0 / np.asarray(sigma_px, float) ** 2                        # R_i^-1 = w_i I
    w_rows = np.repeat(w, 2)[:, None]                                 # per pixel row
    J_rows = J_pose.reshape(-1, 6)                                    # (2n, 6)
    A = J_rows.T @ (w_rows * J_rows)                                  # sum w J^T J
    proj = J_X @ X_cov @ np.transpose(J_X, (0, 2, 1))                 # (n,2,2) px^2
    B = J_rows.T @ (w_rows ** 2 * (proj @ J_pose).reshape(-1, 6))     # sum w^2 J^T P J
    try:
        A_inv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.zeros((6, 6))
    S = A_inv @ B @ A_inv
    return 0.5 * (S + S.T)


def carry_pose_covariance(cov: np.ndarray, c_from: np.ndarray, r_to: np.ndarray
                          ) -> np.ndarray:
    """Covariances (n,6,6) of a world error (dp, dtheta) at centres c_from (n,3) as
    seen by a camera at r_to (3,): dp' = dp + dtheta x (r_to - c_from)."""
    lever = np.asarray(r_to, float) - np.asarray(c_from, float).reshape(-1, 3)
    J = np.tile(np.eye(6), (len(lever), 1, 1))
    J[:, :3, 3:] = -geo.skew_batch(lever)
    return J @ cov @ np.transpose(J, (0, 2, 1))


def adjusted_pose_covariance(T_world_cam: np.ndarray, cov_adjusted: np.ndarray
                             ) -> np.ndarray:
    """6x6 world covariance (dp, dtheta) of a pose from the windowed adjustment's
    marginal `cov_adjusted` of its increments (dtheta, dC), with R_cw = exp(dtheta)
    R_cw0 (local_ba.py): R_wc = exp(-R_wc dtheta) R_wc, so the world rotation vector is
    -R_wc dtheta and the position error dC."""
    J = np.zeros((6, 6))
    J[:3, 3:] = np.eye(3)
    J[3:, :3] = -np.asarray(T_world_cam, float)[:3, :3]
    C = J @ np.asarray(cov_adjusted, float) @ J.T
    return 0.5 * (C + C.T)


def anchor_covariance(anchor_cov: np.ndarray, anchor_c: np.ndarray, r_cam: np.ndarray
                      ) -> np.ndarray:
    """The common-mode 6x6 covariance of a camera at r_cam tracking points with anchors
    (anchor_cov (n,6,6), anchor_c (n,3)): item 2 of the module docstring."""
    if len(anchor_cov) == 0:
        return np.zeros((6, 6))
    S = np.mean(carry_pose_covariance(anchor_cov, anchor_c, r_cam), axis=0)
    return 0.5 * (S + S.T)


def relative_pose_covariance(K: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray,
                             X_world: np.ndarray, sigma_px: float) -> np.ndarray:
    """6x6 world covariance (r, theta) of view b given view a exactly and the scale held
    (item 3 of the module docstring), for points X_world seen by both with pixel noise
    sigma_px."""
    X = np.asarray(X_world, float).reshape(-1, 3)
    _, J_Xa, _ = pose_point_jacobians(K, T_world_a, X)
    J_pose, J_Xb, _ = pose_point_jacobians(K, T_world_b, X)
    w = 1.0 / sigma_px ** 2
    Hpp = w * (np.transpose(J_Xa, (0, 2, 1)) @ J_Xa + np.transpose(J_Xb, (0, 2, 1)) @ J_Xb)
    Hpp_inv = np.linalg.inv(Hpp + np.eye(3) * _INFO_REGULARISER)
    Hcp = w * np.transpose(J_pose, (0, 2, 1)) @ J_Xb                  # (n,6,3)
    Hcc = w * np.einsum('nji,njk->ik', J_pose, J_pose)
    S = Hcc - np.einsum('nij,njk,nlk->il', Hcp, Hpp_inv, Hcp)
    # hold the scale: no information is needed (or possible) along the baseline
    baseline = T_world_b[:3, 3] - T_world_a[:3, 3]
    norm = np.linalg.norm(baseline)
    if norm <= 0:
        return np.zeros((6, 6))
    u = np.zeros(6)
    u[:3] = baseline / norm
    N = np.linalg.svd(np.eye(6) - np.outer(u, u))[0][:, :5]             # basis of u's complement
    try:
        C = N @ np.linalg.inv(N.T @ S @ N) @ N.T
    except np.linalg.LinAlgError:
        return np.zeros((6, 6))
    return 0.5 * (C + C.T)


class WorldCovariance:
    """The published pose covariance of one VisualOdometry: the filter's (relative to the
    map) plus the map's (points and anchors); and the anchors new points inherit.

    `carry()` at a re-bootstrap keeps the last published covariance as the anchor of the
    next map, so a new map never starts more certain than the pose it is attached to."""

    def __init__(self, enabled: bool, K: np.ndarray, sigma_px: float) -> None:
        self.enabled = bool(enabled)
        self.K = np.asarray(K, float)
        self.sigma_px = float(sigma_px)
        self._carried = (np.zeros((6, 6)), np.zeros(3))
        self.last = (np.zeros((6, 6)), np.zeros(3))   #: last published (cov, centre)
        self.points_part = np.zeros((6, 6))          #: last frame's terms (diagnostics)
        self.anchor_part = np.zeros((6, 6))
        #: error the online checks found beyond the covariance (rotation_check.py): added
        #: to every later published covariance of this map, not to the anchors
        self.evidence = np.zeros((6, 6))

    def add_rotation_evidence(self, d_world: np.ndarray) -> None:
        """A rotation error d (world rotation vector) the covariance did not allow for:
        from now on the published covariance holds d d^T more."""
        self.evidence[3:, 3:] += np.outer(d_world, d_world)

    def cover_rotation(self, d_world: np.ndarray) -> None:
        """A rotation error of at least d (world rotation vector, a drift summed over
        keyframe pairs): from now on the published covariance holds at least |d|^2 along
        d, counting what it already holds there (the last published covariance and the
        evidence), so that evidence found twice is not added twice."""
        norm2 = float(d_world @ d_world)
        if norm2 <= 0.0:
            return
        u = d_world / np.sqrt(norm2)
        held = float(u @ (self.last[0][3:, 3:] + self.evidence[3:, 3:]) @ u)
        if norm2 > held:
            self.evidence[3:, 3:] += (norm2 - held) * np.outer(u, u)

    def carry(self, filter_cov: np.ndarray, r_now: np.ndarray) -> None:
        """A re-bootstrap at the filter's current pose (centre r_now, covariance
        filter_cov): the next map is anchored at the last published covariance carried
        there, plus what the filter's own covariance has grown to since."""
        carried = carry_pose_covariance(self.last[0][None] + self.evidence, self.last[1],
                                        r_now)[0]
        self._carried = (carried + filter_cov, np.asarray(r_now, float).copy())

    def new_map(self) -> None:
        """The map was dropped: its evidence went into the carried covariance (carry);
        a relocalisation keeps the map, and with it the evidence."""
        self.evidence = np.zeros((6, 6))

    @property
    def carried_covariance(self) -> np.ndarray:
        """6x6 covariance a new map is anchored at (zero for the first map)."""
        return self._carried[0]

    def widen_carried(self, extra: np.ndarray) -> None:
        """What the anchor's pose is uncertain by beyond the carried covariance (a
        6x6 at the same centre): the orientation chain before a map."""
        self._carried = (self._carried[0] + extra, self._carried[1])

    def bootstrap_anchor(self, T_world_a: np.ndarray, T_world_b: np.ndarray,
                         X_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Anchor (6x6, centre) of a bootstrap map made from views a (the map's origin,
        where a re-bootstrap attaches it) and b."""
        c_b = T_world_b[:3, 3]
        if not self.enabled:
            return np.zeros((6, 6)), c_b
        rel = relative_pose_covariance(self.K, T_world_a, T_world_b, X_world, self.sigma_px)
        carried = carry_pose_covariance(self._carried[0][None], self._carried[1], c_b)[0]
        return rel + carried, c_b

    def origin_anchor(self, T_world_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Anchor of the bootstrap's first view (what a re-bootstrap carried over)."""
        c_a = T_world_a[:3, 3]
        return carry_pose_covariance(self._carried[0][None], self._carried[1], c_a)[0], c_a

    def compose(self, filter_cov: np.ndarray, T_world_cam: np.ndarray, landmarks,
                ids: np.ndarray, X_world: np.ndarray, sigma_px: np.ndarray | None,
                inflation: float = 1.0, remember: bool = True,
                ray_anchors: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Published 6x6 covariance of a tracked frame: the filter's `filter_cov` plus
        the map's, from the update's inlier landmarks `ids` at X_world (n,3) measured
        with pixel noise sigma_px (n,) (None: the nominal) and the anchors (covariances
        (b,6,6), centres (b,3)) of its inlier rays without depth (bearing.py).
        `inflation` (health.py) scales what this frame measured (the filter's and the
        points' terms), not the anchors: those were inflated when the poses they come
        from were published. `remember`: False for a frame that is not published (a
        failed frame): new points and a re-bootstrap then take the last published
        covariance."""
        cov = filter_cov * inflation
        n_rays = 0 if ray_anchors is None else len(ray_anchors[0])
        if self.enabled and len(ids) + n_rays:
            self.points_part = np.zeros((6, 6))
            if len(ids):
                sigma = np.full(len(ids), self.sigma_px) if sigma_px is None else sigma_px
                J_pose, J_X, front = pose_point_jacobians(self.K, T_world_cam, X_world)
                self.points_part = point_consider_covariance(
                    J_pose[front], J_X[front], sigma[front],
                    landmarks.covariances(ids[front]))
            a_cov, a_c = landmarks.anchors(ids)
            if n_rays:
                a_cov = np.concatenate((a_cov, ray_anchors[0]))
                a_c = np.concatenate((a_c, ray_anchors[1]))
            self.anchor_part = anchor_covariance(a_cov, a_c, T_world_cam[:3, 3])
            cov = inflation * (filter_cov + self.points_part) + self.anchor_part
        cov = nearest_psd(cov)       # a barely held point must not make a variance negative
        if remember:
            self.last = (cov, T_world_cam[:3, 3].copy())
        return cov + self.evidence
