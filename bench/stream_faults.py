"""What a camera, its driver or its mounting does to a stream, applied to a rendered
sequence (bench.rotation_nees suffixes ``_repeat``, ``_jitter``, ``_flicker``,
``_exposure``, ``_overlay``, ``_body``, ``_hotpixels``, ``_dark``, ``_vignette``;
docs/ros.md §5, §7, §8, docs/method.md §3.5, §6.1, §6.10). Each takes and returns
[(stamp ns, image, T_world_cam)], in stamp order; the ground truth of a frame stays that
of the image it carries.

- ``repeat``: each frame, with probability REPEAT_SHARE, sent again half a frame later
  (a driver whose camera runs slower than it publishes, or a relay);
- ``jitter``: every stamp moved by N(0, JITTER_S) (a driver that stamps on arrival);
- ``flicker``: every image scaled by a gain uniform in 1 +- FLICKER_GAIN (lamps at the
  mains frequency, an auto-exposure that hunts);
- ``exposure``: the scene's light jumps now and then (a door, a shadow, a cloud) and the
  camera's auto-exposure brings the image back, overshooting a little (EXPOSURE_*);
- ``overlay``: a clock burned into the top-left corner (a dashcam, a security camera);
- ``body``: the vehicle's own body over the bottom BODY_SHARE of the view;
- ``hotpixels``: stuck bright and dead sensor pixels;
- ``dark``: a dim scene, DARK_GAIN of the brightness with DARK_NOISE of sensor noise;
- ``vignette``: a lens's fall-off to half the brightness in the corners.
"""
from __future__ import annotations

import cv2
import numpy as np

REPEAT_SHARE = 0.2
JITTER_S = 0.005
FLICKER_GAIN = 0.1
#: the auto-exposure: the light jumps on average every EXPOSURE_JUMP_FRAMES frames by a
#: factor whose log is uniform within +-log(EXPOSURE_JUMP_MAX); the exposure answers as a
#: damped second-order loop, rate <- A rate + B error, in log units (settles in about 8
#: frames, undershooting by 5 %; a 2x jump shows as 1.84, then 1.63, 1.43, 1.26, ...)
EXPOSURE_JUMP_FRAMES, EXPOSURE_JUMP_MAX = 60, 2.0
EXPOSURE_LOOP_A, EXPOSURE_LOOP_B = 0.6, 0.12


