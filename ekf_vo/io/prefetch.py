"""Read ahead: run an iterator in a thread of its own, a bounded queue ahead of its user.

Offline runs read a bag and decode each image (rosbags' CDR deserialisation, JPEG / PNG
decoding) between two frames of the estimator. In a reader thread that work overlaps the
estimator's: OpenCV releases the GIL while it decodes and while the estimator tracks, so
on two cores the decode costs the frame loop little (docs/method.md §17.4). Order is kept
(one producer, one FIFO queue); an exception of the iterator is raised in the user's
thread at the item where it happened; stopping early (break, an exception in the user)
stops and joins the reader.
"""
from __future__ import annotations

import queue
import threading
from typing import Iterator, TypeVar

T = TypeVar('T')

_END = object()
#: how long the reader waits for room in the queue before it checks whether to stop [s]
_POLL_S = 0.05


def prefetched(items: Iterator[T], depth: int = 8) -> Iterator[T]:
    """Yield the items of `items`, produced by a reader thread up to `depth` ahead."""
    if depth < 1:
        raise ValueError(f'prefetch depth must be >= 1, not {depth}')
    slots: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry: tuple) -> bool:
        while not stop.is_set():
            try:
                slots.put(entry, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def read() -> None:
        try:
            for item in items:
                if not put((item, None)):
                    return
            put((_END, None))
        except BaseException as exc:        # handed to the user's thread, raised there
            put((_END, exc))
        finally:
            close = getattr(items, 'close', None)
            if close is not None:
                close()

    reader = threading.Thread(target=read, name='ekf_vo-prefetch', daemon=True)
    reader.start()
    try:
        while True:
            item, exc = slots.get()
            if item is _END:
                if exc is not None:
                    raise exc
                return
            yield item
    finally:
        stop.set()
        reader.join()
