"""Progress of long work: a rich bar on a terminal, a callback of the caller's, or nothing.

Progress is reported from host code only, between calls of compiled programs: a function
that wants a bar cuts its work into host-side batches (each one call of the same compiled
program) and advances the bar after each.  Nothing here runs inside `jax.jit`, so a
compiled loop is never slowed by a host callback.

The `progress` argument of the public functions: `None` (default) shows a bar when stdout
is a terminal (and the job is long enough to want one), `True` always, `False` never; a
callable is called as `progress(done, total)` on the host after each batch, with `done`
increasing to `total`, and no bar is drawn.  Callers cut their work into batches only when
something listens (`ProgressReport.shown`), so a silent call is the single call it was.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

ProgressArgument = bool | None | Callable[[int, int], object]


def check_progress(progress, owner: str):
    """`progress` as given if it is `None`, a bool or a callable; else a `ValueError`."""
    if progress is None or callable(progress):
        return progress
    if isinstance(progress, (bool, np.bool_)):
        return bool(progress)
    raise ValueError(
        f"{owner}: progress must be None (a bar on a terminal), True, False or a callable "
        f"progress(done, total), got {progress!r}"
    )


class ProgressReport:
    """What `progress_bar` yields: `advance(k)` after each batch, `describe(text)` to name a
    new phase of the job; `shown` says whether anything listens (else both do nothing)."""

    def __init__(self, total: int, callback=None, bar=None):
        self.total = int(total)
        self.done = 0
        self._callback = callback
        self._bar = bar

    @property
    def shown(self) -> bool:
        return self._callback is not None or self._bar is not None

    def advance(self, k: int = 1) -> None:
        k = int(k)
        if k <= 0:
            return
        self.done = min(self.done + k, self.total)
        if self._bar is not None:
            self._bar[0].update(self._bar[1], completed=self.done)
        if self._callback is not None:
            self._callback(self.done, self.total)

    def describe(self, text: str) -> None:
        if self._bar is not None:
            self._bar[0].update(self._bar[1], description=text)


@contextlib.contextmanager
def progress_bar(description: str, total: int, progress, *, owner: str, auto: bool = True) -> Iterator[ProgressReport]:
    """A `ProgressReport` of a job of `total` units (module docstring for `progress`;
    `auto=False` keeps the default `None` silent even on a terminal, e.g. for a job of one
    batch).  The bar is removed from the live display when the block ends, however it ends."""
    progress = check_progress(progress, owner)
    if callable(progress):
        yield ProgressReport(total, callback=progress)
        return
    if progress is False or (progress is None and not (auto and sys.stdout.isatty())):
        yield ProgressReport(total)
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    bar.start()
    try:
        yield ProgressReport(total, bar=(bar, bar.add_task(description, total=total)))
    finally:
        bar.stop()


#: Host-side batches a job is cut into when its progress is shown: enough for a bar that
#: moves, few enough that the calls' overhead and lost vectorisation do not matter.
MAX_BATCHES = 20


def batch_size(total: int, max_batches: int = MAX_BATCHES) -> int:
    """Units per batch: `total` cut into at most `max_batches` equal batches, and at least
    two units per batch where there are two: a vmap of width one compiles to a program of
    its own whose rounding differs (bootstrap refits differed by 1e-11), while widths of
    two or more gave the refits and fits of the single call bit for bit (measured; not
    every program is so indifferent to the width: `stability_atlas` keeps its widths)."""
    total = int(total)
    return min(total, max(2, -(-total // min(total, max_batches))))


def padded_batch(tree, start: int, size: int):
    """Rows `start ... start + size - 1` (axis 0) of every array of `tree`, the last batch
    padded to `size` by repeating its last row: every batch has one shape, so one compiled
    program serves them all (the caller drops the padding's results)."""

    def rows(a):
        part = a[start:start + size]
        short = size - part.shape[0]
        return part if short == 0 else jnp.concatenate([part, jnp.repeat(part[-1:], short, axis=0)])

    return jax.tree.map(rows, tree)


def scan_in_batches(fn, carry, xs, total: int, size: int, report: ProgressReport):
    """`fn(carry, batch) -> (carry, out)` over the batches of `size` rows of the pytree `xs`
    (`total` rows; the last batch padded, `padded_batch`), advancing `report` after each;
    returns the final carry and the outputs (axis 0 of every array) of the `total` rows.
    Each batch is waited for before the bar moves, so the bar tells the work done."""
    outs = []
    for start in range(0, total, size):
        stop = min(start + size, total)
        carry, out = jax.block_until_ready(fn(carry, padded_batch(xs, start, size)))
        outs.append(jax.tree.map(lambda a, n=stop - start: a[:n], out))
        report.advance(stop - start)
    return carry, jax.tree.map(lambda *parts: jnp.concatenate(parts), *outs)
