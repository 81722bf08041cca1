"""Image and CameraInfo paired by stamp (core/pairing.py), through the core's front door
(VoStream) and ekf-vo-run on real bags whose CameraInfo comes after its image."""
from __future__ import annotations

import numpy as np

from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pairing import CalibrationBook

K1 = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
CAM1 = PinholeCamera(640, 480, K1)
CAM2 = PinholeCamera(640, 480, K1 * [[1.1], [1.1], [1]])


def test_an_image_waits_for_the_camera_info_of_its_stamp():
    book = CalibrationBook()
    book.add(100, CAM1)
    p = book.pair(200)                      # its own CameraInfo has not come yet
    assert p.wait and p.camera is CAM1
    book.add(200, CAM2)
    p = book.pair(200)
    assert not p.wait and p.camera is CAM2


def test_an_image_before_every_camera_info_takes_the_first():
    book = CalibrationBook()
    assert book.pair(50).wait and book.pair(50).camera is None
    book.add(100, CAM1)
    p = book.pair(50)
    assert not p.wait and p.camera is CAM1


def test_an_invalid_camera_info_takes_its_image_with_it_and_the_last_valid_stays():
    book = CalibrationBook()
    book.add(100, CAM1)
    book.add(200, None)
    book.add(300, CAM1)
    assert book.pair(200).invalid
    p = book.pair(250)
    assert p.camera is CAM1 and not p.invalid and not p.wait


def test_camera_infos_at_other_stamps_serve_the_images_between_them():
    book = CalibrationBook()
    book.add(0, CAM1)
    book.add(1000, CAM2)
    assert book.pair(500).camera is CAM1 and not book.pair(500).wait
    assert book.pair(1500).camera is CAM2 and book.pair(1500).wait


def test_the_book_is_bounded():
    book = CalibrationBook(keep=8)
    for k in range(100):
        book.add(k, CAM1)
    assert len(book) == 8 and book.pair(99).camera is CAM1


def test_the_last_valid_calibration_outlives_a_run_of_invalid_ones():
    book = CalibrationBook(keep=8)
    book.add(0, CAM2)
    for k in range(1, 100):
        book.add(k, None)
    assert book.pair(99).invalid
    p = book.pair(150)
    assert p.camera is CAM2 and not p.invalid


# ---------------------------------------------------------------- ekf-vo-run on real bags
def _write_bag(path, info, frames, order, bad_info_at=None):
    """A rosbag2 of the demo's frames: each CameraInfo 'before' or 'after' its image;
    `bad_info_at`: the frame index whose CameraInfo has K = 0."""
    from ekf_vo.io.bag import CAMERA_INFO, BagWriter, camera_info_msg
    with BagWriter(path) as bag:
        for k, (stamp, gray) in enumerate(frames):
            def add_info():
                msg = camera_info_msg(info['width'], info['height'], info['K'], info['D'],
                                      info['distortion_model'], stamp, 'camera')
                if k == bad_info_at:
                    msg.k[:] = 0.0          # an uncalibrated driver's CameraInfo
                bag.write('/camera/camera_info', CAMERA_INFO, msg, stamp)
            if order == 'before':
                add_info()
            bag.add_image('/camera/image_raw', gray, stamp, 'camera')
            if order == 'after':
                add_info()
    return path


def test_the_message_order_does_not_change_the_run(tmp_path):
    """CameraInfo logged after its image (a live publisher's order) gives the same run as
    before it: the first image is not lost, the same frames are processed and the
    trajectories are identical."""
    from ekf_vo.tools.demo import load_demo_frames
    from ekf_vo.tools.run import run_bag
    info, frames = load_demo_frames()
    runs = {}
    for order in ('before', 'after'):
        bag = _write_bag(tmp_path / order, info, frames[:60], order)
        runs[order] = run_bag(bag, seed=0)
    a, b = runs['before'], runs['after']
    assert a.frames == b.frames == 60 and a.frames_skipped == b.frames_skipped == 0
    assert np.array_equal(a.est_stamps_s, b.est_stamps_s) and len(a.est_stamps_s) > 40
    assert np.allclose(np.array(a.est_T_world_cam), np.array(b.est_T_world_cam))


def test_an_invalid_camera_info_costs_only_its_own_image(tmp_path):
    """A CameraInfo with K = 0 mid-stream: its image is rejected with it, the last valid
    calibration stays, the estimator is not restarted and tracking goes on."""
    from ekf_vo.tools.demo import load_demo_frames
    from ekf_vo.tools.run import run_bag
    info, frames = load_demo_frames()
    for order in ('before', 'after'):
        s = run_bag(_write_bag(tmp_path / order, info, frames[:60], order, bad_info_at=30),
                    seed=0)
        assert s.frames == 59 and s.frames_skipped == 1, order
        assert s.n_resets == 0 and s.n_camera_changes == 0, order
        published = np.asarray(s.est_stamps_s)

        def was_published(stamp_ns):       # seconds as float64: compare to 1 us
            return bool(np.any(np.abs(published - stamp_ns * 1e-9) < 1e-6))
        assert not was_published(frames[30][0])
        assert all(was_published(f[0]) for f in frames[31:60]), order
