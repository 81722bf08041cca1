"""FeatureTracker on synthetic textures with known motion, and on real KITTI frames."""
from __future__ import annotations

import glob
import json
import os

import cv2
import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.features import FeatureTracker, Tracks

DATA = os.path.join(os.path.dirname(__file__), '..', '..', 'shared', 'data', 'kitti06_f0-50')
W, H = 640, 480


def texture(h: int, w: int, seed: int) -> np.ndarray:
    """Smooth multi-octave value noise, uint8, textured everywhere (corners in every cell)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float64)
    for s in (4, 8, 16, 32, 64, 128):
        n = rng.random((h // s + 3, w // s + 3))
        up = cv2.resize(n, ((w // s + 3) * s, (h // s + 3) * s), interpolation=cv2.INTER_CUBIC)
        img += up[s:s + h, s:s + w] * s
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img.astype(np.uint8)


BIG = texture(1000, 1400, 7)


def shifted(dx: float, dy: float, w: int = W, h: int = H, base: np.ndarray = BIG
            ) -> np.ndarray:
    """A w x h view of `base` whose content sits at +(dx, dy) relative to view (200, 200):
    a scene point at frame pixel p in shifted(0, 0) is at p + (dx, dy) here."""
    M = np.float32([[1, 0, dx - 200], [0, 1, dy - 200]])
    return cv2.warpAffine(base, M, (w, h), flags=cv2.INTER_LINEAR)


def match(a: Tracks, b: Tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    return ids, ia, ib


def test_subpixel_shift_is_recovered() -> None:
    tr = FeatureTracker(VoConfig())
    t0 = tr.track(shifted(0.0, 0.0))
    t1 = tr.track(shifted(3.37, -2.61))
    ids, i0, i1 = match(t0, t1)
    assert len(ids) > 0.9 * len(t0)
    err = np.linalg.norm(t1.px[i1] - t0.px[i0] - [3.37, -2.61], axis=1)
    assert np.median(err) < 0.1
    assert np.percentile(err, 90) < 0.3


def test_large_translation_uses_the_pyramid() -> None:
    tr = FeatureTracker(VoConfig())
    t0 = tr.track(shifted(0.0, 0.0))
    t1 = tr.track(shifted(60.0, 8.0))
    ids, i0, i1 = match(t0, t1)
    stays = (t0.px[:, 0] + 60 < W - 15) & (t0.px[:, 1] + 8 < H - 15)
    assert len(ids) >= 0.85 * stays.sum()
    err = np.linalg.norm(t1.px[i1] - t0.px[i0] - [60.0, 8.0], axis=1)
    assert np.median(err) < 0.1


def test_prediction_extends_the_capture_range() -> None:
    cfg = VoConfig(klt_pyramid_levels=2)       # capture range ~10 * 4 = 40 px
    shift = np.array([90.0, 0.0])
    plain = FeatureTracker(cfg)
    p0 = plain.track(shifted(0.0, 0.0))
    p1 = plain.track(shifted(*shift))
    n_plain = len(match(p0, p1)[0])

    tr = FeatureTracker(cfg)
    t0 = tr.track(shifted(0.0, 0.0))
    rng = np.random.default_rng(3)
    guess = t0.px + shift + rng.normal(0.0, 2.0, t0.px.shape)     # a 2 px-noisy prior
    t1 = tr.track(shifted(*shift), predicted=(t0.ids, guess))
    ids, i0, i1 = match(t0, t1)
    stays = t0.px[:, 0] + shift[0] < W - 15
    assert tr.stats.n_predicted == len(t0)
    assert len(ids) >= 0.85 * stays.sum()
    assert len(ids) > 2 * n_plain
    err = np.linalg.norm(t1.px[i1] - t0.px[i0] - shift, axis=1)
    assert np.median(err) < 0.1


def test_bad_prediction_falls_back_to_plain_klt() -> None:
    tr = FeatureTracker(VoConfig())
    t0 = tr.track(shifted(0.0, 0.0))
    wrong = {int(i): (float(u) - 40.0, float(v) + 35.0) for i, (u, v) in zip(t0.ids, t0.px)}
    t1 = tr.track(shifted(4.0, 1.0), predicted=wrong)
    ids, i0, i1 = match(t0, t1)
    assert len(ids) > 0.9 * len(t0)
    err = np.linalg.norm(t1.px[i1] - t0.px[i0] - [4.0, 1.0], axis=1)
    assert np.median(err) < 0.1


def test_ids_unique_stable_and_never_reused() -> None:
    cfg = VoConfig()
    tr = FeatureTracker(cfg)
    rng = np.random.default_rng(11)
    pos = np.zeros(2)
    prev = tr.track(shifted(*pos))
    seen = set(prev.ids.tolist())
    assert prev.n_new == len(prev) and np.all(prev.age == 0)
    for _ in range(12):
        step = rng.normal(0.0, 12.0, 2)
        pos = pos + step
        cur = tr.track(shifted(*pos))
        assert cur.ids.dtype == np.int64 and cur.px.dtype == np.float64
        assert cur.age.dtype == np.int32
        assert np.all(np.diff(cur.ids) > 0)                  # unique, ascending
        ids, ip, ic = match(prev, cur)
        assert np.all(cur.age[ic] == prev.age[ip] + 1)
        err = np.linalg.norm(cur.px[ic] - prev.px[ip] - step, axis=1)
        assert np.percentile(err, 95) < 0.5                   # same id, same scene point
        new = cur.ids[cur.age == 0]
        assert len(new) == cur.n_new
        assert np.all(cur.ids[-cur.n_new:] == new) if cur.n_new else True
        assert not (set(new.tolist()) & seen)                 # never reused
        assert cur.n_lost == len(prev) - len(ids)
        seen |= set(new.tolist())
        prev = cur
    tr.reset()
    after = tr.track(shifted(*pos))
    assert after.ids.min() > max(seen)                        # not even after reset


def test_redetection_keeps_the_count_near_max_features() -> None:
    cfg = VoConfig(max_features=200)
    tr = FeatureTracker(cfg)
    counts = []
    for k in range(15):                                       # 14 px / frame to the left:
        t = tr.track(shifted(-14.0 * k, 0.0))                 # tracks leave on one side
        counts.append(len(t))
        assert len(t) <= cfg.max_features
    assert min(counts) >= 0.9 * cfg.redetect_ratio * cfg.max_features
    assert np.mean(counts) >= 0.85 * cfg.max_features


def test_bucketing_fills_every_cell_and_keeps_min_distance() -> None:
    cfg = VoConfig()
    tr = FeatureTracker(cfg)
    t = tr.track(shifted(0.0, 0.0))
    assert len(t) >= 0.95 * cfg.max_features
    r = np.minimum((t.px[:, 1] / H * cfg.grid_rows).astype(int), cfg.grid_rows - 1)
    c = np.minimum((t.px[:, 0] / W * cfg.grid_cols).astype(int), cfg.grid_cols - 1)
    per_cell = np.bincount(r * cfg.grid_cols + c, minlength=cfg.grid_rows * cfg.grid_cols)
    assert per_cell.min() > 0
    assert per_cell.max() <= 2 * np.ceil(cfg.max_features / per_cell.size)
    d = np.linalg.norm(t.px[:, None] - t.px[None], axis=2) + np.eye(len(t)) * 1e9
    assert d.min() >= cfg.min_feature_distance_px - 1.0
    # Top-up detections keep the distance to live tracks too.
    t2 = tr.track(shifted(-100.0, 0.0))
    assert t2.n_new > 0
    d2 = np.linalg.norm(t2.px[:, None] - t2.px[None], axis=2) + np.eye(len(t2)) * 1e9
    assert d2[-t2.n_new:].min() >= cfg.min_feature_distance_px - 1.5


@pytest.mark.parametrize('image', [
    np.zeros((H, W), np.uint8),
    np.full((H, W), 128, np.uint8),
    np.full((370, 1226), 255, np.uint8),
    np.random.default_rng(0).integers(0, 3, (H, W)).astype(np.uint8),   # dark sensor noise
    np.zeros((15, 200), np.uint8),                                      # too small
    np.zeros((0, 0), np.uint8),
    np.zeros((H, W), np.float32),                                       # wrong dtype
])
def test_degenerate_frames_give_zero_tracks(image: np.ndarray) -> None:
    tr = FeatureTracker(VoConfig())
    before = tr.track(shifted(0.0, 0.0))
    t = tr.track(image)
    assert len(t) == 0 and t.px.shape == (0, 2) and t.n_lost == len(before)
    assert tr.stats.rejected_frame
    again = tr.track(shifted(0.0, 0.0))                 # recovers with fresh detections
    assert len(again) > 0 and again.ids.min() > before.ids.max()


@pytest.mark.parametrize('shape', [(16, 16), (17, 40), (64, 48), (370, 1226)])
def test_any_valid_size_works(shape: tuple[int, int]) -> None:
    tr = FeatureTracker(VoConfig())
    img = texture(shape[0], shape[1], 5)
    for dx in (0.0, 1.0):
        t = tr.track(np.ascontiguousarray(shifted(dx, 0.0, shape[1], shape[0], BIG)))
        assert len(t) == len(t.ids) == len(t.px) == len(t.age)
    assert tr.track(img) is not None


def test_image_size_change_resets_tracks() -> None:
    tr = FeatureTracker(VoConfig())
    a = tr.track(shifted(0.0, 0.0))
    b = tr.track(shifted(0.0, 0.0, 320, 240))
    assert b.n_new == len(b) and b.n_lost == len(a)


def test_clahe_option_tracks_dark_frames() -> None:
    cfg = VoConfig()
    cfg.clahe_clip_limit = 3.0          # not a VoConfig field yet: read with getattr
    dark = (BIG.astype(np.float32) * (12.0 / 255.0)).astype(np.uint8)   # grey 0..12
    tr = FeatureTracker(cfg)
    t0 = tr.track(shifted(0.0, 0.0, base=dark))
    t1 = tr.track(shifted(2.0, 1.0, base=dark))
    assert len(t0) > 100
    ids, i0, i1 = match(t0, t1)
    assert len(ids) > 0.8 * len(t0)


def test_stats_are_reported() -> None:
    tr = FeatureTracker(VoConfig())
    tr.track(shifted(0.0, 0.0))
    s = tr.stats
    assert s.detect_ms > 0 and s.track_ms == 0.0 and s.n_new == s.n_tracked
    tr.track(shifted(1.0, 0.0))
    assert tr.stats.track_ms > 0 and tr.stats.total_ms >= tr.stats.track_ms


@pytest.mark.data
def test_kitti_frames_track_with_epipolar_consistency() -> None:
    files = sorted(glob.glob(os.path.join(DATA, 'image_0', '*.png')))
    if len(files) < 5:
        pytest.skip('../shared/data absent')
    with open(os.path.join(DATA, 'camera.json'), encoding='utf-8') as f:
        cam = json.load(f)
    K = np.array([[cam['fx'], 0, cam['cx']], [0, cam['fy'], cam['cy']], [0, 0, 1.0]])
    tr = FeatureTracker(VoConfig())
    prev = None
    for name in files[:5]:
        cur = tr.track(cv2.imread(name, cv2.IMREAD_GRAYSCALE))
        if prev is not None:
            ids, ip, ic = match(prev, cur)
            assert len(ids) >= 150
            # rectified, undistorted: raw pixels are ideal pixels here
            _, inl = cv2.findEssentialMat(prev.px[ip], cur.px[ic], K, method=cv2.RANSAC,
                                          prob=0.999, threshold=1.0)
            assert inl.mean() > 0.7
        prev = cur


@pytest.mark.data
def test_the_large_window_retry_can_wait_for_finish() -> None:
    """With `needed_ids`, the lost tracks nobody needs yet are tried again with the large
    window in finish(), after the pose (docs/method.md §17.3): before it, every needed
    track KLT keeps is there at its pixel and only tracks of the others are missing;
    after it, the same tracks, pixels, ages and counts as without waiting. When fewer
    than `min_needed` needed tracks are kept, nothing waits."""
    files = sorted(glob.glob(os.path.join(DATA, 'image_0', '*.png')))
    if len(files) < 12:
        pytest.skip('../shared/data absent')
    whole, split, short = (FeatureTracker(VoConfig()) for _ in range(3))
    waited = 0
    for name in files[:12]:
        gray = cv2.imread(name, cv2.IMREAD_GRAYSCALE)
        needed = split.live_ids[::2].copy()          # say, the tracks with a map point
        a = whole.track(gray)
        half = split.track(gray, finish=False, needed_ids=needed)
        here = np.isin(a.ids, half.ids)
        np.testing.assert_array_equal(a.ids[here], half.ids)
        np.testing.assert_array_equal(a.px[here], half.px)
        assert np.isin(a.ids[~here][:len(a) - a.n_new], needed).sum() == 0
        waited += int((~here).sum()) - a.n_new
        b = split.finish()
        for x, y in ((a.ids, b.ids), (a.px, b.px), (a.age, b.age)):
            np.testing.assert_array_equal(x, y)
        assert (b.n_new, b.n_lost) == (a.n_new, a.n_lost)
        for field in ('n_tracked', 'n_lost', 'n_klt_failed', 'n_fb_rejected',
                      'n_border_rejected', 'n_wide_tried', 'n_wide_kept'):
            assert getattr(split.stats, field) == getattr(whole.stats, field), field
        now = short.track(gray, finish=False, needed_ids=needed, min_needed=10 ** 6)
        np.testing.assert_array_equal(now.ids, a.ids[:len(a) - a.n_new])
        short.finish()
    assert waited > 0 and whole.stats.n_wide_tried > 0


def test_detection_split_over_two_threads_finds_the_same_corners(monkeypatch) -> None:
    """Half the cells go to a helper thread (docs/method.md §17.8): same corners, same
    order, as one thread; and close() stops the helper without ending the tracker."""
    import ekf_vo.core.features as features
    frames = [shifted(0.0, 0.0), shifted(-40.0, 3.0), shifted(-90.0, 7.0)]

    def run(min_cells: int) -> list[Tracks]:
        monkeypatch.setattr(features, '_PARALLEL_MIN_CELLS', min_cells)
        tr = FeatureTracker(VoConfig())
        out = [tr.track(f) for f in frames]
        assert (tr._pool is not None) == (min_cells <= VoConfig().grid_rows *
                                          VoConfig().grid_cols)
        tr.close()
        assert tr._pool is None
        out.append(tr.track(shifted(-120.0, 9.0)))      # works after close()
        tr.close()
        return out

    one, two = run(10 ** 6), run(1)
    for a, b in zip(one, two):
        assert a.n_new == b.n_new
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.px, b.px)
    assert sum(t.n_new for t in one[1:]) > 0        # top-ups ran, not only the first frame


def test_the_new_corners_can_wait_for_finish() -> None:
    """track(finish=False) returns the tracks KLT kept and no new corner; finish() adds
    the corners track() would have (same ids, pixels, ages, counts), and the next track,
    adopt or reset finishes a frame nobody finished, so the ids never change."""
    frames = [shifted(2.0 * k, -1.5 * k) for k in range(6)]
    # the view moves on: some tracks leave it, and each frame tops them up
    frames += [shifted(30.0 + 25.0 * k, 0.0) for k in range(4)]
    whole, split, lazy = (FeatureTracker(VoConfig()) for _ in range(3))
    topped_up = []
    for k, gray in enumerate(frames):
        a = whole.track(gray)
        topped_up.append(a.n_new if k else 0)
        half = split.track(gray, finish=False)
        assert half.n_new == 0 and not np.isin(half.ids, a.ids[len(a) - a.n_new:]).any()
        np.testing.assert_array_equal(half.ids, a.ids[:len(half)])
        np.testing.assert_array_equal(half.px, a.px[:len(half)])
        assert half.n_lost == a.n_lost
        b = split.finish()
        for x, y in ((a.ids, b.ids), (a.px, b.px), (a.age, b.age)):
            np.testing.assert_array_equal(x, y)
        assert (b.n_new, b.n_lost) == (a.n_new, a.n_lost)
        assert split.stats.n_tracked == whole.stats.n_tracked == len(a)
        assert split.finish().n_new == b.n_new           # nothing left: the same tracks
        lazy.track(gray, finish=False)        # never finished: the next call does it
    assert sum(topped_up) > 0 and whole.stats.n_new > 0
    assert lazy.next_id == whole.next_id - whole.stats.n_new     # the last is pending
    lazy.reset()
    assert lazy.next_id == whole.next_id
    # adopt finishes first too: the pending corners, then the adopted track
    split.track(frames[0], finish=False)
    n_before = split.next_id
    live = split.adopt(np.array([10 ** 6]), np.array([[320.0, 240.0]]))
    assert split.next_id > n_before and live.ids[-1] == 10 ** 6
