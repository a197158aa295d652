"""The accuracy-vs-time plots, drawn from the study's rows (its CSV)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gonio.studies.accuracy_analysis import (
    adaptive_material,
    is_plan_row,
    lamp_widening,
    light_distance_m,
    pareto,
    spp_summary,
    summarise,
)
from gonio.studies.accuracy_sweep import AREA_LAMP_RADIUS_M, MATERIALS
from gonio.studies.common import plain_log_ticks, pyplot, save_png

__all__ = ["plot", "plot_adaptive_spp", "plot_floor"]


_COLOURS = {"short": "#228833", "single": "#4477aa", "bracket": "#ee6677"}


_MARKERS = {"rough": "o", "glossy": "s"}


def plot(rows: list[dict[str, Any]], path: Path) -> Path:
    """Roughness error vs lab time and vs compute time for every plan on the base scene, with
    the Pareto front of each material."""
    plt = pyplot()
    from matplotlib.lines import Line2D

    summary = [s for s in summarise(rows, "m") if is_plan_row(s)]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, cost, label in (
        (axes[0], "lab_time_s", "lab time per measurement [min]"),
        (axes[1], "compute_s", "compute time (simulate + calibrate + fit) [s]"),
    ):
        scale = 60.0 if cost == "lab_time_s" else 1.0
        for mat in sorted({s["material"] for s in summary}):
            pts = [s for s in summary if s["material"] == mat]
            for s in pts:
                colour = _COLOURS.get(s["exposures"], "k")
                hollow = s["plan_type"] == "adaptive"
                ax.scatter(
                    s[cost] / scale,
                    100 * s["rel_error"],
                    marker=_MARKERS.get(mat, "^"),
                    facecolors="none" if hollow else colour,
                    edgecolors=colour,
                    linewidths=1.5,
                    s=20 + s["mcmc_steps"] / 20,
                    alpha=0.9,
                )
            xy = [(s[cost] / scale, 100 * s["rel_error"]) for s in pts]
            front = pareto(xy)
            ax.plot(
                [xy[i][0] for i in front],
                [xy[i][1] for i in front],
                "-" if mat == "rough" else "--",
                color="0.3",
                lw=1,
                zorder=0,
            )
        ax.set_xlabel(label)
        ax.set_ylabel("error of roughness m, median over seeds [%]")
        ax.set_yscale("log")
        plain_log_ticks(ax)
        ax.grid(alpha=0.3, which="both")
    handles = [
        Line2D([], [], marker="o", ls="", color="0.4", label="rough lobe (m = 0.30)"),
        Line2D([], [], marker="s", ls="", color="0.4", label="glossy lobe (m = 0.05)"),
        Line2D([], [], marker="s", ls="", mfc="none", mec="0.4", label="adaptive plan (hollow)"),
        Line2D([], [], marker="o", ls="", color=_COLOURS["short"], label="1 short exposure"),
        Line2D([], [], marker="o", ls="", color=_COLOURS["single"], label="1 exposure"),
        Line2D([], [], marker="o", ls="", color=_COLOURS["bracket"], label="2-exposure bracket"),
        Line2D([], [], color="0.3", label="Pareto front, rough"),
        Line2D([], [], color="0.3", ls="--", label="Pareto front, glossy"),
    ]
    axes[1].legend(handles=handles, fontsize=8, loc="upper right")
    fig.suptitle(
        "What accuracy costs: roughness error vs lab and compute time (marker size ∝ MCMC steps)"
    )
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)
    return path


def plot_adaptive_spp(rows: list[dict[str, Any]], path: Path) -> Path:
    """Top: adaptive vs grid plans, roughness error (per seed and median) and 68% half-width
    vs lab time. Bottom: the spp side sweep, roughness error and simulate time vs spp."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(13, 9.5))
    mat = adaptive_material(rows)
    for ax, metric, ylabel in (
        (axes[0, 0], "rel_error", "error of roughness m [%]"),
        (axes[0, 1], "rel_half_width_68", "68% credible half-width of m [%]"),
    ):
        if mat is None:
            ax.text(0.5, 0.5, "no adaptive plan in this study", ha="center", transform=ax.transAxes)
        else:
            _plot_adaptive_panel(ax, rows, mat, metric)
        ax.set_xlabel("lab time per measurement [min]")
        ax.set_ylabel(ylabel)
        ax.set_yscale("log")
        plain_log_ticks(ax)
        ax.grid(alpha=0.3, which="both")

    sp = spp_summary(rows, "m")
    ax, axt = axes[1, 0], axes[1, 1]
    for mat in sorted({s["material"] for s in sp}):
        pts = [s for s in sp if s["material"] == mat]
        spp = [s["spp"] for s in pts]
        ax.errorbar(
            spp,
            [100 * s["signed_rel_error"] for s in pts],
            yerr=[100 * s["rel_half_width_68"] for s in pts],
            fmt="-" + _MARKERS.get(mat, "^"),
            capsize=3,
            label=f"{mat} lobe (m = {MATERIALS[mat]['alpha']:g})",
        )
        axt.plot(spp, [s["simulate_s"] for s in pts], "-" + _MARKERS.get(mat, "^"), label=mat)
        est = lamp_widening(MATERIALS[mat]["alpha"], light_distance_m())
        ax.axhline(100 * est, ls="--", lw=0.8, color=ax.lines[-1].get_color())
        for s in pts:
            if s["spp"] == s["planned_spp"]:
                for a, y in ((ax, 100 * s["signed_rel_error"]), (axt, s["simulate_s"])):
                    a.annotate(
                        "planner's spp",
                        (s["spp"], y),
                        textcoords="offset points",
                        xytext=(-80, 12),
                        fontsize=8,
                        arrowprops={"arrowstyle": "->", "lw": 0.6},
                    )
    lamp = f"area lamp ({2e3 * AREA_LAMP_RADIUS_M:.0f} mm disk)"
    if not sp:
        for a in (ax, axt):
            a.text(0.5, 0.5, "no scene here needs spp > 1", ha="center", transform=a.transAxes)
    else:
        ax.legend(fontsize=8)
        axt.legend(fontsize=8)
        ticks = sorted({s["spp"] for s in sp})
        for a in (ax, axt):
            a.set_xscale("log", base=2)
            a.set_xticks(ticks, [str(t) for t in ticks])
            a.margins(y=0.15)
    ax.axhline(0.0, color="0.5", lw=0.8)
    if sp:
        ax.plot([], [], "k--", lw=0.8, label="first-order lamp-size widening m_eff/m − 1")
        ax.legend(fontsize=8)
    ax.set_xlabel("render samples per pixel (spp)")
    ax.set_ylabel(
        "relative error of fitted m (fitted/true − 1) [%]\n"
        "(median over seeds; bars: ±68% half-width)"
    )
    ax.set_title(f"render spp, {lamp}: roughness error")
    ax.grid(alpha=0.3, which="both")
    axt.set_xlabel("render samples per pixel (spp)")
    axt.set_ylabel("simulate (render + sensor) time per measurement [s]")
    axt.set_title(f"render spp, {lamp}: compute time")
    axt.grid(alpha=0.3, which="both")
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)
    return path


