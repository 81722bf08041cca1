"""A synthetic wheel odometry for rendered ground-robot sequences (docs/method.md §16.4).

The robot's base (its turning axis on the floor) follows synth_scene's `ground_robot` or
`ground_robot_arcs` path; the wheels measure each step's travelled distance with a relative white noise and,
in slip episodes, too much distance (the wheels spin); the heading integrates the true
heading change with a small relative error. Positions are integrated in the odometry's
own frame (starting at the origin), as a real wheel odometry would publish them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .synth_scene import robot_base


@dataclass(frozen=True)
class WheelNoise:
    distance_sigma: float = 0.02     #: relative white noise of one step's distance
    heading_sigma: float = 0.01      #: relative error of one step's heading change
    slip: float = 0.3                #: extra distance read in a slip episode (0.3 = +30 %)
    slip_share: float = 0.05         #: share of the time in slip episodes
    slip_episode_s: float = 1.0      #: length of one slip episode [s]


def wheel_odometry(trajectory: str, stamps_s: np.ndarray, noise: WheelNoise, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N,3) in the odometry frame [m], slipping (N,) bool) at `stamps_s`, the
    trajectory's own time (0 at its start, synth_scene.trajectory_pose)."""
    rng = np.random.default_rng(seed + 7919)
    t = np.asarray(stamps_s, float)
    duration = float(t[-1] - t[0]) if len(t) else 0.0
    n_episodes = int(round(noise.slip_share * duration / noise.slip_episode_s))
    starts = t[0] + rng.uniform(0.0, max(duration - noise.slip_episode_s, 0.0), n_episodes)
    slipping = np.zeros(len(t), bool)
    for s in starts:
        slipping |= (t >= s) & (t < s + noise.slip_episode_s)
    xyz = np.zeros((len(t), 3))
    x0, y0, h_prev = robot_base(trajectory, t[0]) if len(t) else (0.0, 0.0, 0.0)
    prev, heading = np.array([x0, y0]), 0.0
    for k in range(1, len(t)):
        xb, yb, h = robot_base(trajectory, t[k])
        step = np.array([xb, yb]) - prev
        forward = np.array([math.cos(h_prev), math.sin(h_prev)])
        dist = float(np.linalg.norm(step)) * (1.0 if step @ forward >= 0 else -1.0)
        dist *= 1.0 + noise.distance_sigma * rng.standard_normal() + \
            (noise.slip if slipping[k] else 0.0)
        turn = (h - h_prev + math.pi) % (2 * math.pi) - math.pi
        heading += turn * (1.0 + noise.heading_sigma * rng.standard_normal())
        xyz[k] = xyz[k - 1] + dist * np.array([math.cos(heading), math.sin(heading), 0.0])
        prev, h_prev = np.array([xb, yb]), h
    return xyz, slipping


__all__ = ['WheelNoise', 'wheel_odometry']
