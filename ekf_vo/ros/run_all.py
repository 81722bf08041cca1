"""vo_node and map_node in one process (`ekf_vo_nodes`): the no-launch way to run both.

Both nodes share one SingleThreadedExecutor: vo_node's callbacks only enqueue (its
estimator runs on its own worker thread) and map_node is light, while rclpy's
MultiThreadedExecutor costs enough GIL time here to make the estimator drop frames.
ROS arguments (remaps, --params-file) apply to both, as with a composed process.
"""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from ..config import ConfigError
from .map_node import MapNode
from .vo_node import VoNode


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    nodes = []
    executor = SingleThreadedExecutor()
    try:
        nodes = [VoNode(), MapNode()]
        for node in nodes:
            executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ConfigError as exc:
        rclpy.logging.get_logger('ekf_vo_nodes').fatal(f'invalid parameters: {exc}')
        raise SystemExit(2) from exc
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
