"""How gonio's numba kernels are compiled and threaded: the one policy for every numeric layer.

- :data:`njit`: the compile flags every kernel uses (IEEE arithmetic, numpy's error model, the
  GIL released), so a serial and a parallel twin agree bit for bit.
- the vector width: on an AVX-512 CPU, 512-bit vectors (set before anything is compiled).
- :func:`set_threading`, :func:`dispatch`, :func:`prefers_threads`: whether a kernel runs its
  parallel (prange) or its serial twin, chosen by measured speed under the machine's load.

No domain in it (it knows kernels and threads, not BRDFs or pixels), so it lives with the
plumbing: the model kernels (fitting.models) and the calibration's HDR merge and pixel geometry
(calibration.hdr, calibration.geometry) use it alike.
"""

from __future__ import annotations

import functools
import os
import time

import numba

__all__ = ["njit", "PARALLEL_MIN_WORK", "set_threading", "dispatch", "prefers_threads"]


def _prefer_512_bit_vectors() -> None:
    """On an AVX-512 CPU let LLVM vectorise with 512-bit registers (8 float64 lanes, not 4).

    LLVM's tuning for Intel's AVX-512 cores says "prefer 256-bit" (older parts dropped their clock
    on 512-bit code); numba inherits it. On this project's machine type the wide vectors measured
    15–20 % faster for the seed torrance-sparrow, the conductor forms and phong, and within noise
    for GGX (docs/performance.md, "Kernels"). Done through numba's own NUMBA_CPU_FEATURES (the
    host's features plus "-prefer-256-bit"), before anything here is compiled; left alone when the
    user has chosen the features, and a no-op without AVX-512. numba keys its cache by the features,
    so a machine switching this on recompiles once."""
    if os.environ.get("NUMBA_CPU_FEATURES") or numba.config.CPU_FEATURES is not None:
        return
    import llvmlite.binding as llvm

    features = llvm.get_host_cpu_features()
    if not features.get("avx512f", False):
        return
    os.environ["NUMBA_CPU_FEATURES"] = features.flatten() + ",-prefer-256-bit"
    numba.core.config.reload_config()


_prefer_512_bit_vectors()

# No fast-math flag at all. "contract" (fused multiply-adds) measured 14–28 % faster, but LLVM fuses
# differently in the serial and the parallel twin of a kernel (each is compiled on its own), so
# their results differed in the last bit (a fresh-clone run of
# tests/fitting/models/test_models.py::test_large_problem_uses_parallel_kernels_identically) and the
# "auto" threading policy would make a seeded fit depend on the machine's load. Without it both
# twins round every operation as IEEE says, whatever the vector width, so they agree bit for bit.
# Flags that assume finite values (nnan, ninf) would also break the kernels' inf/NaN guards.
# error_model="numpy": a float division by zero gives ±inf/NaN as IEEE says instead of numba's
# default Python-style check, whose raise path keeps LLVM from vectorising any loop that divides
# (the kernels guard their divisions themselves). nogil: a kernel releases the GIL while it runs, so
# a thread beside it (the calibration's frame decoder, calibration.reduce) keeps working: held, a 24
# MP RAW's decode took 24× its time. numba's on-disk cache is keyed by a kernel's source, not by
# these options: after changing them, edit every module that imports this njit (or clear its
# __pycache__), or their old builds load with the new flags reported (a fresh checkout has no cache;
# tests/house/test_kernels_release_the_gil.py checks the flags only: a timing check would flake on a
# loaded machine).
njit = functools.partial(numba.njit, fastmath=False, error_model="numpy", nogil=True)


# Below this many (set × sample) evaluations the serial kernels are always used.
PARALLEL_MIN_WORK = 65536

_POLICIES = ("auto", "parallel", "serial")
_policy = ["auto"]


def set_threading(policy: str) -> str:
    """Choose how the kernels use numba's threads; returns the previous policy.

    "parallel": the prange kernels whenever the work is ≥ PARALLEL_MIN_WORK; "serial": never;
    "auto" (default): time both twins as they are used and keep the faster one per kernel,
    re-trying the other every 64 calls. Why: with free cores the parallel kernels are ~2×
    faster, but when the cores are oversubscribed (other processes busy) every parallel
    launch waits for a scheduler time slice — measured 5–40× slower than serial. Results are
    bitwise identical either way (tested), only the speed differs.
    """
    if policy not in _POLICIES:
        raise ValueError(f"threading policy {policy!r}; choose one of {', '.join(_POLICIES)}")
    previous = _policy[0]
    _policy[0] = policy
    return previous


class _Chooser:
    """Per-kernel running timings (ns per unit of work) of the parallel and serial twins."""

    def __init__(self):
        self.ns = {True: [], False: []}
        self.calls = 0

    def pick(self) -> bool:
        self.calls += 1
        for par in (True, False):
            if len(self.ns[par]) < 2:
                return par
        best = min(self.ns, key=lambda p: min(self.ns[p]))
        return (not best) if self.calls % 64 == 0 else best

    def record(self, par: bool, seconds: float, work: int) -> None:
        hist = self.ns[par]
        hist.append(seconds * 1e9 / work)
        del hist[:-4]  # recent timings only: the machine's load changes


_choosers: dict[str, _Chooser] = {}


def dispatch(name, par_fn, ser_fn, work, *args):
    """Run the parallel or the serial twin of a kernel (``par_fn``, ``ser_fn``, called with
    ``args``) according to the threading policy; ``work`` counts its units (set × sample, or
    pixels) and ``name`` keys its timings."""
    policy = _policy[0]
    if work < PARALLEL_MIN_WORK or numba.get_num_threads() < 2 or policy == "serial":
        return ser_fn(*args)
    if policy == "parallel":
        return par_fn(*args)
    chooser = _choosers.setdefault(name, _Chooser())
    par = chooser.pick()
    t0 = time.perf_counter()
    result = (par_fn if par else ser_fn)(*args)
    chooser.record(par, time.perf_counter() - t0, work)
    return result


def prefers_threads(name: str, work: int) -> bool:
    """Whether a geometry pass of kernel ``name``'s call should use threads (follows that
    kernel's timings)."""
    policy = _policy[0]
    if work < PARALLEL_MIN_WORK or numba.get_num_threads() < 2 or policy == "serial":
        return False
    if policy == "parallel":
        return True
    c = _choosers.get(name)
    if c is None or any(len(v) < 2 for v in c.ns.values()):
        return False
    return min(c.ns[True]) < min(c.ns[False])
