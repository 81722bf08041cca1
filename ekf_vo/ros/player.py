"""Replay a rosbag2 over DDS without ros2cli: ``ekf-vo-play BAG``.

A small stand-in for ``ros2 bag play --clock``: messages are read with rosbags
(:func:`ekf_vo.io.bag.read_raw`) and published as the recorded CDR bytes (rclpy's
``Publisher.publish`` accepts serialized ``bytes``; nothing is deserialized), paced by the
recorded log times divided by ``rate``. Before each message, ``/clock``
(rosgraph_msgs/Clock) is set to its log time, so nodes with ``use_sim_time`` follow the bag.
With ``loop`` the bag restarts at its end and the clock jumps back (deliberately: it
exercises the nodes' reset handling).

Pacing by the node's progress (``pace_topic``): after each image the player waits until
the odometry for that image's stamp (or a later one) has come back, at most
``pace_timeout_s`` (frames without odometry: the bootstrap, a lost frame); the next
message still waits for its bag time / ``rate``. A replay then never outruns the
estimator, however loaded the machine, and ``rate`` only sets the top speed.

Library use (tests, the demo)::

    stats = play_bag(node, 'bags/demo', rate=2.0)      # returns when done
    stats['messages'], stats['wall_s'], stats['effective_rate']
"""
from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from ..cli import entry_point
from ..io.bag import BagError, bag_topics, read_raw
from .lifecycle import init_rclpy

logger = logging.getLogger(__name__)

__all__ = ['play_bag', 'resolve_msg_class', 'parse_remaps', 'main', 'PlayError']

_NS_PER_S = 1_000_000_000


class PlayError(RuntimeError):
    """The bag cannot be played (missing, no playable topic, bad arguments)."""


def resolve_msg_class(msgtype: str) -> Any:
    """``'sensor_msgs/msg/Image'`` -> the rclpy class ``sensor_msgs.msg.Image``.

    Also accepts the ROS 1 style ``'sensor_msgs/Image'``. Raises PlayError when the package
    or the type cannot be imported.
    """
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise PlayError(f'not a message type name: {msgtype!r}')
    pkg, kind, name = parts
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError) as exc:
        raise PlayError(f'message type {msgtype} is not available to rclpy ({exc})') from None


def parse_remaps(items: Iterable[str] | None) -> dict[str, str]:
    """``['OLD:=NEW', ...]`` -> ``{OLD: NEW}`` (names are made absolute with a leading '/')."""
    out: dict[str, str] = {}
    for item in items or ():
        old, sep, new = item.partition(':=')
        if not sep or not old or not new:
            raise PlayError(f'bad remap {item!r}; expected OLD:=NEW')
        out[_absolute(old)] = _absolute(new)
    return out


def _absolute(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


def _qos(kind: str) -> Any:
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                           qos_profile_sensor_data)
    if kind == 'reliable':
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    if kind == 'sensor':
        return qos_profile_sensor_data
    raise PlayError(f"qos must be 'reliable' or 'sensor', got {kind!r}")


def _sleep_until(deadline: float, stop_event: threading.Event | None) -> bool:
    """Wait until ``time.monotonic() >= deadline``; False if ``stop_event`` was set."""
    while True:
        remaining = deadline - time.monotonic()
        if stop_event is not None and stop_event.is_set():
            return False
        if remaining <= 0:
            return True
        if stop_event is not None:
            if stop_event.wait(min(remaining, 0.1)):
                return False
        else:
            time.sleep(min(remaining, 0.1))


