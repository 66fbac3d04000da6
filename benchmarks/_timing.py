"""Wall-clock timing shared by the benchmark scripts."""

from __future__ import annotations

import time

import jax


def best_time(fn, repeats: int) -> float:
    """Best of `repeats` wall-clock runs of `fn()`, waiting for JAX results to be ready
    (numpy results are returned ready)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best
