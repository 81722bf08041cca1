"""Where the local map's adjustments run: a Python process of their own (docs/method.md §17.9).

An adjustment is numpy work in many small steps (local_ba.py). In a thread it shares the
interpreter lock with the frame loop: on the demo the frame after a keyframe tracked in
~30 ms instead of ~15 while it ran. In a process it shares only the cores.

One worker per Python process, shared by every estimator in it (each waits only for its
own result, at a fixed frame: local_map.py), started with the first estimator that has a
local map, so the ~0.3 s a new interpreter takes to import numpy is not a frame's. It is
`python -m ekf_vo.core.ba_process`, reading pickled jobs on stdin and writing results on
stdout: not `multiprocessing`, whose `spawn` and `forkserver` import the user's main module
again in the worker (a script without an `if __name__ == '__main__'` guard ran twice), and
whose `fork` is unsafe in a process with threads, as a ROS node is. The worker ignores
Ctrl-C (its parent decides) and ends when its stdin closes, i.e. with its parent, or
quietly when its parent has gone while a job ran. When it cannot be started or has died,
adjustments run in a thread, and the log says so once.
"""
from __future__ import annotations

import logging
import os
import pickle
import signal
import struct
import subprocess
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, BinaryIO, Callable

logger = logging.getLogger(__name__)

_HEADER = struct.Struct('<Q')     # length of the pickled message that follows


class WorkerGone(RuntimeError):
    """The worker process ended before answering."""


def _write(stream: BinaryIO, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _read(stream: BinaryIO) -> Any:
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError
    n = _HEADER.unpack(head)[0]
    data = stream.read(n)
    if len(data) < n:
        raise EOFError
    return pickle.loads(data)


class _Worker:
    """The client side: one process, jobs answered in order."""

    def __init__(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED='1')
        self._proc = subprocess.Popen(
            [sys.executable, '-m', 'ekf_vo.core.ba_process'], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, env=env, start_new_session=True)
        self._lock = threading.Lock()
        self._waiting: dict[int, Future] = {}
        self._next_id = 0
        self.alive = True
        threading.Thread(target=self._answers, name='ekf_vo_ba_answers', daemon=True).start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        future: Future = Future()
        with self._lock:
            if not self.alive:
                raise WorkerGone('the adjustment process has ended')
            job = self._next_id
            self._next_id += 1
            self._waiting[job] = future
            try:
                _write(self._proc.stdin, (job, fn, args))
            except (OSError, ValueError) as exc:
                self._waiting.pop(job, None)
                self.alive = False
                raise WorkerGone(f'the adjustment process has ended ({exc})') from exc
        return future

    def _answers(self) -> None:
        while True:
            try:
                job, ok, value = _read(self._proc.stdout)
            except (EOFError, OSError, pickle.UnpicklingError):
                break
            with self._lock:
                future = self._waiting.pop(job, None)
            if future is not None:
                (future.set_result if ok else future.set_exception)(value)
        with self._lock:
            self.alive = False
            waiting, self._waiting = self._waiting, {}
        for future in waiting.values():
            future.set_exception(WorkerGone('the adjustment process has ended'))


_lock = threading.Lock()
_worker: _Worker | None = None
_thread: ThreadPoolExecutor | None = None


def _use_a_thread(why: str) -> None:
    global _thread
    logger.warning('local map: %s; adjusting in a thread', why)
    _thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix='ekf_vo_ba')


def start() -> None:
    """Start the worker process if none was started (cheap once one was); once it has
    ended, adjustments run in a thread."""
    global _worker
    with _lock:
        if _thread is not None:
            return
        if _worker is not None:
            if not _worker.alive:
                _use_a_thread('the adjustment process has ended')
            return
        try:
            _worker = _Worker()
        except OSError as exc:
            _use_a_thread(f'no adjustment process ({exc})')


def submit(fn: Callable[..., Any], *args: Any) -> Future:
    """Run fn(*args) (a module-level function; arguments and result picklable) on the
    worker, or in a thread once the worker has ended."""
    start()
    if _thread is None:
        try:
            return _worker.submit(fn, *args)
        except WorkerGone:
            start()
    return _thread.submit(fn, *args)


def _serve() -> None:
    """The worker: answer jobs until stdin closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr            # a stray print must not corrupt the answers
    while True:
        try:
            job, fn, args = _read(stdin)
        except EOFError:
            return
        try:
            answer = (job, True, fn(*args))
        except Exception as exc:  # noqa: BLE001 - handed to the caller's future
            answer = (job, False, exc)
        try:
            _write(stdout, answer)
        except (BrokenPipeError, ValueError, OSError):
            # the parent ended while this job ran (a run that stops during an
            # adjustment): nobody waits for the answer. Leave quietly, with the pipe
            # pointed at /dev/null so that the flush at exit raises nothing either
            os.dup2(os.open(os.devnull, os.O_WRONLY), stdout.fileno())
            return


if __name__ == '__main__':
    _serve()
