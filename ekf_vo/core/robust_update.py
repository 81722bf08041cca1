"""The one robust update: 1-point RANSAC + high-innovation rescue around the EKF update.

Civera, Grasa, Davison & Montiel, "1-Point RANSAC for EKF filtering", J. Field Robotics
2010 (docs/method.md §6). Works on any state (x, P) and any reprojection model
(observation.py): the camera-only filter (fixed map points) and the joint filter of the
in-filter refinement (map points + inverse-depth points) are the same code.
  1. hypotheses: a partial update of the state with ONE match (covariance untouched);
     predict every other match from that state, count those within `ransac_inlier_px` as
     its support; n_hyp = log(1 - p) / log(1 - eps), eps = best inlier ratio so far
     (m = 1), adapted as hypotheses are drawn;
  2. low-innovation inliers: a full EKF update (ekf.update) with the supporters of the
     best hypothesis;
  3. high-innovation rescue: re-predict the remaining matches with the updated state and
     covariance; those whose Mahalanobis distance passes the chi-square gate (2 dof,
     `gate_probability`) are inliers too; a second update with them.
Without RANSAC (`one_point_ransac: false`) the prior innovation gate of step 3 alone is used.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..config import VoConfig
from .ekf import UpdateStats, chi2_2dof_quantile, update
from .observation import ReprojectionModel
from .state import QUAT

logger = logging.getLogger(__name__)

#: hypotheses whose projections numpy evaluates together
_HYPOTHESIS_BATCH = 16


@dataclass(frozen=True)
class RansacSettings:
    """The configuration of one robust update (read from VoConfig; no defaults here)."""

    one_point: bool
    inlier_px: float
    probability: float
    max_hypotheses: int
    gate_probability: float
    iterations: int          #: 1 = EKF, > 1 = iterated EKF

    @classmethod
    def from_config(cls, cfg: VoConfig) -> 'RansacSettings':
        return cls(cfg.one_point_ransac, cfg.ransac_inlier_px, cfg.ransac_probability,
                   cfg.ransac_max_hypotheses, cfg.gate_probability,
                   cfg.iekf_iterations if cfg.estimator == 'iekf' else 1)


@dataclass
class RobustUpdateResult:
    """Outcome of one robust update; index arrays refer to the input rows."""

    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  #: (n,) bool
    n_low_innovation: int = 0     #: inliers of the best hypothesis (step 2)
    n_rescued: int = 0            #: high-innovation inliers rescued (step 3)
    n_hypotheses: int = 0
    stats: UpdateStats = field(default_factory=UpdateStats)

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def innovation_covariances(P: np.ndarray, H: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per-measurement 2x2 innovation covariances S_i = H_i P H_i^T + R_i, (n,2,2)."""
    Hn = H.reshape(-1, 2, P.shape[0])
    S = Hn @ P @ Hn.transpose(0, 2, 1)
    S[:, 0, 0] += sigma ** 2
    S[:, 1, 1] += sigma ** 2
    return S


def _mahalanobis2(innovation: np.ndarray, S: np.ndarray) -> np.ndarray:
    return np.einsum('ni,nij,nj->n', innovation, np.linalg.inv(S), innovation)


def _single_point_states(x: np.ndarray, P: np.ndarray, H: np.ndarray,
                         innovation: np.ndarray, sigma: np.ndarray, batch: np.ndarray
                         ) -> np.ndarray:
    """States after a partial update with ONE measurement each, (h,D); the covariance is
    not touched (Civera et al. 2010, Algorithm 1)."""
    Hb = H.reshape(-1, 2, len(x))[batch]                            # (h,2,D)
    PHt = P @ Hb.transpose(0, 2, 1)                                 # (h,D,2)
    S = Hb @ PHt
    S[:, 0, 0] += sigma[batch] ** 2
    S[:, 1, 1] += sigma[batch] ** 2
    states = x[None] + (PHt @ np.linalg.solve(S, innovation[batch][:, :, None]))[:, :, 0]
    states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1, keepdims=True)
    return states


def _best_hypothesis(x, P, H, innovation, z_px, model, sigma, valid, rng,
                     settings: RansacSettings) -> tuple[np.ndarray, int]:
    """Step 1: the support (n,) bool of the best 1-point hypothesis, hypotheses tried."""
    candidates = np.flatnonzero(valid)
    n_hyp, best_support, tried = settings.max_hypotheses, -1, 0
    low = np.zeros(len(z_px), bool)
    while tried < n_hyp:
        batch = rng.choice(candidates, size=min(n_hyp - tried, _HYPOTHESIS_BATCH),
                           replace=True)
        states = _single_point_states(x, P, H, innovation, sigma, batch)
        err = np.linalg.norm(model.project_states(states) - z_px[None], axis=2)
        support = (err < settings.inlier_px) & valid[None]
        counts = support.sum(axis=1)
        tried += len(batch)
        b = int(np.argmax(counts))
        if counts[b] > best_support:
            best_support = int(counts[b])
            low = support[b]
            eps = best_support / len(candidates)
            if eps >= 1.0:
                break
            if eps > 0.0:
                # adaptive hypothesis count for m = 1 (Civera 2010, eq. 19); with no
                # support yet (eps = 0) the bound stays at max_hypotheses
                n_hyp = min(settings.max_hypotheses, int(np.ceil(
                    np.log(1.0 - settings.probability) / np.log(1.0 - eps))))
    return low, tried


def robust_update(x: np.ndarray, P: np.ndarray, z_px: np.ndarray, model: ReprojectionModel,
                  sigma_px: float | np.ndarray, rng: np.random.Generator,
                  settings: RansacSettings
                  ) -> tuple[np.ndarray, np.ndarray, RobustUpdateResult]:
    """Update (x, P) with the inliers among the n matches z_px (n,2) of `model`.

    Returns the updated (x, P) and which rows were used (result.inliers)."""
    n = len(z_px)
    result = RobustUpdateResult(inliers=np.zeros(n, bool))
    if n == 0:
        return x, P, result
    sigma = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,)).copy()
    px_pred, in_front, H = model.observe(x)
    innovation = z_px - px_pred
    valid = in_front & np.all(np.isfinite(innovation), axis=1)
    gate = chi2_2dof_quantile(settings.gate_probability)

    if settings.one_point and np.count_nonzero(valid) >= 2:
        low, result.n_hypotheses = _best_hypothesis(
            x, P, H, innovation, z_px, model, sigma, valid, rng, settings)
    else:
        # plain innovation gate on the prior
        d2 = _mahalanobis2(innovation, innovation_covariances(P, H, sigma))
        low = valid & (d2 < gate)

    result.n_low_innovation = int(np.count_nonzero(low))
    if result.n_low_innovation == 0:
        return x, P, result
    rows = np.flatnonzero(low)
    x, P, result.stats = update(x, P, z_px[rows], model.subset(rows), sigma[rows],
                                settings.iterations)
    inliers = low.copy()

    rest = np.flatnonzero(valid & ~low)
    if settings.one_point and len(rest):
        # step 3: high-innovation inlier rescue with the updated state and covariance
        sub = model.subset(rest)
        px_r, front_r, H_r = sub.observe(x)
        d2 = _mahalanobis2(z_px[rest] - px_r, innovation_covariances(P, H_r, sigma[rest]))
        rescued = rest[front_r & (d2 < gate)]
        if len(rescued):
            x, P, result.stats = update(x, P, z_px[rescued], model.subset(rescued),
                                        sigma[rescued], settings.iterations)
            inliers[rescued] = True
            result.n_rescued = len(rescued)
    result.inliers = inliers
    return x, P, result
