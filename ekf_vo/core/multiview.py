"""Multi-view bootstrap: K keyframes reconstructed together, then bundle adjustment.

`bootstrap: multi_view` (docs/method.md §2.4, after Li et al. 2016, who reconstruct
30 keyframes in a batch before the filter starts). The default two-view bootstrap
(bootstrap.py) triangulates the first map from ONE pair, so the map and the filter's
initial pose carry that pair's errors for as long as its points are seen. Here:

1. two-view start: TwoViewBootstrap (essential matrix, or the ground-truth poses of the
   paper's protocol) between keyframe 0 and the first frame with enough parallax
   (keyframe 1); |C1 - C0| = bootstrap_baseline_m fixes the scale;
2. every following frame: PnP of the current map (EPnP in RANSAC + LM, pnp.solve_epnp,
   which also gives a covariance so the pose can be published); a frame becomes a keyframe
   when the median parallax of its map points against the last keyframe exceeds
   `multiview_keyframe_parallax_deg`; new tracks are triangulated (triangulation.py)
   between the current keyframe and the oldest keyframe that saw them (widest baseline);
3. with `multiview_keyframes` keyframes (or when no new keyframe comes within
   bootstrap_max_frames): sparse bundle adjustment of all keyframe poses and points on
   the reprojection error (Triggs et al., "Bundle adjustment - a modern synthesis", 2000),
   Huber loss, the gauge fixed by keyframe 0 (pose) and |C1 - C0| (scale);
4. the filter starts at the last keyframe's BA pose with the BA'd map, velocity and
   angular velocity from the last two keyframes.

Degenerate cases: a pure rotation before keyframe 1 is refused by the two-view test; PnP
failures (fewer than 6 map points, RANSAC failure) three times in a row restart the
bootstrap from the current frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..config import VoConfig
from . import geometry as geo
from .bootstrap import TwoViewBootstrap
from .local_map import Keyframe
from .pnp import solve_epnp
from .triangulation import triangulate_points

logger = logging.getLogger(__name__)

#: PnP failures in a row before the multi-view bootstrap starts over
_MAX_PNP_FAILURES = 3


# ---------------------------------------------------------------------- bundle adjustment
@dataclass
class BundleResult:
    """Output of `bundle_adjust`: refined poses (k,4,4) T_world_cam, points (m,3),
    per-observation reprojection errors (o,) before and after [px]."""

    T_world_cam: np.ndarray
    X_world: np.ndarray
    err_before_px: np.ndarray
    err_after_px: np.ndarray
    n_evaluations: int = 0

    @property
    def rms_before_px(self) -> float:
        return float(np.sqrt(np.mean(self.err_before_px ** 2)))

    @property
    def rms_after_px(self) -> float:
        return float(np.sqrt(np.mean(self.err_after_px ** 2)))


def _jacobian_sparsity(k: int, n_cam: int, n_params: int, cam_idx: np.ndarray,
                       pt_idx: np.ndarray):
    """Which parameters each residual depends on: observation j, its camera's block (not
    camera 0, the gauge; camera 1 has 5 parameters, the others 6) and its point's 3."""
    from scipy.sparse import lil_matrix                 # lazy: see bundle_adjust
    o = len(cam_idx)
    A = lil_matrix((2 * o, n_params), dtype=np.int8)
    rows = np.arange(o)
    for c in range(1, k):
        sel = rows[cam_idx == c]
        cols = range(0, 5) if c == 1 else range(5 + 6 * (c - 2), 11 + 6 * (c - 2))
        for col in cols:
            A[2 * sel, col] = 1
            A[2 * sel + 1, col] = 1
    for d in range(3):
        A[2 * rows, n_cam + 3 * pt_idx + d] = 1
        A[2 * rows + 1, n_cam + 3 * pt_idx + d] = 1
    return A


