"""Work on one item while the next are prepared: `prefetched(fn, items, ahead=1)` yields
fn(item) for each item in order, computing the next `ahead` ones in background threads while
the caller works on the current one. For reading and decoding frames (file reads, LibRaw,
OpenEXR and SHA-256 release the GIL) ahead of the numeric work on the last ones: at most
ahead + 1 results exist at once, so memory stays that of a few items. One ahead suits a caller
with much work per item (a pose's reduction keeps the other core busy); two suit a caller that
only accumulates (master darks and flats, which wait on the decoder). An exception in fn is
raised where its item's result is taken, in order, as a plain loop would raise it.

The caller's compiled kernels release the GIL (numba ``nogil=True``; held, they stopped the
decoding thread at its first Python step: 24× a 24 MP decode's time). ``fn`` itself should not
launch parallel kernels: two launches at once are safe under numba's OpenMP or TBB layer but
abort under its ``workqueue`` fallback. The decoders here (rawpy, OpenEXR, numpy) launch none.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["prefetched"]

T = TypeVar("T")
R = TypeVar("R")


def prefetched(fn: Callable[[T], R], items: Iterable[T], ahead: int = 1) -> Iterator[R]:
    it = iter(items)
    with ThreadPoolExecutor(max_workers=ahead) as workers:
        pending = deque(workers.submit(fn, item) for item in itertools.islice(it, ahead))
        while pending:
            result = pending.popleft().result()
            for item in itertools.islice(it, 1):
                pending.append(workers.submit(fn, item))
            yield result
            del result  # the caller's copy is the only one left while the next ones are made
