"""Covariances stay covariances (core/psd.py): the fallbacks for inverses that rounding
broke, and that they leave good inputs bit for bit."""
import numpy as np

from ekf_vo.core.psd import (inverse_information_3x3, is_psd_3x3, nearest_psd,
                             psd_blocks_3x3, spd_inverse)


def _random_spd(rng, n, k, cond=1e3):
    A = rng.normal(size=(n, k, k))
    Q, _ = np.linalg.qr(A)
    w = np.exp(rng.uniform(0, np.log(cond), size=(n, k)))
    return (Q * w[:, None, :]) @ np.swapaxes(Q, -1, -2)


def test_sylvester_test_matches_eigenvalues():
    rng = np.random.default_rng(0)
    C = rng.normal(size=(500, 3, 3))
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    assert np.array_equal(is_psd_3x3(C), np.linalg.eigvalsh(C)[:, 0] >= 0)


def test_good_information_is_inverted_as_before():
    rng = np.random.default_rng(1)
    H = _random_spd(rng, 50, 3)
    assert np.array_equal(inverse_information_3x3(H, 1e-9), np.linalg.inv(H + 1e-9 * np.eye(3)))


def test_broken_blocks_become_psd_and_keep_their_good_neighbours():
    rng = np.random.default_rng(2)
    C = _random_spd(rng, 10, 3)
    C[3] = np.diag([1.0, -2.0, 3.0])                 # what a rounded inverse can return
    out = psd_blocks_3x3(C)
    assert is_psd_3x3(out).all()
    assert np.array_equal(np.delete(out, 3, 0), np.delete(C, 3, 0))
    assert np.allclose(out[3], np.diag([1.0, 0.0, 3.0]))


def test_singular_information_gets_a_huge_variance_not_a_negative_one():
    d = np.array([0.0, 0.0, 1.0])
    H = np.eye(3)[None] - np.outer(d, d)[None]       # nothing along d
    C = spd_inverse(H, 1e-9)
    assert np.linalg.eigvalsh(C[0])[0] > 0
    assert d @ C[0] @ d > 1e8


def test_nearest_psd_is_identity_on_a_covariance_and_clips_otherwise():
    rng = np.random.default_rng(3)
    P = _random_spd(rng, 1, 6)[0]
    P = 0.5 * (P + P.T)
    assert nearest_psd(P) is P
    bad = P - 2 * np.linalg.eigvalsh(P)[0] * np.eye(6)
    fixed = nearest_psd(bad)
    assert np.linalg.eigvalsh(fixed)[0] >= -1e-12 * np.abs(fixed).max()
