"""One way to run ekf_vo's nodes in a process: start, spin, stop cleanly on SIGINT/SIGTERM.

rclpy's own signal handler shuts the context down the moment a signal arrives, while a
node's worker thread may still be publishing ("publisher's context is invalid"). Here
rclpy is initialised WITHOUT its handlers; SIGINT and SIGTERM (what launch, systemd and
a CI runner send) only set a flag that the spin loop checks every SPIN_PERIOD_S. Then,
in order: the nodes' workers stop (`stop()`, nothing is published after it), the
executor and the nodes are destroyed, the context shuts down, and the process exits 0.
"""
from __future__ import annotations

import signal
import sys
import threading
from typing import Callable, Sequence

import rclpy
import rclpy.logging
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy._rclpy_pybind11 import RCLError   # what rclpy.init raises on bad --ros-args
from rclpy.signals import SignalHandlerOptions

from ..config import ConfigError

#: how often the spin loop looks at the stop flag [s]: the bound on the reaction time
SPIN_PERIOD_S = 0.1


def _rcl_reason(exc: Exception) -> str:
    """rcl's message without the C source locations it appends (', at file.c:123')."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.split(', at /')[0]


def init_rclpy(name: str, args: list[str] | None) -> bool:
    """rclpy.init without its signal handlers. A bad --ros-args (missing or broken
    --params-file, bad remap) is one line on stderr naming `name`; returns False then."""
    # rcl logs its own "Failed to parse global arguments" before raising: we say it once
    rclpy.logging.set_logger_level('rcl', rclpy.logging.LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        return True
    except RCLError as exc:
        print(f'{name}: error: {_rcl_reason(exc)}', file=sys.stderr)
        return False
    finally:
        rclpy.logging.set_logger_level('rcl', rclpy.logging.LoggingSeverity.UNSET)


def run_nodes(name: str, make_nodes: Callable[[], Sequence[Node]],
              args: list[str] | None = None, config_error_code: int = 2) -> int:
    """Build the nodes (after rclpy.init), spin them on one SingleThreadedExecutor until
    SIGINT, SIGTERM or an external shutdown, then stop them. Returns the exit code:
    0, or `config_error_code` when a parameter is invalid (logged as one line)."""
    if not init_rclpy(name, args):
        return 2
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    executor = SingleThreadedExecutor()
    nodes: Sequence[Node] = []
    try:
        nodes = make_nodes()
        for node in nodes:
            executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_PERIOD_S)
        return 0
    except ConfigError as exc:
        rclpy.logging.get_logger(name).fatal(f'invalid parameters: {exc}')
        return config_error_code
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        for node in nodes:
            stop_worker = getattr(node, 'stop', None)
            if stop_worker is not None:
                stop_worker()
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
