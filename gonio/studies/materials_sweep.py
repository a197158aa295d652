"""The real-materials sweep: six materials through the one spine, every model fitted, each fit
scored on held-out directions (fitting.heldout); rows to CSV (the study: gonio/studies/__init__.py).
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.config import PlanConfig
from brdfdata.samples import row_kinds
from fitting.mcmc import ConvergenceTarget
from gonio.studies.common import load_average, read_typed_rows, sim_rig, write_rows
from gonio.studies.materials_models import MODELS, NEW_MODELS, ModelSpec
from plumbing.progress import Progress

__all__ = [
    "MaterialSpec",
    "ModelSpec",
    "MATERIALS",
    "MODELS",
    "NEW_MODELS",
    "RealMaterialsConfig",
    "CSV_COLUMNS",
    "PARAM_COLUMNS",
    "SLICE_COLUMNS",
    "CSV_NAME",
    "PARAMS_NAME",
    "SLICES_NAME",
    "RECORD_NAME",
    "RHAT_MAX",
    "ESS_MIN",
    "subsample_per_pose",
    "run_sweep",
    "write_csv",
    "read_csv",
    "read_slices",
    "with_models",
]

#: The study's convergence target (fitting.mcmc.ConvergenceTarget: R̂ < 1.01, ESS ≥ 400).
RHAT_MAX = ConvergenceTarget().rhat_max
ESS_MIN = ConvergenceTarget().ess_min


@dataclass(frozen=True)
class MaterialSpec:
    """One material: ``key`` (file names), a readable label, its scene file in configs/scenes,
    and for RGL materials the tensor file it needs from data/rgl_brdf (brdfdata.data_paths)."""

    key: str
    label: str
    scene: str
    bsdf_file: str | None = None
    source: str = ""


MATERIALS: tuple[MaterialSpec, ...] = (
    MaterialSpec(
        "paper",
        "white paper",
        "rgl_paper_white.toml",
        "paper_white_rgb.bsdf",
        "RGL paper_white (measured)",
    ),
    MaterialSpec(
        "red-paint",
        "red wall paint",
        "rgl_colodur_napoli_4f.toml",
        "colodur_napoli_4f_rgb.bsdf",
        "RGL colodur_napoli_4f (measured)",
    ),
    MaterialSpec(
        "satin-vinyl",
        "satin vinyl film",
        "rgl_satin_rosaline.toml",
        "satin_rosaline_rgb.bsdf",
        "RGL satin_rosaline (measured)",
    ),
    MaterialSpec(
        "gold-film",
        "gold vinyl film",
        "rgl_vch_golden_yellow.toml",
        "vch_golden_yellow_rgb.bsdf",
        "RGL vch_golden_yellow (measured)",
    ),
    MaterialSpec(
        "nickel", "nickel", "ngan_nickel.toml", None, "MERL nickel, Ngan et al. Cook-Torrance fit"
    ),
    MaterialSpec(
        "teflon", "teflon", "ngan_teflon.toml", None, "MERL teflon, Ngan et al. Cook-Torrance fit"
    ),
)


# The default isotropic plan's grid (configs/plans/isotropic.toml) with a third, short exposure:
# the gold film's and nickel's mirror peaks (f ≈ 10 sr⁻¹) collect ≈ 1.5e4 e⁻ in 0.2 ms and
# saturate the 3e4 e⁻ full well at 2 ms (tests/gonio/test_real_materials.py).
FULL_PLAN: dict[str, Any] = {
    "name": "isotropic-3x",
    "type": "isotropic",
    "theta_i_deg": [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0],
    "theta_o_deg": [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0],
    "delta_phi_deg": [0.0, 45.0, 90.0, 135.0, 180.0],
    "exposures_s": [0.0002, 0.002, 0.016],
    "order": "nearest",
}


# --quick: every other incidence angle and no Δφ = 45° (≈ 40% of the poses), same brackets.
QUICK_PLAN: dict[str, Any] = {
    **FULL_PLAN,
    "name": "isotropic-quick",
    "theta_i_deg": [10.0, 30.0, 50.0, 70.0],
    "delta_phi_deg": [0.0, 90.0, 135.0, 180.0],
}


#: Incidence angles of the plotted in-plane slices (measured by both plans), and how far from
#: them and from the plane of incidence a measured sample may lie to be drawn in the slice.
SLICE_THETA_I_DEG = (30.0, 50.0)


SLICE_TOL_DEG = 1.5


@dataclass(frozen=True)
class RealMaterialsConfig:
    """What the study runs. ``channels``: the colour channels fitted and scored. MCMC runs to
    emcee's own criterion (fitting.mcmc), then on until every R̂ < RHAT_MAX and ESS ≥ ESS_MIN,
    at most ``max_steps`` steps in all."""

    materials: tuple[str, ...] = tuple(m.key for m in MATERIALS)
    models: tuple[str, ...] = tuple(m.label for m in MODELS)
    plan: dict = field(default_factory=lambda: dict(FULL_PLAN))
    bin_px: int = 4
    per_pose: int = 12
    channels: tuple[str, ...] = ("R", "G", "B")
    walkers: int = 32
    max_steps: int = 20000
    n_starts: int = 8
    seed: int = 0
    quick: bool = False

    @classmethod
    def quick_config(cls, seed: int = 0) -> RealMaterialsConfig:
        # One channel (G) keeps 4–5 parameters per model instead of 8–10: τ and the cost of a
        # step both drop ≈ 3×, which is what lets 42 converged fits fit in the 10-minute budget.
        return cls(
            plan=dict(QUICK_PLAN),
            bin_px=4,
            per_pose=4,
            channels=("G",),
            walkers=16,
            max_steps=8000,
            n_starts=4,
            seed=seed,
            quick=True,
        )


CSV_COLUMNS = [
    "material",
    "model",
    "options",
    "channels",
    "poses",
    "samples",
    "heldout_pairs",
    "rel_rms",
    "ngan_l2",
    "rel_rms_lsq",
    "lambert_floor",
    "discrepancy",
    "discrepancy_p16",
    "discrepancy_p84",
    "rhat_max",
    "rhat_worst",
    "ess_min",
    "ess_worst",
    "converged",
    "mcmc_steps",
    "stop_reason",
    "loo_rank",
    "elpd_loo",
    "se_loo",
    "d_elpd",
    "d_se",
    "n_khat_bad",
    "waic",
    "chi2_red",
    "fit_s",
]


PARAM_COLUMNS = ["material", "model", "param", "unit", "map", "median", "p16", "p84", "rhat", "ess"]


# -- real data --------------------------------------------------------------------------------
def _load_material_scene(spec: MaterialSpec, seed: int):
    """The shipped scene (its ``data:`` tensor path resolved by brdfdata.data_paths, a one-line
    error naming every place looked when it is missing), the sensor seed offset by ``seed``."""
    from brdfdata.data_paths import find_data
    from gonio.backends import load_scene
    from gonio.pipeline import config_dir

    if spec.bsdf_file is not None:
        find_data(f"rgl_brdf/{spec.bsdf_file}")  # say what is missing before anything else
    scene = load_scene(config_dir() / "scenes" / spec.scene)
    return scene.model_copy(update={"seed": scene.seed + 1000 * seed})


def subsample_per_pose(table, per_pose: int, rng: np.random.Generator):
    """At most ``per_pose`` calibrated regions per pose (capture), drawn at random; every
    channel of a kept region is kept.

    Why not a coarser bin instead: with one pixel per 16×16 region no region centre falls on the
    sample at grazing θ_o (5 cm foreshortened to < 9 px at θ_o = 80°), so θ_o ≳ 65° would go
    unmeasured; fine regions subsampled per pose keep every pose, grazing ones included.
    """
    cid = np.asarray(table.extra["capture_id"])
    px = np.asarray(table.extra.get("pixel_x", np.zeros_like(cid)))
    py = np.asarray(table.extra.get("pixel_y", np.zeros_like(cid)))
    keys = np.stack([cid, px, py], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    keep_region = np.zeros(len(uniq), dtype=bool)
    for c in np.unique(uniq[:, 0]):
        regions = np.flatnonzero(uniq[:, 0] == c)
        pick = rng.choice(regions, size=min(per_pose, regions.size), replace=False)
        keep_region[pick] = True
    return table.select(keep_region[inverse])


def _in_plane_slice(table, theta_i_deg: float, channel: str, tol_deg: float = SLICE_TOL_DEG):
    """Measured samples near one incidence angle, within ``tol_deg`` of the plane of incidence:
    (signed θ_o in deg — positive on the specular side —, f, σ). The one-pixel-per-region
    samples sit up to a few degrees off the plan's nominal directions, hence the tolerance."""
    ti = np.radians(theta_i_deg)
    dphi = np.angle(np.exp(1j * (table.phi_o - table.phi_i)))
    # Angular distance of ω_o from the plane of incidence: asin(sin θ_o |sin Δφ|).
    off = np.arcsin(np.clip(np.sin(table.theta_o) * np.abs(np.sin(dphi)), 0, 1))
    sel = (
        (table.channel.astype(str) == channel)
        & (np.abs(table.theta_i - ti) < np.radians(tol_deg))
        & (off < np.radians(tol_deg))
        & row_kinds(table).measured
    )
    sign = np.where(np.cos(dphi[sel]) < 0, 1.0, -1.0)
    return np.degrees(sign * table.theta_o[sel]), table.f[sel], table.sigma[sel]


