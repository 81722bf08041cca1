"""A street for ``ekf-vo-synth``: the ``car`` trajectory's world (docs/method.md §15.16).

Every other rendered sequence is in one 7 m x 5.5 m room, 1-5 m from its walls. A car
camera sees something else: a road plane running to the horizon, facades 6-12 m to the
side that stream past at a metre a frame, parked cars, gaps between buildings that open
onto a farther row, and nothing at all (the sky) in the top of the image. Forward motion
puts the epipole inside the image, where the points barely move: the two-view bootstrap's
and the filter's hard case, and the one the shared KITTI frames show only 51 frames of.

World frame z up, x along the street (the car drives towards +x), y to the left. Textures
are drawn at a quarter of the room's scale (blotches of 10-90 cm, not 2.5-22 cm) and at
STREET_PPM texels per metre, so a 200 m street stays a few hundred MB and a few seconds.
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


@functools.lru_cache(maxsize=2)
def make_street_scene(seed: int = 0) -> Scene:
    """A straight street of STREET_X: road and pavements (20 m segments), a row of
    buildings on each side (8-30 m long, 5-18 m high, 8-12 m from the street's axis,
    with gaps of 0-8 m), a farther row FAR_ROW_M out seen through the gaps over open
    ground, and parked cars.
    Geometry and textures depend on ``seed``; cached like synth_scene.make_scene."""
    rng = np.random.default_rng([int(seed), 8080])
    quads: list[Quad] = []
    textures: list[np.ndarray] = []

    def add(quad_list: list[Quad], tex: list[np.ndarray]) -> None:
        quads.extend(quad_list)
        textures.extend(tex)

    x0, x1 = STREET_X
    seg = 20.0
    for k in range(int(math.ceil((x1 - x0) / seg))):
        xa = x0 + k * seg
        # the road runs on under the kerbs (no crack where the pavement rises 2 cm)
        w = 2 * (ROAD_HALF_M + 0.25)
        add([_ground(_rect(f'road{k}', (xa, -w / 2, 0.0), (seg, 0, 0), (0, w, 0),
                           len(textures)))],
            [_texture(rng, seg, w, 95.0, contrast=0.55, ppm=GROUND_PPM)])
        for side, sgn in (('l', 1.0), ('r', -1.0)):
            y_in, y_out = sgn * ROAD_HALF_M, sgn * PAVEMENT_HALF_M
            o = (xa, min(y_in, y_out), 0.02)
            add([_ground(_rect(f'pavement{side}{k}', o, (seg, 0, 0),
                               (0, PAVEMENT_HALF_M - ROAD_HALF_M, 0), len(textures)))],
                [_texture(rng, seg, PAVEMENT_HALF_M - ROAD_HALF_M, 140.0, contrast=0.7,
                          ppm=GROUND_PPM)])
            # the ground behind the facades, seen through the gaps, up to the far row
            o = (xa, min(y_out, sgn * FAR_ROW_M), 0.0)
            add([_rect(f'yard{side}{k}', o, (seg, 0, 0), (0, FAR_ROW_M - PAVEMENT_HALF_M, 0),
                       len(textures))],
                [_texture(rng, seg, FAR_ROW_M - PAVEMENT_HALF_M, 110.0, contrast=0.6)])
    for sgn in (1.0, -1.0):
        x = x0
        while x < x1:
            length = float(rng.uniform(8.0, 30.0))
            height = float(rng.uniform(5.0, 18.0))
            y = sgn * float(rng.uniform(FACADE_MIN_M, PAVEMENT_HALF_M))
            # the facade faces the street: its normal points towards y = 0
            if sgn > 0:
                quad = _rect('facade', (x, y, 0.0), (length, 0, 0), (0, 0, height), len(textures))
            else:
                quad = _rect('facade', (x + length, y, 0.0), (-length, 0, 0), (0, 0, height),
                             len(textures))
            add([quad], [_texture(rng, length, height, float(rng.uniform(100, 160)))])
            x += length + float(rng.choice([0.0, 0.0, rng.uniform(3.0, 8.0)]))
        far = sgn * FAR_ROW_M
        o = (x0, far, 0.0) if sgn > 0 else (x1, far, 0.0)
        u = (x1 - x0, 0, 0) if sgn > 0 else (x0 - x1, 0, 0)
        add([_rect('far_row', o, u, (0, 0, 12.0), len(textures))],
            [_texture(rng, x1 - x0, 12.0, float(rng.uniform(100, 150)))])
        for xc in np.arange(x0 + 15.0, x1, 1.0):
            if rng.uniform() < 0.06:      # a parked car every ~17 m on average
                first = len(textures)
                add(_box('car', (float(xc), sgn * (ROAD_HALF_M - 1.2)), (4.3, 1.8, 1.5),
                         float(rng.uniform(-3, 3)), first),
                    [_texture(rng, 4.3, 1.5, float(rng.uniform(60, 190))) for _ in range(5)])
    return Scene(quads, textures, STREET_PPM, tile_m=STREET_TILE_M)


def car_pose(t: float, seed: int = 0) -> np.ndarray:
    """T_world_cam (optical frame) of the ``car`` trajectory at time ``t`` [s]: driving
    along the street at CAR_SPEED_MPS +- CAR_SPEED_SWING_MPS, weaving +-1.2 m across its
    lane (the heading follows the path: +-4 deg), with a suspension's pitch and roll of
    +-0.6 deg and 2 cm of heave."""
    rng = np.random.default_rng([int(seed), 4243])
    ph = rng.uniform(0, 2 * np.pi, 6)
    w_speed, w_lane = 2 * np.pi / 9.0, 2 * np.pi / 11.0
    x = CAR_SPEED_MPS * t - CAR_SPEED_SWING_MPS / w_speed * (math.cos(w_speed * t + ph[0])
                                                             - math.cos(ph[0]))
    speed = CAR_SPEED_MPS + CAR_SPEED_SWING_MPS * math.sin(w_speed * t + ph[0])
    y = -2.0 + 1.2 * math.sin(w_lane * t + ph[1])
    yaw = math.atan2(1.2 * w_lane * math.cos(w_lane * t + ph[1]), speed)
    pitch = math.radians(0.6) * math.sin(2 * np.pi / 1.7 * t + ph[2])
    roll = math.radians(0.6) * math.sin(2 * np.pi / 2.3 * t + ph[3])
    z = CAR_CAM_HEIGHT_M + 0.02 * math.sin(2 * np.pi / 1.3 * t + ph[4])
    T = np.eye(4)
    T[:3, :3] = _euler_to_R(yaw, pitch, roll)
    T[:3, 3] = [x, y, z]
    return T
