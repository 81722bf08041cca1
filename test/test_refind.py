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


def test_corners_in_a_mask_are_those_of_the_whole_frame():
    """Describer.corners searches only the mask's bounding box: on real images (the demo
    bag), with masks of scattered search windows like find_again's, the corners and their
    order are those of one Shi-Tomasi call over the whole frame with the same mask, also
    when a window touches the image border."""
    from ekf_vo.core import refind
    from ekf_vo.tools.demo import load_demo_frames
    _, frames = load_demo_frames()
    d = Describer()
    rng = np.random.default_rng(0)
    compared = 0
    for _, gray in frames[::60]:
        h, w = gray.shape
        for n_windows in (1, 5, 40):
            mask = np.zeros((h, w), np.uint8)
            centres = rng.uniform((0, 0), (w, h), (n_windows, 2)).astype(int)
            centres[0] = (w - 3, 2)                       # one window at a corner
            for (u, v), r in zip(centres.tolist(), rng.integers(4, 21, n_windows).tolist()):
                cv2.circle(mask, (u, v), r, 255, -1)
            whole = cv2.goodFeaturesToTrack(gray, 2000, refind._CORNER_QUALITY, 2.0,
                                            mask=mask, blockSize=3)
            whole = np.zeros((0, 2)) if whole is None else whole.reshape(-1, 2)
            got = d.corners(gray, mask)
            assert got.shape == whole.shape
            np.testing.assert_array_equal(got, whole)
            compared += len(got)
    assert compared > 100
    assert d.corners(frames[0][1], np.zeros(frames[0][1].shape, np.uint8)).shape == (0, 2)
