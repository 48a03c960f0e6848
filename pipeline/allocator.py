"""The C allocator tuned for a batch job that churns whole-frame temporaries.

Every stage allocates and frees arrays of a frame's size (1-4 MB per 1024 x 1024 frame)
by the thousand. glibc's malloc serves those with fresh ``mmap`` pages (or trims them off
its heap as soon as they are freed), so each one costs the kernel a page fault per 4 KB
when it is first written: on 100 tiles of 1024 x 1024 px, ingest faulted in 200 000 pages
(800 MB) for 100 MB of images, a third of its CPU time in the kernel. Raising the mmap and
trim thresholds keeps freed memory in the heap for the next frame: 84 000 faults, 1.0 s
less kernel time in ingest, 0.6-0.8 s less in register, peak memory +5-15 %.

The other side of keeping freed memory: :func:`return_freed_memory` hands it back where a
job is done with a large heap (between stages; at the end of :func:`lean_heap`), and
:func:`lean_heap` lowers both thresholds for a step whose C++ heap is made of many blocks of
a megabyte or more that it frees and makes again (GTSAM's eliminations, each a few hundred
MB of clique matrices): kept in the heap, they left optimize's peak 1223 MiB on a 40 x 40 m
floor, 1099 MiB with ``lean_heap`` (CPU 0.96x).

One arena for every thread (``M_ARENA_MAX`` 1): glibc otherwise gives each thread that
allocates a heap of its own, and memory one thread frees is not reused by another. The
render's tasks run on a worker thread after optimize ran on the main one, so the render's
frame cache and block buffers were laid beside what the earlier stages had left in the main
arena rather than in it: a 20 x 20 m floor's optimize then render in one process peaked at
932 MB with an arena per thread, 807 MB with one (user CPU 34.2 vs 33.6 s); the whole
nightly build with one worker, 40 x 40 m: 1169 -> 1040 MB, 10 x 10 m: 707 -> 646 MB
(bench/bench_scale.py). On two render threads the one arena's lock is within this machine's
noise (render alone, 20 x 20 m: CPU 1.03x, 0.95-1.15 over four pairs; peak 1089 -> 1037 MB).

Only on glibc (Linux); elsewhere, or if ``mallopt`` is missing, nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import platform
from contextlib import contextmanager
from typing import Iterator

__all__ = ["ARENA_MAX", "MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "LEAN_THRESHOLD_BYTES", "lean_heap",
           "return_freed_memory", "trim_heap", "tune_allocator"]

# Blocks above this still come from mmap (and go back to the system when freed): a whole
# shard of frames, a mosaic tile batch. 32 MB is glibc's own ceiling for its adaptive
# threshold.
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
# Free memory at the top of the heap is returned to the system beyond this.
TRIM_THRESHOLD_BYTES = 128 * 1024 * 1024
# Both thresholds inside :func:`lean_heap`: blocks from 1 MB up are mapped and unmapped on
# their own, and free memory at the top of the heap beyond 1 MB goes back.
LEAN_THRESHOLD_BYTES = 1024 * 1024

# Arenas glibc may make for the process's threads (set before the worker threads start: a
# thread keeps the arena it first allocated from).
ARENA_MAX = 1

_M_TRIM_THRESHOLD = -1
_M_ARENA_MAX = -8
_M_MMAP_THRESHOLD = -3
# glibc's own starting values (its mmap threshold then adapts; ours stay fixed once set)
_GLIBC_DEFAULT_BYTES = 128 * 1024


def _glibc():
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


_LIBC = _glibc()
_thresholds: tuple[int, int] | None = None  # (mmap, trim) as last set here; None = glibc's own


def _set_thresholds(mmap_bytes: int, trim_bytes: int) -> bool:
    global _thresholds
    if _LIBC is None:
        return False
    ok = _LIBC.mallopt(_M_MMAP_THRESHOLD, mmap_bytes) == 1
    ok = _LIBC.mallopt(_M_TRIM_THRESHOLD, trim_bytes) == 1 and ok
    if ok:
        _thresholds = (mmap_bytes, trim_bytes)
    return ok


def tune_allocator() -> bool:
    """Set glibc's mmap and trim thresholds and its arena limit (:data:`ARENA_MAX`) for this
    process (once; early, before the worker threads start); True when set."""
    if _thresholds == (MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES):
        return True
    arena = _LIBC is not None and _LIBC.mallopt(_M_ARENA_MAX, ARENA_MAX) == 1
    return _set_thresholds(MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES) and arena


@contextmanager
def lean_heap() -> Iterator[None]:
    """Inside: glibc's mmap and trim thresholds at :data:`LEAN_THRESHOLD_BYTES`, then back to
    what they were (glibc's own starting values if never set), the heap trimmed on the way
    out. For a single-threaded step whose large blocks should go back to the system when
    freed rather than wait in the heap beside the Python objects made next. Nothing
    elsewhere than glibc."""
    global _thresholds
    before = _thresholds
    _set_thresholds(LEAN_THRESHOLD_BYTES, LEAN_THRESHOLD_BYTES)
    try:
        yield
    finally:
        if before is None:
            _set_thresholds(_GLIBC_DEFAULT_BYTES, _GLIBC_DEFAULT_BYTES)
            _thresholds = None
        else:
            _set_thresholds(*before)
        return_freed_memory()


def return_freed_memory() -> None:
    """Collect reference cycles, then ask the C library to hand the heap pages freed so far
    back to the system (glibc's ``malloc_trim``; nothing elsewhere), whatever the trim
    threshold. Called between stages (millions of small Python objects freed by register and
    optimize otherwise stay resident under the render's buffers) and inside a stage after a
    step whose C++ heap it is done with: Python takes its small objects from arenas of its
    own, never from pages the C library keeps, so without it the two pile up (optimize:
    GTSAM's eliminations, then the links' residuals and the plots)."""
    gc.collect()
    trim_heap()


def trim_heap() -> None:
    """Hand the C heap's free pages back to the system, wherever they lie (glibc's
    ``malloc_trim(0)``; nothing elsewhere), without collecting Python's garbage: after each
    of GTSAM's solves, whose freed clique matrices sit between the factors it keeps (a 40 x
    40 m floor's optimize: ~300 MB resident between solves without it, and the links'
    residuals then computed on top of it)."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