def _slice_directions(theta_i_deg: float, n: int = 361) -> tuple[np.ndarray, ...]:
    """In-plane curve: signed θ_o from −88° to 88° (positive = specular side, Δφ = 180°)."""
    from brdfdata.directions import spherical_to_vector

    s = np.linspace(-88.0, 88.0, n)
    to = np.radians(np.abs(s))
    po = np.where(s >= 0, np.pi, 0.0)
    wi = spherical_to_vector(np.full(n, np.radians(theta_i_deg)), np.zeros(n))
    return s, wi, spherical_to_vector(to, po)


CSV_NAME = "real-materials.csv"
PARAMS_NAME = "real-materials-params.csv"
SLICES_NAME = "real-materials-slices.csv"
RECORD_NAME = "real-materials.json"
SLICE_COLUMNS = ["material", "theta_i_deg", "curve", "theta_o_deg", "f", "sigma"]


def _check_names(cfg: RealMaterialsConfig) -> None:
    from gonio.errors import UserError

    mats = {m.key for m in MATERIALS}
    mods = {m.label for m in MODELS}
    bad = [k for k in cfg.materials if k not in mats] + [k for k in cfg.models if k not in mods]
    if bad:
        raise UserError(
            f"unknown material/model {', '.join(bad)}; materials: {', '.join(mats)}; "
            f"models: {', '.join(mods)}"
        )