def _plot_adaptive_panel(ax, rows: list[dict[str, Any]], mat: str, metric: str) -> None:
    summ = [s for s in summarise(rows, "m") if s["material"] == mat and is_plan_row(s)]
    exp = next(s["exposures"] for s in summ if s["plan_type"] == "adaptive")
    steps = min(s["mcmc_steps"] for s in summ if s["plan_type"] == "adaptive")
    for kind, style, colour in (("grid", "-o", "#4477aa"), ("adaptive", "--D", "#ee6677")):
        pts = sorted(
            (
                s
                for s in summ
                if s["plan_type"] == kind and s["exposures"] == exp and s["mcmc_steps"] == steps
            ),
            key=lambda s: s["lab_time_s"],
        )
        names = {s["plan"] for s in pts}
        raw = [
            r
            for r in rows
            if r["param"] == "m"
            and r["material"] == mat
            and r["plan"] in names
            and r["exposures"] == exp
            and int(r["mcmc_steps"]) == steps
            and r.get("axis") != "spp"
        ]
        ax.scatter(
            [r["lab_time_s"] / 60 for r in raw],
            [100 * r[metric] for r in raw],
            color=colour,
            alpha=0.3,
            s=14,
        )
        ax.plot(
            [s["lab_time_s"] / 60 for s in pts],
            [100 * s[metric] for s in pts],
            style,
            color=colour,
            label=f"{kind} plans, median over seeds",
        )
        for s in pts:
            ax.annotate(
                f"{s['plan']} ({s['poses']})",
                (s["lab_time_s"] / 60, 100 * s[metric]),
                textcoords="offset points",
                xytext=(5, 3),
                fontsize=8,
                color=colour,
            )
    ax.scatter([], [], color="0.5", alpha=0.3, s=14, label="single seeds")
    what = "error" if metric == "rel_error" else "precision (68% half-width)"
    ax.set_title(f"{mat} lobe, {exp} exposure: adaptive vs grid, {what}\n(poses in brackets)")
    ax.legend(fontsize=8, loc="lower left")


