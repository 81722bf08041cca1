"""Map points found again (core/refind.py) and the tracker's adoption of them."""
import cv2
import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.features import FeatureTracker
from ekf_vo.core.refind import Describer, hamming, match_in_windows


def _textured(seed=0, shape=(240, 320)):
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, shape[::-1], interpolation=cv2.INTER_NEAREST),
                            (3, 3), 0)


def test_hamming_counts_differing_bits():
    a = np.zeros((1, 32), np.uint8)
    b = np.zeros((2, 32), np.uint8)
    b[1, 0] = 0b1011
    assert hamming(a, b).tolist() == [[0, 3]]


def test_corners_are_found_again_after_the_image_moves():
    """Describe corners in one image, shift the image by (7, -4) px, predict each corner
    with a 2 px error: the search returns the shifted corner, and nothing for points whose
    window holds no match."""
    img = _textured()
    d = Describer()
    px = cv2.goodFeaturesToTrack(img, 60, 0.01, 10).reshape(-1, 2).astype(float)
    desc, rows = d.describe(img, px)
    px = px[rows]
    shift = np.array([7.0, -4.0])
    moved = cv2.warpAffine(img, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]),
                           img.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(1)
    pred = px + shift + rng.normal(0, 1.0, px.shape)
    corners = d.corners(moved)
    corner_desc, ok = d.describe(moved, corners)
    corners = corners[ok]
    match = match_in_windows(pred, np.full(len(pred), 5.0), desc, corners, corner_desc, 50)
    found = match >= 0
    assert found.mean() > 0.6
    err = np.linalg.norm(corners[match[found]] - (px[found] + shift), axis=1)
    assert np.median(err) < 0.5 and err.max() < 2.0
    # a prediction far from its corner finds nothing (not the nearest lookalike)
    far = match_in_windows(pred + 40.0, np.full(len(pred), 3.0), desc, corners,
                           corner_desc, 50)
    assert (far >= 0).mean() < 0.1


def test_the_tracker_adopts_found_tracks_under_their_old_ids():
    cfg = VoConfig()
    tracker = FeatureTracker(cfg)
    img = _textured(2)
    first = tracker.track(img)
    lost_ids = first.ids[:5]
    # pretend the first five ended: drop them, then adopt them back
    tracker._ids, tracker._px, tracker._age = (tracker._ids[5:], tracker._px[5:],
                                               tracker._age[5:])
    tracks = tracker.adopt(lost_ids, first.px[:5])
    assert np.all(np.diff(tracks.ids) > 0)
    assert set(lost_ids) <= set(tracks.ids)
    nxt = tracker.track(img)                  # the adopted tracks are followed onward
    assert set(lost_ids) <= set(nxt.ids)
    with pytest.raises(ValueError):
        tracker.adopt(nxt.ids[:1], nxt.px[:1])
