"""Work on one item while the next is prepared: `prefetched(fn, items)` yields fn(item) for
each item in order, computing the next one in a background thread while the caller works on
the current one. For reading and decoding frames (file reads, LibRaw, OpenEXR and SHA-256
release the GIL) ahead of the numeric work on the last ones: at most two results exist at
once, so memory stays that of two items. An exception in fn is raised where its item's result
is taken, in order, as a plain loop would raise it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["prefetched"]

T = TypeVar("T")
R = TypeVar("R")


def prefetched(fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
    it = iter(items)
    with ThreadPoolExecutor(max_workers=1) as worker:
        try:
            ahead = worker.submit(fn, next(it))
        except StopIteration:
            return
        while True:
            result = ahead.result()
            try:
                ahead = worker.submit(fn, next(it))
            except StopIteration:
                yield result
                return
            yield result
            del result  # the caller's copy is the only one left while the next one is made
