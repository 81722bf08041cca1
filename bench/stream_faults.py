"""What a camera driver does to a stream, applied to a rendered sequence (bench.rotation_nees
suffixes ``_repeat``, ``_jitter``, ``_flicker``; docs/ros.md §5, §7, §8, docs/method.md
§3.5, §6.1). Each takes and returns [(stamp ns, image, T_world_cam)], in stamp order; the
ground truth of a frame stays that of the image it carries.

- ``repeat``: each frame, with probability REPEAT_SHARE, sent again half a frame later
  (a driver whose camera runs slower than it publishes, or a relay);
- ``jitter``: every stamp moved by N(0, JITTER_S) (a driver that stamps on arrival);
- ``flicker``: every image scaled by a gain uniform in 1 +- FLICKER_GAIN (lamps at the
  mains frequency, an auto-exposure that hunts).
"""
from __future__ import annotations

import numpy as np

REPEAT_SHARE = 0.2
JITTER_S = 0.005
FLICKER_GAIN = 0.1


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


def flicker(seq: list, rng: np.random.Generator) -> list:
    out = []
    for t, im, T in seq:
        gain = 1.0 + FLICKER_GAIN * rng.uniform(-1.0, 1.0)
        out.append((t, np.clip(im.astype(np.float32) * gain, 0, 255).astype(np.uint8), T))
    return out


FAULTS = {'repeat': repeat, 'jitter': jitter, 'flicker': flicker}


def apply(name: str, seq: list, seed: int) -> list:
    """The fault `name` applied to `seq` with its own random stream of `seed`."""
    return FAULTS[name](seq, np.random.default_rng([seed, 77]))
