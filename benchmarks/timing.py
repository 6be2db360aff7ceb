"""Timing shared by the benchmarks: the median and the best of repeated calls."""
import statistics
import time


def timed(fn, repeat):
    """(median ms, min ms, last result) of `repeat` calls of fn()."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), min(times), out
