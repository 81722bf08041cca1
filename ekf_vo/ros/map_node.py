"""map_node: accumulate vo_node's landmark updates into the global sparse map.

Topics
------
Subscribes ``landmarks`` (sensor_msgs/PointCloud2; reliable, keep last 50), one incremental
update per message, in the odom frame::

    x, y, z  FLOAT32  position in the odom frame (NaN allowed when removed == 1)
    id       UINT32   landmark id (unique for the life of vo_node)            [required]
    n_obs    UINT32   number of observations so far                [optional, default 0]
    removed  UINT8    1: delete this id from the map; 0: insert/update  [optional, default 0]

Points are upserted by id (the last message wins) and deleted on ``removed == 1``. A point
with ``removed == 0`` and a non-finite coordinate is skipped (counted). A cloud whose
non-empty ``frame_id`` differs from the ``odom_frame`` parameter is rejected: without tf2
there is nothing to transform it with.

Publishes ``map_points`` (sensor_msgs/PointCloud2; reliable + transient_local, depth 1 so a
late RViz gets the last map): fields x y z FLOAT32, id UINT32, n_obs UINT32, height 1,
width N, points sorted by id, frame ``odom_frame``, stamp = the newest landmark stamp (or
the node clock before any). Published at ``publish_rate_hz`` when the map changed since the
last publish, and once at start-up (an empty map).

Service ``~/clear`` (std_srvs/Trigger) empties the map.

Malformed input never crashes the node: it is counted (``bad_messages``) and reported with
a warning throttled to one per 5 s.
"""
from __future__ import annotations

import sys
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from ekf_vo.config import MapNodeConfig
from ekf_vo.bridge.common import ConversionError, stamp_to_ns
from ekf_vo.bridge.pointcloud2 import pointcloud2_to_numpy, points_to_pointcloud2
from ekf_vo.ros.lifecycle import run_nodes
from ekf_vo.ros.params import (declare_from_dataclass, install_validation,
                               warn_unknown_parameters)

__all__ = ['MapNode', 'main', 'LANDMARKS_QOS', 'MAP_QOS']

#: QoS of the ``landmarks`` input: every update matters (no best effort), a burst is queued.
LANDMARKS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE)
#: QoS of ``map_points``: latched (transient_local, depth 1) so late subscribers get the map.
MAP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

_WARN_PERIOD_S = 5.0


