"""Synthetic monocular sequences: a procedurally textured room seen by a moving pinhole camera.

Console script ``ekf-vo-synth OUT_BAG [options]`` writes a rosbag2 (MCAP) with
``/camera/image_raw`` (or ``/camera/image_raw/compressed``), ``/camera/camera_info`` and
``/ground_truth/pose`` (T_world_cam of the optical frame, frame_id ``world``), all with the
same stamps.  Library use (no bag)::

    cfg = SynthConfig(frames=100, seed=3)
    for stamp_ns, image, T_world_cam in render_sequence(cfg):
        ...

Conventions: world frame z up; camera optical frame z forward, x right, y down;
``T_a_b`` maps b-frame points into frame a; pixel (0, 0) is the centre of the top-left
pixel (OpenCV); quaternions are ``*_xyzw``.

Rendering: every scene surface is a textured rectangle, split into tiles of at most
``tile_m`` metres.  Each visible tile is clipped against the near plane (z > near in the
camera frame), its texture (mip level chosen from the tile's distance) is warped into the
image with the exact plane-induced homography (cv2.warpPerspective) inside the projected
clipped polygon, and a per-pixel inverse-depth z-buffer (inverse depth is affine in the
pixel coordinates on a plane) resolves occlusions.  Optional supersampling, plumb_bob
distortion (cv2 remap consistent with OpenCV's model), linear motion blur and Gaussian
intensity noise are applied afterwards.
"""
from __future__ import annotations

import argparse
import functools
import logging
import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)

EPOCH_NS = 1_700_000_000 * 1_000_000_000
"""Stamp of frame 0 (fixed so output is reproducible)."""

TRAJECTORIES = ('walk', 'orbit', 'figure8')

# Room: x in [-3.5, 3.5], y in [-2.75, 2.75], z in [0, 2.8] (metres, world frame, z up).
ROOM_MIN = np.array([-3.5, -2.75, 0.0])
ROOM_MAX = np.array([3.5, 2.75, 2.8])


# =========================================================================== scene
@dataclass
class Quad:
    """Textured rectangle ``origin + a * axis_u + b * axis_v``, a in [0, size_u], b in [0, size_v].

    ``normal = axis_u x axis_v`` points to the visible side (unless ``double_sided``).
    Texture texel (i, j) of mip level L has its centre at a = (i + .5) 2^L / ppm,
    b = (j + .5) 2^L / ppm (i: column along axis_u, j: row along axis_v).
    """

    name: str
    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size_u: float
    size_v: float
    texture: int
    double_sided: bool = False

    @property
    def normal(self) -> np.ndarray:
        """Unit normal on the visible side."""
        return np.cross(self.axis_u, self.axis_v)


