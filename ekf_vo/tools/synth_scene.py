"""The synthetic world of ``ekf-vo-synth``: a procedurally textured room, its renderer and
the camera trajectories through it.

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
intensity noise are applied afterwards, by :class:`ekf_vo.tools.synth.SequenceRenderer`.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

TRAJECTORIES = ('walk', 'orbit', 'figure8', 'ground_robot', 'ground_robot_arcs',
                'handheld_rotation', 'drone_nadir', 'car', 'car_turn')
#: trajectories that drive down the street of synth_street.py, not through the room
STREET_TRAJECTORIES = ('car', 'car_turn')

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
    #: texels per metre of this quad's texture (None: the scene's ``ppm``)
    ppm: float | None = None

    @property
    def normal(self) -> np.ndarray:
        """Unit normal on the visible side."""
        return np.cross(self.axis_u, self.axis_v)


@dataclass
class Scene:
    """Quads plus their textures (mip pyramids, level 0 at ``ppm`` texels per metre, or
    at the quad's own)."""

    quads: list[Quad]
    textures_bgr: list[np.ndarray]
    ppm: float
    tile_m: float = 1.0        #: the renderer's tile size on this scene [m]
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


def scene_for(trajectory: str, seed: int = 0, ppm: float = 256.0) -> Scene:
    """The world `trajectory` moves through: the street for STREET_TRAJECTORIES (its own
    texel density), else the room at `ppm`."""
    if trajectory in STREET_TRAJECTORIES:
        from .synth_street import make_street_scene
        return make_street_scene(seed, trajectory == 'car_turn')
    return make_scene(seed, ppm)


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
                 color: bool = False, near: float = 0.05, tile_m: float | None = None,
                 lod_bias: float = 0.0) -> None:
        """Args: K 3x3 intrinsics, image size, colour (BGR) or grey, near-plane distance (m),
        tile size (m; None: the scene's), mip LOD bias (levels; >0 blurrier)."""
        tile_m = scene.tile_m if tile_m is None else tile_m
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

    def render(self, T_world_cam: np.ndarray, rows: tuple[int, int] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Render the view of camera pose ``T_world_cam``.

        Returns ``(image uint8 (H, W) or (H, W, 3), inverse_depth float32 (H, W))``,
        inverse depth = 1/z of the optical-frame z (0 where nothing was drawn).
        ``rows``: draw only image rows [first, last) (a rolling shutter's band).
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
        for ti in np.flatnonzero(keep):
            qi, a0, a1, b0, b1 = self.tiles[ti]
            q = self.scene.quads[qi]
            ppm = self.scene.ppm if q.ppm is None else q.ppm
            poly = _clip_near(pc_all[ti], self.near)
            if len(poly) < 3:
                continue
            uvw = poly @ self.K.T
            pix = uvw[:, :2] / uvw[:, 2:3]
            x0 = max(int(math.floor(pix[:, 0].min())) - 1, 0)
            x1 = min(int(math.ceil(pix[:, 0].max())) + 2, W)
            y0 = max(int(math.floor(pix[:, 1].min())) - 1, 0 if rows is None else rows[0])
            y1 = min(int(math.ceil(pix[:, 1].max())) + 2, H if rows is None else rows[1])
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


#: ground_robot: the rectangle's corners (m, counter-clockwise), speed on an edge (m/s),
#: turn rate in place (rad/s), pause before and after each turn (s), camera height and
#: how far ahead of the turning axis it sits (m)
_ROBOT_CORNERS = ((-1.5, -1.0), (1.5, -1.0), (1.5, 1.0), (-1.5, 1.0))
_ROBOT_SPEED, _ROBOT_TURN_RATE, _ROBOT_PAUSE = 0.6, np.radians(60.0), 0.3
_ROBOT_CAM_HEIGHT, _ROBOT_CAM_AHEAD = 0.4, 0.1
#: ground_robot: the camera optical frame's origin in the base frame (x ahead, z up; the
#: base is the turning axis on the floor): vo_node's T_base_cam_xyz for this robot [m]
GROUND_ROBOT_T_BASE_CAM_XYZ = (_ROBOT_CAM_AHEAD, 0.0, _ROBOT_CAM_HEIGHT)


def _smoothstep(u: float) -> float:
    """0 -> 1 with zero slope at both ends (the speed starts and ends at rest)."""
    u = min(max(u, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * u)


def ground_robot_base(t: float) -> tuple[float, float, float]:
    """(x, y, heading) of a robot that drives each edge of a rectangle, stops, turns
    90 deg in place, stops, and drives the next edge (peak speed pi/2 x the mean)."""
    n = len(_ROBOT_CORNERS)
    edges = []
    for k in range(n):
        a, b = np.array(_ROBOT_CORNERS[k]), np.array(_ROBOT_CORNERS[(k + 1) % n])
        edges.append((a, b, float(np.linalg.norm(b - a)) / _ROBOT_SPEED))
    turn = (np.pi / 2) / _ROBOT_TURN_RATE
    period = sum(e[2] for e in edges) + n * (turn + 2 * _ROBOT_PAUSE)
    t = t % period
    heading0 = 0.0
    for a, b, drive in edges:
        if t < drive:
            p = a + (b - a) * _smoothstep(t / drive)
            return float(p[0]), float(p[1]), heading0
        t -= drive
        if t < _ROBOT_PAUSE:
            return float(b[0]), float(b[1]), heading0
        t -= _ROBOT_PAUSE
        if t < turn:
            return float(b[0]), float(b[1]), heading0 + np.pi / 2 * _smoothstep(t / turn)
        t -= turn
        heading0 += np.pi / 2
        if t < _ROBOT_PAUSE:
            return float(b[0]), float(b[1]), heading0
        t -= _ROBOT_PAUSE
    a = edges[0][0]
    return float(a[0]), float(a[1]), heading0


#: ground_robot_arcs: the same rectangle with corners rounded to this radius (m), driven
#: at this constant speed (m/s): the robot turns while it drives, never in place
_ARC_RADIUS, _ARC_SPEED = 0.5, 0.5


def _rounded_rectangle(s: float) -> tuple[float, float, float]:
    """(x, y, heading) at arc length `s` along the rounded rectangle (counter-clockwise,
    starting at the first straight edge's start)."""
    (x0, y0), (x1, y1) = _ROBOT_CORNERS[0], _ROBOT_CORNERS[2]
    r = _ARC_RADIUS
    straights = (x1 - x0 - 2 * r, y1 - y0 - 2 * r) * 2
    starts = ((x0 + r, y0), (x1, y0 + r), (x1 - r, y1), (x0, y1 - r))
    arc = math.pi / 2 * r
    s = s % (sum(straights) + 4 * arc)
    for k in range(4):
        heading = k * math.pi / 2
        d = np.array([math.cos(heading), math.sin(heading)])
        if s < straights[k]:
            p = np.array(starts[k]) + s * d
            return float(p[0]), float(p[1]), heading
        s -= straights[k]
        if s < arc:
            end = np.array(starts[k]) + straights[k] * d
            centre = end + r * np.array([-d[1], d[0]])
            phi = s / r
            p = centre + r * np.array([math.sin(heading + phi), -math.cos(heading + phi)])
            return float(p[0]), float(p[1]), heading + phi
        s -= arc
    return float(starts[0][0]), float(starts[0][1]), 0.0


def robot_base(name: str, t: float) -> tuple[float, float, float]:
    """(x, y, heading) of the base of the robot trajectory `name` at time `t`."""
    if name == 'ground_robot':
        return ground_robot_base(t)
    if name == 'ground_robot_arcs':
        return _rounded_rectangle(_ARC_SPEED * t)
    raise ValueError(f'{name!r} is not a ground-robot trajectory')


def trajectory_pose(name: str, t: float, seed: int = 0) -> np.ndarray:
    """T_world_cam (optical frame) at time ``t`` seconds of trajectory ``name``.

    walk, orbit and figure8 are smooth in all six DOF, stay inside the free space of the
    room (1-5 m from the surfaces they look at), peak ~0.5-1 m/s and ~20-40 deg/s.
    ground_robot: a camera 0.4 m above the floor, 0.1 m ahead of the axis a robot turns
    about, driving a 3 m x 2 m rectangle at up to 0.94 m/s, stopping and turning 90 deg
    in place (up to 94 deg/s) at each corner (period 25.1 s; ``seed`` does not change it).
    ground_robot_arcs: the same robot and rectangle, corners rounded to 0.5 m, driven at a
    constant 0.5 m/s (57 deg/s in the arcs; period 18.3 s).
    handheld_rotation: a hand-held camera at 1.5 m that mostly rotates: yaw +-30 deg,
    pitch +-20 deg, roll +-15 deg at up to ~100 deg/s, with a few cm of translation.
    drone_nadir: a camera 2.0-2.2 m up looking (nearly) straight down at the floor while
    it flies a 2.8 m x 1.8 m figure of eight at up to ~0.5 m/s: the scene is a plane
    (the floor, with a box now and then), the two-view geometry's hard case.
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
    elif name in ('ground_robot', 'ground_robot_arcs'):
        xb, yb, heading = robot_base(name, float(t))
        x = xb + _ROBOT_CAM_AHEAD * math.cos(heading)
        y = yb + _ROBOT_CAM_AHEAD * math.sin(heading)
        z, yaw, pitch, roll = _ROBOT_CAM_HEIGHT, heading, 0.0, 0.0
    elif name == 'handheld_rotation':  # standing at the room's centre, facing east
        x = 0.03 * np.sin(w(2.9) * t + ph[0])
        y = 0.03 * np.sin(w(3.7) * t + ph[1])
        z = 1.5 + 0.02 * np.sin(w(2.3) * t + ph[2])
        yaw = np.radians(30.0) * np.sin(w(2.0) * t + ph[3])
        pitch = 0.1 + np.radians(20.0) * np.sin(w(2.7) * t + ph[4])
        roll = np.radians(15.0) * np.sin(w(3.3) * t + ph[5])
    elif name == 'drone_nadir':  # looking straight down at the floor: a planar scene
        th = w(20.0) * t + ph[0]
        x, y = 1.4 * np.sin(th), 0.9 * np.sin(2 * th)
        z = 2.1 + 0.1 * np.sin(w(6.5) * t + ph[1])
        yaw = ph[2] + 0.25 * np.sin(w(9.0) * t + ph[3])
        pitch = np.pi / 2 - 0.08 + 0.06 * np.sin(w(5.0) * t + ph[4])
        roll = 0.06 * np.sin(w(4.0) * t + ph[5])
    elif name == 'figure8':  # lemniscate, heading follows the path loosely
        th = w(16.0) * t + ph[0]
        x, y = 1.5 * np.sin(th), 1.0 * np.sin(2 * th)
        z = 1.4 + 0.15 * np.sin(w(5.5) * t + ph[1])
        yaw = (ph[5] + 0.7 * np.sin(th) + 0.4 * np.sin(2 * th + ph[6])
               + 0.15 * np.sin(w(7.0) * t + ph[2]))
        pitch = 0.15 + 0.12 * np.sin(w(6.0) * t + ph[3])
        roll = 0.08 * np.sin(w(5.0) * t + ph[4])
    elif name == 'car':
        from .synth_street import car_pose
        return car_pose(float(t), seed)
    elif name == 'car_turn':
        from .synth_street import car_turn_pose
        return car_turn_pose(float(t), seed)
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
