"""Elementwise kernels evaluated a chunk of points at a time.

The register solve is a few dozen dependent elementwise steps, each a pass over its
arrays.  Written out over a whole batch on a CPU, every intermediate array streams through
main memory; a `lax.map` over cache-sized chunks keeps them in cache.  On an accelerator
the chunks are large (each is a round of kernel launches).  Values do not depend on the
chunk size beyond rounding (other sizes are other XLA programs).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Points per chunk.  On a CPU: cache-sized (best of 256 ... 16384 on 2 CPU cores,
# benchmarks/bench_equilibria.py).  On an accelerator every chunk is a round of kernel
# launches, so chunks are as large as memory allows (measured on an H100:
# benchmarks/bench_device.py).
CPU_CHUNK = 1024
ACCELERATOR_CHUNK = 1 << 21


def default_chunk() -> int:
    """The chunk size for the default backend (read at trace time)."""
    return CPU_CHUNK if jax.default_backend() == "cpu" else ACCELERATOR_CHUNK


def map_chunks(fn, args, size: int, chunk: int | None = None):
    """`fn(*args)` for a kernel that acts independently on each index of axis 0.

    Every leaf of `args` (a tuple of pytrees) has leading axis `size`; so has every leaf
    of the result.  Batches larger than `chunk` (default: `default_chunk()`) are padded by
    repeating their last point and mapped over chunk by chunk.
    """
    chunk = default_chunk() if chunk is None else chunk
    if size <= chunk:
        return fn(*args)
    chunks = -(-size // chunk)
    pad = chunks * chunk - size

    def split(x):
        x = jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1), mode="edge")
        return x.reshape((chunks, chunk) + x.shape[1:])

    out = jax.lax.map(lambda a: fn(*a), jax.tree.map(split, args))
    return jax.tree.map(lambda y: y.reshape((chunks * chunk,) + y.shape[2:])[:size], out)
