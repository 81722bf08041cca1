"""Windowed bundle adjustment of the local map, and the uncertainty of its points.

docs/method.md §12. The last keyframes of the local map (local_map.py) and the map
points they see are refined together by minimising the robust (Huber) reprojection error
of every keyframe observation. The oldest keyframes of the window are held fixed: they fix
the gauge of a monocular problem (position, orientation AND scale need two fixed views),
as ORB-SLAM's local mapping holds fixed the keyframes that see the local points without
being in the local window (Mur-Artal et al., T-RO 2015, sec. VI-E).

Parametrisation: each free keyframe has a left rotation increment dtheta
(R_cw = exp(dtheta) R_cw0, no singularity near the initial rotation) and its centre C;
each point its world position X. Residual of observation o (point i in keyframe j),
in units of the pixel noise sigma:

    r_o = (pi(R_cw_j (X_i - C_j)) - z_o) / sigma,   pi = pinhole of the IDEAL pixels.

Solver: Levenberg-Marquardt on the normal equations with the points eliminated (Schur
complement; Triggs et al., "Bundle adjustment - a modern synthesis", 2000, sec. 6.1):
each point's 3x3 block is inverted in closed form, the reduced camera system (6 per free
keyframe, a few dozen unknowns) is solved densely, the points follow by back
substitution. The keyframe-point blocks are computed per observation (a point is seen by
a few of the window's keyframes) and placed in one (6F x 3m) matrix for the reduced
system's product; sums over the observations of a point or a keyframe are reductions over
an order sorted once per adjustment (together 8-10 % faster than a dense (6F x 3) block per
point built by per-component bincounts, on KITTI 06's 6- and 10-keyframe windows, with the
same solution to 1e-11). The Huber loss enters as iteratively reweighted least squares.
Written here rather than taken from scipy: scipy.optimize.least_squares with the analytic
sparse Jacobian (trust-region reflective, LSMR steps) needed ~100 evaluations and 150 ms
to converge on a 6-keyframe, 200-point window that these Gauss-Newton steps solve in
5-10 iterations of ~2 ms (measured in test/test_local_ba.py's scene).

The uncertainty of each refined point is its MARGINAL covariance from the same normal
equations at the solution: the Schur complement gives the free keyframes' covariance,
which then flows back into each point, so a point's covariance includes the uncertainty
of the keyframes it was seen from (relative to the fixed ones), not only its own pixel
noise.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import geometry as geo
from .observation import pinhole_project
from .psd import inverse_information_3x3, psd_blocks_3x3

#: added to each point's information block before inverting it (a point seen along one
#: ray has a singular block; 1e-9 in units of 1/length^2 keeps the inverse finite)
_INFO_REGULARISER = 1e-9
#: Levenberg-Marquardt: initial damping (relative to the diagonal), its factor on a
#: rejected / accepted step, and the relative cost decrease that ends the iterations
_LM_LAMBDA0, _LM_UP, _LM_DOWN, _LM_RTOL = 1e-4, 10.0, 0.3, 1e-6


@dataclass
class WindowProblem:
    """A window's bundle adjustment input.

    T_world_cam (k,4,4) keyframe poses; fixed (k,) bool, those held fixed (the gauge:
    at least two with distinct centres, or one when no keyframe is free);
    X_world (m,3) points; observation o is point pt_idx[o] seen by keyframe cam_idx[o]
    at the IDEAL pixel px[o]."""

    T_world_cam: np.ndarray
    fixed: np.ndarray
    X_world: np.ndarray
    cam_idx: np.ndarray
    pt_idx: np.ndarray
    px: np.ndarray
    #: optional (k,6,6) information of a prior on each keyframe's pose (zeros: none),
    #: about T_world_cam, in the increments (dtheta, dC) and units of the pixel sigma
    prior_info: np.ndarray | None = None


@dataclass
class WindowSolution:
    """Refined poses and points, their errors and the points' marginal covariances."""

    T_world_cam: np.ndarray   #: (k,4,4)
    X_world: np.ndarray       #: (m,3)
    X_cov: np.ndarray         #: (m,3,3) marginal covariance [length^2]
    err_before_px: np.ndarray  #: (o,) reprojection error per observation
    err_after_px: np.ndarray   #: (o,)
    point_median_err_px: np.ndarray  #: (m,) median error of each point over its views
    n_iterations: int
    elapsed_ms: float
    #: (k,6,6) marginal covariance of each keyframe's (dtheta, dC) (zeros: fixed)
    T_cov: np.ndarray | None = None

    @property
    def rms_after_px(self) -> float:
        return float(np.sqrt(np.mean(self.err_after_px ** 2))) if len(self.err_after_px) \
            else 0.0


