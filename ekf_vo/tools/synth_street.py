"""A street for ``ekf-vo-synth``: the world of the ``car`` and ``car_turn`` trajectories
(docs/method.md §15.16).

Every other rendered sequence is in one 7 m x 5.5 m room, 1-5 m from its walls. A car
camera sees something else: a road plane running to the horizon, facades 8-12 m to the
side that stream past at a metre a frame, parked cars, gaps between buildings that open
onto a farther row, and nothing at all (the sky) in the top of the image. Forward motion
puts the epipole inside the image, where the points barely move: the two-view bootstrap's
and the filter's hard case, and the one the shared KITTI frames show only 51 frames of.

World frame z up, x along the street (the car drives towards +x), y to the left. Textures
are drawn at a quarter of the room's scale (blotches of 10-90 cm, not 2.5-22 cm), at
STREET_PPM texels per metre (the road and pavements at GROUND_PPM): a 300 m street is
~650 MB of textures and ~20 s to make, once per seed.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .synth_scene import Quad, Scene, _box, _euler_to_R, _rect, make_texture

#: texels per metre of the street's textures (a facade 10 m away is ~1.1 px per texel
#: through a 707 px lens); the renderer's tiles on the street [m]
STREET_PPM = 64.0
#: texels per metre of the road and the pavements: the road under the image's bottom row
#: is 6 m away, where a pixel spans 9 mm across it. A coarser texture is magnified there
#: (blurred, its gradient left to the farther rows of a KLT window), which biases the
#: tracking of near road points in a way a real camera's sharp near road does not
#: (docs/method.md §15.16)
GROUND_PPM = 128.0
STREET_TILE_M = 4.0
#: the street's extent along x [m] (the car drives 0 -> ~170 m in its 180 frames)
STREET_X = (-20.0, 280.0)
#: where the side street of the ``car_turn`` scene joins from the left [m along x], and
#: how far it runs [m along y]
JUNCTION_X, SIDE_STREET_END_M = 150.0, 160.0
#: half widths [m]: the carriageway, the nearest facade, the pavement's outer edge (the
#: farthest facade)
ROAD_HALF_M, FACADE_MIN_M, PAVEMENT_HALF_M = 5.5, 8.0, 12.0
#: the farther row of buildings seen through the gaps [m from the axis]
FAR_ROW_M = 25.0
#: the car's camera: height above the road [m], cruise speed and its swing [m/s]
CAR_CAM_HEIGHT_M, CAR_SPEED_MPS, CAR_SPEED_SWING_MPS = 1.65, 9.5, 1.5
#: the street's textures are drawn as if this many times smaller, then stretched
_FEATURE_SCALE = 4.0


def _texture(rng: np.random.Generator, width_m: float, height_m: float, brightness: float,
             contrast: float = 1.0, ppm: float = STREET_PPM) -> np.ndarray:
    s = _FEATURE_SCALE
    return make_texture(rng, width_m / s, height_m / s, ppm * s, brightness=brightness,
                        contrast=contrast)


def _ground(quad: Quad) -> Quad:
    """The quad with GROUND_PPM texels per metre (see there)."""
    quad.ppm = GROUND_PPM
    return quad


class _Street:
    """One straight street, built in its own frame (x along it, y to its left) and placed
    in the world at `origin` (x, y), turned by `heading` [rad] about z."""

    def __init__(self, rng: np.random.Generator, quads: list[Quad],
                 textures: list[np.ndarray], origin=(0.0, 0.0), heading: float = 0.0
                 ) -> None:
        self.rng, self.quads, self.textures = rng, quads, textures
        c, s = math.cos(heading), math.sin(heading)
        self._R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._o = np.array([origin[0], origin[1], 0.0])
        self._heading_deg = math.degrees(heading)

    def _point(self, p) -> np.ndarray:
        return self._o + self._R @ np.asarray(p, float)

    def _vector(self, v) -> np.ndarray:
        return self._R @ np.asarray(v, float)

    def rect(self, name: str, origin, u, v, tex: np.ndarray, ground: bool = False) -> None:
        quad = _rect(name, self._point(origin), self._vector(u), self._vector(v),
                     len(self.textures))
        self.quads.append(_ground(quad) if ground else quad)
        self.textures.append(tex)

    def box(self, centre_xy, size, yaw_deg: float) -> None:
        c = self._point((centre_xy[0], centre_xy[1], 0.0))
        first = len(self.textures)
        self.quads.extend(_box('car', (float(c[0]), float(c[1])), size,
                               yaw_deg + self._heading_deg, first))
        self.textures.extend(_texture(self.rng, size[0], size[2],
                                      float(self.rng.uniform(60, 190))) for _ in range(5))

    def build(self, x0: float, x1: float, left_gap: tuple[float, float] | None = None
              ) -> None:
        """Road, pavements, yards, facades, far rows and parked cars from x0 to x1; on
        the left, nothing but the road within `left_gap` (a side street joins there).
        (The order of the random draws is the scene's identity: keep it.)"""
        self._gap = left_gap
        self._ground_strips(x0, x1)
        for sgn in (1.0, -1.0):
            self._facades(sgn, x0, x1)
            self._far_row(sgn, x0, x1)
            self._parked_cars(sgn, x0, x1)

    def _in_gap(self, sgn: float, a: float, b: float) -> bool:
        """Whether [a, b] on side `sgn` (+1 left) overlaps the side street's mouth."""
        return sgn > 0 and self._gap is not None and a < self._gap[1] and b > self._gap[0]

    def _ground_strips(self, x0: float, x1: float, seg: float = 20.0) -> None:
        rng = self.rng
        for k in range(int(math.ceil((x1 - x0) / seg))):
            xa = x0 + k * seg
            # the road runs on under the kerbs (no crack where the pavement rises 2 cm)
            w = 2 * (ROAD_HALF_M + 0.25)
            self.rect(f'road{k}', (xa, -w / 2, 0.0), (seg, 0, 0), (0, w, 0),
                      _texture(rng, seg, w, 95.0, contrast=0.55, ppm=GROUND_PPM), True)
            for side, sgn in (('l', 1.0), ('r', -1.0)):
                y_in, y_out = sgn * ROAD_HALF_M, sgn * PAVEMENT_HALF_M
                pavement = _texture(rng, seg, PAVEMENT_HALF_M - ROAD_HALF_M, 140.0,
                                    contrast=0.7, ppm=GROUND_PPM)
                yard = _texture(rng, seg, FAR_ROW_M - PAVEMENT_HALF_M, 110.0, contrast=0.6)
                if self._in_gap(sgn, xa, xa + seg):
                    continue
                self.rect(f'pavement{side}{k}', (xa, min(y_in, y_out), 0.02), (seg, 0, 0),
                          (0, PAVEMENT_HALF_M - ROAD_HALF_M, 0), pavement, True)
                # the ground behind the facades, seen through the gaps, up to the far row
                self.rect(f'yard{side}{k}', (xa, min(y_out, sgn * FAR_ROW_M), 0.0),
                          (seg, 0, 0), (0, FAR_ROW_M - PAVEMENT_HALF_M, 0), yard)

    def _facades(self, sgn: float, x0: float, x1: float) -> None:
        rng = self.rng
        x = x0
        while x < x1:
            length = float(rng.uniform(8.0, 30.0))
            height = float(rng.uniform(5.0, 18.0))
            y = sgn * float(rng.uniform(FACADE_MIN_M, PAVEMENT_HALF_M))
            tex = _texture(rng, length, height, float(rng.uniform(100, 160)))
            if not self._in_gap(sgn, x, x + length):
                # the facade faces the street: its normal points towards y = 0
                if sgn > 0:
                    self.rect('facade', (x, y, 0.0), (length, 0, 0), (0, 0, height), tex)
                else:
                    self.rect('facade', (x + length, y, 0.0), (-length, 0, 0),
                              (0, 0, height), tex)
            x += length + float(rng.choice([0.0, 0.0, rng.uniform(3.0, 8.0)]))

    def _far_row(self, sgn: float, x0: float, x1: float) -> None:
        far = sgn * FAR_ROW_M
        spans = [(x0, x1)]
        if sgn > 0 and self._gap is not None:
            spans = [(x0, self._gap[0]), (self._gap[1], x1)]
        tex = _texture(self.rng, x1 - x0, 12.0, float(self.rng.uniform(100, 150)))
        for a, b in spans:
            o = (a, far, 0.0) if sgn > 0 else (b, far, 0.0)
            u = (b - a, 0, 0) if sgn > 0 else (a - b, 0, 0)
            self.rect('far_row', o, u, (0, 0, 12.0), tex if len(spans) == 1 else
                      np.ascontiguousarray(tex[:, int((a - x0) * STREET_PPM):
                                               int((b - x0) * STREET_PPM)]))

    def _parked_cars(self, sgn: float, x0: float, x1: float) -> None:
        for xc in np.arange(x0 + 15.0, x1, 1.0):
            if self.rng.uniform() < 0.06:      # a parked car every ~17 m on average
                if self._in_gap(sgn, xc - 3.0, xc + 3.0):
                    continue
                self.box((float(xc), sgn * (ROAD_HALF_M - 1.2)), (4.3, 1.8, 1.5),
                         float(self.rng.uniform(-3, 3)))


@functools.lru_cache(maxsize=2)
def make_street_scene(seed: int = 0, junction: bool = False) -> Scene:
    """A straight street of STREET_X: road and pavements (20 m segments), a row of
    buildings on each side (8-30 m long, 5-18 m high, 8-12 m from the street's axis,
    with gaps of 0-8 m), a farther row FAR_ROW_M out seen through the gaps over open
    ground, and parked cars. `junction`: a side street joins from the left at
    x = JUNCTION_X (the ``car_turn`` trajectory turns into it).
    Geometry and textures depend on ``seed``; cached like synth_scene.make_scene."""
    rng = np.random.default_rng([int(seed), 8080])
    quads: list[Quad] = []
    textures: list[np.ndarray] = []
    gap = (JUNCTION_X - 10.0, JUNCTION_X + 10.0) if junction else None
    _Street(rng, quads, textures).build(*STREET_X, left_gap=gap)
    if junction:
        # the side street runs along +y; up to the main street's far row only its road
        # and its pavements (the corners are the main street's yards), then all of it
        side = _Street(rng, quads, textures, origin=(JUNCTION_X, 0.0), heading=np.pi / 2)
        kerb, gap_half = ROAD_HALF_M + 0.25, (gap[1] - gap[0]) / 2
        length = FAR_ROW_M - kerb
        side.rect('road_in', (kerb, -kerb, 0.0), (length, 0, 0), (0, 2 * kerb, 0),
                  _texture(rng, length, 2 * kerb, 95.0, contrast=0.55, ppm=GROUND_PPM), True)
        for sgn in (1.0, -1.0):
            side.rect('pavement_in', (ROAD_HALF_M, min(sgn * ROAD_HALF_M, sgn * gap_half), 0.02),
                      (FAR_ROW_M - ROAD_HALF_M, 0, 0), (0, gap_half - ROAD_HALF_M, 0),
                      _texture(rng, FAR_ROW_M - ROAD_HALF_M, gap_half - ROAD_HALF_M, 140.0,
                               contrast=0.7, ppm=GROUND_PPM), True)
        side.build(FAR_ROW_M, SIDE_STREET_END_M)
    return Scene(quads, textures, STREET_PPM, tile_m=STREET_TILE_M)


def _suspension(t: float, seed: int) -> tuple[float, float, float]:
    """(pitch, roll [rad], camera height [m]) of a car at t [s]: +-0.6 deg, 2 cm."""
    ph = np.random.default_rng([int(seed), 4243]).uniform(0, 2 * np.pi, 6)
    return (math.radians(0.6) * math.sin(2 * np.pi / 1.7 * t + ph[2]),
            math.radians(0.6) * math.sin(2 * np.pi / 2.3 * t + ph[3]),
            CAR_CAM_HEIGHT_M + 0.02 * math.sin(2 * np.pi / 1.3 * t + ph[4]))


def _car_T(x: float, y: float, yaw: float, t: float, seed: int) -> np.ndarray:
    pitch, roll, z = _suspension(t, seed)
    T = np.eye(4)
    T[:3, :3] = _euler_to_R(yaw, pitch, roll)
    T[:3, 3] = [x, y, z]
    return T


def car_pose(t: float, seed: int = 0) -> np.ndarray:
    """T_world_cam (optical frame) of the ``car`` trajectory at time ``t`` [s]: driving
    along the street at CAR_SPEED_MPS +- CAR_SPEED_SWING_MPS, weaving +-1.2 m across its
    lane (the heading follows the path: +-4 deg), with a suspension's pitch and roll of
    +-0.6 deg and 2 cm of heave."""
    ph = np.random.default_rng([int(seed), 4243]).uniform(0, 2 * np.pi, 6)
    w_speed, w_lane = 2 * np.pi / 9.0, 2 * np.pi / 11.0
    x = CAR_SPEED_MPS * t - CAR_SPEED_SWING_MPS / w_speed * (math.cos(w_speed * t + ph[0])
                                                             - math.cos(ph[0]))
    speed = CAR_SPEED_MPS + CAR_SPEED_SWING_MPS * math.sin(w_speed * t + ph[0])
    y = -2.0 + 1.2 * math.sin(w_lane * t + ph[1])
    yaw = math.atan2(1.2 * w_lane * math.cos(w_lane * t + ph[1]), speed)
    return _car_T(x, y, yaw, t, seed)


#: ``car_turn``: where it starts [m along x], the radius of its left turn into the side
#: street [m], its speed before and after the turn and in it [m/s], how long it takes
#: to slow down and to speed up again [s]
_TURN_START_X, _TURN_RADIUS_M = 60.0, 10.0
#: its lane: this far right of each street's axis [m]
_TURN_LANE_M = 2.0
_TURN_CRUISE_MPS, _TURN_SLOW_MPS, _TURN_RAMP_S = 9.0, 4.5, 5.0


def _turn_distance(t: float) -> float:
    """Distance driven by the ``car_turn`` car after t [s]: cruising, slowing down
    (linearly) to be at _TURN_SLOW_MPS where the arc begins, round the arc, speeding up
    again, cruising."""
    v0, v1, ramp = _TURN_CRUISE_MPS, _TURN_SLOW_MPS, _TURN_RAMP_S
    arc_start = (JUNCTION_X + _TURN_LANE_M - _TURN_RADIUS_M) - _TURN_START_X
    slow = 0.5 * (v0 + v1) * ramp
    phases = [((arc_start - slow) / v0, v0, v0), (ramp, v0, v1),
              (0.5 * np.pi * _TURN_RADIUS_M / v1, v1, v1), (ramp, v1, v0)]
    s = 0.0
    for duration, va, vb in phases:
        if t <= duration:
            return s + va * t + 0.5 * (vb - va) / duration * t * t
        s += 0.5 * (va + vb) * duration
        t -= duration
    return s + v0 * t                  # cruising on up the side street


def car_turn_pose(t: float, seed: int = 0) -> np.ndarray:
    """T_world_cam (optical frame) of the ``car_turn`` trajectory at t [s]: the car drives
    down the street from x = _TURN_START_X in the right-hand lane (y = -_TURN_LANE_M), slows to
    4.5 m/s, turns left into the side street on a 10 m radius (26 deg/s) and drives up it
    (x = JUNCTION_X + _TURN_LANE_M), with car_pose's suspension."""
    s = _turn_distance(float(t))
    R, x_arc, y0 = _TURN_RADIUS_M, JUNCTION_X + _TURN_LANE_M - _TURN_RADIUS_M, -_TURN_LANE_M
    straight = x_arc - _TURN_START_X
    arc = 0.5 * np.pi * R
    if s < straight:
        x, y, yaw = _TURN_START_X + s, y0, 0.0
    elif s < straight + arc:
        phi = (s - straight) / R
        x, y, yaw = x_arc + R * math.sin(phi), y0 + R * (1.0 - math.cos(phi)), phi
    else:
        x, y, yaw = x_arc + R, y0 + R + (s - straight - arc), 0.5 * np.pi
    return _car_T(x, y, yaw, float(t), seed)