@dataclass
class Scene:
    """Quads plus their textures (mip pyramids, level 0 at ``ppm`` texels per metre)."""

    quads: list[Quad]
    textures_bgr: list[np.ndarray]
    ppm: float
    _pyr: dict[tuple[int, bool], list[np.ndarray]] = field(default_factory=dict, repr=False)

    def pyramid(self, tex: int, color: bool) -> list[np.ndarray]:
        """Mip pyramid (cv2.pyrDown) of texture ``tex``, grey (uint8 HxW) or BGR."""
        key = (tex, color)
        if key not in self._pyr:
            img = self.textures_bgr[tex]
            if not color:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            levels = [img]
            while min(levels[-1].shape[:2]) > 16 and len(levels) < 7:
                levels.append(cv2.pyrDown(levels[-1]))
            self._pyr[key] = levels
        return self._pyr[key]

    def raycast(self, origin: np.ndarray, dirs_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of rays ``origin + s * d`` (d rows of ``dirs_world``, (N, 3)).

        Returns ``(s (N,), quad_index (N,))``; s = inf / index -1 when nothing is hit.
        Independent of the renderer (exact rectangle intersection), used to check it.
        """
        d = np.atleast_2d(np.asarray(dirs_world, dtype=np.float64))
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        best = np.full(len(d), np.inf)
        idx = np.full(len(d), -1, dtype=np.int64)
        for qi, q in enumerate(self.quads):
            n = q.normal
            den = d @ n
            with np.errstate(divide='ignore', invalid='ignore'):
                s = ((q.origin - o) @ n) / den
            p = o + s[:, None] * d - q.origin
            a, b = p @ q.axis_u, p @ q.axis_v
            ok = (s > 1e-9) & (a >= 0) & (a <= q.size_u) & (b >= 0) & (b <= q.size_v)
            if not q.double_sided:
                ok &= den < 0
            ok &= s < best
            best[ok] = s[ok]
            idx[ok] = qi
        return best, idx


def _value_noise(rng: np.random.Generator, h: int, w: int, cell_px: float, ch: int) -> np.ndarray:
    """Smooth random field with feature size ``cell_px`` (bicubic upsampled random grid)."""
    gh, gw = int(math.ceil(h / cell_px)) + 4, int(math.ceil(w / cell_px)) + 4
    g = rng.standard_normal((gh, gw, ch)).astype(np.float32)
    # dst(x, y) = grid(x / cell + 1, y / cell + 1): cost proportional to the output size only
    A = np.array([[1.0 / cell_px, 0.0, 1.0], [0.0, 1.0 / cell_px, 1.0]])
    out = cv2.warpAffine(g, A, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REFLECT)
    return out.reshape(h, w, ch)


def make_texture(rng: np.random.Generator, width_m: float, height_m: float, ppm: float,
                 brightness: float = 128.0, contrast: float = 1.0) -> np.ndarray:
    """Natural-looking non-repetitive BGR texture of ``width_m x height_m`` metres.

    Multi-octave value noise (fractal, colour-tinted) plus random filled polygons, ellipses,
    rectangles and strokes of random colour/opacity (these give well-spread corners), then
    a 1-texel Gaussian blur so the texture is band-limited for the mip pyramid.
    """
    w, h = max(8, int(round(width_m * ppm))), max(8, int(round(height_m * ppm)))
    # Fractal noise: grey structure at all scales, colour only at low frequency.
    grey = np.zeros((h, w), np.float32)
    for cell_m, amp in ((1.2, 34.0), (0.5, 24.0), (0.22, 18.0), (0.09, 12.0), (0.04, 8.0),
                        (0.018, 5.0)):
        n = _value_noise(rng, h, w, max(2.0, cell_m * ppm), 1)[:, :, 0]
        cv2.scaleAdd(n, amp, grey, dst=grey)
    grey += np.float32(brightness)
    tint = _value_noise(rng, h, w, 1.0 * ppm, 3)
    offs = rng.uniform(-25, 25, 3)
    img = cv2.merge([cv2.scaleAdd(tint[:, :, c], 18.0, grey) + np.float32(offs[c])
                     for c in range(3)])

    # Random shapes drawn onto an overlay with random opacity (a few layers).
    n_shapes = int(55 * width_m * height_m) + 10
    for layer in range(3):
        overlay = img.copy()
        for _ in range(n_shapes // 3):
            color = tuple(float(c) for c in rng.uniform(0, 255, 3))
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            size = ppm * float(np.exp(rng.uniform(np.log(0.025), np.log(0.22))))
            kind = rng.integers(0, 5)
            if kind == 0:  # random polygon (3-6 vertices)
                k = int(rng.integers(3, 7))
                ang = np.sort(rng.uniform(0, 2 * np.pi, k))
                rad = size * rng.uniform(0.4, 1.0, k)
                pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1)
                cv2.fillPoly(overlay, [np.round(pts * 16).astype(np.int32)], color,
                             cv2.LINE_AA, shift=4)
            elif kind == 1:  # rotated rectangle
                rect = ((cx, cy), (size * rng.uniform(0.5, 1.5), size * rng.uniform(0.3, 1.2)),
                        float(rng.uniform(0, 180)))
                pts = cv2.boxPoints(rect)
                cv2.fillPoly(overlay, [np.round(pts * 16).astype(np.int32)], color,
                             cv2.LINE_AA, shift=4)
            elif kind == 2:  # ellipse
                axes = (int(size * rng.uniform(0.3, 0.9)) + 1,
                        int(size * rng.uniform(0.2, 0.7)) + 1)
                cv2.ellipse(overlay, (int(cx), int(cy)), axes, float(rng.uniform(0, 180)), 0, 360,
                            color, -1, cv2.LINE_AA)
            else:  # stroke / polyline
                k = int(rng.integers(2, 5))
                pts = [np.array([cx, cy])]
                for _ in range(k):
                    step = size * rng.uniform(0.5, 1.2)
                    a = rng.uniform(0, 2 * np.pi)
                    pts.append(pts[-1] + step * np.array([np.cos(a), np.sin(a)]))
                th = max(1, int(ppm * rng.uniform(0.006, 0.03)))
                cv2.polylines(overlay, [np.round(np.array(pts) * 16).astype(np.int32)], False,
                              color, th, cv2.LINE_AA, shift=4)
        alpha = float(rng.uniform(0.55, 0.95)) if layer < 2 else 1.0
        cv2.addWeighted(overlay, alpha, img, 1.0 - alpha, 0.0, dst=img)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    # Normalise contrast robustly into the displayable range.
    lo, hi = np.percentile(img[::4, ::4], (1, 99))
    mid = 0.5 * (lo + hi)
    scale = contrast * 190.0 / max(hi - lo, 1e-3)
    img = cv2.addWeighted(img, scale, img, 0.0, brightness - mid * scale + 0.5)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


def _rect(name: str, origin: Sequence[float], u: Sequence[float], v: Sequence[float],
          tex: int, double_sided: bool = False) -> Quad:
    u_, v_ = np.asarray(u, float), np.asarray(v, float)
    su, sv = float(np.linalg.norm(u_)), float(np.linalg.norm(v_))
    return Quad(name, np.asarray(origin, float), u_ / su, v_ / sv, su, sv, tex, double_sided)


def _box(name: str, center_xy: Sequence[float], size: Sequence[float], yaw_deg: float,
         first_tex: int) -> list[Quad]:
    """Four vertical sides and the top of a box standing on the floor (outward normals)."""
    sx, sy, sz = size
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    o = np.array([center_xy[0], center_xy[1], 0.0]) - 0.5 * sx * ex - 0.5 * sy * ey
    corners = [o, o + sx * ex, o + sx * ex + sy * ey, o + sy * ey]
    quads = []
    for k in range(4):  # side from corner k to k+1, outward normal = edge x up
        a, b = corners[k], corners[(k + 1) % 4]
        quads.append(_rect(f'{name}_side{k}', a, b - a, sz * ez, first_tex + k))
    # top: normal +z  ->  u x v = +z with u = ex, v = ey
    quads.append(_rect(f'{name}_top', o + sz * ez, sx * ex, sy * ey, first_tex + 4))
    return quads


@functools.lru_cache(maxsize=2)
def make_scene(seed: int = 0, ppm: float = 256.0) -> Scene:
    """The textured room (floor, ceiling, 4 walls, 3 boxes, 2 free-standing panels).

    Geometry is fixed (it keeps clear of every trajectory); textures depend on ``seed``.
    ``ppm``: texels per metre of the finest mip level.  Takes ~1.5 s, so results are cached
    (the returned Scene is shared: treat it as read-only).
    """
    rng = np.random.default_rng([int(seed), 1729])
    (x0, y0, z0), (x1, y1, z1) = ROOM_MIN, ROOM_MAX
    quads: list[Quad] = [
        # inward normals (u x v points into the room)
        _rect('floor', (x0, y0, z0), (x1 - x0, 0, 0), (0, y1 - y0, 0), 0),
        _rect('ceiling', (x0, y0, z1), (0, y1 - y0, 0), (x1 - x0, 0, 0), 1),
        _rect('wall_south', (x0, y0, z0), (0, 0, z1 - z0), (x1 - x0, 0, 0), 2),   # y = y0
        _rect('wall_north', (x0, y1, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), 3),   # y = y1
        _rect('wall_west', (x0, y0, z0), (0, y1 - y0, 0), (0, 0, z1 - z0), 4),    # x = x0
        _rect('wall_east', (x1, y0, z0), (0, 0, z1 - z0), (0, y1 - y0, 0), 5),    # x = x1
    ]
    quads += _box('box_a', (2.55, 1.85), (0.9, 0.8, 1.1), 20.0, 6)
    quads += _box('box_b', (-2.6, -1.9), (1.0, 0.7, 0.8), -15.0, 11)
    quads += _box('box_c', (0.4, -2.25), (1.3, 0.6, 0.55), 5.0, 16)
    # free-standing panels (double sided), for depth variety
    a = math.radians(25.0)
    quads.append(_rect('panel_n', (-1.6, 2.0, 0.35), (1.3 * math.cos(a), 1.3 * math.sin(a), 0),
                       (0, 0, 1.6), 21, double_sided=True))
    a = math.radians(-70.0)
    quads.append(_rect('panel_e', (2.75, -1.6, 0.5), (-1.2 * math.cos(a), -1.2 * math.sin(a), 0),
                       (0, 0, 1.5), 22, double_sided=True))
    bright = {0: 105.0, 1: 150.0}
    textures = []
    for ti in range(23):
        q = next(qq for qq in quads if qq.texture == ti)
        textures.append(make_texture(rng, q.size_u, q.size_v, ppm,
                                     brightness=bright.get(ti, float(rng.uniform(110, 145)))))
    return Scene(quads, textures, ppm)


# =========================================================================== renderer
def undistort_pixels(pts: np.ndarray, K: np.ndarray, D: np.ndarray,
                     P: np.ndarray | None = None) -> np.ndarray:
    """Ideal (undistorted) coordinates of distorted pixels ``pts`` (N, 2), accurate iterative
    inversion of OpenCV's plumb_bob model; pixels if ``P`` (3x3) is given, else normalized."""
    src = np.asarray(pts, dtype=np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    K = np.asarray(K, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    if hasattr(cv2, 'undistortPointsIter'):  # OpenCV 4.x
        out = cv2.undistortPointsIter(src, K, D, None, P, crit)
    else:  # OpenCV 5: undistortPoints takes the criteria
        out = cv2.undistortPoints(src, K, D, R=None, P=P, criteria=crit)
    return out.reshape(-1, 2)


def _clip_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of polygon P (N, 3) (camera frame) to z >= near."""
    out = []
    n = len(P)
    for i in range(n):
        a, b = P[i], P[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


class Renderer:
    """Z-buffered homography renderer of a :class:`Scene` for a pinhole camera ``K``."""

    def __init__(self, scene: Scene, K: np.ndarray, width: int, height: int, *,
                 color: bool = False, near: float = 0.05, tile_m: float = 1.0,
                 lod_bias: float = 0.0) -> None:
        """Args: K 3x3 intrinsics, image size, colour (BGR) or grey, near-plane distance (m),
        tile size (m), mip LOD bias (levels; >0 blurrier)."""
        self.scene, self.K = scene, np.asarray(K, dtype=np.float64)
        self.Kinv = np.linalg.inv(self.K)
        self.width, self.height = int(width), int(height)
        self.color, self.near, self.lod_bias = color, near, lod_bias
        uu, vv = np.meshgrid(np.arange(self.width, dtype=np.float32),
                             np.arange(self.height, dtype=np.float32))
        self._u, self._v = uu, vv
        # tiles: (quad index, a0, a1, b0, b1); interior edges overlap a little to avoid cracks
        tiles, corners = [], []
        for qi, q in enumerate(scene.quads):
            nu = max(1, math.ceil(q.size_u / tile_m - 1e-9))
            nv = max(1, math.ceil(q.size_v / tile_m - 1e-9))
            eps = 0.004
            for i in range(nu):
                for j in range(nv):
                    a0, a1 = q.size_u * i / nu, q.size_u * (i + 1) / nu
                    b0, b1 = q.size_v * j / nv, q.size_v * (j + 1) / nv
                    a0, b0 = (a0 - eps if i else a0), (b0 - eps if j else b0)
                    a1, b1 = (a1 + eps if i < nu - 1 else a1), (b1 + eps if j < nv - 1 else b1)
                    tiles.append((qi, a0, a1, b0, b1))
                    corners.append([q.origin + a * q.axis_u + b * q.axis_v
                                    for a, b in ((a0, b0), (a1, b0), (a1, b1), (a0, b1))])
        self.tiles = tiles
        self.tile_corners = np.asarray(corners)  # (T, 4, 3) world
        self.tile_quad = np.array([t[0] for t in tiles])
        self.quad_normals = np.array([q.normal for q in scene.quads])
        self.quad_origins = np.array([q.origin for q in scene.quads])
        self.quad_double = np.array([q.double_sided for q in scene.quads])

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Render the view of camera pose ``T_world_cam``.

        Returns ``(image uint8 (H, W) or (H, W, 3), inverse_depth float32 (H, W))``,
        inverse depth = 1/z of the optical-frame z (0 where nothing was drawn).
        """
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
        cam_center = np.asarray(T_world_cam)[:3, 3]
        W, H = self.width, self.height
        shape = (H, W, 3) if self.color else (H, W)
        img = np.full(shape, 128, np.uint8)
        zbuf = np.zeros((H, W), np.float32)
        # per-quad back-face culling
        facing = ((cam_center - self.quad_origins) * self.quad_normals).sum(1) > 1e-9
        visible_q = facing | self.quad_double
        pc_all = self.tile_corners @ R.T + t  # (T, 4, 3)
        keep = visible_q[self.tile_quad] & (pc_all[:, :, 2].max(1) > self.near)
        # frustum culling: a tile with all corners outside one side plane is invisible
        K = self.K
        X, Y, Z = pc_all[..., 0], pc_all[..., 1], pc_all[..., 2]
        u_num = K[0, 0] * X + K[0, 1] * Y + K[0, 2] * Z  # u * z
        v_num = K[1, 1] * Y + K[1, 2] * Z                # v * z
        keep &= ~(u_num < -Z).all(1) & ~(u_num > W * Z).all(1)
        keep &= ~(v_num < -Z).all(1) & ~(v_num > H * Z).all(1)
        fx = self.K[0, 0]
        ppm = self.scene.ppm
        for ti in np.flatnonzero(keep):
            qi, a0, a1, b0, b1 = self.tiles[ti]
            q = self.scene.quads[qi]
            poly = _clip_near(pc_all[ti], self.near)
            if len(poly) < 3:
                continue
            uvw = poly @ self.K.T
            pix = uvw[:, :2] / uvw[:, 2:3]
            x0 = max(int(math.floor(pix[:, 0].min())) - 1, 0)
            x1 = min(int(math.ceil(pix[:, 0].max())) + 2, W)
            y0 = max(int(math.floor(pix[:, 1].min())) - 1, 0)
            y1 = min(int(math.ceil(pix[:, 1].max())) + 2, H)
            if x1 <= x0 or y1 <= y0:
                continue
            # mip level from the texel footprint at the mean depth of the clipped tile
            zmean = float(poly[:, 2].mean())
            tpp = zmean * ppm / fx
            pyr = self.scene.pyramid(q.texture, self.color)
            level = int(np.clip(round(math.log2(max(tpp, 1e-6)) + self.lod_bias), 0, len(pyr) - 1))
            tex = pyr[level]
            s = (2.0 ** level) / ppm
            # texture index (i, j, 1) -> world -> camera -> pixels
            M = np.column_stack([s * q.axis_u, s * q.axis_v,
                                 q.origin + 0.5 * s * (q.axis_u + q.axis_v)])
            Hm = self.K @ np.column_stack([R @ M[:, 0], R @ M[:, 1], R @ M[:, 2] + t])
            Hm = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], float) @ Hm
            rw, rh = x1 - x0, y1 - y0
            warped = cv2.warpPerspective(tex, Hm, (rw, rh), flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_REPLICATE)
            mask = np.zeros((rh, rw), np.uint8)
            pts = np.round((pix - [x0, y0]) * 16).astype(np.int32)
            cv2.fillPoly(mask, [pts], 1, cv2.LINE_8, shift=4)
            # inverse depth on the plane n_c . X = d_c:  1/z = n_c . K^-1 [u v 1] / d_c
            n_c = R @ self.quad_normals[qi]
            d_c = float(n_c @ (R @ q.origin + t))
            if abs(d_c) < 1e-9:
                continue
            g = (n_c @ self.Kinv) / d_c
            invz = (g[0] * self._u[y0:y1, x0:x1] + g[1] * self._v[y0:y1, x0:x1]
                    + np.float32(g[2]))
            zroi = zbuf[y0:y1, x0:x1]
            upd = (mask != 0) & (invz > zroi)
            np.copyto(zroi, invz, where=upd)
            iroi = img[y0:y1, x0:x1]
            np.copyto(iroi, warped, where=upd[:, :, None] if self.color else upd)
        return img, zbuf


# =========================================================================== trajectories
def _euler_to_R(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """R_world_optical from body yaw/pitch/roll (body x forward, y left, z up; ZYX order;
    pitch > 0 looks down)."""
    R_wb = Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_matrix()
    # columns: optical x, y, z axes expressed in the body frame
    R_bo = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return R_wb @ R_bo


def trajectory_pose(name: str, t: float, seed: int = 0) -> np.ndarray:
    """T_world_cam (optical frame) at time ``t`` seconds of trajectory ``name``.

    All trajectories are smooth in all six DOF, stay inside the free space of the room
    (1-5 m from the surfaces they look at), peak ~0.5-1 m/s and ~20-40 deg/s.
    """
    rng = np.random.default_rng([int(seed), 4242])
    ph = rng.uniform(0, 2 * np.pi, 12)
    w = lambda period: 2 * np.pi / period  # noqa: E731
    if name == 'walk':  # hand-held wander
        x = 1.25 * np.sin(w(15.0) * t + ph[0]) + 0.25 * np.sin(w(5.3) * t + ph[1])
        y = 0.9 * np.sin(w(11.0) * t + ph[2]) + 0.15 * np.sin(w(4.1) * t + ph[3])
        z = 1.45 + 0.15 * np.sin(w(6.7) * t + ph[4]) + 0.02 * np.sin(w(1.1) * t + ph[5])
        yaw = (ph[6] + 0.12 * t + 0.8 * np.sin(w(17.0) * t + ph[7])
               + 0.12 * np.sin(w(4.9) * t + ph[8]))
        pitch = 0.12 + 0.15 * np.sin(w(9.0) * t + ph[9]) + 0.03 * np.sin(w(2.3) * t + ph[10])
        roll = 0.07 * np.sin(w(7.7) * t + ph[11]) + 0.02 * np.sin(w(2.9) * t + ph[0])
    elif name == 'orbit':  # circle of radius 1.3 m, looking outward-forward at the walls
        th = w(13.0) * t + ph[0]
        x, y = 1.3 * np.cos(th), 1.3 * np.sin(th)
        z = 1.5 + 0.12 * np.sin(w(5.0) * t + ph[1])
        yaw = th + np.pi / 2 - 0.6 + 0.12 * np.sin(w(6.0) * t + ph[2])  # tangent, turned outward
        pitch = 0.1 + 0.12 * np.sin(w(7.0) * t + ph[3])
        roll = 0.06 * np.sin(w(4.5) * t + ph[4])
    elif name == 'figure8':  # lemniscate, heading follows the path loosely
        th = w(16.0) * t + ph[0]
        x, y = 1.5 * np.sin(th), 1.0 * np.sin(2 * th)
        z = 1.4 + 0.15 * np.sin(w(5.5) * t + ph[1])
        yaw = (ph[5] + 0.7 * np.sin(th) + 0.4 * np.sin(2 * th + ph[6])
               + 0.15 * np.sin(w(7.0) * t + ph[2]))
        pitch = 0.15 + 0.12 * np.sin(w(6.0) * t + ph[3])
        roll = 0.08 * np.sin(w(5.0) * t + ph[4])
    else:
        raise ValueError(f'unknown trajectory {name!r}; choose from {TRAJECTORIES}')
    T = np.eye(4)
    T[:3, :3] = _euler_to_R(float(yaw), float(pitch), float(roll))
    T[:3, 3] = [x, y, z]
    return T


def trajectory_stats(name: str, seconds: float, seed: int = 0,
                     rate: float = 100.0) -> dict[str, float]:
    """Peak/mean speed (m/s) and angular rate (deg/s) of a trajectory (finite differences)."""
    ts = np.arange(0, seconds, 1.0 / rate)
    Ts = np.stack([trajectory_pose(name, float(t), seed) for t in ts])
    v = np.linalg.norm(np.diff(Ts[:, :3, 3], axis=0), axis=1) * rate
    dR = np.einsum('nji,njk->nik', Ts[:-1, :3, :3], Ts[1:, :3, :3])
    ang = np.degrees(Rotation.from_matrix(dR).magnitude()) * rate
    return {'speed_max': float(v.max()), 'speed_mean': float(v.mean()),
            'rot_max_deg_s': float(ang.max()), 'rot_mean_deg_s': float(ang.mean())}


# =========================================================================== sequences
@dataclass
class SynthConfig:
    """All options of a synthetic sequence (defaults = the CLI defaults)."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float | None = None          # default: fx
    cx: float | None = None          # default: (width - 1) / 2
    cy: float | None = None          # default: (height - 1) / 2
    rate: float = 30.0
    frames: int = 300
    seed: int = 0
    trajectory: str = 'walk'
    noise_px: float = 2.0            # Gaussian intensity noise sigma (grey levels)
    blur: float = 0.0                # linear motion-blur kernel length (px)
    distortion: tuple[float, ...] | None = None  # plumb_bob k1 k2 p1 p2 k3
    supersample: int = 1
    encoding: str = 'mono8'          # or 'bgr8'
    start_ns: int = EPOCH_NS
    ppm: float = 256.0               # texture texels per metre

    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        fy = self.fx if self.fy is None else self.fy
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        return np.array([[self.fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def D(self) -> np.ndarray:
        """plumb_bob distortion (5,), zeros when undistorted."""
        if self.distortion is None:
            return np.zeros(5)
        return np.asarray(self.distortion, float).reshape(5)

    def stamp_ns(self, k: int) -> int:
        """Stamp of frame ``k`` (exact integer nanoseconds)."""
        return int(self.start_ns + round(k * 1e9 / self.rate))


class SequenceRenderer:
    """Frames of a :class:`SynthConfig` (supersampling, distortion, blur and noise included)."""

    def __init__(self, config: SynthConfig, scene: Scene | None = None) -> None:
        self.cfg = config
        self.scene = scene if scene is not None else make_scene(config.seed, config.ppm)
        ss = max(1, int(config.supersample))
        K = config.K()
        W, H = config.width, config.height
        self._map: tuple[np.ndarray, np.ndarray] | None = None
        mx = my = 0
        if config.distortion is not None and np.any(config.D() != 0):
            # for each distorted pixel: where is it in the ideal (undistorted) image?
            uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            pts = np.stack([uu.ravel(), vv.ravel()], 1)
            und = undistort_pixels(pts, K, config.D(), K).reshape(H, W, 2)
            mx = int(min(max(0.0, -und[..., 0].min(), und[..., 0].max() - (W - 1)), W)) + 2
            my = int(min(max(0.0, -und[..., 1].min(), und[..., 1].max() - (H - 1)), H)) + 2
            self._map = ((und[..., 0] + mx).astype(np.float32),
                         (und[..., 1] + my).astype(np.float32))
        self._margin = (mx, my)
        Wc, Hc = W + 2 * mx, H + 2 * my
        Kc = K.copy()
        Kc[0, 2] += mx
        Kc[1, 2] += my
        Kss = Kc.copy()
        Kss[:2, :2] *= ss
        Kss[0, 2] = (Kc[0, 2] + 0.5) * ss - 0.5
        Kss[1, 2] = (Kc[1, 2] + 0.5) * ss - 0.5
        self._ss = ss
        self._canvas = (Wc, Hc)
        self.renderer = Renderer(self.scene, Kss, Wc * ss, Hc * ss,
                                 color=config.encoding == 'bgr8',
                                 lod_bias=math.log2(ss) if ss > 1 else 0.0)

    def pose(self, k: int) -> np.ndarray:
        """T_world_cam of frame ``k``."""
        return trajectory_pose(self.cfg.trajectory, k / self.cfg.rate, self.cfg.seed)

    def render_clean(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Noise- and blur-free (but distorted, if configured) image at a pose."""
        img, _ = self.renderer.render(T_world_cam)
        if self._ss > 1:
            img = cv2.resize(img, self._canvas, interpolation=cv2.INTER_AREA)
        if self._map is not None:
            img = cv2.remap(img, self._map[0], self._map[1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        return img

    def _blur_kernel(self, k: int) -> np.ndarray | None:
        L = float(self.cfg.blur)
        if L < 1.0:
            return None
        # direction of the image motion of the point 3 m ahead of the image centre
        K = self.cfg.K()
        half = 0.5 / self.cfg.rate
        Ta = trajectory_pose(self.cfg.trajectory, k / self.cfg.rate - half, self.cfg.seed)
        Tb = trajectory_pose(self.cfg.trajectory, k / self.cfg.rate + half, self.cfg.seed)
        X = Ta @ np.array([0.0, 0.0, 3.0, 1.0])
        pb = np.linalg.inv(Tb) @ X
        uv_b = (K @ pb[:3])[:2] / pb[2]
        d = uv_b - K[:2, 2]
        ang = math.atan2(d[1], d[0]) if np.linalg.norm(d) > 1e-6 else 0.0
        n = int(math.ceil(L)) | 1
        ker = np.zeros((n, n), np.float32)
        c = n // 2
        p0 = (c - 0.5 * (L - 1) * math.cos(ang), c - 0.5 * (L - 1) * math.sin(ang))
        p1 = (c + 0.5 * (L - 1) * math.cos(ang), c + 0.5 * (L - 1) * math.sin(ang))
        cv2.line(ker, (int(round(p0[0] * 16)), int(round(p0[1] * 16))),
                 (int(round(p1[0] * 16)), int(round(p1[1] * 16))), 1.0, 1, cv2.LINE_AA, shift=4)
        return ker / ker.sum()

    def frame(self, k: int) -> tuple[int, np.ndarray, np.ndarray]:
        """``(stamp_ns, image uint8, T_world_cam)`` of frame ``k``."""
        T = self.pose(k)
        img = self.render_clean(T)
        ker = self._blur_kernel(k)
        if ker is not None:
            img = cv2.filter2D(img, -1, ker, borderType=cv2.BORDER_REPLICATE)
        if self.cfg.noise_px > 0:
            rng = np.random.default_rng([int(self.cfg.seed), int(k), 99])
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            # img + sigma * noise, rounded and saturated to uint8
            noisy = cv2.scaleAdd(noise, float(self.cfg.noise_px), img.astype(np.float32))
            np.rint(noisy, out=noisy)
            np.clip(noisy, 0, 255, out=noisy)
            img = noisy.astype(np.uint8)
        return self.cfg.stamp_ns(k), img, T


def render_sequence(config: SynthConfig, scene: Scene | None = None
                    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield ``(stamp_ns, image, T_world_cam)`` for frames 0..config.frames-1."""
    seq = SequenceRenderer(config, scene)
    for k in range(config.frames):
        yield seq.frame(k)


def write_bag(config: SynthConfig, out: str | Path, *, raw: bool = True, compressed: bool = False,
              compressed_format: str = 'jpeg', jpeg_quality: int = 90, overwrite: bool = False,
              tum: str | Path | None = None, progress: bool = False) -> dict[str, float]:
    """Render ``config`` into the rosbag2 ``out`` (MCAP); returns timing statistics."""
    from ekf_vo.tools.bagio import BagWriter  # local: keeps the renderer importable alone
    from ekf_vo.tools.trajectory_io import write_tum

    cam_frame, world_frame = 'camera_optical', 'world'
    seq = SequenceRenderer(config)
    K, D = config.K(), config.D()
    stamps, poses = [], []
    t_render = 0.0
    t0 = time.perf_counter()
    it = range(config.frames)
    if progress:
        try:
            from tqdm import tqdm
            it = tqdm(it, unit='frame', desc='synth')
        except ImportError:  # pragma: no cover
            pass
    with BagWriter(out, overwrite=overwrite) as bag:
        for k in it:
            tr = time.perf_counter()
            stamp, img, T = seq.frame(k)
            t_render += time.perf_counter() - tr
            bag.add_camera_info('/camera/camera_info', config.width, config.height, K, D,
                                'plumb_bob', stamp, cam_frame)
            if raw:
                bag.add_image('/camera/image_raw', img, stamp, cam_frame)
            if compressed:
                bag.add_compressed('/camera/image_raw/compressed', img, stamp, cam_frame,
                                   compressed_format, jpeg_quality)
            bag.add_pose('/ground_truth/pose', T, stamp, world_frame)
            stamps.append(stamp)
            poses.append(T)
    total = time.perf_counter() - t0
    if tum is not None:
        write_tum(tum, np.asarray(stamps, dtype=np.int64) * 1e-9, np.asarray(poses))
    return {'frames': config.frames, 'render_s': t_render, 'total_s': total,
            'render_fps': config.frames / max(t_render, 1e-9)}


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


def build_parser() -> argparse.ArgumentParser:
    """argparse parser of ``ekf-vo-synth``."""
    p = argparse.ArgumentParser(prog='ekf-vo-synth', description=__doc__.split('\n')[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument('out_bag', type=Path, help='output rosbag2 directory (must not exist)')
    p.add_argument('--width', type=int, default=640)
    p.add_argument('--height', type=int, default=480)
    p.add_argument('--fx', type=float, default=525.0,
                   help='focal length (px); fy = fx unless --fy')
    p.add_argument('--fy', type=float, default=None)
    p.add_argument('--rate', type=float, default=30.0, help='frame rate (Hz)')
    p.add_argument('--frames', type=int, default=300)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--trajectory', choices=TRAJECTORIES, default='walk',
                   help='walk = smooth hand-held 6-DoF wander')
    p.add_argument('--noise-px', type=float, default=2.0,
                   help='Gaussian intensity noise sigma (grey levels)')
    p.add_argument('--blur', type=float, default=0.0, help='motion-blur kernel length (px)')
    p.add_argument('--distortion', type=float, nargs=5, metavar=('K1', 'K2', 'P1', 'P2', 'K3'),
                   default=None, help='plumb_bob distortion applied to the images')
    p.add_argument('--supersample', type=int, default=1, help='anti-aliasing factor')
    p.add_argument('--encoding', choices=('mono8', 'bgr8'), default='mono8')
    p.add_argument('--compressed', action='store_true',
                   help='also write /camera/image_raw/compressed')
    p.add_argument('--compressed-only', action='store_true',
                   help='write /camera/image_raw/compressed instead of /camera/image_raw')
    p.add_argument('--compressed-format', choices=('jpeg', 'png'), default='jpeg')
    p.add_argument('--jpeg-quality', type=int, default=90)
    p.add_argument('--tum', type=Path, default=None, help='also write ground truth as TUM text')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUT_BAG')
    p.add_argument('--stats', action='store_true', help='print trajectory speed statistics')
    p.add_argument('-q', '--quiet', action='store_true')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``ekf-vo-synth``."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format='%(levelname)s %(name)s: %(message)s')
    cfg = SynthConfig(width=args.width, height=args.height, fx=args.fx, fy=args.fy,
                      rate=args.rate, frames=args.frames, seed=args.seed,
                      trajectory=args.trajectory, noise_px=args.noise_px, blur=args.blur,
                      distortion=tuple(args.distortion) if args.distortion else None,
                      supersample=args.supersample, encoding=args.encoding)
    if args.out_bag.exists() and not args.overwrite:
        print(f'error: {args.out_bag} exists (use --overwrite)', file=sys.stderr)
        return 2
    if args.stats:
        print(trajectory_stats(cfg.trajectory, cfg.frames / cfg.rate, cfg.seed))
    res = write_bag(cfg, args.out_bag, raw=not args.compressed_only,
                    compressed=args.compressed or args.compressed_only,
                    compressed_format=args.compressed_format, jpeg_quality=args.jpeg_quality,
                    overwrite=args.overwrite, tum=args.tum, progress=not args.quiet)
    size = _dir_size(args.out_bag)
    logger.info('%d frames, render %.1f frames/s, total %.1f s, bag %.2f MB',
                res['frames'], res['render_fps'], res['total_s'], size / 1e6)
    if not args.quiet:
        print(f'{args.out_bag}: {res["frames"]} frames, {size / 1e6:.2f} MB, '
              f'render {res["render_fps"]:.1f} frames/s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