@dataclass
class _Normal:
    """Normal equations of the window, points not yet eliminated."""

    cost: float                #: robust cost 1/2 sum rho(|r|^2)
    Hcc: np.ndarray            #: (6F,6F)
    #: (c,6,3) keyframe-point block of each observation by a free keyframe (_Structure)
    Hcp: np.ndarray
    Hpp: np.ndarray            #: (m,3,3)
    gc: np.ndarray             #: (6F,)
    gp: np.ndarray             #: (m,3)
    #: Hcc of the observations alone (without the pose priors): the information this
    #: window hands on, which must not include what it was handed (it would pile up)
    Hcc_obs: np.ndarray | None = None
    #: Hcp placed in one (6F,3m) matrix, built once here: every damped step and the
    #: marginal covariances multiply by it (the blocks change only when this is rebuilt)
    Hcp_dense: np.ndarray | None = None


class _Segments:
    """Sums of stacked values by an index that does not change between iterations:
    sorted once, then one np.add.reduceat per sum (np.bincount per component was most
    of the normal equations' time)."""

    def __init__(self, index: np.ndarray, n: int) -> None:
        index = np.asarray(index, np.int64)
        self.order = np.argsort(index, kind='stable')
        sorted_index = index[self.order]
        self.starts = np.flatnonzero(np.r_[True, sorted_index[1:] != sorted_index[:-1]]) \
            if len(index) else np.zeros(0, np.int64)
        self.present = sorted_index[self.starts]
        self.n = int(n)

    def gram(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """out[k] = sum of A[o]^T B[o] over o with index[o] == k, for A, B (o,r,c): one
        BLAS product per index (a (c,c) product per observation, then summed, was a
        third of the normal equations' time)."""
        out = np.zeros((self.n, A.shape[2], B.shape[2]))
        ends = np.r_[self.starts[1:], len(self.order)]
        for k, lo, hi in zip(self.present, self.starts, ends):
            rows = self.order[lo:hi]
            out[k] = A[rows].reshape(-1, A.shape[2]).T @ B[rows].reshape(-1, B.shape[2])
        return out

    def sum(self, values: np.ndarray) -> np.ndarray:
        """out[k] = sum of values[o] over o with index[o] == k; out (n, *values.shape[1:])."""
        out = np.zeros((self.n,) + values.shape[1:])
        if len(self.starts):
            out[self.present] = np.add.reduceat(values[self.order], self.starts, axis=0)
        return out


class _Structure:
    """Who sees what, fixed for the whole adjustment: the observations by a free keyframe
    (`rows`, into the problem's observations), their keyframe slot and point."""

    def __init__(self, cam_slot: np.ndarray, pt_idx: np.ndarray, m: int, nf: int) -> None:
        self.rows = np.flatnonzero(cam_slot >= 0)
        self.slot = cam_slot[self.rows]
        self.pt = pt_idx[self.rows]
        self.m, self.nf = int(m), int(nf)
        if len(np.unique(self.slot * m + self.pt)) < len(self.rows):
            raise ValueError('a keyframe sees a point of the window twice')
        self.by_slot = _Segments(self.slot, nf)
        self.by_point = _Segments(self.pt, m)

    def dense(self, blocks: np.ndarray) -> np.ndarray:
        """(6F, 3m) matrix with each observation's (6,3) block at (its slot, its point)
        (zeros elsewhere): one BLAS product then sums over the points, 3x faster than a
        (6,6) product per pair of observations of one point."""
        out = np.zeros((self.nf, 6, self.m, 3))
        out[self.slot, :, self.pt, :] = blocks
        return out.reshape(6 * self.nf, 3 * self.m)


class _Window:
    """The window's state (rotations, centres, points), residuals and normal equations."""

    def __init__(self, problem: WindowProblem, K: np.ndarray, sigma_px: float,
                 huber_px: float) -> None:
        self.p = problem
        self.K = np.asarray(K, float)
        self.sigma = float(sigma_px)
        self.huber = float(huber_px) / self.sigma         # in units of sigma
        T = np.asarray(problem.T_world_cam, float)
        self.R_cw = np.transpose(T[:, :3, :3], (0, 2, 1)).copy()
        self.C = T[:, :3, 3].copy()
        self.X = np.asarray(problem.X_world, float).copy()
        free = np.flatnonzero(~np.asarray(problem.fixed, bool))
        self.slot = -np.ones(len(T), np.int64)             # keyframe -> free slot
        self.slot[free] = np.arange(len(free))
        self.free = free
        self.nc = 6 * len(free)
        self.R_prior, self.C_prior = self.R_cw[free].copy(), self.C[free].copy()
        self.obs_by_point = _Segments(problem.pt_idx, len(self.X))
        self.structure = _Structure(self.slot[problem.cam_idx], np.asarray(problem.pt_idx),
                                    len(self.X), len(free))
        info = problem.prior_info
        self.prior_info = None if info is None or not np.any(info[free]) else \
            np.asarray(info, float)[free]

    def _prior_residual(self) -> np.ndarray:
        """(F,6): (dtheta, dC) of each free keyframe from its prior (small-angle log)."""
        dR = self.R_cw[self.free] @ np.transpose(self.R_prior, (0, 2, 1))
        w = 0.5 * np.stack((dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                            dR[:, 1, 0] - dR[:, 0, 1]), axis=1)
        return np.concatenate((w, self.C[self.free] - self.C_prior), axis=1)

    def _prior_cost(self) -> float:
        if self.prior_info is None:
            return 0.0
        d = self._prior_residual()
        return 0.5 * float(np.einsum('fi,fij,fj->', d, self.prior_info, d))

    def state(self):
        return self.R_cw.copy(), self.C.copy(), self.X.copy()

    def restore(self, state) -> None:
        self.R_cw, self.C, self.X = state

    def camera_points(self) -> np.ndarray:
        ci = self.p.cam_idx
        return np.einsum('oij,oj->oi', self.R_cw[ci], self.X[self.p.pt_idx] - self.C[ci])

    def errors_px(self) -> np.ndarray:
        """Reprojection error per observation [px] (inf behind a camera)."""
        px, front, _ = pinhole_project(self.camera_points(), self.K, with_jacobian=False)
        return np.where(front, np.linalg.norm(px - self.p.px, axis=1), np.inf)

    def _weights(self, s: np.ndarray) -> np.ndarray:
        """IRLS weights of the Huber loss for residual norms s (units of sigma)."""
        return np.where(s <= self.huber, 1.0, self.huber / np.maximum(s, 1e-12))

    def cost(self) -> float:
        s = self.errors_px() / self.sigma
        s = np.where(np.isfinite(s), s, 1e6)
        k = self.huber
        return float(np.sum(np.where(s <= k, 0.5 * s ** 2, k * (s - 0.5 * k)))) + \
            self._prior_cost()

    def normal_equations(self) -> _Normal:
        ci, pi = self.p.cam_idx, self.p.pt_idx
        m, nc = len(self.X), self.nc
        Xc = self.camera_points()
        px, front, Jp = pinhole_project(Xc, self.K)
        r = (px - self.p.px) / self.sigma                    # (o,2)
        s = np.linalg.norm(r, axis=1)
        w = np.where(front, self._weights(s), 0.0)          # behind a camera: no say
        k = self.huber
        cost = float(np.sum(np.where(front, np.where(s <= k, 0.5 * s ** 2,
                                                      k * (s - 0.5 * k)), 0.5 * 1e12)))
        J_X = (Jp / self.sigma) @ self.R_cw[ci]              # (o,2,3)
        wJ_X = w[:, None, None] * J_X
        Hpp = self.obs_by_point.sum(np.transpose(J_X, (0, 2, 1)) @ wJ_X)
        gp = self.obs_by_point.sum(np.einsum('oki,ok->oi', wJ_X, r))
        st = self.structure
        rows = st.rows
        Hcc, Hcp, gc = np.zeros((nc, nc)), np.zeros((len(rows), 6, 3)), np.zeros(nc)
        if len(rows):
            # d Xc / d dtheta = -[Xc]x (left increment), d Xc / d C = -R_cw
            J_c = np.concatenate(((Jp[rows] / self.sigma) @ -geo.skew_batch(Xc[rows]),
                                  -J_X[rows]), axis=2)                # (c,2,6)
            wJ_c = w[rows, None, None] * J_c
            nf = len(self.free)
            # an observation involves one keyframe: Hcc is block diagonal
            H6 = st.by_slot.gram(J_c, wJ_c)                                  # (F,6,6)
            Hcc = np.zeros((nf, 6, nf, 6))
            Hcc[np.arange(nf), :, np.arange(nf), :] = H6
            Hcc = Hcc.reshape(nc, nc)
            gc = st.by_slot.sum(np.einsum('oki,ok->oi', wJ_c, r[rows])).ravel()
            Hcp = np.transpose(J_c, (0, 2, 1)) @ wJ_X[rows]
        Hcc_obs = Hcc
        if self.prior_info is not None and nc:
            d = self._prior_residual()
            nf = len(self.free)
            Hcc = Hcc.copy().reshape(nf, 6, nf, 6)
            Hcc[np.arange(nf), :, np.arange(nf), :] += self.prior_info
            Hcc = Hcc.reshape(nc, nc)
            gc = gc + np.einsum('fij,fj->fi', self.prior_info, d).ravel()
            cost += self._prior_cost()
        return _Normal(cost, Hcc, Hcp, Hpp, gc, gp, Hcc_obs, st.dense(Hcp) if nc else None)

    def solve(self, ne: _Normal, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Damped step (cameras (6F,), points (m,3)) by Schur complement."""
        Hpp = ne.Hpp + lam * np.einsum('mii->mi', ne.Hpp)[:, :, None] * np.eye(3) + \
            np.eye(3) * _INFO_REGULARISER
        Hpp_inv = _inverse_3x3(Hpp)
        if self.nc == 0:
            return np.zeros(0), -np.einsum('mij,mj->mi', Hpp_inv, ne.gp)
        st = self.structure
        Hcc = ne.Hcc + lam * np.diag(np.diag(ne.Hcc))
        W = ne.Hcp @ Hpp_inv[st.pt]                                # (c,6,3)
        S = Hcc - st.dense(W) @ ne.Hcp_dense.T
        b = ne.gc - st.by_slot.sum(np.einsum('cij,cj->ci', W, ne.gp[st.pt])).ravel()
        d_cam = np.linalg.solve(S + np.eye(self.nc) * 1e-12, -b)
        back = st.by_point.sum(np.einsum('cji,cj->ci', ne.Hcp, d_cam.reshape(-1, 6)[st.slot]))
        d_pts = -np.einsum('mij,mj->mi', Hpp_inv, ne.gp + back)
        return d_cam, d_pts

    def apply(self, d_cam: np.ndarray, d_pts: np.ndarray) -> None:
        if self.nc:
            d = d_cam.reshape(-1, 6)
            self.R_cw[self.free] = geo.rotvecs_to_matrices(d[:, :3]) @ self.R_cw[self.free]
            self.C[self.free] += d[:, 3:]
        self.X += d_pts

    def marginal_covariances(self, ne: _Normal) -> tuple[np.ndarray, np.ndarray]:
        """Marginal covariances of each point (m,3,3) and each keyframe's (dtheta, dC)
        (k,6,6; zeros for the fixed ones) from one Schur complement (no damping), of the
        observations alone (the pose priors are this window's inputs, not its findings)."""
        Hpp_inv = inverse_information_3x3(ne.Hpp, _INFO_REGULARISER)
        T_cov = np.zeros((len(self.slot), 6, 6))
        if self.nc == 0:
            return Hpp_inv, T_cov
        st = self.structure
        W = st.dense(ne.Hcp @ Hpp_inv[st.pt])                      # (6F,3m)
        S = (ne.Hcc if ne.Hcc_obs is None else ne.Hcc_obs) - W @ ne.Hcp_dense.T
        S_inv = np.linalg.pinv(S)
        nf = len(self.free)
        blocks = S_inv.reshape(nf, 6, nf, 6)
        T_cov[self.free] = blocks[np.arange(nf), :, np.arange(nf), :]
        # cov(X_i) = Hpp_i^-1 + W_i^T S^-1 W_i with W_i = Hcp_i Hpp_i^-1 (6F x 3);
        # rounding in a barely held gauge can leave S or a block not PSD (psd.py)
        W_i = np.transpose(W.reshape(self.nc, -1, 3), (1, 0, 2))       # (m,6F,3)
        return psd_blocks_3x3(Hpp_inv + np.transpose(W_i, (0, 2, 1)) @ (S_inv @ W_i)), T_cov


def _inverse_3x3(H: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3x3 point information blocks. Where one is singular in
    floating point (rays all but parallel: the absolute regulariser is lost against
    entries of 10^8), the regulariser is made relative to its trace: the depth then gets
    a huge variance (honest), never the zero a pseudo-inverse would give it."""
    try:
        return np.linalg.inv(H)
    except np.linalg.LinAlgError:
        scale = np.einsum('mii->m', H)[:, None, None]
        return np.linalg.inv(H + np.eye(3) * (_INFO_REGULARISER * (1.0 + scale)))


def adjust_window(problem: WindowProblem, K: np.ndarray, sigma_px: float, huber_px: float,
                  max_iterations: int) -> WindowSolution:
    """Robust bundle adjustment of one window (see the module docstring)."""
    t0 = time.perf_counter()
    win = _Window(problem, K, sigma_px, huber_px)
    err0 = win.errors_px()
    ne = win.normal_equations()
    lam, n_iter = _LM_LAMBDA0, 0
    for _ in range(int(max_iterations)):
        n_iter += 1
        saved = win.state()
        win.apply(*win.solve(ne, lam))
        new_cost = win.cost()
        if new_cost < ne.cost:
            done = ne.cost - new_cost < _LM_RTOL * ne.cost
            ne = win.normal_equations()
            lam = max(lam * _LM_DOWN, 1e-9)
            if done:
                break
        else:
            win.restore(saved)
            lam *= _LM_UP
            if lam > 1e6:
                break
    T_out = np.stack([geo.make_T(R.T, c) for R, c in zip(win.R_cw, win.C)])
    err1 = win.errors_px()
    X_cov, T_cov = win.marginal_covariances(ne)
    return WindowSolution(T_out, win.X.copy(), X_cov, err0, err1,
                          _median_per_point(err1, problem.pt_idx, len(win.X)), n_iter,
                          (time.perf_counter() - t0) * 1e3, T_cov)


def _median_per_point(err: np.ndarray, pt_idx: np.ndarray, m: int) -> np.ndarray:
    """Median of err over the observations of each point (inf for unobserved ones)."""
    order = np.lexsort((err, pt_idx))
    bounds = np.searchsorted(pt_idx[order], np.arange(m + 1))
    counts = np.diff(bounds)
    out = np.full(m, np.inf)
    seen = counts > 0
    lo = bounds[:-1][seen] + (counts[seen] - 1) // 2
    hi = bounds[:-1][seen] + counts[seen] // 2
    out[seen] = 0.5 * (err[order[lo]] + err[order[hi]])
    return out


def point_covariances(X_world: np.ndarray, T_cam_world_views: list[np.ndarray],
                      K: np.ndarray, sigma_px: float) -> np.ndarray:
    """Covariance (n,3,3) of points triangulated from views at known, exact poses:
    the inverse of the summed Gauss-Newton information of their reprojections. A view
    is one pose (4,4) for every point, or one per point (n,4,4)."""
    X = np.asarray(X_world, float).reshape(-1, 3)
    H = np.zeros((len(X), 3, 3))
    for T in T_cam_world_views:
        J = pinhole_project(geo.transform_points(T, X), K)[2] @ T[..., :3, :3] / sigma_px
        H += np.transpose(J, (0, 2, 1)) @ J
    return inverse_information_3x3(H, _INFO_REGULARISER)
