"""Landmark map bookkeeping: lookup, culling of repeated outliers, bounded size, changes."""
import numpy as np

from ekf_vo.core.map import LandmarkMap


def test_lookup_and_changes():
    m = LandmarkMap(max_points=100, cull_after_misses=3)
    m.add(np.array([5, 7, 9]), np.arange(9.0).reshape(3, 3), frame_index=0)
    mask, X = m.lookup(np.array([1, 7, 9]))
    assert mask.tolist() == [False, True, True]
    assert np.allclose(X, [[3, 4, 5], [6, 7, 8]])
    ch = m.pop_changes()
    assert sorted(ch.ids.tolist()) == [5, 7, 9] and len(ch.removed_ids) == 0
    assert len(m.pop_changes().ids) == 0


def test_repeated_outliers_are_culled_and_reported():
    m = LandmarkMap(max_points=100, cull_after_misses=3)
    m.add(np.array([1, 2]), np.zeros((2, 3)), 0)
    m.pop_changes()
    for k in range(3):
        culled = m.record_observations(np.array([1, 2]), np.array([True, False]), k)
    assert culled.tolist() == [2]
    assert m.contains(np.array([1, 2])).tolist() == [True, False]
    assert m.pop_changes().removed_ids.tolist() == [2]
    # an inlier verdict resets the miss count
    m.record_observations(np.array([1]), np.array([False]), 5)
    m.record_observations(np.array([1]), np.array([True]), 6)
    m.record_observations(np.array([1]), np.array([False]), 7)
    m.record_observations(np.array([1]), np.array([False]), 8)
    assert m.contains(np.array([1])).all()


def test_size_stays_bounded_oldest_unseen_first():
    m = LandmarkMap(max_points=50, cull_after_misses=3)
    for frame in range(40):
        ids = np.arange(frame * 10, frame * 10 + 10)
        m.add(ids, np.random.default_rng(frame).normal(size=(10, 3)), frame)
        assert len(m) <= 50
    # the newest points survive
    assert m.contains(np.arange(390, 400)).all()
    assert not m.contains(np.arange(0, 10)).any()
    assert len(m.ids) == len(set(m.ids.tolist())) == 50
