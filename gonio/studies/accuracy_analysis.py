"""Reading the accuracy-vs-time rows: per-configuration summaries, Pareto fronts, adaptive vs
grid, the spp side sweep, and the plan `gonio plan --target` recommends."""

from __future__ import annotations

import itertools
import math
from collections import defaultdict
from typing import Any

import numpy as np

from gonio.studies.accuracy_sweep import AREA_LAMP_RADIUS_M

__all__ = [
    "shared_scale_floor",
    "summarise",
    "is_plan_row",
    "pareto",
    "adaptive_vs_grid",
    "lab_time_to_reach",
    "spp_summary",
    "lamp_widening",
    "light_distance_m",
    "pick_plan",
    "adaptive_material",
    "systematic_floor",
    "stated_budget",
    "shared_scale_sigma",
    "realistic_choices",
]


def _key(r: dict[str, Any]) -> tuple:
    return (
        r["material"],
        r["plan"],
        r["exposures"],
        int(r["mcmc_steps"]),
        r.get("light", "point"),
        int(r.get("spp", 1)),
    )


def summarise(
    rows: list[dict[str, Any]], param: str = "m", rig: str = "ideal"
) -> list[dict[str, Any]]:
    """One row per configuration of `rig` ("ideal" or "realistic") for `param`: medians over
    seeds (lab/compute time, error, width, its systematic part), the root-mean-square error,
    and coverage pooled over seeds."""
    groups: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        if r["param"] == param and r.get("rig", "ideal") == rig:
            groups[_key(r)].append(r)
    out = []
    for (mat, plan, exp, steps, light, spp), rs in sorted(groups.items()):
        out.append(
            {
                "material": mat,
                "plan": plan,
                "plan_type": rs[0].get("plan_type", "grid"),
                "axis": rs[0].get("axis", "plan"),
                "exposures": exp,
                "mcmc_steps": steps,
                "light": light,
                "spp": spp,
                "planned_spp": int(rs[0].get("planned_spp", 1)),
                "poses": int(np.median([r["poses"] for r in rs])),
                "refine_poses": int(np.median([r.get("refine_poses", 0) for r in rs])),
                "samples": int(np.median([r["samples"] for r in rs])),
                "lab_time_s": float(np.median([r["lab_time_s"] for r in rs])),
                "simulate_s": float(np.median([r.get("simulate_s", math.nan) for r in rs])),
                "compute_s": float(np.median([r["compute_s"] for r in rs])),
                "rel_error": float(np.median([r["rel_error"] for r in rs])),
                "rel_half_width_68": float(np.median([r["rel_half_width_68"] for r in rs])),
                "coverage_68": float(np.mean([r["covered_68"] for r in rs])),
                "coverage_95": float(np.mean([r.get("covered_95", math.nan) for r in rs])),
                "rms_rel_error": float(np.sqrt(np.mean([r["rel_error"] ** 2 for r in rs]))),
                "rel_sys_68": float(np.median([r.get("rel_sys_68", 0.0) for r in rs])),
                "rig": rig,
                "n": len(rs),
            }
        )
    return out


