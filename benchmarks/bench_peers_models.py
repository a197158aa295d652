"""gonio's model evaluation against its peers, in the same run on identical inputs (issue 23,
item 1 "kernels" and the roofline of item 2): the fused numba kernels (``model.evaluate``) vs a
``jax.jit`` float64 version of the same equations (benchmarks/_jax_models.py) and, for the models
it has, Mitsuba 3's BSDFs (Dr.Jit LLVM backend), plus the CPU's own limit measured in numba.

Run: ``.venv/bin/python benchmarks/bench_peers_models.py [--n 10000] [--w 64] [--repeat 9]
[--threads 2]``. Every peer gets the same thread count (numba, XLA, Dr.Jit). Each peer's output is
first checked equal to gonio's on the same inputs; a failed check is printed loudly and that row
gets no ratio. Times are the best of ``repeat`` calls after a warm-up (compile) call, in ns per
(sample × parameter set); ratios are gonio / peer, so < 1 means gonio is faster. Speed is printed,
never asserted. Without jax (``pip install -e '.[bench]'``) or an LLVM-capable Mitsuba the
respective columns are skipped with one line saying so.

Mitsuba (llvm_ad_rgb, float32) runs one kernel over N·W lanes with *one* parameter set for all of
them (its BSDF parameters are scalars: the most favourable case for it; gonio's figure is for W
different sets); its rows use kd = 0, ks = 1 (roughconductor has no diffuse lobe and
specular_reflectance = 1) and φ₀ = 0 (Mitsuba's α_u lies along +x). Its time is a replay of a
frozen function (``dr.freeze``): input checks, one recorded kernel launch and the wait for it —
no Python tracing, no compilation; "Mi krnl" is the kernel's own execution time.
gonio's float32 kernels (``evaluate(precision="float32")``, what its MCMC runs where the rounding
is negligible: fitting.likelihood) are timed too ("g f32") and checked against Mitsuba the same
way; g/Mi compares like with like: float32 with float32 where gonio has it (marked *), else
gonio's float64. g/JAX compares float64 with float64.
The roofline column is this CPU's limit for the operations each model's numba path performs
(counted in OPS, costed by the microbenchmarks printed first).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import dataclass, field

import numba
import numpy as np
from bench_models import _VALUES, _best
from numba import prange

from brdfdata.directions import uniform_hemisphere
from fitting import models
from fitting.models import kernel_math
from plumbing import numba_policy
from plumbing.numba_policy import njit  # the kernels' own flags, so ops cost what they cost there
from simulator.variant import probe_variant

__all__ = ["main", "CASES", "OPS"]


@dataclass(frozen=True)
class Case:
    """One model state: gonio's ``models.get(name, **options)``, the same in JAX, and the Mitsuba
    BSDF that computes the same function (None: Mitsuba has no such model)."""

    name: str
    options: dict = field(default_factory=dict)
    mitsuba: str | None = None  # "diffuse", or the roughconductor distribution

    @property
    def label(self) -> str:
        return self.name + (" " + ",".join(self.options.values()) if self.options else "")


CASES: list[Case] = [
    Case("lambert", {}, "diffuse"),
    Case("phong"),
    Case("blinn-phong"),
    Case("torrance-sparrow"),  # seed form: beckmann, v-cavity, dielectric
    # Mitsuba's roughconductor: π-normalised D (α = m), separable Smith with Walter's rational G₁
    # for Beckmann / the exact G₁ for GGX, exact conductor Fresnel (docs/design.md §7)
    Case("torrance-sparrow", {"shadowing": "smith-rational", "fresnel": "conductor"}, "beckmann"),
    Case(
        "torrance-sparrow",
        {"distribution": "ggx", "shadowing": "smith", "fresnel": "conductor"},
        "ggx",
    ),
    # the anisotropic model's options default to fresnel="dielectric" (bench_models' case); the
    # conductor variant is the one Mitsuba's anisotropic roughconductor (alpha_u, alpha_v) has
    Case("torrance-sparrow-anisotropic", {"distribution": "ggx", "shadowing": "smith"}),
    Case(
        "torrance-sparrow-anisotropic",
        {"distribution": "ggx", "shadowing": "smith", "fresnel": "conductor"},
        "ggx",
    ),
]

# -- roofline: operations per evaluation ----------------------------------------------------------
# Counted by reading the numba path each model takes for per-set parameters ((W, 1) arrays), as of
# this writing: fitting.models.lobe_kernels (_lobe_row/_lobe_block) and
# fitting.models.microfacet_kernels (_geometry_row and the _ts_block stages _stage_d, _stage_g,
# _stage_f), fitting.models.anisotropic (_aniso_row, _block_per_set with _stage_d, _stage_g_frac)
# and fitting.models.seed.Lambert._numba, in float64 (the roof column is gonio's float64).
# Conventions:
#   addmul  one add, sub, mul, compare, select, min or max (all ~1 vector µop on x86)
#   fma     one explicit a*b + c pattern (the kernels' njit does not fuse it — IEEE rounding keeps
#           serial and parallel twins identical — so the microbenchmark below, compiled by the
#           same njit, measures the mul + add pair it compiles to)
#   div, sqrt, exp, log, pow, erfc  one call each; gonio's vectorisable exp_neg counts as an exp
# "set" is the work per (sample × parameter set), "pair" the per-direction-pair geometry pass done
# once per call and shared by the W sets (charged 1/W per sample·set). Per-set parameter tables
# (work / N) and loop/buffer loads are not counted; each evaluation also stores one float64 (the
# "store" bound below). A count is a reading, not a measurement: ±10 % is its honest precision.
_TS_PAIR = {"addmul": 21, "fma": 8, "div": 6, "sqrt": 3}  # _geometry_row: s, t2, ω·h, cos θ_h,
# sin θ_i,o (sqrt each), the V-cavity G/(4 ci co) (3 divides, 2 mins) — computed for every option
_ANISO_PAIR = {"addmul": 25, "fma": 8, "div": 9, "sqrt": 4}  # _aniso_row: as _geometry_row plus
# Ward's three normalisations (computed for the TS model too)
_D_BECKMANN = {"addmul": 8, "exp": 1}  # x = t2/m², min, exp_neg, (1+t2)²·e·dn, underflow select
_D_GGX = {"addmul": 3, "fma": 1, "div": 1}  # r = (1+t2)/(1 + t2/m²), r²·dn
_G_RATIONAL = {"addmul": 23, "fma": 6}  # per side u = m s, numerator, denominator, a < 1.6
# selects; its one divide is folded into the combine's
# (fitting.models.microfacet_kernels.stage_shadowing_frac)
_G_GGX = {"addmul": 9, "fma": 2, "sqrt": 2}  # 1/((ci + Ri)(co + Ro)), Ri = √(ci² + m²si²); the
# divide folded into the combine's F as a fraction
# (fitting.models.microfacet_kernels.stage_fresnel_frac); both torrance-sparrow kernels fold its
# divide into the combine's
_F_DIELECTRIC = {"addmul": 14, "fma": 4, "sqrt": 1}  # Rs + Rp over one denominator, TIR select
_F_CONDUCTOR = {"addmul": 19, "fma": 2, "sqrt": 2}  # Möller's real form, one denominator
_COMBINE = {"addmul": 5, "fma": 1, "div": 1}  # kd/π + ks·(d·g·f)/(gden·fden), valid select
_D_GGX_ANISO = {"addmul": 12, "fma": 3, "div": 1}  # rotate s by φ₀, Q = x'²/αx² + y'²/αy²,
# r = |s|²/(sz² + Q) (no q: one divide), select, r²·dn
_G_GGX_ANISO = {"addmul": 14, "fma": 6, "sqrt": 2}  # u² = |M ω|² per side (M: the rotation by φ₀
# times α, per set), (ci + √(ci² + ui²))(co + √(co² + uo²)), selects; the divide folded into the
# combine's


def _sum(*parts: dict) -> dict:
    total: dict[str, int] = {}
    for part in parts:
        for op, count in part.items():
            total[op] = total.get(op, 0) + count
    return total


_LOBE_SET = {"addmul": 6, "fma": 1, "exp": 1}  # _lobe_block fast path: x = −n log base, min,
# exp_neg, underflow select, kd/π + ks N·e, valid select (the norm N(n) is per set)
OPS: dict[str, dict[str, dict[str, int]]] = {
    # Lambert._numba: kd/π broadcast straight into `out` (numpy), then 0 where the pair is below
    # the horizon — one store per sample·set
    "lambert": {"set": {"addmul": 1}, "pair": {"addmul": 3}},
    # _lobe_row: l̂·r̂ = 2 ci co − ω_i·ω_o, clamp, log base (one log per pair)
    "phong": {"set": _LOBE_SET, "pair": {"addmul": 7, "fma": 2, "log": 1}},
    # _lobe_row: cos θ_h = s_z/|s| (sqrt + divide), clamp, log base
    "blinn-phong": {
        "set": _LOBE_SET,
        "pair": {"addmul": 8, "fma": 2, "sqrt": 1, "div": 1, "log": 1},
    },
    # _ts_block: D Beckmann + V-cavity (a copy of the per-pair G) + dielectric F + combine
    "torrance-sparrow": {"set": _sum(_D_BECKMANN, _F_DIELECTRIC, _COMBINE), "pair": _TS_PAIR},
    "torrance-sparrow smith-rational,conductor": {
        "set": _sum(_D_BECKMANN, _G_RATIONAL, _F_CONDUCTOR, _COMBINE),
        "pair": _TS_PAIR,
    },
    "torrance-sparrow ggx,smith,conductor": {
        "set": _sum(_D_GGX, _G_GGX, _F_CONDUCTOR, _COMBINE),
        "pair": _TS_PAIR,
    },
    # _block_per_set: _stage_d (GGX), _stage_g_frac (GGX separable), stage_fresnel_frac, combine
    "torrance-sparrow-anisotropic ggx,smith": {
        "set": _sum(_D_GGX_ANISO, _G_GGX_ANISO, _F_DIELECTRIC, _COMBINE),
        "pair": _ANISO_PAIR,
    },
    "torrance-sparrow-anisotropic ggx,smith,conductor": {
        "set": _sum(_D_GGX_ANISO, _G_GGX_ANISO, _F_CONDUCTOR, _COMBINE),
        "pair": _ANISO_PAIR,
    },
}

# -- roofline: what one operation costs on this CPU -----------------------------------------------
_CHAIN = 8  # steps per element (chain kernels) or passes over the array (map kernels)
_ROOF_SIZE = 1 << 16  # float64 elements (512 KiB): cache-resident, so ops are timed, not memory
_LANES = 8  # independent chains per element: latency hidden by out-of-order execution


@njit(inline="always")
def _step_addmul(y):
    return (y + 1e-3) * 0.999  # 2 ops


@njit(inline="always")
def _step_fma(y):
    return y * 0.999 + 1e-3


@njit(inline="always")
def _step_div(y):
    return 1.0001 / y  # alternates between y and ≈ 1/y: stays in [0.5, 2]


@njit(inline="always")
def _step_sqrt(y):
    return math.sqrt(y)


@njit(inline="always")
def _step_exp(y):
    return math.exp(-y)  # stays in (0, 1]


@njit(inline="always")
def _step_exp_neg(y):
    return kernel_math.exp_neg_scalar(y)  # gonio's vectorisable exp(−y)


@njit(inline="always")
def _step_log(y):
    return math.log(y + 2.0)  # the add is noise next to the call


@njit(inline="always")
def _step_pow(y):
    return y**0.9


@njit(inline="always")
def _step_erfc(y):
    return math.erfc(y)  # stays in (0, 2)


# name → (step, operations per step, kernel form): see _chain_kernels and _map_kernels
_STEPS = {
    "addmul": (_step_addmul, 2, "chain"),
    "fma": (_step_fma, 1, "chain"),
    "div": (_step_div, 1, "chain"),
    "sqrt": (_step_sqrt, 1, "chain"),
    "exp (libm)": (_step_exp, 1, "map"),
    "exp (gonio exp_neg)": (_step_exp_neg, 1, "map"),
    "log": (_step_log, 1, "map"),
    "pow": (_step_pow, 1, "map"),
    "erfc": (_step_erfc, 1, "map"),
}
_OPS_PER_ELEMENT = {"chain": _CHAIN * _LANES, "map": _CHAIN}


def _chain_kernels(step):
    """Serial and prange kernels applying ``step`` _CHAIN times to _LANES independent values per
    array element, for the ops that take a few cycles: they vectorise across elements, and the
    independent chains hide their latency; the element's load and store are amortised over 64
    ops. ``error_model="numpy"``: no ZeroDivisionError check, so divisions vectorise too (this is
    the CPU's limit, not what any one kernel achieves)."""

    @njit(inline="always", error_model="numpy")
    def element(x):
        y0, y1, y2, y3 = x, x + 0.01, x + 0.02, x + 0.03
        y4, y5, y6, y7 = x + 0.04, x + 0.05, x + 0.06, x + 0.07
        for _ in range(_CHAIN):
            y0, y1, y2, y3 = step(y0), step(y1), step(y2), step(y3)
            y4, y5, y6, y7 = step(y4), step(y5), step(y6), step(y7)
        return ((y0 + y1) + (y2 + y3)) + ((y4 + y5) + (y6 + y7))

    @njit(error_model="numpy")
    def serial(x, out):
        for i in range(x.size):
            out[i] = element(x[i])

    @njit(parallel=True, error_model="numpy")
    def parallel(x, out):
        for i in prange(x.size):
            out[i] = element(x[i])

    return serial, parallel


def _map_kernels(step):
    """Serial and prange kernels applying ``step`` to every element, _CHAIN passes over the array,
    for the function calls (exp, log, pow, erfc): independent calls, so their throughput is timed
    rather than their latency, and a loop this simple is the one LLVM vectorises (gonio's exp_neg
    is written for that; libm's calls stay scalar). The load and store are noise next to a call."""

    @njit(error_model="numpy")
    def serial(x, out):
        for _ in range(_CHAIN):
            for i in range(x.size):
                out[i] = step(x[i])

    @njit(parallel=True, error_model="numpy")
    def parallel(x, out):
        # chunks of the array across the threads, each with the serial form's simple loop inside
        # (gonio's own layout), so that it vectorises the same way; one parallel launch per call
        n_chunks = 64
        size = (x.size + n_chunks - 1) // n_chunks
        for c in prange(n_chunks):
            lo, hi = c * size, min((c + 1) * size, x.size)
            for _ in range(_CHAIN):
                for i in range(lo, hi):
                    out[i] = step(x[i])

    return serial, parallel


@njit
def _store_serial(out, value):
    for i in range(out.size):
        out[i] = value


@njit(parallel=True)
def _store_parallel(out, value):
    for i in prange(out.size):
        out[i] = value


def measure_op_costs(threads: int, evals: int, repeat: int) -> dict[str, tuple[float, float]]:
    """ns per operation on one core (serial kernel) and with ``threads`` numba threads (prange
    kernel, ns of wall time per op), for every op of _STEPS and for one float64 store into an
    array of ``evals`` elements (the size of a model's output)."""
    x = np.random.default_rng(1).uniform(1.0, 2.0, _ROOF_SIZE)
    out = np.empty_like(x)
    costs = {}
    for name, (step, per_step, form) in _STEPS.items():
        ops = _ROOF_SIZE * _OPS_PER_ELEMENT[form] * per_step
        make = _chain_kernels if form == "chain" else _map_kernels
        timed = []
        for kernel in make(step):
            wall, _ = _best(lambda kernel=kernel: kernel(x, out), repeat)
            timed.append(wall / ops * 1e9)
        costs[name] = (timed[0], timed[1])
    big = np.empty(evals)
    costs["store"] = tuple(
        _best(lambda fn=fn: fn(big, 1.0), repeat)[0] / evals * 1e9
        for fn in (_store_serial, _store_parallel)
    )
    if threads < 2:  # the prange twins ran on one thread: the same figure
        costs = {k: (v[0], v[0]) for k, v in costs.items()}
    return costs


def roofline_ns(ops: dict, costs: dict, threads: int, w: int) -> float:
    """The CPU's limit for one sample·set: Σ count × (ns per op on one core) / threads over the
    per-set ops and 1/W of the per-pair ops, or the output store if that is slower (the store
    bound uses the measured bandwidth, which does not scale with threads)."""
    per_core = {op: c[0] for op, c in costs.items()}
    per_core["exp"] = min(per_core["exp (libm)"], per_core["exp (gonio exp_neg)"])
    counts = _sum(ops["set"], {k: v / w for k, v in ops["pair"].items()})
    compute = sum(n * per_core[op] for op, n in counts.items()) / threads
    return max(compute, min(costs["store"]))


# -- threads --------------------------------------------------------------------------------------


def limit_threads(requested: int) -> tuple[int, str]:
    """Give numba, XLA and Dr.Jit the same thread count; call before jax or mitsuba is imported.

    XLA: the documented knobs are ``--xla_cpu_multi_thread_eigen`` and
    ``intra_op_parallelism_threads`` in XLA_FLAGS (jax issues #743, #1539); they are set, but with
    jaxlib 0.10 they do not limit the fused elementwise kernels measured here (per-thread CPU
    ticks showed 3–4 busy XLA threads either way), whose pool is sized from the process's CPU
    affinity (taskset -c 0 gave one busy thread). So below the available core count the whole
    process is pinned to ``threads`` cores, which treats every peer alike.
    (``--xla_force_host_platform_device_count`` makes several CPU *devices* for pmap/sharding; a
    single-device jit does not use it, so it is left alone.)
    """
    cpus = sorted(os.sched_getaffinity(0))
    threads = max(1, min(requested, len(cpus), numba.config.NUMBA_NUM_THREADS))
    note = ""
    if threads < requested:
        note = f" (asked for {requested}; {len(cpus)} cores available)"
    if threads < len(cpus):
        # before any pool starts: threads created later inherit the mask
        os.sched_setaffinity(0, cpus[:threads])
        note += f"; process pinned to cores {cpus[:threads]}"
    eigen = "true" if threads > 1 else "false"
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_cpu_multi_thread_eigen={eigen} intra_op_parallelism_threads={threads}"
    ).strip()
    numba.set_num_threads(threads)  # starts numba's pool: after the affinity
    # gonio's default "auto" policy picks serial or parallel from timings as it runs; here the
    # peers' own thread pools (XLA's spin after each call) would make its early picks noise. Every
    # peer gets the threads, so gonio runs its parallel kernels (bench_models measures "auto").
    numba_policy.set_threading("parallel" if threads > 1 else "serial")
    return threads, note