def run_sweep(
    cfg: RealMaterialsConfig,
    *,
    progress: bool = True,
    work_dir: Path | None = None,
    on_event: Callable[[str], None] | None = None,
) -> tuple[list[dict], list[dict], list[dict], dict]:
    """Every material through the one spine (acquire → calibrate), every model fitted to its
    samples and scored on the held-out grid: (rows, parameter rows, slice rows, run record)."""
    _check_names(cfg)
    mats = {m.key: m for m in MATERIALS}
    # Resolve every scene (and the data) before spending minutes on the first material.
    scenes = {k: _load_material_scene(mats[k], cfg.seed) for k in cfg.materials}
    t_start = time.perf_counter()
    out: tuple[list, list, list] = ([], [], [])
    timing: dict[str, float] = {}
    total = len(cfg.materials) * (1 + len(cfg.models))
    tmp_ctx = tempfile.TemporaryDirectory() if work_dir is None else None
    root = Path(tmp_ctx.name) if tmp_ctx is not None else Path(work_dir)
    with Progress("real materials", total, enabled=progress) as bar:

        def step(msg: str) -> None:
            bar.update(description=msg)
            if on_event is not None:
                on_event(msg)

        try:
            for key in cfg.materials:
                m_rows, m_params, m_slices = _material(key, scenes[key], cfg, root, step, bar)
                for acc, new in zip(out, (m_rows, m_params, m_slices), strict=True):
                    acc += new
                timing[key] = sum(r["fit_s"] for r in m_rows)
        finally:
            if tmp_ctx is not None:
                tmp_ctx.cleanup()
    record = {
        "config": dataclasses.asdict(cfg),
        "total_s": time.perf_counter() - t_start,
        "load": load_average(),
        "fit_s": timing,
    }
    return out[0], out[1], out[2], record