def play_bag(node: Any, path: str | Path, rate: float = 1.0, topics: Iterable[str] | None = None,
             remap: Mapping[str, str] | None = None, clock: bool = True, loop: bool = False,
             stop_event: threading.Event | None = None, *, qos: str = 'reliable',
             start_paused_s: float = 0.0, wait_for: Iterable[str] | None = None,
             wait_timeout_s: float = 10.0, ack_timeout_s: float = 2.0,
             pace: Callable[[str, bytes], float] | None = None) -> dict[str, Any]:
    """Publish the bag at ``path`` from ``node``, paced by its log times / ``rate``.

    Args:
        node: An rclpy Node; publishers are created on it (and destroyed at the end). The node
            need not be spun: publishing does not need an executor.
        path: rosbag2 directory (or its single storage file).
        rate: Playback speed factor (> 0); 2.0 plays twice as fast.
        topics: Only these bag topics (default: all). Names with or without leading '/'.
        remap: ``{bag topic: published topic}``; a ``'/clock'`` key renames the clock topic.
        clock: Publish ``/clock`` (rosgraph_msgs/Clock) with each message's log time.
        loop: Restart at the end until ``stop_event`` is set (the clock jumps back).
        stop_event: Set it (from another thread) to stop; play_bag returns promptly.
        qos: ``'reliable'`` (keep last 100, default) or ``'sensor'`` (best effort, keep last 5).
        start_paused_s: Wait this long before the first message (after ``wait_for``), so
            subscribers have discovered the publishers (DDS discovery is not instantaneous;
            with volatile QoS anything published before the match is lost).
        wait_for: Published topic names (after remapping; ``'*'`` = every played topic) that
            must each have a matched subscriber before playback starts. Across processes,
            discovery on these machines has been seen to take 3 s or more, so a fixed pause
            alone is not enough for tests.
        wait_timeout_s: Give up waiting for ``wait_for`` after this long (log a warning and
            play anyway).
        ack_timeout_s: At the end, wait up to this long per publisher until reliable
            subscribers acknowledged everything (0 disables).
        pace: Called after each image is published with (msgtype, serialized bytes); it
            may block until the node has processed it (:class:`OdometryPacer`).

    Returns:
        ``{'messages', 'per_topic' {published topic: count}, 'loops', 'bag_duration_s'
        (log-time span played, summed over loops), 'wall_s' (from the first message),
        'effective_rate' (bag_duration_s / wall_s), 'stopped' (True if stop_event ended it),
        'skipped_types' {bag topic: type not importable}, 'waited_s' (pause + wait_for),
        'unmatched' (wait_for topics still without a subscriber)}``.

    Raises:
        PlayError: missing bag, bad rate, or no playable topic.
    """
    path = Path(path)
    if not path.exists():
        raise PlayError(f'bag {path} does not exist')
    if not rate > 0:
        raise PlayError(f'rate must be > 0, got {rate}')
    remap = {_absolute(k): _absolute(v) for k, v in (remap or {}).items()}
    publishers, skipped = _create_publishers(node, path, topics, remap, _qos(qos))
    clock_pub = _clock_publisher(node, remap) if clock else None
    all_pubs = [*publishers.values(), *([clock_pub] if clock_pub is not None else [])]
    progress = _Progress()
    unmatched: list[str] = []
    wall_start: float | None = None
    wall_s = 0.0
    pause_start = time.monotonic()
    try:
        unmatched, progress.stopped = _wait_for_subscribers(publishers, wait_for,
                                                            wait_timeout_s, stop_event)
        # Also after a match: the writer may know the reader before the reader knows the
        # writer, and a volatile reader drops samples from writers it has not matched yet.
        if not progress.stopped and start_paused_s > 0 and \
                not _sleep_until(time.monotonic() + start_paused_s, stop_event):
            progress.stopped = True
        wall_start = time.monotonic()
        while not progress.stopped:
            played = _play_once(path, publishers, clock_pub, rate, stop_event, progress,
                                pace)
            if not loop or not played:
                break
        wall_s = time.monotonic() - wall_start
        if ack_timeout_s > 0 and progress.messages and not progress.stopped:
            _wait_acked(all_pubs, ack_timeout_s)
    finally:
        for pub in all_pubs:
            node.destroy_publisher(pub)
    waited_s = (wall_start if wall_start is not None else time.monotonic()) - pause_start
    return _stats(progress, wall_s, skipped, waited_s, unmatched)