def _settle() -> None:
    # numba's OpenMP layer spin-waits briefly after a parallel region; let those threads sleep
    # before the next peer is timed so they do not steal its cores.
    time.sleep(0.05)


# -- equality -------------------------------------------------------------------------------------
# JAX vs gonio, both float64 with the same formulas: they differ by rounding only (operation order,
# libm vs XLA's exp/pow, gonio's polynomial exp_neg ≈ 2 ulp, the conductor Fresnel in complex form
# in JAX vs Möller's real form in the kernels). exp(−x) and base^n = exp(n log base) amplify a
# relative error of their argument by up to x ≤ 745 (then they underflow), so ~745 × 2 ulp ≈ 3e-13
# is the worst to expect: rtol 1e-12. Values near 0 carry no relative information (underflowed
# lobes, XLA flushing denormals to 0), hence an absolute floor of 1e-14 × the largest |f|.
_JAX_RTOL = 1e-12
_JAX_ATOL_OF_MAX = 1e-14
# Mitsuba vs gonio on the same float32-rounded inputs: Mitsuba's float32 arithmetic (a few ulps of
# 6e-8, times the condition number of exp(−tan²θ_h/m²) up to its D cut-off) bounds the difference: ≲
# 1e-5 worst case, ~1e-7 typical — tests/fitting/models/test_models_vs_mitsuba.py's median ≤ 1e-5,
# max ≤ 1e-3 relative where Mitsuba is > 0, and f·cos θ_o < 1e-15 where Mitsuba cut D off.
_MI_MEDIAN, _MI_MAX, _MI_CUTOFF = 1e-5, 1e-3, 1e-15


