"""The local map's adjustment worker (core/ba_process.py): a process of its own, errors
handed back, and a thread when the process is gone (docs/method.md §17.9)."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from ekf_vo.core import ba_process


@pytest.fixture
def fresh_worker():
    """The module's worker as a new process starts it; put back that way afterwards."""
    def clear():
        with ba_process._lock:
            ba_process._worker = None
            ba_process._thread = None
    clear()
    yield
    clear()


def test_jobs_run_in_another_process_and_errors_come_back(fresh_worker) -> None:
    assert ba_process.submit(os.getpid).result(timeout=30) != os.getpid()
    with pytest.raises(ValueError):
        ba_process.submit(int, 'not a number').result(timeout=30)
    # the worker survives a job's error, and answers in order
    futures = [ba_process.submit(abs, -k) for k in range(20)]
    assert [f.result(timeout=30) for f in futures] == list(range(20))


def test_a_dead_worker_fails_its_job_and_a_thread_takes_over(fresh_worker) -> None:
    ba_process.start()
    worker = ba_process._worker
    assert worker.submit(os.getpid).result(timeout=30) != os.getpid()
    pending = worker.submit(time.sleep, 5.0)
    worker._proc.kill()
    with pytest.raises(ba_process.WorkerGone):
        pending.result(timeout=30)
    assert ba_process.submit(os.getpid).result(timeout=30) == os.getpid()


def test_the_worker_ends_with_its_parent(fresh_worker) -> None:
    ba_process.start()
    proc = ba_process._worker._proc
    proc.stdin.close()              # what the parent's exit does
    assert proc.wait(timeout=30) == 0


def test_a_parent_that_leaves_during_a_job_leaves_no_traceback() -> None:
    """A run that ends while an adjustment is in flight (ekf-vo-run at the end of a bag,
    a node shut down): the worker finds its answer's pipe closed. Before, it printed a
    BrokenPipeError traceback on the user's terminal after the run had ended."""
    script = ('import time\n'
              'from ekf_vo.core import ba_process\n'
              'ba_process.submit(time.sleep, 1.0)\n'
              'time.sleep(0.3)\n')      # the worker has the job; the parent leaves now
    # stderr is read to its end, which the worker holds too: its last words are in it
    run = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert 'Traceback' not in run.stderr and 'Error' not in run.stderr, run.stderr


def test_the_estimator_goes_on_when_the_worker_dies(fresh_worker) -> None:
    """The demo with the worker killed while its adjustments run: every frame is still
    processed, tracking goes on, and the adjustments after it run in a thread."""
    from ekf_vo.config import VoConfig
    from ekf_vo.core.stream import VoStream
    from ekf_vo.tools.demo import load_demo_frames
    info, frames = load_demo_frames()
    stream = VoStream(VoConfig())
    stream.set_camera(info)
    killed = False
    results = []
    for k, (stamp, gray) in enumerate(frames[:150]):
        if k == 60:
            ba_process._worker._proc.kill()
            killed = True
        results.append(stream.process(gray, stamp))
    assert killed and ba_process._thread is not None
    assert all(r.ok for r in results[80:])
    assert stream.vo.local_map.stats.n_runs > 0