def _stats(progress: '_Progress', wall_s: float, skipped: dict, waited_s: float,
           unmatched: list[str]) -> dict[str, Any]:
    """play_bag's result (see its docstring)."""
    bag_s = progress.bag_ns / _NS_PER_S
    return {'messages': progress.messages, 'per_topic': progress.per_topic,
            'loops': progress.loops, 'bag_duration_s': bag_s, 'wall_s': wall_s,
            'effective_rate': bag_s / wall_s if wall_s > 0 else float('nan'),
            'stopped': progress.stopped, 'skipped_types': skipped, 'waited_s': waited_s,
            'unmatched': unmatched}


@dataclass
class _Progress:
    """What :func:`play_bag` has played so far."""

    per_topic: dict[str, int] = field(default_factory=dict)   #: published topic -> messages
    messages: int = 0
    loops: int = 0
    bag_ns: int = 0        #: log-time span played, summed over loops
    stopped: bool = False  #: stop_event ended the playback


def _create_publishers(node: Any, path: Path, topics: Iterable[str] | None,
                       remap: Mapping[str, str], qos_profile: Any
                       ) -> tuple[dict[str, Any], dict[str, str]]:
    """``({bag topic: publisher}, {bag topic: type not importable})`` of the played topics."""
    try:
        bag_types = bag_topics(path)
    except BagError as exc:
        raise PlayError(str(exc)) from None
    if topics is not None:
        wanted = {_absolute(t) for t in topics}
        unknown = wanted - {_absolute(t) for t in bag_types}
        if unknown:
            logger.warning('topics not in the bag: %s', sorted(unknown))
        bag_types = {t: ty for t, ty in bag_types.items() if _absolute(t) in wanted}
    publishers: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    for topic, msgtype in sorted(bag_types.items()):
        try:
            cls = resolve_msg_class(msgtype)
        except PlayError as exc:
            logger.warning('skipping %s: %s', topic, exc)
            skipped[topic] = msgtype
            continue
        out_topic = remap.get(_absolute(topic), _absolute(topic))
        publishers[topic] = node.create_publisher(cls, out_topic, qos_profile)
    if not publishers:
        raise PlayError(f'{path}: no playable topic (bag has {sorted(bag_topics(path))})')
    return publishers, skipped


