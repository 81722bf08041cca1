"""A rolling shutter's rows, brought to the stamp's time with the camera's motion.

docs/method.md §15.14. A rolling-shutter sensor exposes its rows one after the other: row
r of an image stamped t was read at t + (r / (H - 1) - 1/2) * readout (the stamp taken as
the middle row's time). A camera turning at w rad/s meanwhile turns by w * dt, so a
frame's rows do not share one orientation: a 30 ms readout at 100 deg/s skews the image
by 3 deg from top to bottom, 27 px at a 525 px focal length. Every model downstream
(two-view bootstrap, the rotation chain before the map, the EKF update) assumes one
pose per image.

The tracked ideal pixels are moved to where the camera at the stamp would have seen
them, with the motion model's prediction (w in the camera frame, v in the world, as the
EKF's state):

    rotation     R_wc(t + dt) = R_wc(t) Exp(w dt), so the bearing at t is
                 Exp(w dt) times the bearing at t + dt: the same at any depth;
    translation  X_cam(t + dt) = X_cam(t) - dt R_cw v: f v dt / depth pixels, undone
                 at the map point's depth (or, without one, at the map's median depth).

Before the map there is no filter: the rotation alone is undone there, at the rate of
the step from the last frame fitted to this frame's own tracks
(initialisation.Initialisation._initialising_to_stamp_time).
"""
from __future__ import annotations

import numpy as np

from . import geometry as geo
from .camera import PinholeCamera


def row_time_offsets_s(rows_px: np.ndarray, height: int, readout_s: float) -> np.ndarray:
    """Time of each raw pixel row relative to the stamp (the middle row's) [s]."""
    return (np.asarray(rows_px, float) / max(height - 1, 1) - 0.5) * float(readout_s)


def rotation_to_stamp_time(px_ideal: np.ndarray, rows_px: np.ndarray, omega_cam: np.ndarray,
                           readout_s: float, camera: PinholeCamera) -> np.ndarray:
    """Ideal pixels (n,2) seen on the raw rows `rows_px` (n,), moved to where the camera's
    orientation at the stamp would have seen them, the camera turning at `omega_cam`
    (3,) [rad/s, camera frame] during the readout `readout_s` of `camera`'s image.
    Unchanged when the readout or the rotation is zero."""
    px_ideal = np.asarray(px_ideal, float)
    if not len(px_ideal) or readout_s <= 0.0 or not np.any(omega_cam):
        return px_ideal
    dt = row_time_offsets_s(rows_px, camera.height, readout_s)
    R = geo.rotvecs_to_matrices(dt[:, None] * np.asarray(omega_cam, float)[None, :])
    b = np.einsum('nij,nj->ni', R, camera.unproject(px_ideal))
    out = px_ideal.copy()
    ok = b[:, 2] > 1e-6          # a ray turned behind the camera keeps its pixel
    out[ok] = camera.project(b[ok])
    return out


def points_on_rays(px_ideal: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray,
                   depth: float) -> np.ndarray:
    """World points (n,3) at optical depth `depth` on the rays of ideal pixels (n,2)."""
    b = camera.unproject(px_ideal)
    return (b * (depth / b[:, 2:3])) @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def translation_to_stamp_time(px_ideal: np.ndarray, rows_px: np.ndarray, X_world: np.ndarray,
                              T_world_cam: np.ndarray, v_world: np.ndarray, readout_s: float,
                              camera: PinholeCamera) -> np.ndarray:
    """Ideal pixels (n,2) of the points X_world (n,3), seen on the raw rows `rows_px`,
    moved by what the camera's translation at `v_world` (3,) [map units/s] during the
    readout moved them: their projection from the pose T_world_cam at the stamp minus
    that from where the camera was at the row's time. A point at or behind the camera
    keeps its pixel."""
    px_ideal = np.asarray(px_ideal, float)
    if not len(px_ideal) or readout_s <= 0.0 or not np.any(v_world):
        return px_ideal
    dt = row_time_offsets_s(rows_px, camera.height, readout_s)
    R_cw = T_world_cam[:3, :3].T
    X_c = (np.asarray(X_world, float) - T_world_cam[:3, 3]) @ R_cw.T
    X_row = X_c - dt[:, None] * (R_cw @ np.asarray(v_world, float))[None, :]
    ok = (X_c[:, 2] > 1e-6) & (X_row[:, 2] > 1e-6)
    out = px_ideal.copy()
    out[ok] += camera.project(X_c[ok]) - camera.project(X_row[ok])
    return out
