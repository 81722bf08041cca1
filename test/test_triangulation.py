"""Two-view triangulation (core/triangulation.py): one first view, or one per point."""
import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.core.local_ba import point_covariances
from ekf_vo.core.triangulation import (TriangulationResult, depth_debiased,
                                       triangulate_points, triangulate_points_from)

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _pose(rotvec_deg, centre):
    """T_cam_world of a camera at `centre` turned by rotvec_deg."""
    R_wc = geo.quat_to_matrix(geo.rotvec_to_quat(np.radians(rotvec_deg)))
    return geo.invert_T(geo.make_T(R_wc, np.asarray(centre, float)))


def _project(T_cw, X, rng):
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * K[0, 0] + K[:2, 2] + rng.normal(0, 0.3, (len(X), 2))


def test_points_first_seen_from_several_views_are_triangulated_as_view_by_view():
    """Map growth triangulates the candidates of several first frames at once: each
    point comes out as triangulate_points gives it from its own first view (the same
    DLT, the same checks; the first view's projection in one pass differs by rounding),
    with behind-camera, far and garbled points refused alike, and the same order."""
    rng = np.random.default_rng(0)
    X = np.column_stack((rng.uniform(-2, 2, 90), rng.uniform(-1, 1, 90),
                         rng.uniform(3, 9, 90)))
    X[5] = [0.0, 0.0, -4.0]                    # behind every camera
    X[6] = [0.0, 0.0, 5000.0]                  # too far for parallax
    firsts = [_pose([0, 0, 0], [0, 0, 0]), _pose([0, 3, 0], [0.3, 0, 0]),
              _pose([1, -2, 0], [-0.2, 0.1, 0.2])]
    now = _pose([0, 8, 1], [0.9, 0.05, 0.4])
    first = rng.integers(0, 3, 90)
    px1 = np.array([_project(firsts[v], X[i:i + 1], rng)[0] for i, v in enumerate(first)])
    px2 = _project(now, X, rng)
    px2[7] += 25.0                             # a garbled track
    batch = triangulate_points_from(firsts, first, now, px1, px2, K, 2.0, 1.0)
    assert isinstance(batch, TriangulationResult)
    for v in range(3):
        rows = first == v
        one = triangulate_points(firsts[v], now, px1[rows], px2[rows], K, 2.0, 1.0)
        np.testing.assert_array_equal(batch.valid[rows], one.valid)
        np.testing.assert_array_equal(batch.X_world[rows], one.X_world)
        np.testing.assert_allclose(batch.reproj_err_px[rows], one.reproj_err_px,
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(batch.parallax_deg[rows], one.parallax_deg,
                                   rtol=1e-12, atol=1e-12)
    assert not batch.valid[[5, 6, 7]].any()
    assert batch.valid.sum() >= 80
    # the points' covariances with a first view per point are those view by view
    good = batch.valid
    T1 = np.stack(firsts)[first[good]]
    cov = point_covariances(batch.X_world[good], [T1, now], K, 1.0)
    for v in range(3):
        rows = first[good] == v
        ref = point_covariances(batch.X_world[good][rows], [firsts[v], now], K, 1.0)
        np.testing.assert_allclose(cov[rows], ref, rtol=1e-9, atol=1e-15)


def test_mismatched_inputs_are_refused():
    now = _pose([0, 0, 0], [1, 0, 0])
    with pytest.raises(ValueError):
        triangulate_points_from([now], np.zeros(3, int), now, np.zeros((2, 2)),
                                np.zeros((2, 2)), K, 2.0, 1.0)
    empty = triangulate_points_from([], np.zeros(0, int), now, np.zeros((0, 2)),
                                    np.zeros((0, 2)), K, 2.0, 1.0)
    assert empty.X_world.shape == (0, 3) and empty.valid.shape == (0,)


def _small_parallax_draws(sigma_px, n=4000, seed=3):
    """n noisy two-view observations of points 10 m ahead seen across a 0.25 m baseline
    (about 1.4 deg of parallax, a just-born map point), sigma_px Gaussian pixel noise."""
    rng = np.random.default_rng(seed)
    X = np.column_stack((rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n), np.full(n, 10.0)))
    T1, T2 = _pose([0, 0, 0], [0, 0, 0]), _pose([0, 0, 0], [0.25, 0, 0])
    clean = lambda T: (X @ T[:3, :3].T + T[:3, 3])[:, :2] / 10.0 * K[0, 0] + K[:2, 2]
    px1 = clean(T1) + rng.normal(0, sigma_px, (n, 2))
    px2 = clean(T2) + rng.normal(0, sigma_px, (n, 2))
    return X, T1, T2, px1, px2


def test_summed_squared_residual_measures_the_pixel_noise():
    """Four coordinates fit by three unknowns: the two views' summed squared residual is
    sigma^2 times a chi-square of one dof, so its mean is the pixel variance (map growth's
    noise estimate for the depth correction, docs/method.md §7.2.1)."""
    for sigma in (0.3, 1.0):
        X, T1, T2, px1, px2 = _small_parallax_draws(sigma)
        tri = triangulate_points(T1, T2, px1, px2, K, 50.0, 0.0)
        assert tri.valid.all()
        assert np.mean(tri.sq_err_sum_px2) == pytest.approx(sigma ** 2, rel=0.08)


def test_depth_debiased_removes_the_small_parallax_depth_bias():
    """A depth from a small parallax is too long on average (E[b / (theta + e)] > b /
    theta); moved back by var(depth) / depth along its ray, the mean depth is right to
    within its standard error, and the uncorrected one is not."""
    sigma = 1.0
    X, T1, T2, px1, px2 = _small_parallax_draws(sigma, n=20000)
    tri = triangulate_points(T1, T2, px1, px2, K, 50.0, 0.0)
    keep = tri.valid & (tri.depth1 < 40.0)        # the gated map drops the far-off tail
    cov = point_covariances(tri.X_world[keep], [T1, T2], K, sigma)
    fixed = depth_debiased(tri.X_world[keep], np.zeros(3), cov)
    raw_err = tri.X_world[keep, 2] / X[keep, 2] - 1.0
    fixed_err = fixed[:, 2] / X[keep, 2] - 1.0
    stderr = fixed_err.std() / np.sqrt(keep.sum())
    assert raw_err.mean() > 5 * stderr                 # the bias is real and positive
    assert abs(fixed_err.mean()) < 3 * stderr
    assert abs(fixed_err.mean()) < 0.3 * raw_err.mean()


def test_depth_debiased_leaves_a_sharp_point_and_caps_a_vague_one():
    """The shift is var(depth) / depth: nothing for an exact point, never more than the
    cap for a hopeless one, and a NaN covariance moves nothing."""
    X = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [0.0, 1.0, 5.0]])
    cov = np.zeros((3, 3, 3))
    cov[1] = np.eye(3) * 1e6
    cov[2] = np.nan
    out = depth_debiased(X, np.zeros(3), cov, max_rel_shift=0.25)
    np.testing.assert_array_equal(out[0], X[0])
    np.testing.assert_allclose(np.linalg.norm(out[1]), 0.75 * np.linalg.norm(X[1]))
    np.testing.assert_array_equal(out[2], X[2])