def bundle_adjust(T_world_cam: np.ndarray, X_world: np.ndarray, cam_idx: np.ndarray,
                  pt_idx: np.ndarray, px: np.ndarray, K: np.ndarray,
                  huber_px: float, max_evaluations: int) -> BundleResult:
    """Sparse bundle adjustment of k >= 2 poses and m points from o observations.

    T_world_cam (k,4,4) initial poses; X_world (m,3); observation j is point pt_idx[j]
    seen by camera cam_idx[j] at IDEAL pixel px[j]. Gauge: camera 0 is fixed, camera 1's
    centre moves on the sphere of radius |C1 - C0| about C0 (fixed scale, two angles in a
    basis whose first axis is the initial direction, far from the poles). Rotations are
    left increments exp(dtheta) R_cw of the initial ones (no rotation-vector
    singularity). Huber loss of width `huber_px`.

    scipy is the one exception to the core's numpy + OpenCV rule, imported here only:
    least_squares with `jac_sparsity` groups the columns of the sparse Jacobian
    (cameras x points block structure) for the finite differences and solves the
    trust-region steps with a sparse LSQR, i.e. the Schur-like sparsity is exploited
    without a hand-written Levenberg-Marquardt; it runs once per (re-)bootstrap, never
    in the per-frame path, and scipy is already a package dependency (package.xml).
    """
    from scipy.optimize import least_squares           # lazy: see the docstring

    T_world_cam = np.asarray(T_world_cam, float)
    k, m = len(T_world_cam), len(X_world)
    if k < 2:
        raise ValueError('bundle adjustment needs at least two cameras')
    R_cw0 = np.transpose(T_world_cam[:, :3, :3], (0, 2, 1))
    C_init = T_world_cam[:, :3, 3].copy()
    base = C_init[1] - C_init[0]
    radius = float(np.linalg.norm(base))
    if not radius > 0:
        raise ValueError('cameras 0 and 1 coincide: the scale gauge is undefined')
    b0 = base / radius
    a = np.eye(3)[int(np.argmin(np.abs(b0)))]
    b1 = np.cross(b0, a)
    b1 /= np.linalg.norm(b1)
    B = np.column_stack((b0, b1, np.cross(b0, b1)))
    n_cam = 5 + 6 * (k - 2)          # camera 1: dtheta + (az, el); others dtheta + C

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dtheta = np.zeros((k, 3))
        C = C_init.copy()
        dtheta[1] = p[0:3]
        az, el = p[3], p[4]
        C[1] = C_init[0] + radius * B @ np.array([np.cos(el) * np.cos(az),
                                                  np.cos(el) * np.sin(az), np.sin(el)])
        if k > 2:
            rest = p[5:n_cam].reshape(k - 2, 6)
            dtheta[2:] = rest[:, :3]
            C[2:] = rest[:, 3:]
        R_cw = geo.rotvecs_to_matrices(dtheta) @ R_cw0
        return R_cw, C, p[n_cam:].reshape(m, 3)

    def project(p: np.ndarray) -> np.ndarray:
        R_cw, C, X = unpack(p)
        Xc = np.einsum('oij,oj->oi', R_cw[cam_idx], X[pt_idx] - C[cam_idx])
        with np.errstate(divide='ignore', invalid='ignore'):
            uv = Xc[:, :2] / Xc[:, 2:3]
        return uv @ K[:2, :2].T + K[:2, 2]

    def residuals(p: np.ndarray) -> np.ndarray:
        r = (project(p) - px).ravel()
        return np.where(np.isfinite(r), r, 1e3)         # behind a camera: a large error

    p0 = np.concatenate((np.zeros(5), np.column_stack((np.zeros((k - 2, 3)), C_init[2:])
                                      ).ravel(), np.asarray(X_world, float).ravel()))
    A = _jacobian_sparsity(k, n_cam, len(p0), cam_idx, pt_idx)
    err0 = np.linalg.norm((project(p0) - px), axis=1)
    sol = least_squares(residuals, p0, jac_sparsity=A, method='trf', loss='huber',
                        f_scale=huber_px, x_scale='jac', max_nfev=max_evaluations,
                        xtol=1e-10, ftol=1e-10)
    R_cw, C, X = unpack(sol.x)
    T_out = np.stack([geo.make_T(R.T, c) for R, c in zip(R_cw, C)])
    err1 = np.linalg.norm(project(sol.x) - px, axis=1)
    return BundleResult(T_out, X, np.where(np.isfinite(err0), err0, np.inf),
                        np.where(np.isfinite(err1), err1, np.inf), int(sol.nfev))


# ---------------------------------------------------------------------- the bootstrap
@dataclass
class MultiViewStep:
    """What one frame did to the multi-view bootstrap.

    status: 'pending' (collecting), 'done' (map ready: start the filter). When the
    current frame's pose is known (PnP after keyframe 1), T_world_cam / pose_cov are set.
    When done: keyframes (BA'd poses), point_ids / X_world (the BA'd map)."""

    status: str
    message: str = ''
    T_world_cam: np.ndarray | None = None
    pose_cov: np.ndarray | None = None
    keyframes: list = field(default_factory=list)
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    X_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    ba: BundleResult | None = None


