"""pipeline.allocator: the thresholds a step lowers come back, and freeing is safe anywhere."""

import subprocess
import sys
from pathlib import Path

import pytest

import pipeline.allocator as allocator


def test_tune_allocator_is_idempotent():
    first = allocator.tune_allocator()
    assert allocator.tune_allocator() == first


def test_lean_heap_restores_the_thresholds_it_found():
    tuned = allocator.tune_allocator()
    before = allocator._thresholds
    with allocator.lean_heap():
        if tuned:
            assert allocator._thresholds == (allocator.LEAN_THRESHOLD_BYTES, allocator.LEAN_THRESHOLD_BYTES)
    assert allocator._thresholds == before
    assert allocator.tune_allocator() == tuned


def test_lean_heap_restores_after_an_error():
    allocator.tune_allocator()
    before = allocator._thresholds
    try:
        with allocator.lean_heap():
            raise RuntimeError("step failed")
    except RuntimeError:
        pass
    assert allocator._thresholds == before


def test_return_freed_memory_runs_without_a_heap_to_trim():
    allocator.return_freed_memory()
    allocator.return_freed_memory()


_THREADS_ALLOCATE = """
import ctypes, sys, threading
import pipeline.allocator as allocator
if sys.argv[1] == "tuned":
    assert allocator.tune_allocator()

def work():
    blocks = [bytearray(1 << 20) for _ in range(8)]  # (a thread takes its arena at its first malloc)
    del blocks

threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
ctypes.CDLL(None).malloc_stats()  # one "Arena N:" block per arena, on stderr
"""


@pytest.mark.skipif(allocator._LIBC is None, reason="glibc's mallopt is needed (Linux with glibc)")
def test_tuned_threads_share_one_arena():
    """Threads started after tune_allocator allocate from the main arena: memory one frees,
    another reuses (an arena per thread otherwise, as glibc does by default)."""
    def arenas(mode: str) -> int:
        p = subprocess.run([sys.executable, "-c", _THREADS_ALLOCATE, mode], capture_output=True, text=True,
                           check=True, cwd=Path(__file__).resolve().parents[1])
        return sum(line.startswith("Arena ") for line in p.stderr.splitlines())

    assert arenas("tuned") == allocator.ARENA_MAX
    assert arenas("default") > allocator.ARENA_MAX
