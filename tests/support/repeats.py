"""A pool for a statistical test's independent repeats: one process per core, each started fresh
(spawn: a repeat is then a function of its seed alone, whatever ran before in the suite)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

__all__ = ["repeat_pool", "repeat_map"]


def _repeat_process() -> None:
    """Each repeat process runs its kernels on one thread: the pool's two processes, and the
    suite's other worker beside them, already fill the two cores, and a parallel kernel's
    threads only wait for each other there (numba's spin-waits: ~10 % more CPU, measured). And
    it runs at a lower priority (nice 10): the repeats are batch work, while the other worker
    may be running a file that waits on emulated hardware's real time (tests/conftest.py starts
    those beside the pools), whose frame periods and timeouts should not queue behind them."""
    import numba

    numba.set_num_threads(1)
    os.nice(10)


def repeat_pool(workers: int = 2) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(
        max_workers=workers, mp_context=get_context("spawn"), initializer=_repeat_process
    )


def repeat_map(pool: ProcessPoolExecutor, fn: Callable[[Any], Any], args: Sequence) -> list:
    """fn over args in the pool, in order — the first alone, then the rest together: on a fresh
    checkout the first repeat compiles the numba kernels and writes their cache, and the other
    process then loads them instead of compiling the same kernels at the same time (28 CPU-s
    per process for a realistic repeat, measured; the suite's other worker has the core meanwhile).
    """
    if not args:
        return []
    first = pool.submit(fn, args[0]).result()
    return [first, *pool.map(fn, args[1:])]