def is_plan_row(s: dict[str, Any]) -> bool:
    """Rows that describe a measurement plan on the base scene as the planner renders it (the
    spp side sweep only changes the simulation, not the lab)."""
    return s.get("axis", "plan") != "spp"


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated in (cost, error), both minimised, sorted by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def adaptive_vs_grid(
    rows: list[dict[str, Any]],
    material: str = "glossy",
    exposures: str | None = None,
    metric: str = "rel_error",
) -> list[dict[str, Any]]:
    """For every grid plan of `material` (with the exposure scheme and the shortest MCMC of the
    adaptive runs): its median roughness `metric` E_grid and lab time T_grid, the cheapest
    adaptive plan whose median `metric` is ≤ E_grid (measured, no interpolation) with its lab
    time T_adaptive, and the ratio T_adaptive / T_grid (None when no adaptive plan reaches
    E_grid); also `interp_ratio`, the lab time the adaptive family needs for E_grid read off its
    Pareto front by log-log interpolation (`lab_time_to_reach`) over T_grid. Empty when the rows
    hold no adaptive plan for that material."""
    s = [x for x in summarise(rows, "m") if x["material"] == material and is_plan_row(x)]
    adaptive = [x for x in s if x["plan_type"] == "adaptive"]
    if exposures is not None:
        adaptive = [x for x in adaptive if x["exposures"] == exposures]
    if not adaptive:
        return []
    exp = adaptive[0]["exposures"]
    steps = min(x["mcmc_steps"] for x in adaptive)
    adaptive = [x for x in adaptive if x["exposures"] == exp and x["mcmc_steps"] == steps]
    grids = [
        x
        for x in s
        if x["plan_type"] == "grid" and x["exposures"] == exp and x["mcmc_steps"] == steps
    ]
    out = []
    for g in sorted(grids, key=lambda x: x["lab_time_s"]):
        ok = [a for a in adaptive if a[metric] <= g[metric]]
        best = min(ok, key=lambda a: a["lab_time_s"]) if ok else None
        out.append(
            {
                "material": material,
                "exposures": exp,
                "metric": metric,
                "grid": g["plan"],
                "grid_poses": g["poses"],
                "grid_lab_time_s": g["lab_time_s"],
                "grid_value": g[metric],
                "adaptive": best["plan"] if best else None,
                "adaptive_poses": best["poses"] if best else None,
                "adaptive_lab_time_s": best["lab_time_s"] if best else None,
                "adaptive_value": best[metric] if best else None,
                "ratio": best["lab_time_s"] / g["lab_time_s"] if best else None,
                "interp_ratio": (t / g["lab_time_s"])
                if (t := lab_time_to_reach(adaptive, metric, g[metric])) is not None
                else None,
            }
        )
    return out


def lab_time_to_reach(family: list[dict[str, Any]], metric: str, target: float) -> float | None:
    """Lab time a family of plans needs for `metric` ≤ `target`, read off its Pareto front
    (lab time, metric): the cheapest member if it already meets the target; between two members
    a log-log interpolation — a power law metric ∝ T^(−b) between neighbours, as 1/√N
    statistics give — since the refine step that sizes an adaptive plan is continuous; None
    beyond the best member (no extrapolation)."""
    pts = [(f["lab_time_s"], f[metric]) for f in family]
    front = [pts[i] for i in pareto(pts)]
    if not front or target < front[-1][1]:
        return None
    if target >= front[0][1]:
        return front[0][0]
    for (t0, e0), (t1, e1) in itertools.pairwise(front):
        if e0 > target >= e1:
            frac = math.log(target / e0) / math.log(e1 / e0)
            return math.exp(math.log(t0) + frac * math.log(t1 / t0))
    return None  # unreachable: the front is strictly decreasing in the metric


def spp_summary(rows: list[dict[str, Any]], param: str = "m") -> list[dict[str, Any]]:
    """The spp side sweep, one row per (material, spp): medians over seeds of simulate time,
    error against the truth and the shift of the fitted value from the fit of the planner's
    spp render, paired by seed (same sensor noise), relative to the truth."""
    sp = [r for r in rows if r.get("axis") == "spp" and r["param"] == param]
    ref = {
        (r["material"], int(r["seed"])): r["median"]
        for r in sp
        if int(r["spp"]) == int(r["planned_spp"])
    }
    groups: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in sp:
        groups[(r["material"], int(r["spp"]))].append(r)
    out = []
    for (mat, spp), rs in sorted(groups.items()):
        shifts = [
            abs(r["median"] - ref[(mat, int(r["seed"]))]) / r["truth"]
            for r in rs
            if (mat, int(r["seed"])) in ref
        ]
        out.append(
            {
                "material": mat,
                "spp": spp,
                "planned_spp": int(rs[0]["planned_spp"]),
                "simulate_s": float(np.median([r["simulate_s"] for r in rs])),
                "compute_s": float(np.median([r["compute_s"] for r in rs])),
                "rel_error": float(np.median([r["rel_error"] for r in rs])),
                "signed_rel_error": float(np.median([r["median"] / r["truth"] - 1 for r in rs])),
                "rel_half_width_68": float(np.median([r["rel_half_width_68"] for r in rs])),
                "shift_from_planned": float(np.median(shifts)) if shifts else math.nan,
                "coverage_68": float(np.mean([r["covered_68"] for r in rs])),
                "n": len(rs),
            }
        )
    return out


