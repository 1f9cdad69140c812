"""The shared benchmark helpers measure what they claim (no timing assertions)."""

import numpy as np

from diffloc.benchmark import median_ms, peak_added_mb


def test_median_ms_calls_the_function_repeats_plus_one_times():
    calls = []
    assert median_ms(lambda: calls.append(1), repeats=4) >= 0
    assert len(calls) == 5


def test_peak_added_mb_sees_a_temporary_200_mb_allocation():
    def allocate() -> None:
        block = np.ones(200 * 2**20, dtype=np.uint8)
        assert block.sum() == block.size

    assert 150 <= peak_added_mb(allocate) <= 400


def test_peak_added_mb_counts_temporaries_the_allocator_would_keep_resident():
    np.ones(20 * 2**20, dtype=np.uint8)  # freed: glibc now serves 10 MB from its heap

    def allocate() -> None:
        block = np.ones(10 * 2**20, dtype=np.uint8)
        assert block.sum() == block.size

    allocate()  # its 10 MB stay resident once freed
    assert 8 <= peak_added_mb(allocate) <= 40
