"""vo_node and map_node in one process (`ekf_vo_nodes`): the no-launch way to run both.

Both nodes share a MultiThreadedExecutor; ROS arguments (remaps, --params-file) apply to
both, as with `ros2 run` of a composed process.
"""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

from ..config import ConfigError
from .map_node import MapNode
from .vo_node import VoNode


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    nodes = []
    executor = MultiThreadedExecutor(num_threads=2)
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