class MapNode(Node):
    """Global sparse map keyed by landmark id (see the module docstring for the interface).

    Attributes:
        config: the current :class:`MapNodeConfig`.
        points: ``{id: (x, y, z, n_obs)}``; xyz float32-representable, odom frame.
        received, bad_messages, bad_points, published: counters.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('map_node', **kwargs)
        self.config: MapNodeConfig = declare_from_dataclass(self, MapNodeConfig)
        warn_unknown_parameters(self)
        self.points: dict[int, tuple[float, float, float, int]] = {}
        self.received = 0
        self.bad_messages = 0
        self.bad_points = 0
        self.published = 0
        self._dirty = True          # publish once at start even when empty
        self._last_stamp_ns: int | None = None
        self._pub = self.create_publisher(PointCloud2, 'map_points', MAP_QOS)
        self._sub = self.create_subscription(PointCloud2, 'landmarks', self._on_landmarks,
                                             LANDMARKS_QOS)
        self._clear_srv = self.create_service(Trigger, '~/clear', self._on_clear)
        self._timer = self.create_timer(1.0 / self.config.publish_rate_hz, self._on_timer)
        install_validation(self, MapNodeConfig, self._on_config)
        self.get_logger().info(
            f'map_node: landmarks -> map_points at {self.config.publish_rate_hz} Hz '
            f'in frame {self.config.odom_frame!r}')

    # ------------------------------------------------------------------ parameters
    def _on_config(self, config: MapNodeConfig) -> None:
        old = self.config
        self.config = config
        if config.publish_rate_hz != old.publish_rate_hz:
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(1.0 / config.publish_rate_hz, self._on_timer)
        if config.odom_frame != old.odom_frame:
            self._dirty = True

    # ------------------------------------------------------------------ input
    def _bad(self, reason: str) -> None:
        self.bad_messages += 1
        self.get_logger().warning(
            f'landmarks: dropped bad message ({reason}); {self.bad_messages} dropped so far',
            throttle_duration_sec=_WARN_PERIOD_S)

    def _on_landmarks(self, msg: PointCloud2) -> None:
        self.received += 1
        try:
            self._apply(msg)
        except ConversionError as exc:
            self._bad(str(exc))
        except (ValueError, TypeError, OverflowError) as exc:
            self._bad(f'{type(exc).__name__}: {exc}')

    def _apply(self, msg: PointCloud2) -> None:
        frame = msg.header.frame_id
        if frame and frame != self.config.odom_frame:
            raise ConversionError(
                f"PointCloud2: frame_id '{frame}' is not the odom_frame "
                f"'{self.config.odom_frame}' (no tf2 here to transform it)")
        stamp_ns = stamp_to_ns(msg.header.stamp)
        cols = pointcloud2_to_numpy(msg)
        missing = [c for c in ('x', 'y', 'z', 'id') if c not in cols]
        if missing:
            raise ConversionError(f'PointCloud2: missing field(s) {missing}; have {sorted(cols)}')
        if any(cols[c].ndim != 1 for c in cols):
            raise ConversionError('PointCloud2: every field must have count 1')
        n = cols['x'].shape[0]
        ids = cols['id']
        if ids.dtype.kind not in 'iu':
            raise ConversionError(f'PointCloud2: id has dtype {ids.dtype}, expected uint32')
        if n and int(ids.min()) < 0:
            raise ConversionError('PointCloud2: negative id')
        ids = ids.astype(np.int64)
        xyz = np.stack([cols['x'], cols['y'], cols['z']], axis=1).astype(np.float64)
        n_obs = cols['n_obs'].astype(np.int64) if 'n_obs' in cols else np.zeros(n, np.int64)
        removed = (cols['removed'] != 0) if 'removed' in cols else np.zeros(n, bool)
        finite = np.isfinite(xyz).all(axis=1)
        bad = int(np.count_nonzero(~removed & ~finite))
        if bad:
            self.bad_points += bad
            self.get_logger().warning(
                f'landmarks: skipped {bad} point(s) with NaN/inf position '
                f'({self.bad_points} so far)', throttle_duration_sec=_WARN_PERIOD_S)
        changed = False
        # In message order, so an id repeated within one message ends in its last state.
        for i in range(n):
            key = int(ids[i])
            if removed[i]:
                changed |= self.points.pop(key, None) is not None
            elif finite[i]:
                self.points[key] = (float(xyz[i, 0]), float(xyz[i, 1]), float(xyz[i, 2]),
                                    int(n_obs[i]))
                changed = True
        if changed:
            self._dirty = True
            self._last_stamp_ns = stamp_ns

    # ------------------------------------------------------------------ output
    def map_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The map sorted by id: ``(ids (N,) uint32, xyz (N, 3) float64, n_obs (N,) uint32)``."""
        if not self.points:
            return np.zeros(0, np.uint32), np.zeros((0, 3)), np.zeros(0, np.uint32)
        keys = sorted(self.points)
        rows = np.array([self.points[k] for k in keys], dtype=np.float64)
        return (np.array(keys, dtype=np.uint32), rows[:, :3],
                rows[:, 3].astype(np.uint32))

    def build_cloud(self) -> PointCloud2:
        ids, xyz, n_obs = self.map_arrays()
        stamp_ns = self._last_stamp_ns
        if stamp_ns is None:
            stamp_ns = max(self.get_clock().now().nanoseconds, 0)
        return points_to_pointcloud2(xyz, stamp_ns, self.config.odom_frame,
                                     extra_fields={'id': ids, 'n_obs': n_obs})

    def _on_timer(self) -> None:
        if not self._dirty:
            return
        try:
            cloud = self.build_cloud()
        except ConversionError as exc:  # e.g. a stamp beyond 2038: keep running
            self.get_logger().error(f'cannot build map_points: {exc}',
                                    throttle_duration_sec=_WARN_PERIOD_S)
            return
        self._pub.publish(cloud)
        self.published += 1
        self._dirty = False

    def _on_clear(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        n = len(self.points)
        self.points.clear()
        self._dirty = True
        response.success = True
        response.message = f'cleared {n} map points'
        self.get_logger().info(response.message)
        return response


def main(args: list[str] | None = None) -> int:
    return run_nodes('map_node', lambda: [MapNode()], args, config_error_code=1)


if __name__ == '__main__':
    sys.exit(main())
