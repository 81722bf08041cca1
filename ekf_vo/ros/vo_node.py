"""vo_node: the ROS 2 edge around the estimation core (ekf_vo.core.pipeline).

Subscribes  image (sensor_msgs/Image) or image/compressed (sensor_msgs/CompressedImage),
            camera_info (sensor_msgs/CameraInfo); sensor-data QoS unless reliable_qos;
            scale_odom (nav_msgs/Odometry, e.g. wheel odometry) with scale_source odometry.
Publishes   odom (nav_msgs/Odometry, reliable), landmarks (PointCloud2 updates for
            map_node), ~/path (nav_msgs/Path), ~/status (diagnostic_msgs/DiagnosticArray),
            ~/debug_image (sensor_msgs/Image, only computed while subscribed).
Services    ~/reset (std_srvs/Trigger).

Threading: subscription callbacks only convert and enqueue; with `queue_policy: latest`
the queue holds `queue_size` frames and, when full, the OLDEST frame is dropped and counted;
with `queue_policy: all` (replay) nothing is dropped and frames wait for the first
CameraInfo. One worker thread
runs the estimator and publishes, so a slow frame never blocks the executor.
"""
from __future__ import annotations

import collections
import math
import sys
import threading
import time
from typing import Any

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger

from ..config import NodeConfig, VoConfig
from ..core.camera import CameraModelError
from ..core.frames import camera_to_base, optical_to_body_extrinsic, points_to_odom
from ..core.pipeline import TrackingState, VisualOdometry
from ..core.stream import Rejection, VoStream
from .. import bridge as conv
from .lifecycle import run_nodes
from .params import declare_from_dataclass, install_validation, warn_unknown_parameters

#: each kind of rejected input is logged at most this often (and always counted)
WARN_PERIOD_S = 5.0
#: ~/status at most this often after a processed frame, and at least this often while the
#: estimator has said anything (its counters current when the images stop) [s]
STATUS_PERIOD_S = 0.5
#: the whole map is re-sent once the metric scale moved by this fraction, or its offset
#: by OFFSET_REPUBLISH_M, since it was last sent (metric_scale.py)
SCALE_REPUBLISH_REL = 0.002
OFFSET_REPUBLISH_M = 0.05


