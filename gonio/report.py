"""`report.html`: one self-contained page (plots embedded as PNG data URIs) per run.

Every user-supplied string (run, material and model names, notes) goes through html.escape.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from acquisition.store import RunStore, atomic_write_bytes  # noqa: E402
from fitting import models  # noqa: E402
from fitting.directions import spherical_to_vector  # noqa: E402
from fitting.samples import read_samples  # noqa: E402

__all__ = ["write_report"]

_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;padding:0 1em}
h1{font-size:1.6em}
h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.ok{color:#176e1b}.bad{color:#b00020}.note{color:#555;font-size:.9em}img{max-width:100%}
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
            if fits:
                fit = fits[0]
                model = models.get(fit["model"], **fit.get("options", {}))
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


def _load_posterior(path: Path, fit: dict) -> tuple[list[str], np.ndarray]:
    """Second half of the stored emcee chain, in natural units.

    The chain is stored in the sampling space (log for scale parameters); columns follow the
    parameter order of the fit JSON. Each column's transform (identity or exp) is the one whose
    median reproduces the JSON median — both come from the same chain.
    """
    import h5py

    names = list(fit["parameters"])
    with h5py.File(path, "r") as fh:
        chain = np.asarray(fh["mcmc"]["chain"])
        it = int(fh["mcmc"].attrs["iteration"])
    chain = chain[it // 2 : it].reshape(-1, chain.shape[-1])
    if chain.shape[1] != len(names) or chain.shape[0] == 0:
        raise ValueError("chain does not match the fit")
    out = np.empty_like(chain)
    for j, name in enumerate(names):
        med = fit["parameters"][name]["median"]
        lin, ex = chain[:, j], np.exp(np.clip(chain[:, j], -700, 700))
        err_lin = abs(np.median(lin) - med)
        err_exp = abs(np.median(ex) - med)
        out[:, j] = ex if err_exp < err_lin else lin
    return names, out


def _posterior_plot(run_dir: Path, fit: dict, truth: dict[str, float]) -> str | None:
    """Marginal histograms of the stored chain (fit-<model>.h5), natural units."""
    try:
        names, draws = _load_posterior(run_dir / f"fit-{fit['model']}.h5", fit)
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
    cfg = store.run_config()
    samples_path = run_dir / "samples.parquet"
    samples = read_samples(samples_path)
    fits = [json.loads(p.read_text()) for p in sorted(run_dir.glob("fit-*.json"))]
    truth: dict[str, float] = {}
    if "scene" in cfg:
        from simulator.scene import Scene
        from simulator.truth import reference_parameters

        truth = reference_parameters(Scene.model_validate(cfg["scene"]))
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
    if "scene" in cfg:
        mat = json.dumps(cfg["scene"].get("material", {}))
        parts.append(f"<p class='note'>Simulated material: <code>{html.escape(mat)}</code></p>")
    parts.append("<h2>Measured vs fitted, plane of incidence</h2>")
    parts.append(f"<img src='{_slice_plot(samples, fits)}'>")
    for fit in fits:
        parts.append(
            f"<h2>Fit: {html.escape(fit['model'])} "
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
        post = _posterior_plot(run_dir, fit, truth)
        if post:
            parts.append(
                "<h3>Posterior marginals (black: median, 68% and 95% intervals; "
                "red: the simulated truth)</h3>"
            )
            parts.append(f"<img src='{post}'>")
    parts.append("<h2>Time</h2>")
    lab = store.meta("lab_time_s")
    trows = [["lab time (rig clock)", float(lab) if lab else None]]
    trows += [[f"compute: {k}", v] for k, v in (compute_times_s or {}).items()]
    for fit in fits:
        trows.append([f"compute: fit {fit['model']} (wall)", fit.get("wall_time_s")])
    parts.append(_table(["stage", "seconds"], trows))
    parts.append("</body></html>")
    out = run_dir / "report.html"
    atomic_write_bytes(out, "\n".join(parts).encode(), overwrite=True)
    return out