_PARAM_COLOURS = {"kd": "#4477aa", "ks": "#ee6677", "m": "#228833"}


def plot_floor(rows: list[dict[str, Any]], path: Path) -> Path:
    """Error vs lab time on the realistic rig beside the ideal one (same material, exposures
    and plans), per parameter: the realistic rig's RMS error over its rigs levels off at the
    instrument budget's systematic part (dashed) where the ideal rig's keeps falling."""
    plt = pyplot()

    params = [p for p in ("kd", "ks", "m") if summarise(rows, p, "realistic")]
    fig, axes = plt.subplots(1, len(params), figsize=(4.2 * len(params), 4.2), squeeze=False)
    for ax, param in zip(axes[0], params, strict=True):
        real = sorted(summarise(rows, param, "realistic"), key=lambda s: s["lab_time_s"])
        mat, exp = real[0]["material"], real[0]["exposures"]
        plans = {s["plan"] for s in real}
        ideal = sorted(
            (
                s
                for s in summarise(rows, param)
                if s["material"] == mat
                and s["exposures"] == exp
                and s["plan"] in plans
                and s["axis"] == "plan"
            ),
            key=lambda s: s["lab_time_s"],
        )
        colour = _PARAM_COLOURS.get(param, "k")
        t_real = [s["lab_time_s"] / 60 for s in real]
        ax.plot(t_real, [100 * s["rms_rel_error"] for s in real], "o-", color=colour,
                label="realistic rig: RMS error over rigs")  # fmt: skip
        ax.plot(t_real, [100 * s["rel_half_width_68"] for s in real], "^:", color=colour,
                mfc="none", label="realistic rig: ±68 % (budget included)")  # fmt: skip
        ax.plot(t_real, [100 * s["rel_sys_68"] for s in real], "--", color="0.3",
                label="its systematic part (the floor)")  # fmt: skip
        if ideal:
            ax.plot([s["lab_time_s"] / 60 for s in ideal], [100 * s["rel_error"] for s in ideal],
                    "s-", color="0.6", label="ideal rig: median error")  # fmt: skip
        ax.set_yscale("log")
        plain_log_ticks(ax)
        ax.set_xlabel("lab time per measurement [min]")
        ax.set_ylabel(f"relative error of {param} [%]")
        ax.set_title(f"{param} ({mat} lobe, {exp} exposures)")
        ax.grid(alpha=0.3, which="both")
    axes[0][-1].legend(fontsize=7, loc="best")
    fig.suptitle("The realistic rig's floor: more poses stop helping once the shared errors rule")
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)
    return path
