"""bench.map_usage's twins: an untracked map point is a tracked one's twin only when it is
near it both in the image and in 3D (docs/method.md §12.5). The figures themselves are
the benchmark's."""
import numpy as np

from bench.map_usage import TWIN_DEPTH_SHARE, TWIN_PX, twins


def _camera_points(X):
    """Pixels (fx = 500, centre 320, 240) and depths of points X (n,3) in a camera at the
    origin looking along +z."""
    X = np.asarray(X, float)
    return 500.0 * X[:, :2] / X[:, 2:] + (320.0, 240.0), X[:, 2]


def test_a_point_triangulated_again_next_to_its_old_self_is_a_twin():
    X = np.array([[0.0, 0.0, 10.0],            # tracked
                  [0.02, 0.0, 10.3]])          # untracked: 1 px away, 3 % deeper
    uv, depth = _camera_points(X)
    assert np.linalg.norm(uv[0] - uv[1]) < TWIN_PX
    assert twins(uv, X, depth, np.array([True, False])) == 1


def test_a_point_on_the_same_ray_at_another_depth_is_not_a_twin():
    # the same pixel, but twice as far: another surface seen behind the first
    X = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 20.0]])
    uv, depth = _camera_points(X)
    assert np.linalg.norm(X[1] - X[0]) > TWIN_DEPTH_SHARE * depth[0]
    assert twins(uv, X, depth, np.array([True, False])) == 0


def test_two_tracked_points_side_by_side_are_not_twins():
    # both measured this frame: two live tracks, not a point found twice
    X = np.array([[0.0, 0.0, 10.0], [0.02, 0.0, 10.0], [5.0, 0.0, 10.0]])
    uv, depth = _camera_points(X)
    assert twins(uv, X, depth, np.array([True, True, False])) == 0
    # and a point counts once however many twins it has
    X = np.array([[0.0, 0.0, 10.0], [0.02, 0.0, 10.0], [-0.02, 0.0, 10.0]])
    uv, depth = _camera_points(X)
    assert twins(uv, X, depth, np.array([True, False, False])) == 1
