"""`report.html`: one self-contained page (plots embedded as PNG data URIs) per run.

Sections: run summary and the verdict box of every fit (gonio.report.sections); measured vs
fitted in-plane slices (±1σ); per fit: parameters as value ± uncertainty, MCMC diagnostics,
goodness of fit, residual map over (θ_h, θ_d), polar plots per incidence angle, hemispherical
maps of measured / fitted / residual, directional albedo with the energy check
(gonio.report.maps), trace plots and the corner plot of every parameter, posterior marginals,
the preview render (simulator.preview); where the samples are; the model-comparison table
(compare.json, written by ``gonio fit --model all``); the calibration evidence (dark levels,
flat field, reference scale, flag counts, light monitor); lab and compute time per stage;
provenance (gonio version, reduction options, the samples file's SHA-256).

:func:`write_fit_report` is the same page for a fit that did not come from a run (``gonio report
--samples S --fit F.json``): the samples' provenance instead of the run summary, no lab time.

Every user-supplied string (run, plan, rig and model names, labels, notes) goes through
html.escape.
"""

from __future__ import annotations

import html
import json
import math
import time
from pathlib import Path
from typing import Any

from acquisition.store import RunStore
from fitting.binning import read_bounded
from gonio import version
from gonio.report import maps, plots, sections
from plumbing.atomic import atomic_write_bytes

__all__ = ["write_report", "write_fit_report"]