def _clock_publisher(node: Any, remap: Mapping[str, str]) -> Any:
    """Publisher of rosgraph_msgs/Clock on ``/clock`` (or its remapped name)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    return node.create_publisher(Clock, remap.get('/clock', '/clock'),
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))


def _wait_for_subscribers(publishers: Mapping[str, Any], wait_for: Iterable[str] | None,
                          timeout_s: float, stop_event: threading.Event | None
                          ) -> tuple[list[str], bool]:
    """Wait until each ``wait_for`` topic has a subscriber: ``(unmatched topics, stopped)``."""
    by_name = {pub.topic_name: pub for pub in publishers.values()}
    if wait_for is None:
        return [], False
    names = list(wait_for)
    waited = sorted(by_name) if '*' in names else [_absolute(t) for t in names]
    missing = [t for t in waited if t not in by_name]
    if missing:
        raise PlayError(f'wait_for topics {missing} are not played (playing {sorted(by_name)})')
    unmatched: list[str] = []
    if not waited:
        return unmatched, False
    deadline = time.monotonic() + timeout_s
    while True:
        unmatched = [t for t in waited if by_name[t].get_subscription_count() == 0]
        if not unmatched or time.monotonic() >= deadline:
            break
        if not _sleep_until(time.monotonic() + 0.02, stop_event):
            return unmatched, True
    if unmatched:
        logger.warning('no subscriber on %s after %.1f s; playing anyway', unmatched, timeout_s)
    return unmatched, False


def _play_once(path: Path, publishers: Mapping[str, Any], clock_pub: Any, rate: float,
               stop_event: threading.Event | None, progress: _Progress,
               pace: Callable[[str, bytes], float] | None = None) -> bool:
    """Publish the bag once from its start, paced by log time / ``rate``, updating
    ``progress``; False if the bag had no message to play."""
    from builtin_interfaces.msg import Time

    progress.loops += 1
    first_ns = last_ns = None
    loop_start = time.monotonic()
    for topic, msgtype, stamp_ns, raw in read_raw(path, list(publishers)):
        if first_ns is None:
            first_ns = stamp_ns
        # Log times are sorted; max() guards against equal or odd stamps.
        deadline = loop_start + max(stamp_ns - first_ns, 0) / _NS_PER_S / rate
        if not _sleep_until(deadline, stop_event):
            progress.stopped = True
            break
        if clock_pub is not None:
            sec, nanosec = divmod(stamp_ns, _NS_PER_S)
            clock_pub.publish(clock_pub.msg_type(clock=Time(sec=sec, nanosec=nanosec)))
        publishers[topic].publish(raw)
        name = publishers[topic].topic_name
        progress.per_topic[name] = progress.per_topic.get(name, 0) + 1
        progress.messages += 1
        last_ns = stamp_ns
        if pace is not None and msgtype in _IMAGE_TYPES:
            # wait for the node; the next message still waits for its own bag time, so
            # a node that keeps up is played in real time / rate
            pace(msgtype, raw)
    if first_ns is not None and last_ns is not None:
        progress.bag_ns += last_ns - first_ns
    return first_ns is not None


_IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')


class OdometryPacer:
    """``pace`` for :func:`play_bag`: wait for the odometry of each image played.

    Subscribes nav_msgs/Odometry on ``topic`` with ``node`` and spins the node on its own
    executor while waiting (so the node must not be spun elsewhere)."""

    def __init__(self, node: Any, topic: str, timeout_s: float,
                 stop_event: threading.Event | None = None) -> None:
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.timeout_s = float(timeout_s)
        self.n_timeouts = 0
        self._stop_event = stop_event
        self._latest_ns = -1           # newest odometry stamp seen
        self._last_image_ns = -1
        node.create_subscription(Odometry, topic, self._on_odometry,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(node)

    def _on_odometry(self, msg: Any) -> None:
        from ..bridge import stamp_to_ns
        self._latest_ns = max(self._latest_ns, stamp_to_ns(msg.header.stamp))

    def __call__(self, msgtype: str, raw: bytes) -> float:
        from rclpy.serialization import deserialize_message

        from ..bridge import stamp_to_ns
        stamp = stamp_to_ns(deserialize_message(raw, resolve_msg_class(msgtype)).header.stamp)
        if stamp < self._last_image_ns:
            self._latest_ns = -1       # the bag looped: earlier answers do not count
        self._last_image_ns = stamp
        start = time.monotonic()
        while self._latest_ns < stamp:
            if self._stop_event is not None and self._stop_event.is_set():
                break
            if time.monotonic() - start >= self.timeout_s:
                self.n_timeouts += 1
                break
            self._executor.spin_once(timeout_sec=0.005)
        return time.monotonic() - start


def _wait_acked(publishers: Iterable[Any], timeout_s: float) -> None:
    """Like `ros2 bag play --wait-for-all-acked`: a reliable sample still in flight (or being
    repaired) is lost when its publisher is destroyed right after the last one."""
    from rclpy.duration import Duration
    for pub in publishers:
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9))):
            logger.warning('%s: not all subscribers acknowledged within %.1f s',
                           pub.topic_name, timeout_s)


def _summary(path: str | Path, stats: Mapping[str, Any]) -> str:
    rate = stats['effective_rate']
    msg_rate = stats['messages'] / stats['wall_s'] if stats['wall_s'] > 0 else float('nan')
    return (f"played {stats['messages']} messages on {len(stats['per_topic'])} topics from "
            f"{path} in {stats['wall_s']:.2f} s (bag {stats['bag_duration_s']:.2f} s, "
            f"{stats['loops']} loop(s)); effective rate {rate:.2f}x, {msg_rate:.1f} msg/s"
            + (f"; {stats['pace_timeouts']} frame(s) without odometry in time"
               if 'pace_timeouts' in stats else '')
            + (' [interrupted]' if stats['stopped'] else ''))


def _split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Separate ``--ros-args ... [--]`` sections from our own arguments.

    (rclpy's ``remove_ros_args`` would also eat our ``--remap OLD:=NEW`` values, which look
    like deprecated ROS remap rules.)
    """
    own: list[str] = []
    ros: list[str] = []
    in_ros = False
    for arg in argv:
        if arg == '--ros-args':
            in_ros = True
            ros.append(arg)
        elif in_ros and arg == '--':
            in_ros = False
        elif in_ros:
            ros.append(arg)
        else:
            own.append(arg)
    return own, ros


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='ekf-vo-play',
        description='Replay a rosbag2 directory (or a ROS 1 .bag file, converted on the fly) '
        'over DDS (stand-in for `ros2 bag play`).')
    parser.add_argument('bag', help='rosbag2 directory or ROS 1 .bag file')
    parser.add_argument('--rate', type=float, default=1.0, help='speed factor (default 1.0)')
    parser.add_argument('--loop', action='store_true', help='restart at the end (until Ctrl-C)')
    parser.add_argument('--topics', nargs='+', metavar='T',
                        help='only these topics (default: every topic of the bag)')
    parser.add_argument('--remap', nargs='+', metavar='OLD:=NEW', default=[],
                        help='publish bag topic OLD as NEW')
    parser.add_argument('--start-paused-s', type=float, default=0.5,
                        help='pause before the first message, after --wait-for, so '
                             'subscribers discover the publishers (default 0.5 s)')
    parser.add_argument('--wait-for', nargs='+', metavar='TOPIC',
                        help="first wait until these published topics ('*': all) have a "
                             'subscriber (cross-process discovery can take seconds)')
    parser.add_argument('--wait-timeout-s', type=float, default=10.0,
                        help='give up waiting for --wait-for after this long (default 10 s)')
    parser.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    parser.add_argument('--qos', choices=('reliable', 'sensor'), default='reliable',
                        help='publisher QoS: reliable keep-last-100 (default) or sensor data')
    parser.add_argument('--pace-topic', metavar='TOPIC',
                        help="pace by the node's progress: after each image, wait for the "
                             'odometry of its stamp on TOPIC (e.g. /odom); --rate then only '
                             'caps the speed (default: pace by the bag times only)')
    parser.add_argument('--pace-timeout-s', type=float, default=0.5,
                        help='longest wait for one odometry (frames without one: the '
                             'bootstrap, lost frames) (default 0.5 s)')
    return parser


