"""Reader of the image-folder dataset layout (camera.json, images, groundtruth_tum.txt).

Layout: `camera.json` (fx fy cx cy, dist, width, height), `groundtruth_tum.txt`
(T_world_cam of the camera optical frame), the images, and their times in `times.txt`
(one per line, KITTI) or `frames.txt` (`t name` per line). Shared by the benchmarks and
`ekf-vo-convert folder`.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from .trajectory import read_tum

logger = logging.getLogger(__name__)


@dataclass
class FolderDataset:
    root: Path
    camera: dict            #: width, height, K (3x3), D, distortion_model
    images: list            #: image paths, in time order
    stamps_ns: np.ndarray   #: (N,) int64
    gt_stamps_s: np.ndarray | None
    gt_T_world_cam: np.ndarray | None

    def __len__(self) -> int:
        return len(self.images)

    def frames(self, limit: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """(stamp_ns, grey uint8 image) in order."""
        for k, path in enumerate(self.images[:limit]):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise IOError(f'cannot read {path}')
            yield int(self.stamps_ns[k]), gray

    def gt_at(self, k: int) -> np.ndarray | None:
        """Ground-truth T_world_cam of frame k (same index order as the images)."""
        if self.gt_T_world_cam is None:
            return None
        t = self.stamps_ns[k] * 1e-9
        j = int(np.argmin(np.abs(self.gt_stamps_s - t)))
        return self.gt_T_world_cam[j] if abs(self.gt_stamps_s[j] - t) < 1e-3 else None


def load_folder(root: str | Path) -> FolderDataset:
    root = Path(root)
    cam = json.loads((root / 'camera.json').read_text())
    K = np.array([[cam['fx'], 0, cam['cx']], [0, cam['fy'], cam['cy']], [0, 0, 1.0]])
    D = np.asarray(cam.get('dist', []), float)
    camera = {'width': int(cam['width']), 'height': int(cam['height']), 'K': K, 'D': D,
              'distortion_model': 'plumb_bob' if D.size else ''}
    if (root / 'frames.txt').exists():
        rows = [ln.split() for ln in (root / 'frames.txt').read_text().splitlines()
                if ln.strip() and not ln.startswith('#')]
        stamps = np.array([float(r[0]) for r in rows])
        images = [root / r[1] for r in rows]
    else:
        folder = next(p for p in (root / 'image_0', root / 'images', root) if p.is_dir())
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in ('.png', '.jpg'))
        stamps = np.loadtxt(root / 'times.txt', ndmin=1)[:len(images)]
    stamps_ns = np.round(stamps * 1e9).astype(np.int64)
    gt_s, gt_T = (None, None)
    if (root / 'groundtruth_tum.txt').exists():
        gt_s, gt_T = read_tum(root / 'groundtruth_tum.txt')
    return FolderDataset(root, camera, images, stamps_ns, gt_s, gt_T)