_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;padding:0 1em}
h1{font-size:1.6em}
h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.preview{width:256px;image-rendering:auto}.ok{color:#176e1b}.bad{color:#b00020}.note{color:#555;font-size:.9em}img{max-width:100%}
.verdict{border:2px solid #888;border-radius:6px;padding:.6em 1em;margin:.8em 0}
.verdict.ok{border-color:#176e1b;background:#eef8ee;color:#222}
.verdict.warning{border-color:#b26a00;background:#fff6e5}
.verdict.fail{border-color:#b00020;background:#fdecee}
tr.ok td:first-child{color:#176e1b}tr.warning td:first-child{color:#b26a00;font-weight:bold}
tr.fail td:first-child{color:#b00020;font-weight:bold}
.verdict td{text-align:left}table.params td.num{font-variant-numeric:tabular-nums}
"""


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


def _best_label(run_dir: Path) -> str | None:
    """Label of the rank-1 model in compare.json, if one was ranked."""
    from fitting.compare import read_compare

    try:
        rows, _ = read_compare(run_dir / "compare.json")
    except ValueError:
        return None
    best = [r for r in rows if isinstance(r, dict) and r.get("rank") == 1 and "label" in r]
    return str(best[0]["label"]) if best else None


def _compare_section(run_dir: Path) -> list[str]:
    path = run_dir / "compare.json"
    if not path.exists():
        return []
    from fitting.compare import read_compare

    try:
        rows, skipped = read_compare(path)
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
                r.get("rank") or "not ranked",
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
                "; ".join(str(w) for w in [r.get("why_unranked"), *(r.get("warnings") or [])] if w),
            ]
        )
    return [
        "<h2>Model comparison</h2>",
        "<p class='note'>Ranked by PSIS-LOO expected log predictive density (elpd, nats; "
        "higher is better). ΔELPD is relative to the best model, with the SE of the pointwise "
        "difference; |ΔELPD| below ~2 SE is no clear preference. k̂ > 0.7: that sample's LOO "
        "estimate is unreliable, and a model with any such sample, or whose sampler did not "
        "converge, is not ranked (its notes say why). AIC/BIC at the MAP (lower is better).</p>",
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
        *(
            [
                "<p>Not fitted: "
                + "; ".join(html.escape(f"{k.model}: {k.reason}") for k in skipped)
                + ".</p>"
            ]
            if skipped
            else []
        ),
    ]


def _diagnostics_parts(fit: dict) -> list[str]:
    diag = fit.get("diagnostics", {})
    drows = [
        [n, diag.get("tau", {}).get(n), diag.get("ess", {}).get(n), diag.get("rhat", {}).get(n)]
        for n in fit["parameters"]
    ]
    parts = ["<h3>MCMC diagnostics</h3>"]
    why = diag.get("converged_because") or diag.get("stop_reason", "")
    parts.append(
        f"<p>acceptance {_fmt(diag.get('acceptance'))}, converged "
        f"{_fmt(diag.get('converged'))} ({html.escape(str(why))})</p>"
    )
    parts.append(_table(["parameter", "τ [steps]", "ESS", "R-hat"], drows))
    parts.extend(_modes_parts(diag.get("modes"), diag.get("tempering")))
    parts.extend(_precision_parts(diag.get("precision")))
    good = fit.get("goodness", {})
    if good:
        parts.append("<h3>Goodness of fit</h3>")
        parts.append(_table(list(good), [list(good.values())]))
    return parts


def _modes_parts(modes: dict | None, tempering: dict | None) -> list[str]:
    """A tempered fit's modes (fitting.tempered_run.posterior_modes) in words and as a table
    of each mode's mass and place, and its ladder's swap rates."""
    if not modes:
        return []
    parts = [f"<p>Posterior modes: {html.escape(modes['words'])}.</p>"]
    optima = modes.get("optima") or []
    if len(optima) > 1:
        names = list(optima[0])
        rows = [
            [f"mode {k + 1}", f"{100 * m:.1f} %", *(opt[n] for n in names)]
            for k, (m, opt) in enumerate(zip(modes["masses"], optima, strict=True))
        ]
        parts.append(_table(["mode", "mass", *names], rows))
    if tempering:
        rates = ", ".join(f"{r:.2f}" for r in tempering.get("swap_acceptance", []))
        parts.append(
            f"<p>parallel tempering: {tempering.get('temperatures')} temperatures, "
            f"swap acceptance between neighbours {html.escape(rates)}</p>"
        )
    return parts


def _precision_parts(precision: dict | None) -> list[str]:
    """One line on the precision the model was evaluated in while sampling (fits since
    issue 23; fitting.likelihood.choose_precision)."""
    if not precision or not precision.get("mcmc"):
        return []
    why = precision.get("reason") or ""
    why = f" ({html.escape(why)})" if why else ""
    return [f"<p>model evaluated in {html.escape(precision['mcmc'])} while sampling{why}</p>"]


def _hemisphere_parts(samples, fit: dict) -> list[str]:
    """Residuals over (θ_h, θ_d), polar plots, hemispherical maps and the albedo check."""
    parts: list[str] = []
    figures = (
        ("Residual map over (θh, θd)", plots.residual_map(samples, fit)),
        ("Polar plots per incidence angle", maps.polar_plots(samples, fit)),
        ("Hemisphere: measured, fitted, residual", maps.hemisphere_maps(samples, fit)),
    )
    for title, uri in figures:
        if uri:
            parts += [f"<h3>{title}</h3>", f"<img src='{uri}' alt='{title}'>"]
    uri, peak = maps.albedo_plot(fit)
    if uri:
        verdict = (
            f"<p class='ok'>Energy check passed: the largest directional albedo is {peak:.4f} ≤ 1."
            if peak <= 1.0
            else f"<p class='bad'>Energy check FAILED: the directional albedo reaches "
            f"{peak:.4f} > 1, so the fitted material reflects more light than it receives; "
            "the model or its bounds do not suit this material."
        ) + "</p>"
        parts += ["<h3>Directional albedo and the energy check</h3>", verdict]
        parts.append(f"<img src='{uri}' alt='directional albedo'>")
    return parts


def _chain_parts(fit: dict, label: str, chain_dir: Path, truth: dict[str, float]) -> list[str]:
    """Traces and the corner plot of every parameter (a stated selection beyond the plots'
    limits) and the posterior marginals, from the stored chain ``fit-<label>.h5``."""
    parts: list[str] = []
    try:
        names_, chain, burn = plots.load_chain(plots.chain_path(chain_dir, fit, label), fit)
    except (OSError, KeyError, ValueError):
        return ["<p class='note'>No stored chain beside the fit: no traces or corner plot.</p>"]
    traced = plots.plot_selection(names_, plots.TRACE_LIMIT)
    parts.append(f"<h3>Trace plots ({_selection_words(traced, names_)})</h3>")
    parts.append(f"<img src='{plots.trace_plot(names_, chain, burn, fit)}' alt='traces'>")
    post = plots.posterior_plot(chain_dir, fit, truth, label)
    if post:
        parts.append(
            "<h3>Posterior marginals (black: median, 68% and 95% intervals; "
            "red: the simulated truth)</h3>"
        )
        parts.append(f"<img src='{post}' alt='posterior marginals'>")
    draws = chain[burn:].reshape(-1, chain.shape[-1])
    cornered = plots.plot_selection(names_, plots.CORNER_LIMIT)
    parts.append(f"<h3>Corner plot ({_selection_words(cornered, names_)})</h3>")
    parts.append(f"<img src='{plots.corner_plot(names_, draws, fit, truth)}' alt='corner plot'>")
    return parts


def _selection_words(picked: list[str], names: list[str]) -> str:
    if len(picked) == len(names):
        return f"all {len(names)} parameters"
    return (
        f"{len(picked)} of {len(names)} parameters: the shared ones, then by channel — "
        + ", ".join(picked)
    )


def _fit_section(
    samples, fit: dict, label: str, chain_dir: Path, truth: dict[str, float]
) -> tuple[list[str], float]:
    """The page section of one fit: parameters, diagnostics, goodness, the hemisphere views,
    the chain's plots (``chain_dir/fit-<label>.h5`` when present), preview and Mitsuba XML;
    and the preview render time [s]."""
    parts: list[str] = []
    parts.append(
        f"<h2>Fit: {html.escape(str(fit['model']))} "
        f"{html.escape(json.dumps(fit.get('options', {})))}</h2>"
    )
    parts.append(sections.parameter_table(fit, truth))
    parts += sections.mismatch_parts(fit)
    parts += _diagnostics_parts(fit)
    parts += _hemisphere_parts(samples, fit)
    parts += sections.coverage_parts(samples, fit)
    parts += _chain_parts(fit, label, chain_dir, truth)
    t_prev = time.perf_counter()
    uri, note = plots.preview(fit)
    preview_s = time.perf_counter() - t_prev
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
    return parts, preview_s


def _verdict_parts(labelled: list[tuple[str, dict]]) -> list[str]:
    if not labelled:
        return ["<h2>Verdicts</h2>", "<p class='bad'>No fit yet: nothing to judge.</p>"]
    return ["<h2>Verdicts</h2>"] + [sections.verdict_box(label, fit) for label, fit in labelled]


def _evidence_parts(samples, samples_path: Path, labelled: list[tuple[str, dict]]) -> list[str]:
    """Where the samples are, and the calibration evidence with the light monitor."""
    parts = ["<h2>Where the samples are</h2>"]
    where = maps.sample_map(samples)
    parts.append(f"<img src='{where}' alt='sample map'>" if where else "<p>No good samples.</p>")
    evidence, monitor = sections.calibration_evidence(samples)
    parts += evidence
    drift = maps.monitor_plot(monitor)
    if drift:
        spread = 100.0 * (max(monitor) - min(monitor)) / max(1e-12, sum(monitor) / len(monitor))
        parts.append(
            f"<p class='note'>Light monitor: peak-to-peak {spread:.2f} % of its mean over "
            f"{len(monitor)} poses.</p><img src='{drift}' alt='light monitor'>"
        )
    return parts


def write_report(run_dir: Path | str, compute_times_s: dict[str, float] | None = None) -> Path:
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir)
    try:
        return _write_report(run_dir, store, compute_times_s)
    finally:
        store.close()


def _write_report(run_dir: Path, store: RunStore, compute_times_s: dict[str, float] | None) -> Path:
    from fitting.result import check_samples_match, read_fit
    from gonio.errors import UserError

    cfg = store.run_config()  # the report shows what the run froze, tolerant of old runs
    if store.count("done") == 0:
        raise UserError(
            f"{run_dir}: the run has no completed captures; nothing to report (resume it with "
            f"`gonio acquire --out {run_dir}`)"
        )
    samples_path = run_dir / "samples.parquet"
    if not samples_path.exists():
        raise UserError(f"{samples_path}: no samples yet; run `gonio calibrate {run_dir}` first")
    samples = read_bounded(samples_path)  # binned beyond 10⁶ rows (fitting.binning)
    fit_paths = sorted(run_dir.glob("fit-*.json"))
    # read_fit checks every key the page uses, so a damaged or foreign fit file is one line
    # naming it, not a KeyError halfway through the page.
    fits = [read_fit(p).to_dict() for p in fit_paths]
    for p, fit in zip(fit_paths, fits, strict=True):
        check_samples_match(p, fit, samples_path, samples.source_sha256)
    plots.import_plotting()
    labels = [p.stem[len("fit-") :] for p in fit_paths]
    best = _best_label(run_dir)
    if best in labels:  # the preferred model first: its curves go on the slice plot
        i = labels.index(best)
        labels.insert(0, labels.pop(i))
        fits.insert(0, fits.pop(i))
    truth: dict[str, float] = {}
    if "scene" in cfg:
        from gonio.backends import scene_model, scene_truth

        truth = scene_truth(scene_model(cfg["scene"]))
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
    parts += _verdict_parts(list(zip(labels, fits, strict=True)))
    parts.append("<h2>Measured vs fitted, plane of incidence</h2>")
    parts.append(f"<img src='{plots.slice_plot(samples, fits)}'>")
    for label, fit in zip(labels, fits, strict=True):
        section, preview_s[label] = _fit_section(samples, fit, label, run_dir, truth)
        parts += section
    parts += _compare_section(run_dir)
    parts += _evidence_parts(samples, samples_path, list(zip(labels, fits, strict=True)))
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
    parts.append(
        sections.provenance(samples, samples_path, list(zip(labels, fits, strict=True)), version())
    )
    parts.append("</body></html>")
    out = run_dir / "report.html"
    atomic_write_bytes(out, "\n".join(parts).encode(), overwrite=True)
    return out


def write_fit_report(
    samples_path: Path | str, fit_path: Path | str, out: Path | str | None = None
) -> Path:
    """``report.html`` for any fit: the samples table and fit JSON it was made from (the chain
    ``fit-<label>.h5`` beside the JSON is used when present). Default ``out``: report.html
    beside the fit JSON."""
    from fitting.result import check_samples_match, read_fit
    from gonio.errors import UserError

    samples_path, fit_path = Path(samples_path), Path(fit_path)
    samples = read_bounded(samples_path)  # binned beyond 10⁶ rows (fitting.binning)
    fit = read_fit(fit_path).to_dict()
    check_samples_match(fit_path, fit, samples_path, samples.source_sha256)
    missing = [c for c in fit["channels"] if c not in samples.channels]
    if missing:
        raise UserError(
            f"{fit_path}: fitted channel(s) {', '.join(missing)} are not in {samples_path} "
            f"(it has {', '.join(samples.channels)}); give the samples the fit was made from"
        )
    out = Path(out) if out is not None else fit_path.parent / "report.html"
    plots.import_plotting()
    label = fit_path.stem[len("fit-") :] if fit_path.stem.startswith("fit-") else fit["model"]
    meta = samples.metadata
    source = ", ".join(
        f"{k.split('.')[-1]}: {html.escape(meta[k])}"
        for k in ("gonio.source.format", "gonio.source.file", "gonio.source.sha256")
        if k in meta
    )
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>gonio report — {html.escape(fit_path.name)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>gonio report: {html.escape(fit_path.name)}</h1>",
        f"<p class='note'>Samples {html.escape(str(samples_path))}: {len(samples)} rows "
        f"({len(samples.good())} good; "
        f"{'absolute' if not samples.relative else 'RELATIVE — no absolute calibration'})"
        + (f"; imported from {source}" if source else "")
        + ".</p>",
        *_verdict_parts([(label, fit)]),
        "<h2>Measured vs fitted, plane of incidence</h2>",
        f"<img src='{plots.slice_plot(samples, [fit])}'>",
    ]
    section, preview_s = _fit_section(samples, fit, label, fit_path.parent, {})
    parts += section
    parts += _evidence_parts(samples, samples_path, [(label, fit)])
    parts.append("<h2>Time</h2>")
    trows = [[f"compute: fit {label} (wall)", fit.get("wall_time_s")]]
    trows.append([f"compute: preview render {label}", preview_s])
    parts.append(_table(["stage", "seconds"], trows))
    parts.append(sections.provenance(samples, samples_path, [(label, fit)], version()))
    parts.append("</body></html>")
    atomic_write_bytes(out, "\n".join(parts).encode(), overwrite=True)
    return out