def check_close(peer: np.ndarray, ours: np.ndarray) -> tuple[bool, float]:
    """(equal within _JAX_RTOL / the absolute floor, worst relative error above the floor)."""
    floor = _JAX_ATOL_OF_MAX * np.max(np.abs(ours))
    err = np.abs(peer - ours)
    ok = bool(np.all(np.isfinite(peer)) and np.all(err <= _JAX_RTOL * np.abs(ours) + floor))
    big = np.abs(ours) > floor
    worst = float(np.max(err[big] / np.abs(ours[big]))) if big.any() else 0.0
    return ok, worst


def check_mitsuba(f_mitsuba: np.ndarray, ours: np.ndarray, cos_o: np.ndarray) -> tuple[bool, str]:
    positive = f_mitsuba > 0
    rel = np.abs(ours - f_mitsuba)[positive] / f_mitsuba[positive]
    cut_ok = bool(np.all(np.broadcast_to(ours * cos_o, f_mitsuba.shape)[~positive] < _MI_CUTOFF))
    median, worst = (float(np.median(rel)), float(np.max(rel))) if rel.size else (0.0, 0.0)
    ok = positive.any() and cut_ok and median <= _MI_MEDIAN and worst <= _MI_MAX
    return bool(ok), f"median rel {median:.1e}, max rel {worst:.1e}, cut-off ok {cut_ok}"


