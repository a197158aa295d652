"""`report.html`: one self-contained page (plots embedded as PNG data URIs) per run.

Sections: run summary; measured vs fitted in-plane slices (±1σ); per fit: parameter table,
MCMC diagnostics, goodness of fit, residual map over (θ_h, θ_d), trace plots, posterior
marginals, a corner plot, the preview render (gonio.preview); the model-comparison table
(compare.json, written by ``gonio fit --model all``); lab and compute time per stage.

Every user-supplied string (run, plan, rig and model names, labels, notes) goes through
html.escape.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.store import RunStore, atomic_write_bytes
from fitting.samples import read_samples

__all__ = ["write_report"]

# Plotting and the model registry (matplotlib, numba, scipy: ~1 s to import) are loaded by
# `_import_plotting` only once the run, its samples and its fits have been checked, so a
# report refused for bad input says so at once.
plt: Any = None
MaxNLocator: Any = None
models: Any = None
spherical_to_vector: Any = None
to_half_diff: Any = None


def _import_plotting() -> None:
    global plt, MaxNLocator, models, spherical_to_vector, to_half_diff
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as _plt
    from matplotlib.ticker import MaxNLocator as _locator

    from fitting import models as _models
    from fitting.directions import spherical_to_vector as _s2v
    from fitting.rusinkiewicz import to_half_diff as _thd

    plt, MaxNLocator, models, spherical_to_vector, to_half_diff = (
        _plt,
        _locator,
        _models,
        _s2v,
        _thd,
    )


_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;padding:0 1em}
h1{font-size:1.6em}
h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.preview{width:256px;image-rendering:auto}.ok{color:#176e1b}.bad{color:#b00020}.note{color:#555;font-size:.9em}img{max-width:100%}
"""


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | float):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}g}"
    return html.escape(str(x))