class MultiViewBootstrap:
    """Collects keyframes from tracked ids/pixels, then bundle-adjusts them."""

    def __init__(self, cfg: VoConfig, K: np.ndarray) -> None:
        self.cfg = cfg
        self.K = np.asarray(K, float)
        self.two_view = TwoViewBootstrap(cfg, self.K)
        self.reset()

    def reset(self) -> None:
        self.keyframes: list[Keyframe] = []
        self.points: dict[int, np.ndarray] = {}
        self._failures = 0

    def step(self, frame_index: int, stamp_ns: int, ids: np.ndarray, px: np.ndarray,
             known_T: np.ndarray | None = None, anchor_T: np.ndarray | None = None,
             baseline: float | None = None) -> MultiViewStep:
        """Feed one frame (ids (n,), IDEAL px (n,2)). `anchor_T` places keyframe 0 in the
        world (identity by default); `baseline` overrides bootstrap_baseline_m;
        `known_T` is the ground-truth pose of the paper's protocol (first two keyframes)."""
        c = self.cfg
        ids = np.asarray(ids, np.int64)
        px = np.asarray(px, float)
        kfs = self.keyframes
        if not kfs:
            return self._new_reference(frame_index, stamp_ns, ids, px, known_T)
        if len(kfs) == 1:
            ref = kfs[0]
            n_common = len(np.intersect1d(ref.ids, ids))
            if frame_index - ref.frame_index > c.bootstrap_max_frames or \
                    n_common < c.bootstrap_min_inliers:
                return self._new_reference(frame_index, stamp_ns, ids, px, known_T)
            if ref.T_world_cam is not None and known_T is not None:
                boot = self.two_view.from_known_poses(
                    geo.invert_T(ref.T_world_cam), geo.invert_T(known_T),
                    ref.ids, ref.px, ids, px)
                T_ref, T_cur, X = ref.T_world_cam, known_T, boot.X_world
            else:
                boot = self.two_view.try_pair(ref.ids, ref.px, ids, px, baseline=baseline)
                T_ref = np.eye(4) if anchor_T is None else anchor_T
                T_cur = T_ref @ geo.invert_T(boot.T_cur_ref)
                X = geo.transform_points(T_ref, boot.X_ref) if boot.ok else None
            if not boot.ok:
                return MultiViewStep('pending', f'bootstrap refused: {boot.reason}')
            ref.T_world_cam = T_ref
            kfs.append(Keyframe(frame_index, T_cur, ids, px, stamp_ns))
            self.points = {int(i): x for i, x in zip(boot.point_ids, X)}
            if len(kfs) >= c.multiview_keyframes:
                return self._finish()
            return MultiViewStep('pending', f'multi-view: keyframe 2/{c.multiview_keyframes}'
                                 f' ({len(self.points)} points)', T_world_cam=T_cur)
        # ---- keyframes 2..K-1: PnP, keyframe test, triangulation
        known = np.array([int(i) in self.points for i in ids], bool)
        X = np.array([self.points[int(i)] for i in ids[known]]).reshape(-1, 3)
        pnp = solve_epnp(px[known], X, self.K, c.pixel_sigma_px, c.ransac_inlier_px)
        if not pnp.ok:
            self._failures += 1
            if self._failures >= _MAX_PNP_FAILURES:
                logger.info('multi-view bootstrap: PnP failed, starting over')
                self.reset()
                return self._new_reference(frame_index, stamp_ns, ids, px, None)
            return MultiViewStep('pending', f'multi-view: PnP failed ({pnp.reason})')
        self._failures = 0
        T_cur = pnp.T_world_cam
        last = kfs[-1]
        Xi = X[pnp.inliers]
        r_last = Xi - last.T_world_cam[:3, 3]
        r_cur = Xi - T_cur[:3, 3]
        cos = np.sum(r_last * r_cur, axis=1) / (np.linalg.norm(r_last, axis=1) *
                                               np.linalg.norm(r_cur, axis=1))
        parallax = float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))
        # no new keyframe for too long (slow motion): this frame closes the collection
        stale = frame_index - last.frame_index > c.bootstrap_max_frames
        if parallax < c.multiview_keyframe_parallax_deg and not stale:
            return MultiViewStep('pending', f'multi-view: parallax {parallax:.2f} deg',
                                 T_world_cam=T_cur, pose_cov=pnp.pose_cov)
        use = ~known                                  # PnP outliers stay out of the BA
        use[np.flatnonzero(known)[pnp.inliers]] = True
        kfs.append(Keyframe(frame_index, T_cur, ids[use], px[use], stamp_ns))
        n_new = self._triangulate_new(kfs[-1])
        if len(kfs) >= c.multiview_keyframes or stale:
            return self._finish()
        return MultiViewStep('pending', f'multi-view: keyframe {len(kfs)}/'
                             f'{c.multiview_keyframes} (+{n_new} points)',
                             T_world_cam=T_cur, pose_cov=pnp.pose_cov)

    # ------------------------------------------------------------------ internals
    def _new_reference(self, frame_index, stamp_ns, ids, px, known_T) -> MultiViewStep:
        self.reset()
        if len(ids) < self.cfg.bootstrap_min_inliers:
            return MultiViewStep('pending', f'bootstrap: only {len(ids)} features')
        self.keyframes.append(Keyframe(frame_index, known_T, ids.copy(), px.copy(),
                                       stamp_ns))
        return MultiViewStep('pending', 'bootstrap: new reference frame')

    def _triangulate_new(self, kf: Keyframe) -> int:
        """Triangulate kf's tracks without a point against the oldest keyframe seeing them."""
        c = self.cfg
        todo = np.array([int(i) not in self.points for i in kf.ids], bool)
        n_new = 0
        T_cur_w = geo.invert_T(kf.T_world_cam)
        for old in self.keyframes[:-1]:
            if not np.any(todo):
                break
            common, i_old, i_cur = np.intersect1d(old.ids, kf.ids[todo], return_indices=True)
            if len(common) == 0:
                continue
            rows_cur = np.flatnonzero(todo)[i_cur]
            tri = triangulate_points(geo.invert_T(old.T_world_cam), T_cur_w,
                                     old.px[i_old], kf.px[rows_cur], self.K,
                                     c.triangulation_max_reproj_px,
                                     c.bootstrap_point_min_parallax_deg)
            for tid, X in zip(common[tri.valid], tri.X_world[tri.valid]):
                self.points[int(tid)] = X
            todo[rows_cur[tri.valid]] = False
            n_new += tri.n_valid
        return n_new

    def _finish(self) -> MultiViewStep:
        """Bundle-adjust the keyframes and their points; the map for the filter."""
        c = self.cfg
        kfs = self.keyframes
        pid = np.array(sorted(self.points), np.int64)
        prow = {int(i): j for j, i in enumerate(pid)}
        X0 = np.array([self.points[int(i)] for i in pid]).reshape(-1, 3)
        cam_idx, pt_idx, obs = [], [], []
        for k, kf in enumerate(kfs):
            for tid, p in zip(kf.ids, kf.px):
                j = prow.get(int(tid))
                if j is not None:
                    cam_idx.append(k)
                    pt_idx.append(j)
                    obs.append(p)
        cam_idx = np.array(cam_idx, np.int64)
        pt_idx = np.array(pt_idx, np.int64)
        obs = np.array(obs, float).reshape(-1, 2)
        T = np.stack([kf.T_world_cam for kf in kfs])
        ba = bundle_adjust(T, X0, cam_idx, pt_idx, obs, self.K,
                           huber_px=c.multiview_ba_huber_px,
                           max_evaluations=c.multiview_ba_max_evaluations)
        # keep points seen >= 2 times, every observation within the triangulation gate
        bad = np.zeros(len(pid), bool)
        np.logical_or.at(bad, pt_idx, ~(ba.err_after_px < c.triangulation_max_reproj_px))
        n_seen = np.bincount(pt_idx, minlength=len(pid))
        keep = ~bad & (n_seen >= 2)
        for kf, Tk in zip(kfs, ba.T_world_cam):
            kf.T_world_cam = Tk
        logger.info('multi-view bootstrap: %d keyframes, %d/%d points, rms %.2f -> %.2f px',
                    len(kfs), int(keep.sum()), len(pid), ba.rms_before_px, ba.rms_after_px)
        return MultiViewStep(
            'done', f'bootstrapped (multi-view): {len(kfs)} keyframes, '
            f'{int(keep.sum())} points, BA rms {ba.rms_before_px:.2f} -> '
            f'{ba.rms_after_px:.2f} px', T_world_cam=ba.T_world_cam[-1],
            keyframes=list(kfs), point_ids=pid[keep], X_world=ba.X_world[keep], ba=ba)
