"""io/prefetch.py: the read-ahead thread of the offline runner keeps order, hands the
reader's errors to the user and stops when the user stops."""
import threading
import time

import pytest

from ekf_vo.io.prefetch import prefetched


def test_items_arrive_in_order_and_all() -> None:
    assert list(prefetched(iter(range(1000)), depth=3)) == list(range(1000))


def test_an_error_of_the_reader_is_raised_at_its_item() -> None:
    def items():
        yield 1
        yield 2
        raise OSError('bag truncated')

    got = []
    with pytest.raises(OSError, match='bag truncated'):
        for x in prefetched(items()):
            got.append(x)
    assert got == [1, 2]


def test_stopping_early_stops_and_closes_the_reader() -> None:
    closed = threading.Event()

    def items():
        try:
            n = 0
            while True:
                yield n
                n += 1
        finally:
            closed.set()

    before = threading.active_count()
    gen = prefetched(items(), depth=2)
    for x in gen:
        if x == 5:
            break
    gen.close()
    assert closed.wait(2.0)
    deadline = time.monotonic() + 2.0
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert threading.active_count() == before


def test_reads_ahead_while_the_user_works() -> None:
    produced = []

    def items():
        for k in range(4):
            produced.append(k)
            yield k

    gen = prefetched(items(), depth=8)
    assert next(gen) == 0
    deadline = time.monotonic() + 2.0
    while len(produced) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert produced == [0, 1, 2, 3]          # read on while item 0 was being used
    assert list(gen) == [1, 2, 3]


def test_depth_must_be_positive() -> None:
    with pytest.raises(ValueError):
        list(prefetched(iter([1]), depth=0))