# -- Mitsuba --------------------------------------------------------------------------------------

_MITSUBA_VARIANT = "llvm_ad_rgb"


def mitsuba_unavailable() -> str | None:
    """Why the LLVM variant cannot be used here, or None. LLVM 15/16 abort the whole process
    (docs/design.md §7), so it is probed in a child interpreter by the simulator's own probe."""
    ok, reason = probe_variant(_MITSUBA_VARIANT)
    return None if ok else f"{_MITSUBA_VARIANT} unavailable ({reason})"


class MitsubaPeer:
    """Mitsuba BSDFs evaluated as one Dr.Jit kernel over N·W lanes, one parameter set for all lanes
    (Mitsuba's BSDF parameters are scalars: the most favourable case for it)."""

    def __init__(self, threads: int):
        import drjit as dr
        import mitsuba as mi

        mi.set_variant(_MITSUBA_VARIANT)
        dr.set_thread_count(threads)
        # Kernel history gives each launch's own execution time (a second, kernel-only figure).
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        self.dr, self.mi = dr, mi

    def bsdf(self, case: Case, p: dict):
        if case.mitsuba == "diffuse":
            return self.mi.load_dict({"type": "diffuse", "reflectance": p["kd"]})
        spec = {"type": "roughconductor", "distribution": case.mitsuba, "eta": p["eta"]}
        spec["k"] = p["k"]
        if case.name == "torrance-sparrow-anisotropic":
            spec.update(alpha_u=p["alpha_x"], alpha_v=p["alpha_y"])  # φ₀ = 0: u = +x
        else:
            spec["alpha"] = p["m"]
        return self.mi.load_dict(spec)

    def frozen_eval(self):
        """f·cos θ_o of channel 0 for lanes (ω_i, ω_o), as a frozen function (dr.freeze): the first
        call traces, compiles and records the kernel launches; later calls replay them, with no
        Python tracing or compilation. The RGB channels are equal here, so only one is kept
        (Dr.Jit then compiles one)."""
        dr, mi = self.dr, self.mi

        @dr.freeze
        def eval_cos(bsdf, wi, wo):
            si = dr.zeros(mi.SurfaceInteraction3f, dr.width(wi))
            si.wi = wi
            si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
            return bsdf.eval(mi.BSDFContext(), si, wo)[0]

        return eval_cos

    def vectors(self, v: np.ndarray):
        out = self.mi.Vector3f(v[:, 0], v[:, 1], v[:, 2])
        self.dr.eval(out)
        return out

    def time(self, fn, args, repeat: int) -> tuple[float, float, int]:
        """Best wall time of a replay (launch + kernel + the frozen function's input checks, then
        dr.sync_thread), best kernel execution time from the kernel history, and how many times
        the function was recorded (1 means every timed call was a replay)."""
        dr = self.dr
        fn(*args)  # record: trace + compile (excluded)
        dr.sync_thread()
        wall, kernel = [], []
        for _ in range(repeat):
            dr.kernel_history()  # clear
            t0 = time.perf_counter()
            fn(*args)
            dr.sync_thread()
            wall.append(time.perf_counter() - t0)
            kernel.append(sum(k.get("execution_time", 0.0) for k in dr.kernel_history()) * 1e-3)
        return min(wall), min(kernel), fn.n_recordings