def lamp_widening(alpha: float, light_distance_m: float) -> float:
    """Relative widening m_eff/m − 1 a point-lamp fit sees from the study's area lamp.

    A Beckmann lobe is Gaussian in microfacet slope with per-axis variance m²/2; a lamp disk of
    angular radius ρ = a/d spreads the half vector over a disk of radius ρ/2 (per-axis variance
    ρ²/16). Convolved: m_eff² ≈ m² + ρ²/8 (small angles, near-normal half vectors)."""
    rho = AREA_LAMP_RADIUS_M / light_distance_m
    return math.sqrt(1.0 + rho**2 / (8.0 * alpha**2)) - 1.0


def light_distance_m() -> float:
    from acquisition.config import load_rig
    from gonio.pipeline import config_dir

    return float(load_rig(config_dir() / "rigs" / "sim.toml").geometry.light_distance_m)


def adaptive_material(rows: list[dict[str, Any]]) -> str | None:
    mats = sorted({r["material"] for r in rows if r.get("plan_type") == "adaptive"})
    if "glossy" in mats:
        return "glossy"
    return mats[0] if mats else None


def pick_plan(
    rows: list[dict[str, Any]],
    param: str,
    target_rel_error: float,
    material: str,
    rig: str = "ideal",
) -> dict[str, Any] | None:
    """The plan configuration with the least lab time expected to reach ±`target_rel_error` on
    `param` for a material character: both its median error (over seeds) and its median 68%
    credible half-width — the uncertainty a lab would quote — within the target (the error
    alone, over a few seeds, can be lucky). None if no plan does. The spp side sweep (a
    different lamp, the same lab) is not a plan and is left out. On the realistic `rig` the
    half-width includes the instrument budget's systematic part."""
    ok = [
        s
        for s in summarise(rows, param, rig)
        if s["material"] == material
        and max(s["rel_error"], s["rel_half_width_68"]) <= target_rel_error
        and is_plan_row(s)
    ]
    if not ok:
        return None
    return min(ok, key=lambda s: (s["lab_time_s"], s["compute_s"]))


#: Parameters a shared radiometric scale error moves one for one (fitting.budget: the models'
#: amplitudes); shape parameters (m, n, ior …) are untouched by it.
_AMPLITUDE_PREFIXES = ("kd", "ks")


def shared_scale_floor(rig, param: str) -> tuple[float, str] | None:  # RigConfig
    """The relative error no plan can go below on `param` because of the rig's shared scale
    (`shared_scale_sigma`: its reference target's certificate, or the lamp's certificate and
    distance when there is no target), and where that number comes from; None for a shape
    parameter or a rig that states no such uncertainty."""
    if not param.startswith(_AMPLITUDE_PREFIXES):
        return None
    rel = shared_scale_sigma(rig)
    if not rel:
        return None
    source = (
        "the reference target's certificate ([reference])"
        if rig.reference is not None
        else "the lamp's certificate and distance (light.intensity_rel_sigma, "
        "geometry.light_distance_sigma_m)"
    )
    return float(rel), source


def systematic_floor(rows: list[dict[str, Any]], param: str) -> dict[str, Any] | None:
    """The realistic rig's floor on `param`: on its largest plan (most poses), the median over
    rigs of the systematic part of the 68 % half-width (what the instrument budget's shared
    errors leave however much is measured), with that plan's summary; None when the rows hold
    no realistic rig."""
    s = summarise(rows, param, "realistic")
    if not s:
        return None
    top = max(s, key=lambda x: (x["poses"], x["lab_time_s"]))
    return {"floor": top["rel_sys_68"], "plan": top}


