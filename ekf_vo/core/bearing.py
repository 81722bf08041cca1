"""Tracks without depth as measurements of the orientation (docs/method.md §15.8).

A camera turning in place leaves its map behind faster than a baseline for new points
builds up: the map matches run out in the turn while hundreds of tracks go on. A track
that has no map point yet (a triangulation candidate, map_growth.py) still says where its
ray went: first seen from the camera centre c along the world bearing m, its point is
X(rho) = c + m / rho for an unknown inverse depth rho. Civera, Davison & Montiel (IEEE
T-RO 2008) put rho in the state with a wide prior; the hybrid filter keeps points out of
its state, so here rho stays a nuisance (a Schmidt consider parameter): the measurement is
the projection of X(rho0), rho0 = 1 / (the median depth of the map in view), and the
pixel spread that rho ~ N(rho0, (rel_sigma rho0)^2) causes is added to its noise,

    R_i = 2 sigma_px^2 I + sigma_rho^2 g_i g_i^T,   g_i = d pixel / d rho at the prior,

(the 2: the pixel noise of the first observation, which fixed m, and of this one). g_i
lies along the track's epipolar line and vanishes when the camera has not moved from c:
in a turn in place the measurement holds the full rotation, with a baseline only its
component across the epipolar line. The update takes R_i through whitening
(observation.ReprojectionModel.whiten). The world bearing m carries the orientation of
the frame it was taken in, as every map point carries the pose it was triangulated from:
its anchor goes into the published covariance with the map points' (map_uncertainty.py).

Used only in frames with few map matches (`bearing_max_map_points`): where the map holds
the pose, depthless rays add little, and the figures of the mapped sequences stay theirs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .observation import world_point_jacobian


@dataclass
class BearingMeasurements:
    """The depthless tracks one update uses (all arrays over the b tracks)."""

    rows: np.ndarray            #: (b,) track rows of this frame
    X_world: np.ndarray         #: (b,3) point at the assumed inverse depth rho0
    cov_px2: np.ndarray         #: (b,2,2) what the unknown depth adds to the noise [px^2]
    anchor_cov: np.ndarray      #: (b,6,6) published covariance of the first frame's pose
    anchor_c: np.ndarray        #: (b,3) that frame's camera centre

    def __len__(self) -> int:
        return len(self.rows)


def depth_spread_px2(centres: np.ndarray, bearings: np.ndarray, T_world_cam: np.ndarray,
                     K: np.ndarray, rho0: float, rho_sigma: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Points X = c + m / rho0 (b,3) of rays (centres c, unit world bearings m) and the
    pixel covariance (b,2,2) that rho ~ N(rho0, rho_sigma^2) causes in the camera at
    T_world_cam (linearised at rho0: dX/drho = -m / rho0^2)."""
    X = centres + bearings / rho0
    J_X, front = world_point_jacobian(X, T_world_cam, K)
    g = np.einsum('nij,nj->ni', J_X, -bearings / rho0 ** 2)             # (b,2)
    cov = rho_sigma ** 2 * g[:, :, None] * g[:, None, :]
    return X, np.where(front[:, None, None], cov, 0.0)
