"""Per-texel fitting of a spatially varying BRDF (issue 20): grouping a samples table by its
`texel` column, the fit of one texel, and the assembly of parameter maps.

Each texel is an ordinary fit (`fitting.fit.fit_samples`: least squares, then emcee) of its own
(ω_i, ω_o, f, σ) set, with chains shorter than a single-material fit (`texel_fit_options`): a
texel holds tens to hundreds of samples, the posterior is near-Gaussian and the map has
thousands of texels. The RNG of each texel is seeded from (seed, texel index) through
`numpy.random.SeedSequence`, so a texel's result does not depend on which worker fits it, in
which order or after how many retries.

One result row per texel (`TEXEL_COLUMNS`): ``texel``, ``n_samples``, for every parameter NAME
``NAME.median``, ``NAME.p16``, ``NAME.p84``, ``NAME.p2.5``, ``NAME.p97.5``, and the verdicts
``rhat_max``, ``converged``, ``chi2_red``, ``acceptance``, ``status`` ("ok", or "few_samples"
when the texel has fewer than ``min_samples`` good samples: then the parameters are NaN), and
``cpu_s`` (process CPU seconds of the fit).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Mapping

import numpy as np

from brdfdata.samples import SamplesError, SampleTable
from fitting.fit import FitOptions, fit_samples

__all__ = [
    "QUANTILES",
    "TEXEL_COLUMNS",
    "texel_seed",
    "texel_fit_options",
    "texel_groups",
    "texel_grid",
    "fit_texel",
    "result_row",
    "fit_texels",
    "parameter_maps",
]

QUANTILES = ("median", "p16", "p84", "p2.5", "p97.5")
TEXEL_COLUMNS = ("texel", "n_samples", "status", "rhat_max", "converged", "chi2_red")


def texel_seed(seed: int, texel: int) -> int:
    """A seed for texel `texel` of a run seeded `seed`: independent streams per texel."""
    return int(np.random.SeedSequence([int(seed), int(texel)]).generate_state(1)[0])


def texel_fit_options(
    base: FitOptions | None = None, *, walkers: int = 16, steps: int = 600, n_starts: int = 3
) -> FitOptions:
    """FitOptions for one texel: 16 walkers, ≤ 600 steps, 3 least-squares starts (a texel's
    posterior is near-Gaussian and the map has thousands of them), no wall-time budget (a
    budget would make the result depend on the machine)."""
    opt = (base or FitOptions()).replace(n_starts=n_starts)
    return opt.with_mcmc(walkers=walkers, max_steps=steps, time_budget_s=None)


#: The most texels a per-texel fit maps: a 2048 × 2048 map per parameter (EXR and PNG), ~16 MB a
#: map; beyond, the maps alone are gigabytes.
MAX_TEXELS = 2048 * 2048


def texel_groups(table: SampleTable) -> dict[int, np.ndarray]:
    """Row indices of each texel (texel index → sorted int64 array); rows with texel < 0 (off
    the grid) are left out. SamplesError when the table has no `texel` column."""
    if "texel" not in table.extra:
        raise SamplesError(
            "the samples table has no texel column; make per-texel samples with "
            "`gonio calibrate RUN --per-texel MM`"
        )
    texel = np.asarray(table.extra["texel"], dtype=np.int64)
    n_x, n_y = texel_grid(table)
    if n_x * n_y > MAX_TEXELS:  # one id of 2·10⁹ fitted, then asked for 14.9 GiB of maps
        raise SamplesError(
            f"the texel grid is {n_x} × {n_y} (largest texel id {int(texel.max())}); the maps "
            f"hold at most {MAX_TEXELS:,} texels (2048 × 2048) — check the texel column"
        )
    off = texel >= n_x * n_y
    if off.any():  # such a texel was fitted and then vanished from the maps
        raise SamplesError(
            f"texel {int(texel[off][0])} lies off the table's {n_x} × {n_y} grid "
            f"({int(off.sum())} rows); fix the texel column, or re-create the table with "
            "`gonio calibrate RUN --per-texel MM`"
        )
    order = np.argsort(texel, kind="stable")
    keys, starts = np.unique(texel[order], return_index=True)
    bounds = list(starts[1:]) + [texel.size]
    return {int(k): order[s:e] for k, s, e in zip(keys, starts, bounds, strict=True) if k >= 0}


def texel_grid(table: SampleTable) -> tuple[int, int]:
    """(n_x, n_y) of the texel grid from the metadata (calibration.texels), else the smallest
    square holding every index."""
    raw = table.metadata.get("gonio.texels")
    if raw:
        grid = json.loads(raw)
        return int(grid["n_x"]), int(grid["n_y"])
    top = int(np.max(table.extra["texel"])) + 1 if len(table) else 1
    n = math.isqrt(max(top - 1, 0)) + 1
    return n, n


def fit_texel(
    table: SampleTable, texel: int, options: FitOptions, *, min_samples: int = 20
) -> dict:
    """Fit the samples of one texel (all rows of `table` belong to it); one result row."""
    cpu0 = time.process_time()
    good = table.good()
    row: dict = {"texel": int(texel), "n_samples": len(good)}
    if len(good) < min_samples:
        row.update(status="few_samples", rhat_max=math.nan, converged=False, chi2_red=math.nan)
        row.update(acceptance=math.nan, cpu_s=time.process_time() - cpu0)
        return row
    opt = options.replace(seed=texel_seed(options.seed, texel))
    row.update(result_row(fit_samples(good, opt)), cpu_s=time.process_time() - cpu0)
    return row


def result_row(res) -> dict:
    """The flat summary of a fit (fitting.result.FitResult): NAME.QUANTILE for every parameter
    and the verdicts status, rhat_max, converged, chi2_red, acceptance."""
    row: dict = {}
    for name, summary in res.parameters.items():
        for q in QUANTILES:
            row[f"{name}.{q}"] = float(summary[q])
    rhat = [v for v in (res.diagnostics.get("rhat") or {}).values() if v is not None]
    acc = res.diagnostics.get("acceptance")
    row.update(
        status="ok",
        rhat_max=float(max(rhat)) if rhat else math.nan,
        converged=bool(res.diagnostics.get("converged")),
        chi2_red=float(res.goodness["chi2_red"]),
        acceptance=float(np.mean(acc)) if acc is not None else math.nan,
    )
    return row


def fit_texels(
    table: SampleTable,
    texels: Iterable[int],
    options: FitOptions,
    *,
    min_samples: int = 20,
    groups: Mapping[int, np.ndarray] | None = None,
) -> list[dict]:
    """Result rows of `texels` (a chunk), in the order given."""
    groups = texel_groups(table) if groups is None else groups
    return [
        fit_texel(table.select(_mask(len(table), groups[t])), t, options, min_samples=min_samples)
        for t in texels
    ]


def _mask(n: int, rows: np.ndarray) -> np.ndarray:
    m = np.zeros(n, dtype=bool)
    m[rows] = True
    return m


def parameter_maps(rows: Iterable[Mapping], n_x: int, n_y: int) -> dict[str, np.ndarray]:
    """Maps (n_y, n_x) float64 of every numeric result column, NaN where no texel row exists;
    row iy, column ix holds texel iy·n_x + ix."""
    rows = list(rows)
    names = sorted({k for r in rows for k, v in r.items() if _numeric(v) and k != "texel"})
    maps = {k: np.full(n_y * n_x, np.nan) for k in names}
    for r in rows:
        t = int(r["texel"])
        if 0 <= t < n_x * n_y:
            for k in names:
                v = r.get(k)
                maps[k][t] = float(v) if _numeric(v) else math.nan
    return {k: v.reshape(n_y, n_x) for k, v in maps.items()}


def _numeric(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)