def _float32_params(params: dict, row: int, case: Case) -> dict[str, float]:
    """Parameter set `row` rounded to float32 (Mitsuba stores them so), as the Mitsuba row uses
    it: kd = 0, ks = 1 for roughconductor (Mitsuba's specular_reflectance = 1, no diffuse
    lobe), φ₀ = 0 for the anisotropic model (Mitsuba's α_u lies along +x)."""
    p = {k: float(np.float32(v[row, 0])) for k, v in params.items()}
    if case.mitsuba != "diffuse":
        p.update(kd=0.0, ks=1.0)
    if "phi0" in p:
        p["phi0"] = 0.0
    return p


# -- one model ------------------------------------------------------------------------------------


@dataclass
class Row:
    label: str
    gonio_ns: float
    gonio32_ns: float | None = None  # the float32 kernels, where the model has them
    jax_ns: float | None = None
    jax_ok: bool | None = None
    mi_ns: float | None = None
    mi_kernel_ns: float | None = None
    mi_ok: bool | None = None
    roof_ns: float | None = None


def run_case(case, wi, wo, rng, args, jax_mod, mitsuba, costs, threads) -> Row:
    model = models.get(case.name, **case.options)
    params = {p: rng.uniform(*_VALUES[p], (args.w, 1)) for p in model.parameter_names}
    evals = args.n * args.w
    ours = model.evaluate(params, wi, wo)
    gonio_s, _ = _best(lambda: model.evaluate(params, wi, wo), args.repeat)
    row = Row(case.label, gonio_s / evals * 1e9)
    if model.float32:
        gonio32_s, _ = _best(
            lambda: model.evaluate(params, wi, wo, precision="float32"), args.repeat
        )
        row.gonio32_ns = gonio32_s / evals * 1e9
    if case.label in OPS:
        row.roof_ns = roofline_ns(OPS[case.label], costs, threads, args.w)
    if jax_mod is not None:
        _settle()
        row.jax_ok, row.jax_ns = _run_jax(case, params, wi, wo, ours, jax_mod, args.repeat)
        row.jax_ns /= evals / 1e9
    if mitsuba is not None and case.mitsuba is not None:
        _settle()
        row.mi_ok, times = _run_mitsuba(case, model, params, wi, wo, mitsuba, args)
        row.mi_ns, row.mi_kernel_ns = (t / evals * 1e9 for t in times)
    return row