def _table(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _fit_params(fit: dict, channel: str) -> dict[str, float]:
    """MAP parameters for one channel: `kd_R` → kd for channel R, bare names are shared."""
    out = {}
    for name, p in fit["parameters"].items():
        base, _, ch = name.rpartition("_")
        if base and ch == channel:
            out[base] = p["map"]
        elif not base or ch not in ("R", "G", "B", "Y"):
            out[name] = p["map"]
    return out


def _model_of(fit: dict):
    """The fit's model, or None if this gonio does not know it (a foreign fit JSON)."""
    try:
        return models.get(fit["model"], **fit.get("options", {}))
    except (KeyError, TypeError, ValueError):
        return None


def _slice_plot(samples, fits: list[dict]) -> str:
    """In-plane slices: f vs signed θ_o (positive = specular side) for each θ_i, per channel."""
    good = samples.good()
    dphi = np.abs(np.angle(np.exp(1j * (good.phi_o - good.phi_i))))
    in_plane = np.abs(dphi - np.pi) < np.radians(3)
    retro = dphi < np.radians(3)
    sel = in_plane | retro
    chans = good.channels
    fig, axes = plt.subplots(1, len(chans), figsize=(4.2 * len(chans), 3.6), squeeze=False)
    ti_deg = np.round(np.degrees(good.theta_i) / 5) * 5
    levels = sorted(set(ti_deg[sel].tolist()))
    colours = plt.cm.viridis(np.linspace(0, 0.9, max(len(levels), 1)))
    for ax, ch in zip(axes[0], chans, strict=True):
        for lev, col in zip(levels, colours, strict=False):
            m = sel & (good.channel == ch) & (ti_deg == lev)
            if not m.any():
                continue
            signed = np.where(in_plane[m], 1, -1) * np.degrees(good.theta_o[m])
            order = np.argsort(signed)
            ax.errorbar(
                signed[order],
                good.f[m][order],
                yerr=good.sigma[m][order],
                fmt=".",
                ms=3,
                color=col,
                alpha=0.6,
                label=f"θi≈{lev:.0f}°",
            )
            model = _model_of(fits[0]) if fits else None
            if model is not None:
                fit = fits[0]
                ti = np.radians(np.mean(np.degrees(good.theta_i[m])))
                to = np.radians(np.linspace(-85, 85, 341))
                wi = np.repeat(spherical_to_vector(ti, 0.0)[None, :], to.size, axis=0)
                wo = spherical_to_vector(np.abs(to), np.where(to >= 0, np.pi, 0.0))
                params = {k: np.asarray(v, float) for k, v in _fit_params(fit, ch).items()}
                f = model.evaluate(params, wi, wo)
                ax.plot(np.degrees(to), f, "-", color=col, lw=1.2)
        ax.set_yscale("log")
        ax.set_xlabel("signed θo [deg] (+ = specular side)")
        ax.set_ylabel("f_r [1/sr]")
        ax.set_title(f"channel {ch}")
        ax.legend(fontsize=7)
    fig.suptitle("Plane of incidence: measured (dots, ±1σ) vs MAP fit (lines)")
    fig.tight_layout()
    return _png(fig)


def _load_chain(path: Path, fit: dict) -> tuple[list[str], np.ndarray, int]:
    """The whole stored emcee chain (N, W, D) in natural units, and its burn-in length.

    The chain is stored in the sampling space (log for scale parameters); columns follow the
    parameter order of the fit JSON. Each column's transform (identity or exp) is the one whose
    median over the second half reproduces the JSON median — both come from the same chain.
    Burn-in shown = the first half (what the report's marginals leave out).
    """
    import h5py

    names = list(fit["parameters"])
    with h5py.File(path, "r") as fh:
        it = int(fh["mcmc"].attrs["iteration"])
        chain = np.asarray(fh["mcmc"]["chain"][:it])
    if chain.ndim != 3 or chain.shape[2] != len(names) or it < 2:
        raise ValueError("chain does not match the fit")
    tail = chain[it // 2 :].reshape(-1, chain.shape[-1])
    out = np.empty_like(chain)
    for j, name in enumerate(names):
        med = fit["parameters"][name]["median"]
        err_lin = abs(np.median(tail[:, j]) - med)
        err_exp = abs(np.median(np.exp(np.clip(tail[:, j], -700, 700))) - med)
        out[..., j] = (
            np.exp(np.clip(chain[..., j], -700, 700)) if err_exp < err_lin else chain[..., j]
        )
    return names, out, it // 2


def _load_posterior(path: Path, fit: dict) -> tuple[list[str], np.ndarray]:
    """Second half of the stored chain, flattened to draws (S, D), natural units."""
    names, chain, burn = _load_chain(path, fit)
    return names, chain[burn:].reshape(-1, chain.shape[-1])


def _chain_path(run_dir: Path, fit: dict, label: str) -> Path:
    return run_dir / f"fit-{label}.h5"


def _trace_plot(names: list[str], chain: np.ndarray, burn: int, fit: dict) -> str:
    """Traces of up to 4 parameters (shared first), every walker as a thin line."""
    shared = [n for n in names if "_" not in n or n == "discrepancy"]
    pick = (shared + [n for n in names if n not in shared])[:4]
    fig, axes = plt.subplots(len(pick), 1, figsize=(9, 1.7 * len(pick)), sharex=True)
    axes = np.atleast_1d(axes)
    steps = np.arange(chain.shape[0])
    for ax, name in zip(axes, pick, strict=True):
        j = names.index(name)
        ax.plot(steps, chain[:, :, j], color="#4477aa", lw=0.3, alpha=0.35)
        ax.axvline(burn, color="#cc3311", lw=1, ls="--")
        ax.set_ylabel(f"{name}\n[{fit['parameters'][name].get('unit', '')}]", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.yaxis.set_major_locator(MaxNLocator(4))
        ax.ticklabel_format(axis="y", useOffset=False)
    axes[0].set_title(
        f"MCMC traces, {chain.shape[1]} walkers (red dashed: end of the discarded first half)",
        fontsize=9,
    )
    axes[-1].set_xlabel("step")
    fig.tight_layout()
    return _png(fig)


def _corner_plot(names: list[str], draws: np.ndarray, fit: dict, truth: dict) -> str:
    """Pairwise posterior plot: the shared parameters, then channel-1 ones (≤ 5 in all)."""
    shared = [n for n in names if "_" not in n or n == "discrepancy"]
    first = fit["channels"][0] if fit.get("channels") else ""
    pick = (shared + [n for n in names if n.endswith(f"_{first}") and n not in shared])[:5]
    k = len(pick)
    rng = np.random.default_rng(0)
    sub = draws[rng.choice(draws.shape[0], min(draws.shape[0], 3000), replace=False)]
    fig, axes = plt.subplots(k, k, figsize=(1.9 * k + 0.6, 1.9 * k + 0.6), squeeze=False)
    for r in range(k):
        for c in range(k):
            ax = axes[r][c]
            if c > r:
                ax.axis("off")
                continue
            x = sub[:, names.index(pick[c])]
            if r == c:
                ax.hist(x, bins=35, color="#4477aa", histtype="stepfilled", alpha=0.8)
                if pick[c] in truth:
                    ax.axvline(truth[pick[c]], color="#cc3311", lw=1.2)
            else:
                y = sub[:, names.index(pick[r])]
                ax.plot(x, y, ".", ms=1, color="#4477aa", alpha=0.25, rasterized=True)
                if pick[c] in truth and pick[r] in truth:
                    ax.plot(truth[pick[c]], truth[pick[r]], "+", color="#cc3311", ms=10, mew=1.5)
            ax.tick_params(labelsize=6)
            ax.xaxis.set_major_locator(MaxNLocator(3))
            ax.yaxis.set_major_locator(MaxNLocator(3))
            ax.ticklabel_format(useOffset=False, style="sci", scilimits=(-3, 4))
            if r == k - 1:
                plt.setp(ax.get_xticklabels(), rotation=35, ha="right")
            if r == c:
                ax.set_yticks([])  # a histogram's count axis says nothing here
            ax.xaxis.get_offset_text().set_fontsize(6)
            ax.yaxis.get_offset_text().set_fontsize(6)
            if r == k - 1:
                ax.set_xlabel(pick[c], fontsize=8)
            else:
                ax.set_xticklabels([])
            if c == 0 and r > 0:
                ax.set_ylabel(pick[r], fontsize=8)
            elif c > 0:
                ax.set_yticklabels([])
    fig.suptitle("Posterior pairs (draws after burn-in; red: simulated truth)", fontsize=9)
    fig.tight_layout()
    return _png(fig)


def _residual_map(samples, fit: dict) -> str | None:
    """Mean normalised residual (f − f̂)/σ per (θ_h, θ_d) bin, one panel per channel, at MAP."""
    model = _model_of(fit)
    if model is None:
        return None
    good = samples.good()
    chans = [c for c in fit.get("channels", good.channels) if c in good.channels]
    if not chans or len(good) == 0:
        return None
    th, td, _ = to_half_diff(good.wi, good.wo)
    th_deg, td_deg = np.degrees(th), np.degrees(td)
    edges_h = np.linspace(0, max(5.0, np.ceil(th_deg.max() / 5) * 5), 25)
    edges_d = np.linspace(0, max(5.0, np.ceil(td_deg.max() / 5) * 5), 25)
    fig, axes = plt.subplots(1, len(chans), figsize=(4.0 * len(chans) + 1, 3.6), squeeze=False)
    lim = 3.0
    maps = []
    for ch in chans:
        m = good.channel == ch
        params = {k: np.asarray(v, float) for k, v in _fit_params(fit, ch).items()}
        with np.errstate(all="ignore"):
            fhat = model.evaluate(params, good.wi[m], good.wo[m])
            z = (good.f[m] - fhat) / good.sigma[m]
        ok = np.isfinite(z)
        total, _, _ = np.histogram2d(
            th_deg[m][ok], td_deg[m][ok], [edges_h, edges_d], weights=z[ok]
        )
        count, _, _ = np.histogram2d(th_deg[m][ok], td_deg[m][ok], [edges_h, edges_d])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / count, np.nan)
        maps.append(mean)
        if np.isfinite(mean).any():
            lim = max(lim, float(np.nanpercentile(np.abs(mean), 98)))
    lim = min(lim, 50.0)
    for ax, ch, mean in zip(axes[0], chans, maps, strict=True):
        im = ax.pcolormesh(
            edges_h, edges_d, np.ma.masked_invalid(mean).T, cmap="RdBu_r", vmin=-lim, vmax=lim
        )
        ax.set_xlabel("θh [deg]")
        ax.set_ylabel("θd [deg]")
        ax.set_title(f"channel {ch}", fontsize=10)
        ax.set_facecolor("#eeeeee")
    label = f"mean (f − f̂)/σ per bin (colours clipped at ±{lim:.0f})"
    fig.colorbar(im, ax=axes[0].tolist(), label=label, shrink=0.9)
    fig.suptitle(
        "Normalised residuals at the MAP (red: measured above the model; grey: no samples)",
        fontsize=10,
    )
    return _png(fig)


def _preview(fit: dict) -> tuple[str | None, str]:
    """(data URI of the preview render, or None, and a note on the material used)."""
    try:
        from fitting.export import material_dict
        from gonio.preview import preview_png

        mat = material_dict(fit)
        png = preview_png(fit, size_px=128, spp=64)
    except Exception as exc:  # the report must not fail because a preview could not render
        return None, f"preview not rendered: {type(exc).__name__}: {str(exc)[:120]}"
    uri = "data:image/png;base64," + base64.b64encode(png).decode()
    return uri, f"Mitsuba material: {mat['type']} (posterior medians; see material-*.xml)"


def _best_label(run_dir: Path) -> str | None:
    """Label of the rank-1 model in compare.json, if there is one."""
    from fitting.compare import read_compare

    try:
        rows = read_compare(run_dir / "compare.json")
        return str(rows[0]["label"]) if rows and isinstance(rows[0], dict) else None
    except (ValueError, KeyError):
        return None


def _compare_section(run_dir: Path) -> list[str]:
    path = run_dir / "compare.json"
    if not path.exists():
        return []
    from fitting.compare import read_compare

    try:
        rows = read_compare(path)
    except ValueError as exc:
        return ["<h2>Model comparison</h2>", f"<p class='bad'>{html.escape(str(exc))}</p>"]

    def fixed(x: Any, digits: int = 1) -> str:
        # Fixed point, not significant digits: elpd values of 8.05e4 differing by 1 must show.
        return f"{x:.{digits}f}" if isinstance(x, int | float) and math.isfinite(x) else "–"

    body = []
    for r in rows:
        if not isinstance(r, dict):
            continue
        body.append(
            [
                r.get("rank"),
                r.get("label"),
                ", ".join(map(str, r.get("shared") or [])) or "–",
                r.get("k"),
                fixed(r.get("elpd_loo")),
                fixed(r.get("se_loo")),
                fixed(r.get("p_loo")),
                fixed(r.get("waic")),
                fixed(r.get("d_elpd")),
                fixed(r.get("d_se")),
                fixed(r.get("khat_max"), 2),
                fixed(r.get("aic")),
                fixed(r.get("bic")),
                "; ".join(map(str, r.get("warnings") or [])),
            ]
        )
    return [
        "<h2>Model comparison</h2>",
        "<p class='note'>Ranked by PSIS-LOO expected log predictive density (elpd, nats; "
        "higher is better). ΔELPD is relative to the best model, with the SE of the pointwise "
        "difference; |ΔELPD| below ~2 SE is no clear preference. k̂ > 0.7: that sample's LOO "
        "estimate is unreliable. AIC/BIC at the MAP (lower is better).</p>",
        _table(
            [
                "rank",
                "model",
                "shared",
                "k",
                "elpd_loo",
                "SE",
                "p_loo",
                "WAIC",
                "ΔELPD",
                "SE(Δ)",
                "max k̂",
                "AIC",
                "BIC",
                "notes",
            ],
            body,
        ),
    ]


def _posterior_plot(
    run_dir: Path, fit: dict, truth: dict[str, float], label: str | None = None
) -> str | None:
    """Marginal histograms of the stored chain (fit-<model>.h5), natural units."""
    try:
        names, draws = _load_posterior(_chain_path(run_dir, fit, label or fit["model"]), fit)
    except (OSError, KeyError, ValueError):
        return None
    k = len(names)
    cols = min(k, 4)
    rows = math.ceil(k / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.5 * rows), squeeze=False)
    for i, name in enumerate(names):
        ax = axes[i // cols][i % cols]
        ax.hist(draws[:, i], bins=40, color="#4477aa", alpha=0.8)
        p = fit["parameters"][name]
        for q, ls in (("p2.5", ":"), ("p16", "--"), ("median", "-"), ("p84", "--"), ("p97.5", ":")):
            ax.axvline(p[q], color="k", ls=ls, lw=0.8)
        if name in truth:
            ax.axvline(truth[name], color="#cc3311", lw=1.5, label="truth (scene)")
            ax.legend(fontsize=7)
        ax.set_title(f"{name} [{p.get('unit', '')}]", fontsize=9)
    for j in range(k, rows * cols):
        axes[j // cols][j % cols].axis("off")
    fig.tight_layout()
    return _png(fig)


def write_report(run_dir: Path | str, compute_times_s: dict[str, float] | None = None) -> Path:
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir)
    try:
        return _write_report(run_dir, store, compute_times_s)
    finally:
        store.close()


def _write_report(run_dir: Path, store: RunStore, compute_times_s: dict[str, float] | None) -> Path:
    from fitting.result import read_fit
    from gonio.errors import UserError

    cfg = store.run_config()
    if store.count("done") == 0:
        raise UserError(
            f"{run_dir}: the run has no completed captures; nothing to report (resume it with "
            f"`gonio acquire --out {run_dir}`)"
        )
    samples_path = run_dir / "samples.parquet"
    if not samples_path.exists():
        raise UserError(f"{samples_path}: no samples yet; run `gonio calibrate {run_dir}` first")
    samples = read_samples(samples_path)
    fit_paths = sorted(run_dir.glob("fit-*.json"))
    # read_fit checks every key the page uses, so a damaged or foreign fit file is one line
    # naming it, not a KeyError halfway through the page.
    fits = [read_fit(p).to_dict() for p in fit_paths]
    _import_plotting()
    labels = [p.stem[len("fit-") :] for p in fit_paths]
    best = _best_label(run_dir)
    if best in labels:  # the preferred model first: its curves go on the slice plot
        i = labels.index(best)
        labels.insert(0, labels.pop(i))
        fits.insert(0, fits.pop(i))
    truth: dict[str, float] = {}
    if "scene" in cfg:
        from simulator.scene import Scene
        from simulator.truth import reference_parameters

        truth = reference_parameters(Scene.model_validate(cfg["scene"]))
    preview_s: dict[str, float] = {}
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>gonio report — {html.escape(run_dir.name)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>gonio report: {html.escape(run_dir.name)}</h1>",
        f"<p class='note'>gonio {html.escape(str(cfg.get('gonio', {}).get('version', '?')))}, "
        f"started {html.escape(str(cfg.get('gonio', {}).get('started_at', '?')))}. "
        f"{store.count('done')} captures; {len(samples)} samples "
        f"({'absolute' if not samples.relative else 'RELATIVE — no absolute calibration'}).</p>",
    ]
    names = [
        ("rig", cfg.get("rig", {}).get("name")),
        ("plan", cfg.get("plan", {}).get("name")),
        ("notes", cfg.get("notes") or cfg.get("plan", {}).get("notes")),
    ]
    parts.append(
        "<p class='note'>"
        + "; ".join(f"{k}: {html.escape(str(v))}" for k, v in names if v)
        + "</p>"
    )
    if "scene" in cfg:
        mat = json.dumps(cfg["scene"].get("material", {}))
        parts.append(f"<p class='note'>Simulated material: <code>{html.escape(mat)}</code></p>")
    parts.append("<h2>Measured vs fitted, plane of incidence</h2>")
    parts.append(f"<img src='{_slice_plot(samples, fits)}'>")
    for label, fit in zip(labels, fits, strict=True):
        parts.append(
            f"<h2>Fit: {html.escape(str(fit['model']))} "
            f"{html.escape(json.dumps(fit.get('options', {})))}</h2>"
        )
        rows = []
        for name, p in fit["parameters"].items():
            t = truth.get(name)
            inside = None if t is None else bool(p["p2.5"] <= t <= p["p97.5"])
            rows.append(
                [
                    name,
                    p.get("unit", ""),
                    p["map"],
                    p["median"],
                    p["p16"],
                    p["p84"],
                    p["p2.5"],
                    p["p97.5"],
                    t,
                    inside,
                ]
            )
        parts.append(
            _table(
                [
                    "parameter",
                    "unit",
                    "MAP",
                    "median",
                    "p16",
                    "p84",
                    "p2.5",
                    "p97.5",
                    "truth",
                    "truth in 95%",
                ],
                rows,
            )
        )
        diag = fit.get("diagnostics", {})
        drows = [
            [n, diag.get("tau", {}).get(n), diag.get("ess", {}).get(n), diag.get("rhat", {}).get(n)]
            for n in fit["parameters"]
        ]
        parts.append("<h3>MCMC diagnostics</h3>")
        parts.append(
            f"<p>acceptance {_fmt(diag.get('acceptance'))}, converged "
            f"{_fmt(diag.get('converged'))} ({html.escape(str(diag.get('stop_reason', '')))})</p>"
        )
        parts.append(_table(["parameter", "τ [steps]", "ESS", "R-hat"], drows))
        good = fit.get("goodness", {})
        if good:
            parts.append("<h3>Goodness of fit</h3>")
            parts.append(_table(list(good), [list(good.values())]))
        resid = _residual_map(samples, fit)
        if resid:
            parts.append("<h3>Residual map over (θh, θd)</h3>")
            parts.append(f"<img src='{resid}'>")
        try:
            names_, chain, burn = _load_chain(_chain_path(run_dir, fit, label), fit)
        except (OSError, KeyError, ValueError):
            chain = None
        if chain is not None:
            parts.append("<h3>Trace plots</h3>")
            parts.append(f"<img src='{_trace_plot(names_, chain, burn, fit)}'>")
        post = _posterior_plot(run_dir, fit, truth, label)
        if post:
            parts.append(
                "<h3>Posterior marginals (black: median, 68% and 95% intervals; "
                "red: the simulated truth)</h3>"
            )
            parts.append(f"<img src='{post}'>")
        if chain is not None:
            draws = chain[burn:].reshape(-1, chain.shape[-1])
            parts.append("<h3>Corner plot</h3>")
            parts.append(f"<img src='{_corner_plot(names_, draws, fit, truth)}'>")
        t_prev = time.perf_counter()
        uri, note = _preview(fit)
        preview_s[label] = time.perf_counter() - t_prev
        parts.append("<h3>Preview render</h3>")
        if uri:
            parts.append(
                f"<p><img class='preview' src='{uri}' alt='preview sphere'><br>"
                f"<span class='note'>Unit sphere, point light up-left of the camera, "
                f"{html.escape(note)}</span></p>"
            )
        else:
            parts.append(f"<p class='bad'>{html.escape(note)}</p>")
        try:
            from fitting.export import material_xml

            xml = material_xml(fit)
        except (KeyError, ValueError, TypeError) as exc:
            xml = f"no Mitsuba export: {type(exc).__name__}: {exc}"
        parts.append(
            "<details><summary>Mitsuba 3 material (XML)</summary>"
            f"<pre>{html.escape(xml)}</pre></details>"
        )
    parts += _compare_section(run_dir)
    parts.append("<h2>Time</h2>")
    parts.append(
        "<p class='note'>Lab time: what the rig clock accounts for (moves, settling, "
        "exposures); compute time: wall-clock seconds of each processing stage.</p>"
    )
    lab = store.meta("lab_time_s")
    trows = [["lab time (rig clock)", float(lab) if lab else None]]
    trows += [[f"compute: {k}", v] for k, v in (compute_times_s or {}).items()]
    for label, fit in zip(labels, fits, strict=True):
        trows.append([f"compute: fit {label} (wall)", fit.get("wall_time_s")])
    for label, sec in preview_s.items():
        trows.append([f"compute: preview render {label}", sec])
    parts.append(_table(["stage", "seconds"], trows))
    parts.append("</body></html>")
    out = run_dir / "report.html"
    atomic_write_bytes(out, "\n".join(parts).encode(), overwrite=True)
    return out