def stated_budget(rig) -> dict[str, float]:  # RigConfig
    """The shared-error sizes (k = 1) a rig file states, under the names of the study's
    instrument budget (simulator.instrument_draws.InstrumentBudget): the lamp's or the reference
    target's certificate, the lamp distance, the largest encoder-zero σ, the sample tilt, the
    gears' play, the arms' sag, the sample's bow, the camera's distance, the flat source's
    fall-off and ambient light. What it leaves unstated is absent."""
    g = rig.geometry
    out: dict[str, float] = {}
    cert = rig.reference.rel_sigma if rig.reference is not None else rig.light.intensity_rel_sigma
    if cert:
        out["cert_rel_sigma"] = float(cert)
    zeros = g.axis_zero_sigma_deg
    if isinstance(zeros, dict):
        zeros = max(zeros.values(), default=None)
    for key, value in (
        ("distance_sigma_m", g.light_distance_sigma_m),
        ("zero_sigma_deg", zeros),
        ("tilt_sigma_deg", g.sample_tilt_sigma_deg),
        ("play_deg", g.backlash_deg),
        ("sag_sigma_deg", g.arm_sag_deg),
        ("bow_sigma_m", rig.sample.bow_sigma_m),
        ("camera_distance_sigma_m", g.camera_distance_sigma_m),
        ("flat_falloff_sigma", rig.calibration.flat_source_falloff_sigma),
        ("ambient_sigma_W_m2_sr", rig.light.ambient_sigma_W_m2_sr),
    ):
        if value:
            out[key] = float(value)
    return out


def shared_scale_sigma(rig=None, budget: dict | None = None) -> float | None:
    """The shared radiometric scale's relative σ: of a rig file (its reference target's
    certificate, which absorbs the lamp's intensity and distance, both measured the same way;
    else the lamp's certificate ⊕ 2σ_r/r, E ∝ 1/r²), or of the study's instrument budget (the
    lamp's certificate ⊕ its distance, on the study rig's lamp distance). None: not stated."""
    if budget is not None:
        r = light_distance_m()
        return math.hypot(budget["cert_rel_sigma"], 2.0 * budget["distance_sigma_m"] / r)
    if rig.reference is not None:
        return float(rig.reference.rel_sigma)
    cert = rig.light.intensity_rel_sigma
    dist = rig.geometry.light_distance_sigma_m
    if cert is None and dist is None:
        return None
    return math.hypot(cert or 0.0, 2.0 * (dist or 0.0) / rig.geometry.light_distance_m)


def realistic_choices(
    rows: list[dict[str, Any]],
    param: str,
    scale_study: float | None = None,
    scale_rig: float | None = None,
) -> list[dict[str, Any]]:
    """The realistic rig's plans for `param`, each with its 68 % half-width split into the
    statistical part (`rel_stat_68`) and the systematic part for the user's rig
    (`rel_sys_rig`), their sum in quadrature (`rel_total_rig`), and the RMS error over the rigs
    (`rel_error_rig`). For an amplitude (kd, ks),
    whose systematic part is mostly the shared scale, the study's scale σ is swapped for the
    rig's (first order: sys_rig² = max(sys² − scale_study², 0) + scale_rig², the error's
    likewise); a shape
    parameter's (m) systematic part is the arms' angles', kept as the study measured it."""
    out = []
    swap = param.startswith(_AMPLITUDE_PREFIXES) and None not in (scale_study, scale_rig)
    for s in summarise(rows, param, "realistic"):
        half, sys, err = s["rel_half_width_68"], s["rel_sys_68"], s["rms_rel_error"]
        stat = math.sqrt(max(half**2 - sys**2, 0.0))
        if swap:
            sys = math.sqrt(max(sys**2 - scale_study**2, 0.0) + scale_rig**2)
            err = math.sqrt(max(err**2 - scale_study**2, 0.0) + scale_rig**2)
        out.append({**s, "rel_stat_68": stat, "rel_sys_rig": sys, "rel_error_rig": err,
                    "rel_total_rig": math.hypot(stat, sys), "scale_swapped": swap})  # fmt: skip
    return out