def repeat(seq: list, rng: np.random.Generator) -> list:
    dt = seq[1][0] - seq[0][0]
    out = []
    for t, im, T in seq:
        out.append((t, im, T))
        if rng.random() < REPEAT_SHARE:
            out.append((t + dt // 2, im, T))
    return out


def jitter(seq: list, rng: np.random.Generator) -> list:
    out = [(t + int(rng.normal(0.0, JITTER_S * 1e3) * 1e6), im, T) for t, im, T in seq]
    return sorted(out, key=lambda f: f[0])


def _each_image(seq: list, change) -> list:
    """`seq` with each image replaced by change(stamp ns, image), in stamp order (a
    random draw inside `change` is made frame after frame)."""
    return [(t, change(t, im), T) for t, im, T in seq]


def flicker(seq: list, rng: np.random.Generator) -> list:
    def scaled(t, im):
        gain = 1.0 + FLICKER_GAIN * rng.uniform(-1.0, 1.0)
        return np.clip(im.astype(np.float32) * gain, 0, 255).astype(np.uint8)
    return _each_image(seq, scaled)


def exposure(seq: list, rng: np.random.Generator) -> list:
    """The light jumps now and then; the auto-exposure brings the image back (EXPOSURE_*;
    the image is scaled by light x exposure and clipped, as a sensor saturates)."""
    log_light, log_exposure, rate = 0.0, 0.0, 0.0

    def exposed(t, im):
        nonlocal log_light, log_exposure, rate
        if rng.uniform() < 1.0 / EXPOSURE_JUMP_FRAMES:
            log_light += np.log(EXPOSURE_JUMP_MAX) * rng.uniform(-1.0, 1.0)
        rate = EXPOSURE_LOOP_A * rate + EXPOSURE_LOOP_B * (-log_light - log_exposure)
        log_exposure += rate
        gain = np.exp(log_light + log_exposure)
        return np.clip(im.astype(np.float32) * gain, 0, 255).astype(np.uint8)
    return _each_image(seq, exposed)


#: the burned-in clock's text height as a share of the image height
OVERLAY_HEIGHT = 0.06
#: the share of the image, at the bottom, that the vehicle's own body covers
BODY_SHARE = 0.15
#: the share of pixels of a sensor's defects (stuck bright, or dead)
HOT_PIXEL_SHARE = 0.001
#: a dim scene: the exposure's gain, and the sensor noise that then shows [grey levels]
DARK_GAIN, DARK_NOISE = 0.2, 2.0
#: the lens's loss of brightness in the corners
VIGNETTE_DROP = 0.5


def overlay(seq: list, rng: np.random.Generator) -> list:
    """A clock burned into the image (a dashcam's or a security camera's): white text on a
    black box in the top-left corner, its seconds and milliseconds changing every frame."""
    def stamped(t, im):
        im = im.copy()
        scale = OVERLAY_HEIGHT * im.shape[0] / 22.0
        text = f'2026-11-26 16:{(t // 60_000_000_000) % 60:02d}:{(t // 1_000_000_000) % 60:02d}' \
               f'.{(t // 1_000_000) % 1000:03d}'
        (w, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
        cv2.rectangle(im, (0, 0), (w + 8, th + base + 8), 0, -1)
        cv2.putText(im, text, (4, th + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 2)
        return im
    return _each_image(seq, stamped)


def body(seq: list, rng: np.random.Generator) -> list:
    """The vehicle's own body in the bottom BODY_SHARE of the view (a car's bonnet, a
    robot's bumper): a fixed texture that moves with the camera."""
    h, w = seq[0][1].shape[:2]
    rows = int(round(BODY_SHARE * h))
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (rows, w)).astype(np.float32), (0, 0), 2.0)
    tex = np.clip((tex - tex.mean()) * 4.0 + 90.0, 0, 255).astype(np.uint8)

    def covered(t, im):
        im = im.copy()
        im[h - rows:] = tex
        return im
    return _each_image(seq, covered)


def hotpixels(seq: list, rng: np.random.Generator) -> list:
    """Sensor defects: HOT_PIXEL_SHARE of the pixels stuck bright, as many dead."""
    h, w = seq[0][1].shape[:2]
    n = int(HOT_PIXEL_SHARE * h * w)
    hot = (rng.integers(0, h, n), rng.integers(0, w, n))
    dead = (rng.integers(0, h, n), rng.integers(0, w, n))

    def defective(t, im):
        im = im.copy()
        im[hot] = 255
        im[dead] = 0
        return im
    return _each_image(seq, defective)


def dark(seq: list, rng: np.random.Generator) -> list:
    """A dim scene: the image at DARK_GAIN of its brightness, with DARK_NOISE of noise."""
    def dimmed(t, im):
        noisy = im.astype(np.float32) * DARK_GAIN + rng.normal(0.0, DARK_NOISE, im.shape)
        return np.clip(noisy, 0, 255).astype(np.uint8)
    return _each_image(seq, dimmed)


def vignette(seq: list, rng: np.random.Generator) -> list:
    """A lens's fall-off: a gain of 1 - VIGNETTE_DROP r^2, r the distance from the centre
    over the half-diagonal (half the brightness in the corners)."""
    h, w = seq[0][1].shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((u - w / 2) ** 2 + (v - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    gain = 1.0 - VIGNETTE_DROP * r2
    return _each_image(seq, lambda t, im: np.clip(im * gain, 0, 255).astype(np.uint8))


FAULTS = {'repeat': repeat, 'jitter': jitter, 'flicker': flicker, 'exposure': exposure,
          'overlay': overlay, 'body': body, 'hotpixels': hotpixels, 'dark': dark,
          'vignette': vignette}


def apply(name: str, seq: list, seed: int) -> list:
    """The fault `name` applied to `seq` with its own random stream of `seed`."""
    return FAULTS[name](seq, np.random.default_rng([seed, 77]))
