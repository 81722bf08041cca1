"""Per-landmark measurement noise learned online from each landmark's own residuals.

docs/method.md §13. Real features do not share one pixel noise: a corner on a blurred
edge, a low-texture patch, a point far off-centre under distortion or on a JPEG block edge
is tracked worse than the rest, and stays so for as long as it is tracked. The filter is
told one nominal sigma (`pixel_sigma_px`, or per frame what the caller knows); each
landmark i gets a variance MULTIPLIER m_i, so its noise is sigma_i = sqrt(m_i) * nominal.

m_i has a scaled-inverse-chi-square posterior (the conjugate prior of a Gaussian
variance; the variational-Bayes adaptive Kalman filter of Sarkka & Nummenmaa, IEEE TAC
2009, keeps the same form per measurement channel): nu_i pseudo-observations with mean
square s2_i, starting at nu_0 = `noise_prior_dof` observations of m = 1 (the nominal is
right until the landmark shows otherwise: shrinkage while it is young). After each
update in which landmark i is an inlier, with a posteriori residual r_i (2-vector) and
the part of it the state's own uncertainty explains, tr(H_i P+ H_i^T):

    nu_i  <- nu_i + 2
    s2_i  <- (nu_i_old s2_i + (|r_i|^2 + tr(H_i P+ H_i^T)) / nominal^2) / nu_i

and the multiplier used is m_i = clip(s2_i, min_scale^2, max_scale^2). The map keeps,
per landmark, the data part (n_dof = nu_i - nu_0 and the sum of the normalised squares),
so that it lives and dies with the landmark (map.py). A landmark the
robust update rejects does not teach its noise (an outlier is not noise; culling handles
it), so a gross error cannot inflate a sigma until it sneaks in as an inlier.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import VoConfig
from .observation import projected_variance_px2


@dataclass
class NoiseSettings:
    """The prior and the bounds (config: noise_prior_dof, noise_min_scale,
    noise_max_scale)."""

    prior_dof: float             #: nu_0: observations' weight of the nominal
    min_scale: float             #: floor of sigma_i / nominal
    max_scale: float             #: cap of sigma_i / nominal

    @classmethod
    def from_config(cls, cfg: VoConfig) -> 'NoiseSettings':
        return cls(cfg.noise_prior_dof, cfg.noise_min_scale, cfg.noise_max_scale)


def noise_scales(n_dof: np.ndarray, sum_sq: np.ndarray, settings: NoiseSettings
                 ) -> np.ndarray:
    """sigma_i / nominal of landmarks with n_dof residual components seen so far and
    sum_sq the sum of their normalised squares: sqrt(s2_i) with the prior's nu_0
    observations of 1 included, clipped to [min_scale, max_scale]."""
    nu0 = settings.prior_dof
    s2 = (nu0 + np.asarray(sum_sq, float)) / (nu0 + np.asarray(n_dof, float))
    return np.sqrt(np.clip(s2, settings.min_scale ** 2, settings.max_scale ** 2))


def normalised_squares(residual_px: np.ndarray, explained_px2: np.ndarray,
                       nominal_px: float | np.ndarray) -> np.ndarray:
    """(|r_i|^2 + tr(H_i P+ H_i^T)) / nominal^2 (n,): what one update adds to sum_sq
    (2 residual components each: n_dof grows by 2)."""
    r = np.asarray(residual_px, float).reshape(-1, 2)
    nominal2 = np.broadcast_to(np.asarray(nominal_px, float) ** 2, (len(r),))
    return (np.sum(r ** 2, axis=1) + np.asarray(explained_px2, float)) / \
        np.maximum(nominal2, 1e-12)


def explained_px2(H: np.ndarray, P: np.ndarray) -> np.ndarray:
    """tr(H_i P H_i^T) (n,) [px^2] for the stacked, interleaved Jacobian H (2n, D) of n
    points: the spread of the residuals the state's own uncertainty accounts for."""
    HP = H @ P
    per_row = np.einsum('ij,ij->i', HP, H)
    return per_row[0::2] + per_row[1::2]


def map_measurement_sigmas(cfg: VoConfig, settings: NoiseSettings, landmarks, ids: np.ndarray,
                           X: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray
                           ) -> np.ndarray | None:
    """Pixel std of each map measurement: pixel_sigma_px, times the landmark's learned
    factor with measurement_noise: adaptive, plus the point's position uncertainty
    projected at the pose T_world_cam with map_point_uncertainty (docs/method.md
    §12.3). None = pixel_sigma_px for all (neither option on)."""
    adaptive = cfg.measurement_noise == 'adaptive'
    if not len(ids) or not (adaptive or cfg.map_point_uncertainty):
        return None
    sigma = np.full(len(ids), cfg.pixel_sigma_px)
    if adaptive:
        sigma *= noise_scales(*landmarks.noise_record(ids), settings)
    if cfg.map_point_uncertainty:
        var = projected_variance_px2(X, landmarks.covariances(ids), T_world_cam, K)
        sigma = np.sqrt(sigma ** 2 + var)
    return sigma


def learn_from_update(landmarks, ekf, ids: np.ndarray, z_px: np.ndarray, X: np.ndarray,
                      nominal_px: float) -> None:
    """An update's map inliers (ids, measured IDEAL pixels z_px, points X) teach their
    landmarks' noise from the a posteriori residuals at the filter's state."""
    if not len(ids):
        return
    px, front, H = ekf.observe(X)
    e = normalised_squares(z_px - px, explained_px2(H, ekf.P), nominal_px)
    landmarks.add_residuals(ids[front], e[front])
