"""pipeline.allocator: the thresholds a step lowers come back, and freeing is safe anywhere."""

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