def _run_jax(case, params, wi, wo, ours, jax_mod, repeat) -> tuple[bool, float]:
    jnp = jax_mod.jnp
    fn = jax_mod.get(case.name, **case.options)
    jp = {k: jnp.asarray(v) for k, v in params.items()}
    jwi, jwo = jnp.asarray(wi), jnp.asarray(wo)
    peer = np.asarray(fn(jp, jwi, jwo))  # compiles
    ok, worst = check_close(peer, ours)
    status = "ok" if ok else "!!! FAILED — no ratio for this row !!!"
    print(
        f"  check JAX     {case.label:<48} worst rel err {worst:.1e} "
        f"(rtol {_JAX_RTOL:.0e}, floor {_JAX_ATOL_OF_MAX:.0e}·max|f|): {status}"
    )
    seconds, _ = _best(lambda: fn(jp, jwi, jwo).block_until_ready(), repeat)
    return ok, seconds


def _run_mitsuba(case, model, params, wi, wo, mitsuba, args) -> tuple[bool, tuple[float, float]]:
    p = _float32_params(params, 0, case)
    wi32, wo32 = wi.astype(np.float32), wo.astype(np.float32)
    bsdf = mitsuba.bsdf(case, p)
    # lane w·N + j is pair j: the same N pairs once per parameter set, as gonio evaluates them
    lanes_i = mitsuba.vectors(np.tile(wi32, (args.w, 1)))
    lanes_o = mitsuba.vectors(np.tile(wo32, (args.w, 1)))
    fn = mitsuba.frozen_eval()
    cos_o = wo32[:, 2].astype(np.float64)
    f_mi = np.asarray(fn(bsdf, lanes_i, lanes_o), dtype=np.float64).reshape(args.w, args.n) / cos_o
    wi64, wo64 = wi32.astype(np.float64), wo32.astype(np.float64)
    ok = True
    for precision in ("float64", "float32") if model.float32 else ("float64",):
        ours = model.evaluate(p, wi64, wo64, precision=precision).astype(np.float64)
        ok_one, detail = check_mitsuba(f_mi, ours, cos_o)
        ok = ok and ok_one
        status = "ok" if ok_one else "!!! FAILED — no ratio for this row !!!"
        print(f"  check Mitsuba {case.label:<48} gonio {precision}: {detail}: {status}")
    wall, kernel, recordings = mitsuba.time(fn, (bsdf, lanes_i, lanes_o), args.repeat)
    if recordings != 1:
        print(f"  note: Mitsuba {case.label} was recorded {recordings}× (timing includes tracing)")
    return ok, (wall, kernel)


