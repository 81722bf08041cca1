"""vo_node and map_node in one process (`ekf_vo_nodes`): the no-launch way to run both.

Both nodes share one SingleThreadedExecutor: vo_node's callbacks only enqueue (its
estimator runs on its own worker thread) and map_node is light, while rclpy's
MultiThreadedExecutor costs enough GIL time here to make the estimator drop frames.
ROS arguments (remaps, --params-file) apply to both, as with a composed process.
"""
from __future__ import annotations

import sys

from .lifecycle import run_nodes
from .map_node import MapNode
from .vo_node import VoNode


def main(args: list[str] | None = None) -> int:
    return run_nodes('ekf_vo_nodes', lambda: [VoNode(), MapNode()], args)


if __name__ == '__main__':
    sys.exit(main())
