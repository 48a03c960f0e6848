"""Where the pipeline's parallel stages (register, render) run: dask on a named scheduler."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager

import cv2
import dask
import dask.local
import dask.threaded

from pipeline.errors import BadInput, JobFailed

log = logging.getLogger(__name__)

__all__ = ["dask_scheduler", "opencv_threads"]


@contextmanager
def opencv_threads(workers: int):
    """numpy's BLAS held at one thread, and OpenCV's own thread pool too while ``workers``
    (> 1) threads of ours call it; both restored afterwards.

    Each worker already keeps a core busy; OpenCV's pool on top of that only spins waiting
    for the cores (``sched_yield``: 165 000 calls in one register stage of 180 pairs of
    1024 px tiles on 2 cores, 30 with one OpenCV thread; 15 % less CPU).
    """
    from threadpoolctl import threadpool_limits

    # numpy's BLAS at one thread whatever the workers: the fine stage's products of ~100k x 7
    # float64 matrices are 5x faster through BLAS than einsum, but its threads fought ours,
    # and a sum split over threads would make a map's last bits depend on the worker count
    with threadpool_limits(limits=1, user_api="blas"):
        if workers == 1:
            yield
            return
        before = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            yield
        finally:
            cv2.setNumThreads(before)


def _worker_init() -> None:
    """In a worker process: the C allocator tuned as the command line tunes its own process
    (:func:`pipeline.allocator.tune_allocator`: freed frame-sized blocks reused, not faulted
    in again), one OpenCV thread and one BLAS thread (the pool already has one process per
    core)."""
    import cv2
    from threadpoolctl import threadpool_limits

    from pipeline.allocator import tune_allocator

    tune_allocator()
    cv2.setNumThreads(1)
    threadpool_limits(limits=1, user_api="blas")


def _import(modules: tuple[str, ...]) -> None:
    """In a worker process: import ``modules`` (what its tasks will unpickle)."""
    import importlib

    for name in modules:
        importlib.import_module(name)


@contextmanager
def _quieter(logger: str, level: int):
    """Raise ``logger``'s level to ``level`` for the block, unless this program logs at
    DEBUG (``-v``): third-party noise silenced at its source, kept for diagnosis."""
    lg = logging.getLogger(logger)
    before = lg.level
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        lg.setLevel(level)
    try:
        yield
    finally:
        lg.setLevel(before)


def _each_done(tasks, done):
    """A dask callback calling ``done()`` in the caller as each of ``tasks`` finishes (None
    without ``done``): the local schedulers report per task, so that a progress bar moves
    without splitting the work into batches (each batch a barrier where a worker idles
    while the batch's last task runs)."""
    if done is None:
        return contextlib.nullcontext()
    from dask.callbacks import Callback

    keys = {t.key for t in tasks}
    return Callback(posttask=lambda key, result, dsk, state, worker: done() if key in keys else None)


@contextmanager
def dask_scheduler(name: str, workers: int, *, warm: tuple[str, ...] = ()):
    """A function ``run(tasks, done=None)`` computing a list of dask tasks on the named
    scheduler and returning their results in order; ``done()``, when given, is called in
    the caller each time one of the tasks finishes (for a progress bar).

    ``warm``: modules the tasks need; worker processes start at once and import them while
    the caller goes on preparing the tasks (a spawned worker takes ~1-1.5 s to start and
    import the pipeline: on 2 workers, a tenth of a 40 x 40 m render).

    ``threads`` (one process; OpenCV and numpy release the GIL for the heavy parts),
    ``processes`` (a pool of spawned worker processes: no GIL contention; forking would
    copy zarr's event-loop thread, which hangs), ``sync`` (in the caller, for debugging).
    The schedulers are given to dask as functions, not names: a name makes dask import
    dask.distributed to look for a client (0.1-0.4 s of every build's start).
    """
    if name == "processes":
        from dask.multiprocessing import get as processes_get

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_init) as pool:
            if warm:
                try:
                    for _ in range(workers):
                        pool.submit(_import, warm)
                except BrokenProcessPool:  # (run below says it and falls back to threads)
                    pass

            def run(tasks, done=None):
                try:
                    # one task per submission: dask's default batches 6 ready tasks into one,
                    # so of 8 tasks one worker ran 6 and the other 2 (register on 2 worker
                    # processes was 1.08x one thread on a 10 x 10 m floor)
                    with _each_done(tasks, done):
                        return dask.compute(*tasks, scheduler=processes_get, pool=pool, chunksize=1)
                except BrokenProcessPool:
                    # A script without an `if __name__ == "__main__":` guard cannot spawn
                    # workers; finish on threads rather than fail the build.
                    log.warning("worker processes could not start (is the calling script guarded by "
                                "`if __name__ == '__main__':`?); running on threads instead")
                    with _each_done(tasks, done):
                        return dask.compute(*tasks, scheduler=dask.threaded.get, num_workers=workers)

            yield run
    elif name == "threads":

        def run(tasks, done=None):
            with _each_done(tasks, done):
                return dask.compute(*tasks, scheduler=dask.threaded.get, num_workers=workers)

        with opencv_threads(workers):
            yield run
    elif name == "sync":

        def run(tasks, done=None):
            with _each_done(tasks, done):
                return dask.compute(*tasks, scheduler=dask.local.get_sync)

        with opencv_threads(1):
            yield run
    elif "://" in name:
        # A dask.distributed scheduler: tasks only pass paths and small arrays, and read the
        # work directory themselves, so it must be on storage every worker sees.
        # A worker that dies in a task (killed, out of memory) is replaced and the task rerun
        # elsewhere, up to the scheduler's distributed.scheduler.allowed-failures times.
        # A scheduler that goes away mid-stage: the client tries to reconnect for its
        # timeout, then cancels every pending task; the build stops with one line.
        from concurrent.futures import CancelledError

        from distributed import Client, KilledWorker

        try:
            client = Client(name, timeout="10s", set_as_default=False)
        except OSError as e:
            raise BadInput("--scheduler", f"cannot reach the dask scheduler at {name}: {e}") from None
        resume = "the stages finished so far are kept: rerun the build to resume"

        def run(tasks, done=None):
            try:
                futures = client.compute(list(tasks))
                if done is not None:
                    from distributed import as_completed

                    for _ in as_completed(futures, loop=client.loop):
                        done()
                return client.gather(futures)
            except KilledWorker as e:
                task = e.task[0] if isinstance(e.task, tuple) else e.task
                raise JobFailed(f"dask scheduler {name}: the workers running task {task} died "
                                f"{e.allowed_failures + 1} time(s) (killed, or out of memory?); {resume}") from None
            except (CancelledError, OSError) as e:  # OSError: distributed's CommClosedError too
                if client.status == "running" and not isinstance(e, CancelledError):
                    raise
                raise JobFailed(f"dask scheduler {name}: lost the connection to it mid-stage "
                                f"({type(e).__name__}); {resume}") from None

        # distributed logs its failed reconnection as an ERROR with a traceback: the
        # JobFailed line above says it (the traceback stays visible with -v)
        with _quieter("distributed.client", logging.CRITICAL), client:
            yield run
    else:
        raise BadInput("config scheduler", f"unknown scheduler {name!r} (threads, processes, sync, or tcp://host:port)")
