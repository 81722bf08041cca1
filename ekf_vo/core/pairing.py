"""Which calibration belongs to an image: CameraInfo and images paired by stamp.

image_transport's camera subscriber pairs each image with the CameraInfo of the same
stamp, whichever of the two arrives first. A camera driver publishes both with one stamp,
but in no fixed order: an ordinary publisher writes the image first. The rule here serves
`vo_node` and `ekf-vo-run` alike, through core.stream.VoStream:

- every CameraInfo is recorded with its stamp: valid (its PinholeCamera) or invalid
  (K = 0, NaN, ...: None);
- an image at stamp t uses the valid calibration with the largest stamp <= t, once a
  CameraInfo stamped t or later has arrived: before that it waits (the caller bounds the
  wait: the next image in a log, or a short time in a node, then it goes on with what
  there is);
- an image whose own CameraInfo (stamp t exactly) was invalid is rejected with it, and the
  last valid calibration stays;
- an image older than every valid CameraInfo uses the oldest one (the first image of a
  stream whose CameraInfo comes after it is not lost).
Pure Python; bounded memory (the last `keep` stamps).
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

from .camera import PinholeCamera


@dataclass(frozen=True)
class Pairing:
    """The verdict for one image: `camera` to use (None with `wait` or `invalid`)."""

    camera: PinholeCamera | None
    wait: bool = False       #: no CameraInfo at or after the image's stamp yet
    invalid: bool = False    #: the image's own CameraInfo was invalid: reject the image
    exact: bool = False      #: a valid CameraInfo of exactly this stamp


class CalibrationBook:
    """The recent CameraInfo stamps and their calibrations (see the module docstring)."""

    def __init__(self, keep: int = 256) -> None:
        self.keep = int(keep)
        self._stamps: list[int] = []                  # sorted
        self._cameras: list[PinholeCamera | None] = []  # None = invalid

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, camera: PinholeCamera | None) -> None:
        """Record the CameraInfo stamped `stamp_ns`: its camera, or None when invalid. A
        second one with the same stamp replaces the first."""
        stamp_ns = int(stamp_ns)
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            self._cameras[i] = camera
        else:
            self._stamps.insert(i, stamp_ns)
            self._cameras.insert(i, camera)
        if len(self._stamps) > self.keep:
            drop = len(self._stamps) - self.keep
            dropped = [(t, c) for t, c in zip(self._stamps[:drop], self._cameras[:drop])
                       if c is not None]
            del self._stamps[:drop]
            del self._cameras[:drop]
            if dropped and all(c is None for c in self._cameras):
                # the last valid calibration stays, however many invalid ones came since
                self._stamps.insert(0, dropped[-1][0])
                self._cameras.insert(0, dropped[-1][1])

    def pair(self, stamp_ns: int) -> Pairing:
        """The calibration of an image stamped `stamp_ns`."""
        stamp_ns = int(stamp_ns)
        i = bisect.bisect_right(self._stamps, stamp_ns)        # infos at or before: [:i]
        if i and self._stamps[i - 1] == stamp_ns and self._cameras[i - 1] is None:
            return Pairing(None, invalid=True)
        wait = not self._stamps or self._stamps[-1] < stamp_ns
        exact = bool(i) and self._stamps[i - 1] == stamp_ns
        for cam in reversed(self._cameras[:i]):
            if cam is not None:
                return Pairing(cam, wait=wait, exact=exact)
        for cam in self._cameras[i:]:          # older than every valid one: the oldest
            if cam is not None:
                return Pairing(cam, wait=wait)
        return Pairing(None, wait=True)
