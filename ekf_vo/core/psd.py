"""Covariances that stay covariances: symmetric and positive semi-definite.

An information matrix that is all but singular (a point seen along nearly parallel rays,
a window whose gauge is barely held) has an inverse whose rounding error can exceed its
smallest eigenvalues: `np.linalg.inv` then returns a "covariance" with negative
variances. Summed into the published covariance, one such point made a rotation
variance negative (docs/method.md §15.11). These helpers are the fallback: the fast
inverse is kept where it is already a covariance, so results elsewhere do not change.
"""
from __future__ import annotations

import numpy as np

#: eigenvalues of an information matrix are floored at this share of its largest before
#: inverting: the weakest direction then gets a huge (honest) variance, never a negative
REL_EIGEN_FLOOR = 1e-15


def is_psd_3x3(C: np.ndarray) -> np.ndarray:
    """(n,) bool: each 3x3 block of C (n,3,3) is symmetric positive semi-definite by
    Sylvester's criterion on its leading minors (cheap, vectorised)."""
    a = C[:, 0, 0]
    m2 = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    return (a >= 0) & (m2 >= 0) & (np.linalg.det(C) >= 0) & \
        np.isfinite(C).all(axis=(1, 2))


def spd_inverse(H: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Inverse of a stack of symmetric information matrices (..., k, k), positive
    definite by construction: eigenvalues floored at `floor` + REL_EIGEN_FLOOR x the
    largest."""
    H = 0.5 * (H + np.swapaxes(H, -1, -2))
    w, V = np.linalg.eigh(H)
    lo = floor + REL_EIGEN_FLOOR * np.maximum(w[..., -1:], 0.0) + np.finfo(float).tiny
    w = np.maximum(w, lo)
    return (V / w[..., None, :]) @ np.swapaxes(V, -1, -2)


def inverse_information_3x3(H: np.ndarray, floor: float) -> np.ndarray:
    """Covariances (n,3,3) of information blocks H (n,3,3) regularised by floor x I: the
    plain inverse where it is a covariance, spd_inverse where rounding broke it."""
    H = np.asarray(H, float)
    try:
        C = np.linalg.inv(H + np.eye(3) * floor)
    except np.linalg.LinAlgError:
        return spd_inverse(H, floor)
    bad = ~is_psd_3x3(C)
    if bad.any():
        C[bad] = spd_inverse(H[bad], floor)
    return C


def psd_blocks_3x3(C: np.ndarray) -> np.ndarray:
    """C (n,3,3) with each block that is not PSD replaced by its nearest PSD matrix."""
    bad = ~is_psd_3x3(C)
    if bad.any():
        C = C.copy()
        S = 0.5 * (C[bad] + np.swapaxes(C[bad], -1, -2))
        w, V = np.linalg.eigh(np.nan_to_num(S, posinf=1e300, neginf=-1e300))
        C[bad] = (V * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(V, -1, -2)
    return C


def nearest_psd(C: np.ndarray) -> np.ndarray:
    """C (k,k) itself when it is symmetric PSD, else its symmetric part, with negative
    eigenvalues set to zero if it has any (the nearest PSD matrix in the Frobenius
    norm)."""
    S = 0.5 * (C + C.T)
    if not np.isfinite(S).all():
        return C
    w, V = np.linalg.eigh(S)
    if w[0] >= 0.0:
        return C if np.array_equal(S, C) else S
    return (V * np.maximum(w, 0.0)) @ V.T
