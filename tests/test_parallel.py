"""pipeline.parallel: every local scheduler returns the tasks' results in order and reports
each task as it ends (the progress bars of register and render count on it)."""

from __future__ import annotations

import operator

import dask
import pytest

from pipeline.errors import BadInput
from pipeline.parallel import dask_scheduler


@pytest.mark.parametrize("name", ["threads", "sync", "processes"])
def test_run_returns_results_in_order_and_calls_done_once_per_task(name):
    # a task with a dependency of its own: only the listed tasks are counted
    shared = dask.delayed(operator.add)(1, 1)
    tasks = [dask.delayed(operator.mul)(shared, k) for k in range(7)]
    ended = []
    with dask_scheduler(name, 2) as run:
        out = run(tasks, done=lambda: ended.append(1))
        assert list(out) == [2 * k for k in range(7)]
        assert len(ended) == len(tasks)
        assert list(run(tasks[:2])) == [0, 2]  # done is optional
    assert len(ended) == len(tasks)


def test_an_unknown_scheduler_is_bad_input():
    with pytest.raises(BadInput, match="unknown scheduler"):
        with dask_scheduler("thread", 2):
            pass


def _allocator_state() -> tuple:
    import cv2

    from pipeline import allocator

    return allocator._thresholds, cv2.getNumThreads()


def test_worker_processes_start_tuned():
    """A spawned worker runs with the C allocator tuned as the command line's process is
    (freed frame-sized blocks reused) and one OpenCV thread."""
    from pipeline.allocator import MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES

    with dask_scheduler("processes", 1) as run:
        (thresholds, cv_threads), = run([dask.delayed(_allocator_state)()])
    assert thresholds == (MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES)
    assert cv_threads == 1