def _material(key: str, scene, cfg: RealMaterialsConfig, root: Path, step, bar):
    """One material: acquire and calibrate, then every model's fit, score and slices."""
    from calibration.reduce import ReduceOptions
    from fitting.compare import rank
    from fitting.heldout import heldout_grid, lambert_floor
    from gonio import backends
    from gonio.pipeline import AcquireSpec, SpineSpec, run_spine

    step(f"{key}: acquire + calibrate")
    spine = run_spine(
        root / key / "run",
        SpineSpec(
            AcquireSpec(
                rig=sim_rig(),
                plan=PlanConfig.model_validate(cfg.plan),
                scene=scene,
                progress=False,
                announce=False,
            ),
            reduce=ReduceOptions(bin_px=cfg.bin_px, mode="center"),
        ),
    )
    table = spine.table
    fit_table = subsample_per_pose(
        table.select(np.isin(table.channel.astype(str), cfg.channels)),
        cfg.per_pose,
        np.random.default_rng([cfg.seed, 1]),
    )
    truth_bsdf = backends.truth_bsdf(scene)
    ch_idx = [{"R": 0, "G": 1, "B": 2}[c] for c in cfg.channels]
    grid = heldout_grid()
    truth = truth_bsdf(grid.wi, grid.wo)[:, ch_idx]
    floor = lambert_floor(truth, grid.theta_i, grid.weight)
    curves = {}
    for ti_deg in SLICE_THETA_I_DEG:
        sl, wi, wo = _slice_directions(ti_deg)
        curves[ti_deg] = {
            "theta_o": sl,
            "wi": wi,
            "wo": wo,
            "truth": truth_bsdf(wi, wo)[:, ch_idx[0]],
            "measured": _in_plane_slice(table, ti_deg, cfg.channels[0]),
            "fits": {},
        }
    bar.advance()
    scores, mrows, params = [], [], []
    ctx = _Scoring(key, cfg, grid, truth, floor, spine.poses)
    mods = {m.label: m for m in MODELS}
    for label in cfg.models:
        step(f"{key}: fit {label}")
        row, score, fit = _fit_model(ctx, mods[label], fit_table)
        mrows.append(row)
        scores.append(score)
        params += _param_rows(key, label, fit)
        for c in curves.values():
            c["fits"][label] = fit.predict(c["wi"], c["wo"], cfg.channels[:1])[:, 0]
        bar.advance()
    rank(scores)
    for r, sc in zip(mrows, scores, strict=True):
        r.update(
            loo_rank=float("nan") if sc.rank is None else sc.rank,  # NaN: not ranked
            elpd_loo=sc.elpd_loo,
            se_loo=sc.se_loo,
            d_elpd=sc.d_elpd,
            d_se=sc.d_se,
            n_khat_bad=sc.n_khat_bad,
            waic=sc.waic,
        )
    return mrows, params, _slice_rows(key, curves)


@dataclass(frozen=True)
class _Scoring:
    """What every fit of one material is scored against."""

    key: str
    cfg: RealMaterialsConfig
    grid: Any  # fitting.heldout.HeldoutGrid
    truth: np.ndarray
    floor: float
    poses: int


def _fit_model(ctx: _Scoring, ms: ModelSpec, fit_table):
    """Fit one model (the sampler runs on until R̂ and ESS meet their target by itself, up to the
    study's max_steps: fitting.mcmc), score it on the
    held-out grid, at its MAP and at its least-squares optimum: (row, LOO score, fit)."""
    from fitting.compare import score_fit
    from fitting.fit import FitOptions, fit_samples
    from fitting.heldout import heldout_errors
    from fitting.mcmc import McmcOptions, convergence_verdict

    cfg, grid = ctx.cfg, ctx.grid
    t1 = time.perf_counter()
    fit = fit_samples(
        fit_table,
        FitOptions(
            model=ms.model,
            model_options=ms.options,
            channels=list(cfg.channels),
            shared=ms.shared,
            mcmc=McmcOptions(walkers=cfg.walkers, max_steps=cfg.max_steps),
            seed=cfg.seed,
            n_starts=cfg.n_starts,
            discrepancy=True,
        ),
    )
    fit_s = time.perf_counter() - t1
    score = score_fit(fit, ms.label, seed=cfg.seed)
    err = heldout_errors(
        fit.predict(grid.wi, grid.wo, cfg.channels), ctx.truth, grid.theta_i, grid.weight
    )
    # The same at the σ-weighted least-squares optimum (no discrepancy term): a much smaller
    # error there means the posterior mode moved where no sample constrains the model.
    pred_lsq = fit.predict(grid.wi, grid.wo, cfg.channels, x=fit.extras["lsq"].x)
    err_lsq = heldout_errors(pred_lsq, ctx.truth, grid.theta_i, grid.weight)
    d = fit.diagnostics
    tail = d.get("ess_tail") or {}
    ess = {k: min(v, tail.get(k, v)) for k, v in (d.get("ess") or {}).items()}  # bulk and tail
    conv = convergence_verdict(d.get("rhat") or {}, ess)
    disc = fit.parameters.get("discrepancy", {})
    mc = fit.extras.get("mcmc")
    row = {
        "material": ctx.key,
        "model": ms.label,
        "options": json.dumps(ms.options, sort_keys=True),
        "channels": "".join(cfg.channels),
        "poses": ctx.poses,
        "samples": int(fit.n_samples),
        "heldout_pairs": int(grid.theta_i.size),
        **err,
        "rel_rms_lsq": err_lsq["rel_rms"],
        "lambert_floor": ctx.floor,
        "discrepancy": disc.get("median", float("nan")),
        "discrepancy_p16": disc.get("p16", float("nan")),
        "discrepancy_p84": disc.get("p84", float("nan")),
        **conv,
        "mcmc_steps": int(mc.iterations) if mc is not None else 0,
        "stop_reason": d.get("stop_reason", ""),
        "chi2_red": fit.goodness.get("chi2_red", float("nan")),
        "fit_s": fit_s,
    }
    return row, score, fit