class VoNode(Node):
    """Monocular EKF visual odometry node."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('vo_node', **kwargs)
        self.core_cfg: VoConfig = declare_from_dataclass(self, VoConfig)
        self.node_cfg: NodeConfig = declare_from_dataclass(self, NodeConfig)
        install_validation(self, VoConfig, self._on_core_params)
        install_validation(self, NodeConfig, self._on_node_params)
        warn_unknown_parameters(self)
        self.T_base_cam = optical_to_body_extrinsic(self.node_cfg.T_base_cam_xyz,
                                                    self.node_cfg.T_base_cam_xyzw)

        self._lock = threading.Lock()          # guards node state shared with the worker
        self._queue: collections.deque = collections.deque()
        self._queue_cv = threading.Condition()
        self._stop = threading.Event()
        #: the core's front door: calibration changes, stamp checks, resets (stream.py)
        self.stream = VoStream(self.core_cfg, T_base_cam=self.T_base_cam)
        self._published_scale = (1.0, np.zeros(3))   # the map's (scale, offset) last sent
        self._map_restarted = False            # a new estimator: clear map_node's map
        self._published_ids: set[int] = set()
        self._landmark_subscribers = 0
        self._path = Path()
        self._latencies_ms: collections.deque = collections.deque(maxlen=1000)
        self._frame_times: collections.deque = collections.deque(maxlen=60)
        self._last_status_time = 0.0
        self._last_path_publish = 0.0
        self._last_result = None
        self.counters = collections.Counter()
        self._last_warned: dict[str, float] = {}

        sub_qos = qos_profile_sensor_data
        if self.node_cfg.queue_policy == 'all':
            # replay: nothing may be lost between the player and the queue either
            sub_qos = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                                 history=HistoryPolicy.KEEP_ALL)
        elif self.node_cfg.reliable_qos:
            sub_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                                 history=HistoryPolicy.KEEP_LAST)
        self.create_subscription(CameraInfo, 'camera_info', self._on_camera_info, sub_qos)
        self.image_topic = self._image_topic()
        if self.node_cfg.image_transport == 'compressed':
            self.create_subscription(CompressedImage, self.image_topic, self._on_compressed,
                                     sub_qos)
        else:
            self.create_subscription(Image, self.image_topic, self._on_image, sub_qos)
        if self.core_cfg.scale_source == 'odometry':
            self.create_subscription(Odometry, 'scale_odom', self._on_scale_odom,
                                     QoSProfile(depth=50))
        self._last_image_time = time.monotonic()
        self._last_state: str | None = None          # logged state, see _log_state_change
        self.create_timer(WARN_PERIOD_S, self._check_inputs)

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.odom_pub = self.create_publisher(Odometry, 'odom', reliable)
        self.landmark_pub = self.create_publisher(
            PointCloud2, 'landmarks', QoSProfile(depth=50,
                                                 reliability=ReliabilityPolicy.RELIABLE))
        self.path_pub = self.create_publisher(Path, '~/path', reliable)
        self.status_pub = self.create_publisher(DiagnosticArray, '~/status', reliable)
        self.debug_pub = self.create_publisher(Image, '~/debug_image', qos_profile_sensor_data)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self._worker = threading.Thread(target=self._work, name='vo_worker', daemon=True)
        self._worker.start()
        self.get_logger().info(
            f'vo_node ready: estimator={self.core_cfg.estimator}, '
            f'transport={self.node_cfg.image_transport}, odom_frame='
            f'{self.node_cfg.odom_frame}, base_frame={self.node_cfg.base_frame}')

    def _image_topic(self) -> str:
        """The image topic to subscribe, image_transport's way: the `image` topic after
        remapping, plus `/compressed` for the compressed transport (an explicit remap of
        `image/compressed` still wins)."""
        transport = self.node_cfg.image_transport
        base = self.resolve_topic_name('image')
        if transport == 'compressed':
            own = self.resolve_topic_name('image/compressed')
            if own != self.resolve_topic_name('image/compressed', only_expand=True):
                return own
        return conv.transport_topic(base, transport)

    def _check_inputs(self) -> None:
        """Say so when no image arrives: the commonest set-up mistake is a topic name."""
        idle = time.monotonic() - self._last_image_time
        if idle >= WARN_PERIOD_S:
            what = 'since start' if self.counters['received'] == 0 else f'for {idle:.0f} s'
            self.get_logger().warning(
                f'no image on {self.image_topic} {what} (image_transport: '
                f'{self.node_cfg.image_transport}); check the remapping')

    # ------------------------------------------------------------------ parameters
    def _on_core_params(self, cfg: VoConfig) -> None:
        with self._lock:
            self.core_cfg = cfg
            self.stream.set_config(cfg)
            self._map_restarted = True
        self.get_logger().info('estimator parameters changed: re-initialising')

    def _on_node_params(self, cfg: NodeConfig) -> None:
        with self._lock:
            self.node_cfg = cfg
            self.T_base_cam = optical_to_body_extrinsic(cfg.T_base_cam_xyz,
                                                        cfg.T_base_cam_xyzw)

    # ------------------------------------------------------------------ inputs
    def _warn(self, key: str, text: str) -> None:
        """Count a rejected input and log it at most every 5 s per kind.

        (rclpy's throttle is per call site, which would let one kind hide another.)"""
        self.counters[key] += 1
        now = time.monotonic()
        if now - self._last_warned.get(key, -1e9) >= WARN_PERIOD_S:
            self._last_warned[key] = now
            self.get_logger().warning(f'{text} [{key}: {self.counters[key]} so far]')

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Recorded by stamp for the image of that stamp (core/pairing.py); a changed
        calibration restarts the estimator at that image."""
        stamp_ns = None
        try:
            stamp_ns = conv.stamp_to_ns(msg.header.stamp)
            info = conv.camera_info_to_dict(msg)
            conv.validate_camera_info(info)
            self.stream.add_camera_info(stamp_ns, info)
        except (conv.ConversionError, CameraModelError, ValueError) as exc:
            if stamp_ns is not None:
                self.stream.reject_camera_info(stamp_ns)   # its image goes with it
            self._warn('bad_camera_info', f'CameraInfo rejected: {exc}')
        with self._queue_cv:
            self._queue_cv.notify_all()      # a frame may be waiting for this stamp

    def _on_scale_odom(self, msg: Odometry) -> None:
        """An external odometry for the metric scale: only its position is used."""
        try:
            stamp_ns = conv.stamp_to_ns(msg.header.stamp)
            T = conv.odometry_to_pose(msg)[0]
        except conv.ConversionError as exc:
            self._warn('bad_scale_odom', f'scale_odom ignored: {exc}')
            return
        rejected = self.stream.add_scale_odometry(stamp_ns, T[:3, 3])
        if rejected is not None:
            self._warn(rejected.key, rejected.text)

    def _on_image(self, msg: Image) -> None:
        self._enqueue(msg, conv.IMAGE, 'image')

    def _on_compressed(self, msg: CompressedImage) -> None:
        self._enqueue(msg, conv.COMPRESSED_IMAGE, 'compressed image')

    def _enqueue(self, msg: Any, msgtype: str, what: str) -> None:
        received = time.perf_counter()
        self._last_image_time = time.monotonic()
        self.counters['received'] += 1
        replay = self.node_cfg.queue_policy == 'all'
        try:
            stamp_ns = conv.stamp_to_ns(msg.header.stamp)
            gray = conv.decode_image(msgtype, msg, gray=True)
        except conv.ConversionError as exc:
            self._warn('bad_image', f'{what} rejected: {exc}')
            return
        with self._queue_cv:
            # stamps are checked in arrival order, before the queue may drop frames
            time_resets = self.stream.counters['time_resets']
            rejected = self.stream.admit(stamp_ns)      # VoStream guards its own inputs
            if rejected is not None:
                self._warn(rejected.key, rejected.text)
                return
            if self.stream.counters['time_resets'] != time_resets:
                self._warn('time_resets', 'time went backwards (looping bag or sim reset): '
                           'resetting')
            if not replay and len(self._queue) >= self.node_cfg.queue_size:
                self._queue.popleft()
                self._warn('dropped_behind', 'estimator behind: dropped the oldest frame')
            self._queue.append((stamp_ns, gray, received))
            self._queue_cv.notify()

    def _awaits_camera_info(self, item: tuple) -> bool:
        """The frame `item` (stamp, image, arrival) should still wait for the CameraInfo
        of its stamp: none at or after it has come, it arrived less than
        camera_info_wait_s ago, and CameraInfo has been matching image stamps."""
        stamp_ns, _, received = item
        if time.perf_counter() - received >= self.node_cfg.camera_info_wait_s:
            return False
        pair = self.stream.pairing(stamp_ns)
        if pair is None:
            return True
        return pair.wait and self.stream.last_pair_exact is not False

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self.counters['reset_requests'] += 1
        self.stream.request_reset('~/reset called')
        response.success = True
        response.message = 'reset scheduled: the next frame starts a new bootstrap'
        return response

    # ------------------------------------------------------------------ worker
    def _work(self) -> None:
        while not self._stop.is_set():
            with self._queue_cv:
                # queue_policy all: frames that came before the first CameraInfo wait
                replay = self.node_cfg.queue_policy == 'all'
                while not self._stop.is_set() and (
                        not self._queue or (replay and self.stream.camera is None)):
                    self._queue_cv.wait(timeout=0.2)
                    if not self._queue:
                        self._status_while_idle()
                # the head waits (bounded) for the CameraInfo of its stamp
                while not self._stop.is_set() and self._queue and \
                        self._awaits_camera_info(self._queue[0]):
                    self._queue_cv.wait(timeout=0.005)
                if self._stop.is_set():
                    return
                if not self._queue:
                    continue
                stamp_ns, gray, received = self._queue.popleft()
            try:
                self._process(stamp_ns, gray, received)
            except Exception as exc:  # keep the node alive; say what happened, reset
                self.counters['internal_errors'] += 1
                self.get_logger().error(f'estimator error, resetting: {exc!r}',
                                        throttle_duration_sec=5.0)
                with self._lock:
                    self.stream.restart()
                    self._map_restarted = True

    def _status_while_idle(self) -> None:
        """~/status again when no frame has sent one for STATUS_PERIOD_S (a paused
        camera, the end of a bag): the last state with the counters as they are now, e.g.
        the frames dropped since. On the worker thread, as the estimator is idle there."""
        result = self._last_result
        if result is not None and \
                time.perf_counter() - self._last_status_time > STATUS_PERIOD_S:
            self._last_status_time = time.perf_counter()
            self._publish_status(result)

    def _process(self, stamp_ns: int, gray: np.ndarray, received: float) -> None:
        # the estimator runs outside the node's lock: callbacks (CameraInfo, ~/reset,
        # parameters) are never held up by a frame
        n_requested = self.stream.n_requested_resets
        n_changes = self.stream.n_camera_changes
        published: list[bool] = []

        def publish_pose(res) -> None:
            if res.ok and not published:
                self._publish_odometry(res)
                self._latencies_ms.append((time.perf_counter() - received) * 1e3)
                published.append(True)

        # a tracked frame's odometry goes out before the estimator's map work
        # (docs/method.md §17.3): that work is latency nobody downstream waits for
        result = self.stream.process(gray, stamp_ns, on_pose=publish_pose)
        if self.stream.n_camera_changes != n_changes:
            with self._lock:
                self._map_restarted = True
            self.get_logger().info('CameraInfo changed: re-initialising the estimator')
        vo = self.stream.vo
        if isinstance(result, Rejection):
            self._warn(result.key, result.text)
            return
        with self._lock:
            restarted, self._map_restarted = self._map_restarted, False
        self._log_state_change(result)
        if restarted or self.stream.n_requested_resets != n_requested:
            # a new map: odometry continues, but map_node and ~/path start again
            self._path.poses.clear()
            self._publish_removals(list(self._published_ids))
        self.counters['processed'] += 1
        self._frame_times.append(time.perf_counter())
        if result.ok:
            publish_pose(result)           # bootstrap and relocalised frames: now
            self.counters['published'] += 1
        elif result.message:
            self.get_logger().info(f'[{result.state.value}] {result.message}',
                                   throttle_duration_sec=2.0)
        if result.bootstrapped or self.counters['processed'] % \
                self.node_cfg.landmarks_every_n_frames == 0:
            self._publish_landmarks(vo, stamp_ns)
        self._last_result = result
        if self.debug_pub.get_subscription_count() > 0:
            self._publish_debug(gray, result)
        now = time.perf_counter()
        if now - self._last_status_time > STATUS_PERIOD_S:
            self._last_status_time = now
            self._publish_status(result)

    # ------------------------------------------------------------------ outputs
    def _log_state_change(self, result) -> None:
        """initialising (-> orientation only) -> tracking -> lost, and tracking's ok <->
        degraded, logged once per change with the reason."""
        # the pipeline re-bootstraps at once after a loss: the frame says 'lost: why'
        state_name = 'lost' if result.message.startswith('lost') else result.state.value
        if state_name == 'tracking' and result.health == 'degraded':
            state_name = 'degraded'
        if result.orientation_only:       # before a map (docs/method.md §15.9)
            state_name = 'orientation only'
        if state_name == self._last_state:
            return
        previous = self._last_state or 'started'
        self._last_state = state_name
        why = result.health_reason if state_name in ('degraded', 'orientation only') \
            else result.message
        why = f': {why}' if why else ''
        # rclpy fixes a call site's severity at its first call: one call per severity
        if state_name in ('lost', 'degraded'):
            self.get_logger().warning(f'{previous} -> {state_name}{why}')
        else:
            self.get_logger().info(f'{previous} -> {state_name}{why}')

    def _publish_odometry(self, result) -> None:
        T_odom_base, cov, twist, twist_cov = camera_to_base(
            result.T_world_cam, result.pose_cov, result.twist_cam, result.twist_cov,
            self.T_base_cam)
        try:
            msg = conv.pose_to_odometry(T_odom_base, cov, twist[:3], twist[3:], twist_cov,
                                        result.stamp_ns, self.node_cfg.odom_frame,
                                        self.node_cfg.base_frame)
        except conv.ConversionError as exc:
            self._warn('bad_output', f'odometry not published: {exc}')
            return
        self.odom_pub.publish(msg)
        if self.node_cfg.publish_path:
            pose = PoseStamped()
            pose.header = msg.header
            pose.pose = msg.pose.pose
            self._path.header = msg.header
            self._path.poses.append(pose)
            if len(self._path.poses) > self.node_cfg.max_path_length:
                del self._path.poses[0]
            # serialising a long Path costs O(length): publish it at a bounded rate
            now = time.monotonic()
            if now - self._last_path_publish >= 1.0 / self.node_cfg.path_rate_hz:
                self._last_path_publish = now
                self.path_pub.publish(self._path)

    def _publish_landmarks(self, vo: VisualOdometry, stamp_ns: int) -> None:
        changes = vo.map.pop_changes()
        n_subs = self.landmark_pub.get_subscription_count()
        scale = (self.stream.scale.scale, self.stream.scale.offset.copy())
        old_scale, old_offset = self._published_scale
        moved = abs(scale[0] / old_scale - 1.0) > SCALE_REPUBLISH_REL or \
            np.linalg.norm(scale[1] - old_offset) > OFFSET_REPUBLISH_M
        if n_subs > self._landmark_subscribers or moved:
            # a map_node joined (or restarted), or the metric scale moved the map: send
            # the whole map, not just the changes
            self._published_scale = scale
            # a map_node joined (or restarted): send it the whole map, not just changes
            changes.ids, changes.X_world = vo.map.ids.copy(), vo.map.X_world.copy()
            changes.n_obs = vo.map.n_obs.copy()
        self._landmark_subscribers = n_subs
        removed = [int(i) for i in changes.removed_ids if int(i) in self._published_ids]
        if len(changes.ids) == 0 and not removed:
            return
        X = points_to_odom(self.stream.map_points(changes.X_world), self.T_base_cam) \
            if len(changes.ids) else np.zeros((0, 3))
        xyz = np.vstack((X, np.full((len(removed), 3), np.nan)))
        ids = np.concatenate((changes.ids, np.array(removed, np.int64))).astype(np.uint32)
        n_obs = np.concatenate((changes.n_obs, np.zeros(len(removed), np.int32)))
        flag = np.concatenate((np.zeros(len(changes.ids)), np.ones(len(removed))))
        msg = conv.points_to_pointcloud2(
            xyz.astype(np.float32), stamp_ns, self.node_cfg.odom_frame,
            {'id': ids, 'n_obs': n_obs.astype(np.uint32), 'removed': flag.astype(np.uint8)})
        self.landmark_pub.publish(msg)
        self._published_ids.update(int(i) for i in changes.ids)
        self._published_ids.difference_update(removed)

    def _publish_removals(self, ids: list) -> None:
        if not ids:
            return
        msg = conv.points_to_pointcloud2(
            np.full((len(ids), 3), np.nan, np.float32), self._stamp_now(),
            self.node_cfg.odom_frame,
            {'id': np.array(ids, np.uint32), 'n_obs': np.zeros(len(ids), np.uint32),
             'removed': np.ones(len(ids), np.uint8)})
        self.landmark_pub.publish(msg)
        self._published_ids.clear()

    def _stamp_now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _publish_debug(self, gray: np.ndarray, result) -> None:
        img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        if result.track_px is not None:
            inl = result.track_inlier if result.track_inlier is not None else \
                np.zeros(len(result.track_px), bool)
            has = result.track_has_point if result.track_has_point is not None else inl
            for (u, v), i, h in zip(result.track_px, inl, has):
                color = (0, 255, 0) if i else ((0, 0, 255) if h else (255, 160, 0))
                cv2.circle(img, (int(u), int(v)), 3, color, 1, cv2.LINE_AA)
        cv2.putText(img, f'{result.state.value} inliers {result.n_inliers} map '
                    f'{result.map_size}', (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 1, cv2.LINE_AA)
        self.debug_pub.publish(conv.numpy_to_image(img, 'bgr8', result.stamp_ns,
                                                   'camera_debug'))

    def status_values(self) -> dict:
        """Numbers reported on ~/status (also used by tests and the latency bench)."""
        fps = 0.0
        if len(self._frame_times) > 1:
            span = self._frame_times[-1] - self._frame_times[0]
            fps = (len(self._frame_times) - 1) / span if span > 0 else 0.0
        lat = np.array(self._latencies_ms) if self._latencies_ms else np.zeros(1)
        r = self._last_result
        vals = {'state': r.state.value if r else 'waiting',
                'health': (r.health or r.state.value) if r else 'waiting',
                'health_reason': r.health_reason if r else '',
                'variance_factor': round(r.variance_factor, 2) if r else 1.0,
                'found_share': round(r.found_share, 2) if r else 1.0,
                'fps': round(fps, 2), 'latency_p50_ms': round(float(np.percentile(lat, 50)), 2),
                'latency_p95_ms': round(float(np.percentile(lat, 95)), 2),
                'tracks': r.n_tracks if r else 0, 'inliers': r.n_inliers if r else 0,
                'rays': r.n_rays if r else 0,
                'camera_fixed_share': round(r.camera_fixed_share, 3) if r else 0.0,
                'lens_falloff_drop': round(r.lens_falloff_drop, 3) if r else 0.0,
                'klt_window_px': r.klt_window_px if r else 0,
                'klt_log_gain': round(r.klt_log_gain, 3) if r else 0.0,
                'klt_wide_kept': r.klt_wide_kept if r else 0,
                'sensor_noise_grey': round(r.sensor_noise_grey, 2)
                if r and math.isfinite(r.sensor_noise_grey) else '',
                'denoised': bool(r.denoised) if r else False,
                'readout_ms': round(r.readout_s * 1e3, 2) if r else 0.0,
                'readout_estimate_ms': round(r.readout_estimate_s * 1e3, 2)
                if r and math.isfinite(r.readout_estimate_s) else '',
                'map_points': r.map_size if r else 0,
                'resets': self.stream.n_resets}
        vals.update(self.stream.local_map_stats())
        vals.update(self.stream.scale_status().as_status())
        vals.update(self.counters)
        return vals

    def _publish_status(self, result) -> None:
        vals = self.status_values()
        st = DiagnosticStatus()
        st.name = f'{self.get_name()}: visual odometry'
        st.hardware_id = 'camera'
        # OK / DEGRADED / LOST (docs/ros.md): degraded and initialising warn
        if result.state == TrackingState.TRACKING and result.ok and result.health == 'ok':
            st.level = DiagnosticStatus.OK
        elif result.state == TrackingState.INITIALISING or \
                (result.state == TrackingState.TRACKING and result.health == 'degraded'):
            st.level = DiagnosticStatus.WARN
        else:
            st.level = DiagnosticStatus.ERROR
        health = f' ({result.health})' if result.health else ''
        why = result.health_reason or result.message or 'ok'
        st.message = f'{result.state.value}{health}: {why}'
        st.values = [KeyValue(key=str(k), value=str(v)) for k, v in vals.items()]
        arr = DiagnosticArray()
        arr.header.stamp = conv.ns_to_stamp(result.stamp_ns)
        arr.status = [st]
        self.status_pub.publish(arr)

    def stop(self) -> None:
        """Stop the worker and wait for its frame to finish: after this nothing is
        published, so the context may go (lifecycle.run_nodes calls it first)."""
        self._stop.set()
        with self._queue_cv:
            self._queue_cv.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=5.0)

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_nodes('vo_node', lambda: [VoNode()], args)


if __name__ == '__main__':
    sys.exit(main())