@entry_point
def main(argv: list[str] | None = None) -> int:
    import rclpy

    argv = sys.argv[1:] if argv is None else list(argv)
    own, ros_args = _split_ros_args(argv)
    args = build_parser().parse_args(own)
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    # Ctrl-C / SIGTERM stop the playback cleanly (and still print the summary) instead of
    # raising KeyboardInterrupt somewhere inside rclpy.
    if not init_rclpy('ekf-vo-play', ['ekf-vo-play', *ros_args]):
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = rclpy.create_node('ekf_vo_play')
    pacer = OdometryPacer(node, args.pace_topic, args.pace_timeout_s, stop) \
        if args.pace_topic else None
    try:
        stats = play_bag(node, args.bag, rate=args.rate, topics=args.topics,
                         remap=parse_remaps(args.remap), clock=not args.no_clock,
                         loop=args.loop, stop_event=stop, qos=args.qos,
                         start_paused_s=args.start_paused_s, wait_for=args.wait_for,
                         wait_timeout_s=args.wait_timeout_s, pace=pacer)
        if pacer is not None:
            stats['pace_timeouts'] = pacer.n_timeouts
    except PlayError as exc:
        print(f'ekf-vo-play: error: {exc}', file=sys.stderr)
        return 2
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(_summary(args.bag, stats))
    return 0


if __name__ == '__main__':
    sys.exit(main())