# -- output ---------------------------------------------------------------------------------------


def _fmt(x: float | None, width: int, spec: str = ".2f") -> str:
    return f"{x:{width}{spec}}" if x is not None else f"{'—':>{width}}"


def _ratio(ours: float, peer: float | None, ok: bool | None, width: int) -> str:
    """gonio / peer, or FAIL (loudly, never a number) when the peer's equality check failed."""
    if ok is False:
        return f"{'FAIL':>{width}}"
    return _fmt(ours / peer if peer else None, width)


def print_costs(costs: dict, threads: int) -> None:
    print(
        f"\nCPU throughput (numba over {_ROOF_SIZE} float64: {_LANES} independent chains of "
        f"{_CHAIN} ops per element, or {_CHAIN} passes of one call per element for exp/log/pow/"
        "erfc; store: one float64 into an output-sized array)"
    )
    print(f"  {'op':<22} {'ns/op 1 core':>13} {f'ns/op {threads} thr':>13} {'speed-up':>9}")
    for op, (serial, parallel) in costs.items():
        print(f"  {op:<22} {serial:13.3f} {parallel:13.3f} {serial / parallel:9.2f}")


def print_rows(rows: list[Row]) -> None:
    print(
        "\nns per sample × parameter set (best wall time); ratio = gonio / peer (< 1: gonio "
        "faster); roof = gonio / roofline (4 = 4× slower than this CPU's limit)"
    )
    print("g/Mi*: gonio's float32 kernels against Mitsuba's float32 (like with like)")
    head = (
        f"{'model':<48} {'gonio':>7} {'g f32':>7} {'JAX':>7} {'g/JAX':>6} {'Mitsuba':>8} "
        f"{'Mi krnl':>8} {'g/Mi':>7} {'roofln':>7} {'roof':>6}"
    )
    print(head)
    for r in rows:
        roof = r.gonio_ns / r.roof_ns if r.roof_ns else None
        ours_mi = r.gonio32_ns if r.gonio32_ns is not None else r.gonio_ns
        star = "*" if r.gonio32_ns is not None and r.mi_ns else " "
        print(
            f"{r.label:<48} {r.gonio_ns:7.2f} {_fmt(r.gonio32_ns, 7)} {_fmt(r.jax_ns, 7)} "
            f"{_ratio(r.gonio_ns, r.jax_ns, r.jax_ok, 6)} {_fmt(r.mi_ns, 8)} "
            f"{_fmt(r.mi_kernel_ns, 8)} {_ratio(ours_mi, r.mi_ns, r.mi_ok, 6)}{star} "
            f"{_fmt(r.roof_ns, 7, '.3f')} {_fmt(roof, 6, '.1f')}"
        )


