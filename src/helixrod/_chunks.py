"""Elementwise kernels evaluated a cache-sized chunk of points at a time.

The register solve is a few dozen dependent elementwise steps.  Written out over a
whole batch, every intermediate array streams through main memory, and XLA's CPU
fusion recomputes subexpressions shared by several consumers (measured: 6x the flops
of one solve on a 65536-point batch).  A `lax.map` over chunks of `CHUNK` points keeps
each step's arrays in cache; the result is bit-identical to the unchunked kernel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Points per chunk: best of 256 ... 16384 on 2 CPU cores (benchmarks/bench_equilibria.py).
CHUNK = 1024


def map_chunks(fn, args, size: int, chunk: int = CHUNK):
    """`fn(*args)` for a kernel that acts independently on each index of axis 0.

    Every leaf of `args` (a tuple of pytrees) has leading axis `size`; so has every leaf
    of the result.  Batches larger than `chunk` are padded by repeating their last point
    and mapped over chunk by chunk.
    """
    if size <= chunk:
        return fn(*args)
    chunks = -(-size // chunk)
    pad = chunks * chunk - size

    def split(x):
        x = jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1), mode="edge")
        return x.reshape((chunks, chunk) + x.shape[1:])

    out = jax.lax.map(lambda a: fn(*a), jax.tree.map(split, args))
    return jax.tree.map(lambda y: y.reshape((chunks * chunk,) + y.shape[2:])[:size], out)
