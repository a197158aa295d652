"""The report's views of the hemisphere (gonio.report): polar plots per incidence angle, maps of
measured / fitted / residual over the outgoing hemisphere, where the samples are, the fitted
model's directional albedo with the energy check, and the light monitor over the run. Each is
a PNG data URI (gonio.report.plots.png); plotting is loaded by report_plots.import_plotting.

The hemisphere is drawn as the unit disc of the projected direction (sin θ cos φ, sin θ sin φ)
— equal-projected-solid-angle, the way goniophotometer results are usually shown — with φ
measured from the incidence azimuth, so every incidence angle shares one picture: the specular
direction is on the +x axis, retro-reflection on −x.
"""

from __future__ import annotations

import numpy as np

from gonio.report import plots as rp

__all__ = [
    "incidence_levels",
    "polar_plots",
    "hemisphere_maps",
    "sample_map",
    "albedo_plot",
    "monitor_plot",
]

#: Incidence angles are grouped to the nearest 5° (plans step θ_i in 5° or coarser steps; the
#: per-pixel θ_i of one pose spreads by about ±2° over the sample).
_LEVEL_DEG = 5.0
#: Most hemispheres shown: one row each; more would make an unreadable page.
_MAX_LEVELS = 4
#: Scatter plots subsample to this many points per panel (a run holds up to ~10⁶ samples).
_MAX_POINTS = 20000


def incidence_levels(samples) -> tuple[np.ndarray, list[float]]:
    """θ_i of every good sample rounded to the 5° level (deg), and the levels present,
    most-populated first (at most four)."""
    good = samples.good()
    level = np.round(np.degrees(good.theta_i) / _LEVEL_DEG) * _LEVEL_DEG
    values, counts = np.unique(level, return_counts=True)
    order = np.argsort(-counts)[:_MAX_LEVELS]
    return level, sorted(float(v) for v in values[order])


