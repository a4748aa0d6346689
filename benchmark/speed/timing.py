"""The timer of the bench_*.py scripts."""

import statistics
import time


def median_time(fn, repeats: int, blocks: int = 5) -> float:
    """Seconds per call of fn: one warm-up call, then the median over `blocks` blocks of `repeats` calls."""
    fn()
    times = []
    for _ in range(blocks):
        start = time.perf_counter()
        for _ in range(repeats):
            fn()
        times.append((time.perf_counter() - start) / repeats)
    return statistics.median(times)
