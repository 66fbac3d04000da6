"""Timing shared by the benchmark scripts."""

from __future__ import annotations

import time

import jax


def best_time(fn, repeats: int, clock=time.perf_counter) -> float:
    """Best of `repeats` runs of `fn()` on `clock` (wall time by default), waiting for JAX
    results to be ready (numpy results are returned ready)."""
    best = float("inf")
    for _ in range(repeats):
        start = clock()
        jax.block_until_ready(fn())
        best = min(best, clock() - start)
    return best


def best_cpu_time(fn, repeats: int) -> float:
    """Best of `repeats` process CPU times (all threads) of `fn()`: less sensitive than the
    wall time to other jobs on the cores, which stall a program that waits for its pool."""
    return best_time(fn, repeats, clock=time.process_time)