def _disc(theta: np.ndarray, phi_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projected-disc coordinates of directions at (θ, φ relative to the incidence azimuth);
    the specular side (φ_rel = π) is drawn on +x."""
    r = np.sin(theta)
    return -r * np.cos(phi_rel), r * np.sin(phi_rel)


def _thin(mask: np.ndarray, seed: int = 0) -> np.ndarray:
    idx = np.flatnonzero(mask)
    if idx.size > _MAX_POINTS:
        idx = np.sort(np.random.default_rng(seed).choice(idx, _MAX_POINTS, replace=False))
    return idx


def _fhat(model, fit: dict, good, idx: np.ndarray, channel: str) -> np.ndarray:
    params = {k: np.asarray(v, float) for k, v in rp.fit_params(fit, channel).items()}
    with np.errstate(all="ignore"):
        return np.asarray(model.evaluate(params, good.wi[idx], good.wo[idx]), float)


def polar_plots(samples, fit: dict) -> str | None:
    """f_r in the plane of incidence on polar axes, one panel per incidence angle: measured
    (dots) and the MAP fit (line), first fitted channel. Radius is log₁₀ f_r so the diffuse
    floor and the specular peak both show."""
    model = rp.model_of(fit)
    good = samples.good()
    if model is None or len(good) == 0:
        return None
    ch = next((c for c in fit.get("channels", []) if c in good.channels), good.channels[0])
    level, levels = incidence_levels(samples)
    dphi = np.abs(np.angle(np.exp(1j * (good.phi_o - good.phi_i))))
    in_plane = (np.abs(dphi - np.pi) < np.radians(3)) | (dphi < np.radians(3))
    fig, axes = rp.plt.subplots(
        1, len(levels), figsize=(3.6 * len(levels), 3.4), squeeze=False,
        subplot_kw={"projection": "polar"},
    )  # fmt: skip
    params = {k: np.asarray(v, float) for k, v in rp.fit_params(fit, ch).items()}
    for ax, lev in zip(axes[0], levels, strict=True):
        m = in_plane & (good.channel == ch) & (level == lev) & (good.f > 0)
        signed = np.where(np.abs(dphi[m] - np.pi) < np.radians(3), 1.0, -1.0) * good.theta_o[m]
        ax.plot(signed, np.log10(good.f[m]), ".", ms=3, color="#4477aa", label="measured")
        ti = np.radians(lev)
        to = np.radians(np.linspace(-88, 88, 353))
        wi = np.repeat(rp.spherical_to_vector(ti, 0.0)[None, :], to.size, axis=0)
        wo = rp.spherical_to_vector(np.abs(to), np.where(to >= 0, np.pi, 0.0))
        with np.errstate(all="ignore"):
            f = np.asarray(model.evaluate(params, wi, wo), float)
        ax.plot(to, np.log10(np.where(f > 0, f, np.nan)), "-", color="#cc3311", lw=1.2, label="fit")
        finite = np.log10(np.concatenate([good.f[m], f[f > 0]]))
        if finite.size:  # log radius: the axis starts just below the faintest value shown
            ax.set_rlim(float(finite.min()) - 0.2, float(finite.max()) + 0.1)
        ax.yaxis.set_major_locator(rp.MaxNLocator(4))
        ax.set_rlabel_position(-60)
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
        ax.set_title(f"θi ≈ {lev:.0f}° (channel {ch})", fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.suptitle(
        "Plane of incidence, polar: radius log₁₀ f_r [1/sr], angle θo (+ = specular side)",
        fontsize=10,
    )
    fig.tight_layout()
    return rp.png(fig)


def hemisphere_maps(samples, fit: dict) -> str | None:
    """Measured f_r, the MAP fit and the normalised residual (f − f̂)/σ over the outgoing
    hemisphere, one row per incidence angle (first fitted channel)."""
    model = rp.model_of(fit)
    good = samples.good()
    if model is None or len(good) == 0:
        return None
    ch = next((c for c in fit.get("channels", []) if c in good.channels), good.channels[0])
    level, levels = incidence_levels(samples)
    fig, axes = rp.plt.subplots(len(levels), 3, figsize=(11, 3.3 * len(levels)), squeeze=False)
    for row, lev in zip(axes, levels, strict=True):
        idx = _thin((level == lev) & (good.channel == ch))
        x, y = _disc(good.theta_o[idx], good.phi_o[idx] - good.phi_i[idx])
        f, fhat = good.f[idx], _fhat(model, fit, good, idx, ch)
        with np.errstate(all="ignore"):
            logs = np.log10(np.clip(np.concatenate([f, fhat]), 1e-6, None))
            z = (f - fhat) / good.sigma[idx]
        lo, hi = np.nanpercentile(logs, [1, 99]) if logs.size else (0.0, 1.0)
        panels = (
            (np.log10(np.clip(f, 1e-6, None)), "viridis", lo, hi, "measured log₁₀ f_r"),
            (np.log10(np.clip(fhat, 1e-6, None)), "viridis", lo, hi, "fitted log₁₀ f̂_r"),
            (z, "RdBu_r", -3.0, 3.0, "(f − f̂)/σ (clipped ±3)"),
        )
        for ax, (c, cmap, vmin, vmax, title) in zip(row, panels, strict=True):
            sc = ax.scatter(x, y, c=c, s=3, cmap=cmap, vmin=vmin, vmax=vmax, rasterized=True)
            ax.add_patch(rp.plt.Circle((0, 0), 1, fill=False, lw=0.6, color="#888"))
            ax.set_aspect("equal")
            ax.set_xlim(-1.05, 1.05)
            ax.set_ylim(-1.05, 1.05)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"θi ≈ {lev:.0f}°: {title}", fontsize=8)
            fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.suptitle(
        f"Outgoing hemisphere (projected disc; specular side right, retro left), channel {ch}",
        fontsize=10,
    )
    fig.tight_layout()
    return rp.png(fig)


def sample_map(samples) -> str | None:
    """Where samples exist: incident and outgoing directions on the projected disc, and the
    sample count over (θ_h, θ_d)."""
    good = samples.good()
    if len(good) == 0:
        return None
    first = good.channel == good.channels[0]
    idx = _thin(first)
    fig, axes = rp.plt.subplots(1, 3, figsize=(12, 3.6))
    # Absolute azimuths here (x: the sample's φ = 0 mark), so sample orientations show.
    xi, yi = (
        np.sin(good.theta_i[idx]) * np.cos(good.phi_i[idx]),
        np.sin(good.theta_i[idx]) * np.sin(good.phi_i[idx]),
    )
    xo, yo = (
        np.sin(good.theta_o[idx]) * np.cos(good.phi_o[idx]),
        np.sin(good.theta_o[idx]) * np.sin(good.phi_o[idx]),
    )
    for ax, (x, y, title) in zip(
        axes[:2],
        ((xi, yi, "incident ωi (x: φ = 0 mark)"), (xo, yo, "outgoing ωo")),
        strict=True,
    ):
        ax.plot(x, y, ".", ms=1.5, color="#4477aa", alpha=0.4, rasterized=True)
        ax.add_patch(rp.plt.Circle((0, 0), 1, fill=False, lw=0.6, color="#888"))
        ax.set_aspect("equal")
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-1.05, 1.05)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=9)
    th, td, _ = rp.to_half_diff(good.wi[first], good.wo[first])
    h = axes[2].hist2d(np.degrees(th), np.degrees(td), bins=24, cmap="Blues", cmin=1)
    fig.colorbar(h[3], ax=axes[2], label="samples per bin")
    axes[2].set_xlabel("θh [deg]")
    axes[2].set_ylabel("θd [deg]")
    axes[2].set_title("coverage over (θh, θd); white: none", fontsize=9)
    fig.suptitle(f"Where the samples are ({int(first.sum())} directions per channel)", fontsize=10)
    fig.tight_layout()
    return rp.png(fig)


def albedo_plot(fit: dict) -> tuple[str | None, float | None]:
    """Directional albedo ρ(θ) of the MAP fit per channel (fitting.models.properties quadrature),
    with the energy bound ρ ≤ 1; returns the plot and the largest ρ found (None if the model is
    unknown here)."""
    from fitting.models.properties import directional_albedo

    model = rp.model_of(fit)
    if model is None:
        return None, None
    theta_deg = np.linspace(0.0, 85.0, 18)
    fig, ax = rp.plt.subplots(figsize=(5.5, 3.4))
    peak = 0.0
    for ch in fit.get("channels", []):
        params = {k: np.asarray(v, float) for k, v in rp.fit_params(fit, ch).items()}
        with np.errstate(all="ignore"):
            rho = np.asarray(directional_albedo(model, params, np.radians(theta_deg), n=64))
        peak = max(peak, float(np.nanmax(rho)))
        ax.plot(theta_deg, rho, "-o", ms=3, label=f"channel {ch}")
    ax.axhline(1.0, color="#cc3311", lw=1, ls="--", label="energy bound ρ = 1")
    ax.set_xlabel("θ [deg]")
    ax.set_ylabel("directional albedo ρ")
    ax.set_ylim(0, max(1.1, 1.05 * peak))
    ax.legend(fontsize=7)
    ax.set_title(f"Directional albedo of the MAP fit (max {peak:.3f})", fontsize=10)
    fig.tight_layout()
    return rp.png(fig), peak


def monitor_plot(factors: list[float]) -> str | None:
    """The light monitor's reading per pose over the run, relative to the commanded level."""
    if not factors:
        return None
    fig, ax = rp.plt.subplots(figsize=(6, 2.6))
    ax.plot(np.arange(len(factors)), factors, ".-", ms=3, color="#4477aa")
    ax.axhline(1.0, color="#888", lw=0.8)
    ax.set_xlabel("pose (acquisition order)")
    ax.set_ylabel("monitor / commanded")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_title("Light monitor over the run (calibration divides it out)", fontsize=10)
    fig.tight_layout()
    return rp.png(fig)