# -- main -----------------------------------------------------------------------------------------


def _import_jax():
    try:
        import _jax_models
    except ImportError:
        print("jax not installed: `pip install -e '.[bench]'`; JAX comparison skipped")
        return None
    return _jax_models


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="direction pairs N")
    ap.add_argument("--w", type=int, default=64, help="parameter sets W")
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--threads", type=int, default=2, help="threads for every peer")
    args = ap.parse_args(argv)
    threads, note = limit_threads(args.threads)  # before jax or mitsuba is imported
    jax_mod = _import_jax()
    reason = mitsuba_unavailable()
    mitsuba = None
    if reason:
        print(f"Mitsuba skipped: {reason}")
    else:
        mitsuba = MitsubaPeer(threads)
    print(
        f"N = {args.n}, W = {args.w}, threads = {threads}{note}; gonio: numba "
        f"{numba.__version__} ({numba.threading_layer()}), float64 (and float32 where it has it)"
        + (f"; JAX {jax_mod.jax.__version__} float64" if jax_mod else "")
        + (
            f"; Mitsuba {mitsuba.mi.__version__} {_MITSUBA_VARIANT} (float32; one parameter "
            "set for all N·W lanes, kd = 0, ks = 1, φ₀ = 0; frozen-function replay; "
            "'Mi krnl' = kernel time alone)"
            if mitsuba
            else ""
        )
    )
    costs = measure_op_costs(threads, args.n * args.w, max(3, args.repeat // 2))
    print_costs(costs, threads)
    rng = np.random.default_rng(0)
    wi, wo = uniform_hemisphere(args.n, rng), uniform_hemisphere(args.n, rng)
    print("\nequality checks (before any timing of that peer)")
    rows = [run_case(case, wi, wo, rng, args, jax_mod, mitsuba, costs, threads) for case in CASES]
    print_rows(rows)


if __name__ == "__main__":
    main()
