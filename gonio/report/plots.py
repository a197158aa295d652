"""The report's plots (gonio.report): measured vs fitted slices, traces, posterior marginals, the
corner plot, the residual map, the preview render — each a PNG data URI. Plotting libraries
load on first use (`import_plotting`), after the inputs have been checked."""

from __future__ import annotations

import base64
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "import_plotting",
    "png",
    "fit_params",
    "model_of",
    "slice_plot",
    "load_chain",
    "load_posterior",
    "trace_plot",
    "corner_plot",
    "residual_map",
    "posterior_plot",
    "preview",
    "chain_path",
    "plot_selection",
    "TRACE_LIMIT",
    "CORNER_LIMIT",
]

#: Most parameters drawn as traces (one row each) and in the corner plot (k × k panels): past
#: these the panels are too small to read. Every fit gonio ships has at most 12 parameters
#: for one channel plus the shared ones; a stated selection covers the rest.
TRACE_LIMIT = 16
CORNER_LIMIT = 8


def plot_selection(names: list[str], limit: int) -> list[str]:
    """The parameters a plot shows: shared ones (no channel suffix) first, then per channel in
    the chain's order, at most `limit`."""
    shared = [n for n in names if "_" not in n or n == "discrepancy"]
    return (shared + [n for n in names if n not in shared])[:limit]


# Plotting and the model registry (matplotlib, numba, scipy: ~1 s to import) are loaded by
# `import_plotting` only once the run, its samples and its fits have been checked, so a
# report refused for bad input says so at once.
plt: Any = None


MaxNLocator: Any = None


models: Any = None


spherical_to_vector: Any = None


to_half_diff: Any = None


def import_plotting() -> None:
    global plt, MaxNLocator, models, spherical_to_vector, to_half_diff
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as _plt
    from matplotlib.ticker import MaxNLocator as _locator

    from brdfdata.directions import spherical_to_vector as _s2v
    from brdfdata.rusinkiewicz import to_half_diff as _thd
    from fitting import models as _models

    plt, MaxNLocator, models, spherical_to_vector, to_half_diff = (
        _plt,
        _locator,
        _models,
        _s2v,
        _thd,
    )


def png(fig, *, tight_bbox: bool = False) -> str:
    """The figure as an embedded PNG. Figures laid out by tight_layout are saved as they are;
    ``tight_bbox`` (a figure whose colorbar or suptitle tight_layout does not place) crops to
    the drawn extent instead, which costs a second draw (a third of the report's time when
    every figure did it)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight" if tight_bbox else None)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def fit_params(fit: dict, channel: str) -> dict[str, float]:
    """MAP parameters for one channel: `kd_R` → kd for channel R, bare names are shared;
    parameters held fixed (the fit JSON's ``fixed``) included."""
    out = {}
    values = [(n, p["map"]) for n, p in fit["parameters"].items()]
    values += list((fit.get("fixed") or {}).items())
    for name, value in values:
        base, _, ch = name.rpartition("_")
        if base and ch == channel:
            out[base] = value
        elif not base or ch not in ("R", "G", "B", "Y"):
            out[name] = value
    return out


def model_of(fit: dict):
    """The fit's model, or None if this gonio does not know it (a foreign fit JSON)."""
    try:
        return models.get(fit["model"], **fit.get("options", {}))
    except (KeyError, TypeError, ValueError):
        return None


def slice_plot(samples, fits: list[dict]) -> str:
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
            # the fit's curve where the fit holds this channel (a fit of G alone has no kd_R)
            model = model_of(fits[0]) if fits and ch in fits[0].get("channels", ()) else None
            if model is not None:
                fit = fits[0]
                ti = np.radians(np.mean(np.degrees(good.theta_i[m])))
                to = np.radians(np.linspace(-85, 85, 341))
                wi = np.repeat(spherical_to_vector(ti, 0.0)[None, :], to.size, axis=0)
                wo = spherical_to_vector(np.abs(to), np.where(to >= 0, np.pi, 0.0))
                params = {k: np.asarray(v, float) for k, v in fit_params(fit, ch).items()}
                f = model.evaluate(params, wi, wo)
                ax.plot(np.degrees(to), f, "-", color=col, lw=1.2)
        ax.set_yscale("log")
        ax.set_xlabel("signed θo [deg] (+ = specular side)")
        ax.set_ylabel("f_r [1/sr]")
        ax.set_title(f"channel {ch}")
        ax.legend(fontsize=7)
    fig.suptitle("Plane of incidence: measured (dots, ±1σ) vs MAP fit (lines)")
    fig.tight_layout()
    return png(fig)


def load_chain(path: Path, fit: dict) -> tuple[list[str], np.ndarray, int]:
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


def load_posterior(path: Path, fit: dict) -> tuple[list[str], np.ndarray]:
    """Second half of the stored chain, flattened to draws (S, D), natural units."""
    names, chain, burn = load_chain(path, fit)
    return names, chain[burn:].reshape(-1, chain.shape[-1])


def trace_plot(names: list[str], chain: np.ndarray, burn: int, fit: dict) -> str:
    """Traces of every parameter (up to TRACE_LIMIT, shared first), every walker a thin line."""
    pick = plot_selection(names, TRACE_LIMIT)
    fig, axes = plt.subplots(len(pick), 1, figsize=(9, 1.3 * len(pick) + 0.6), sharex=True)
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
    return png(fig)


def corner_plot(names: list[str], draws: np.ndarray, fit: dict, truth: dict) -> str:
    """Pairwise posterior plot of every parameter (up to CORNER_LIMIT, shared first)."""
    pick = plot_selection(names, CORNER_LIMIT)
    k = len(pick)
    rng = np.random.default_rng(0)
    sub = draws[rng.choice(draws.shape[0], min(draws.shape[0], 3000), replace=False)]
    side_in = min(1.9, 13.0 / k)  # the whole plot stays about a page wide
    fig, axes = plt.subplots(k, k, figsize=(side_in * k + 0.6, side_in * k + 0.6), squeeze=False)
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
    return png(fig)


def residual_map(samples, fit: dict) -> str | None:
    """Mean normalised residual (f − f̂)/σ per (θ_h, θ_d) bin, one panel per channel, at MAP."""
    model = model_of(fit)
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
        params = {k: np.asarray(v, float) for k, v in fit_params(fit, ch).items()}
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
    return png(fig, tight_bbox=True)


def preview(fit: dict) -> tuple[str | None, str]:
    """(data URI of the preview render, or None, and a note on the material used)."""
    try:
        from fitting.export import material_dict
        from gonio.backends import preview_png

        mat = material_dict(fit)
        png = preview_png(fit, size_px=128, spp=64)
    except Exception as exc:  # the report must not fail because a preview could not render
        return None, f"preview not rendered: {type(exc).__name__}: {str(exc)[:120]}"
    uri = "data:image/png;base64," + base64.b64encode(png).decode()
    return uri, f"Mitsuba material: {mat['type']} (posterior medians; see material-*.xml)"


def posterior_plot(
    run_dir: Path, fit: dict, truth: dict[str, float], label: str | None = None
) -> str | None:
    """Marginal histograms of the stored chain (fit-<model>.h5), natural units."""
    try:
        names, draws = load_posterior(chain_path(run_dir, fit, label or fit["model"]), fit)
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
    return png(fig)


def chain_path(run_dir: Path, fit: dict, label: str) -> Path:
    return run_dir / f"fit-{label}.h5"