def _param_rows(key: str, label: str, fit) -> list[dict[str, Any]]:
    d = fit.diagnostics
    return [
        {
            "material": key,
            "model": label,
            "param": pname,
            "unit": p["unit"],
            "map": p["map"],
            "median": p["median"],
            "p16": p["p16"],
            "p84": p["p84"],
            "rhat": (d.get("rhat") or {}).get(pname, float("nan")),
            "ess": (d.get("ess") or {}).get(pname, float("nan")),
        }
        for pname, p in fit.parameters.items()
    ]


def _slice_rows(key: str, curves: dict[float, dict]) -> list[dict[str, Any]]:
    """The plotted slices as rows (so the page's plots can be redrawn from the CSV)."""
    rows = []
    for ti, c in curves.items():
        for s, f in zip(c["theta_o"], c["truth"], strict=True):
            rows.append(dict(zip(SLICE_COLUMNS, (key, ti, "truth", s, f, 0.0), strict=True)))
        for label, y in c["fits"].items():
            for s, f in zip(c["theta_o"], y, strict=True):
                vals = (key, ti, f"fit:{label}", s, f, 0.0)
                rows.append(dict(zip(SLICE_COLUMNS, vals, strict=True)))
        s, f, sig = c["measured"]
        for a, b, e in zip(s, f, sig, strict=True):
            rows.append(dict(zip(SLICE_COLUMNS, (key, ti, "measured", a, b, e), strict=True)))
    return rows


def read_slices(path: Path) -> dict[str, dict[float, dict]]:
    """{material: {θ_i: {"theta_o", "truth", "measured": (s, f, σ), "fits": {label: y}}}}."""
    out: dict[str, dict[float, dict]] = {}
    for r in read_typed_rows(path, ("material", "curve"), required=SLICE_COLUMNS):
        c = out.setdefault(r["material"], {}).setdefault(
            r["theta_i_deg"], {"theta_o": [], "truth": [], "m": [], "fits": {}}
        )
        if r["curve"] == "truth":
            c["theta_o"].append(r["theta_o_deg"])
            c["truth"].append(r["f"])
        elif r["curve"] == "measured":
            c["m"].append((r["theta_o_deg"], r["f"], r["sigma"]))
        else:
            c["fits"].setdefault(r["curve"].removeprefix("fit:"), []).append(r["f"])
    for curves in out.values():
        for c in curves.values():
            m = np.array(c.pop("m"), dtype=np.float64).reshape(-1, 3)
            c["measured"] = (m[:, 0], m[:, 1], m[:, 2])
            c["theta_o"], c["truth"] = np.array(c["theta_o"]), np.array(c["truth"])
            c["fits"] = {k: np.array(v) for k, v in c["fits"].items()}
    return out


def _fmt(v: Any) -> Any:
    if isinstance(v, float):  # np.float64 too: its repr is "np.float64(…)", so repr(float(v))
        return repr(float(v)) if math.isfinite(v) else "nan"
    return v


def write_csv(path: Path, rows: list[dict[str, Any]], columns: Sequence[str]) -> None:
    write_rows(path, rows, columns, _fmt)


_TEXT = {
    "material",
    "model",
    "param",
    "unit",
    "options",
    "channels",
    "rhat_worst",
    "ess_worst",
    "stop_reason",
}


def read_csv(path: Path) -> list[dict[str, Any]]:
    """Rows of a study CSV, numbers as floats (``converged`` as bool)."""
    return read_typed_rows(path, _TEXT, bools=("converged",))


def with_models(cfg: RealMaterialsConfig, **changes: Any) -> RealMaterialsConfig:
    """A copy of ``cfg`` with fields changed (e.g. a subset of materials/models for tests)."""
    return replace(cfg, **changes)
