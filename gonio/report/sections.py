"""The report's text sections (gonio.report): the verdict box, parameters as value ± uncertainty
with the digits the uncertainty needs, the calibration evidence and the provenance block. Every
string that came from a user or a file goes through html.escape.

Value ± uncertainty follows the usual metrology rule (GUM §7.2.6; the Particle Data Group's
rounding): the uncertainty is shown to two significant digits and the value to the same decimal
place, so a 0.4512 with a 0.0031 uncertainty is never printed as "0.45".
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from plumbing.hashing import sha256_file as _sha256

__all__ = [
    "format_pm",
    "format_interval",
    "verdict_box",
    "parameter_table",
    "calibration_evidence",
    "provenance",
    "worst_status",
    "coverage_parts",
]

#: Verdict statuses, best first; anything else a fit file holds is shown as "warning".
_STATUSES = ("ok", "warning", "fail")
#: Values this large or small go to scientific notation with one shared exponent.
_SCI_ABOVE, _SCI_BELOW = 1e5, 1e-3
_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _decimals(step: float) -> int:
    """Decimal places that show `step` with two significant digits."""
    return max(0, 1 - int(math.floor(math.log10(step))))


def format_pm(median: float, lo: float, hi: float) -> str:
    """'value +up −down' (or 'value ± u' when symmetric at the shown precision) for an
    interval [lo, hi] around `median`, the uncertainty to two significant digits and the value
    to the same decimal place. Plain text (no HTML)."""
    vals = (median, lo, hi)
    if any(v is None or not math.isfinite(v) for v in vals):
        return "–"
    up, down = hi - median, median - lo
    step = min(x for x in (up, down, abs(median) or 1.0) if x > 0) if max(up, down) > 0 else None
    if step is None:  # a degenerate interval: the posterior did not move
        return f"{median:.6g} (no spread)"
    scale = abs(median) if median else max(up, down)
    exp = 0
    if scale >= _SCI_ABOVE or scale < _SCI_BELOW:
        exp = int(math.floor(math.log10(scale)))
    m, u, d, s = (x / 10.0**exp for x in (median, up, down, step))
    n = _decimals(s)
    body = (
        f"{m:.{n}f} ± {u:.{n}f}"
        if f"{u:.{n}f}" == f"{d:.{n}f}"
        else f"{m:.{n}f} +{u:.{n}f} −{d:.{n}f}"
    )
    return f"({body})×10{str(exp).translate(_SUPERSCRIPT)}" if exp else body


def format_interval(median: float, lo: float, hi: float) -> str:
    """'[lo, hi]' at the precision format_pm gives the same interval around `median`."""
    if any(v is None or not math.isfinite(v) for v in (median, lo, hi)):
        return "–"
    step = min((x for x in (hi - median, median - lo, abs(median)) if x > 0), default=None)
    if step is None:
        return f"[{lo:.6g}, {hi:.6g}]"
    scale = abs(median) if median else hi - lo
    if scale >= _SCI_ABOVE or scale < _SCI_BELOW:
        n = max(1, _decimals(step / abs(scale)) - 1)
        return f"[{lo:.{n}e}, {hi:.{n}e}]"
    n = _decimals(step)
    return f"[{lo:.{n}f}, {hi:.{n}f}]"


def worst_status(verdicts: list[dict]) -> str:
    statuses = [v.get("status") if v.get("status") in _STATUSES else "warning" for v in verdicts]
    return max(statuses, key=_STATUSES.index) if statuses else "warning"


def verdict_box(label: str, fit: dict) -> str:
    """The fit's verdicts (fit JSON ``verdicts``: name, status, reason, advice) as a coloured
    box; a fit without them is said to be unjudged, never shown as fine."""
    verdicts = fit.get("verdicts")
    model = str(fit.get("model", "?"))
    title = html.escape(label if label == model else f"{label} ({model})")
    if not isinstance(verdicts, list) or not verdicts:
        return (
            f"<div class='verdict warning'><strong>{title}: not judged</strong> — this fit file "
            "holds no verdicts (convergence, goodness of fit); it was written by an older gonio. "
            "Refit "
            "to have it judged; until then do not trust it more than its numbers show.</div>"
        )
    worst = worst_status(verdicts)
    word = {"ok": "all checks passed", "warning": "usable, with warnings", "fail": "FAILED"}
    rows = []
    for v in verdicts:
        status = v.get("status") if v.get("status") in _STATUSES else "warning"
        rows.append(
            f"<tr class='{status}'><td>{html.escape(status)}</td>"
            f"<td>{html.escape(str(v.get('name', '?')))}</td>"
            f"<td>{html.escape(str(v.get('reason', '')))}</td>"
            f"<td>{html.escape(str(v.get('advice', '')))}</td></tr>"
        )
    return (
        f"<div class='verdict {worst}'><strong>{title}: {word[worst]}</strong>"
        "<table><tr><th>status</th><th>check</th><th>why</th><th>what to do</th></tr>"
        + "".join(rows)
        + "</table></div>"
    )


def _cell(x: Any) -> str:
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.6g}" if math.isfinite(x) else str(x)
    return html.escape(str(x))


def parameter_table(fit: dict, truth: dict[str, float]) -> str:
    """Every parameter as median with its 68 % interval (value ± σ, enough digits to show it),
    the 95 % interval at the same precision, MAP, the statistical / systematic split when the
    fit records one (fitting.budget), and the truth when the world is simulated."""
    from fitting.nuisance import is_nuisance_name

    split = any(p.get("sd_stat") is not None for p in fit["parameters"].values())
    # With the shared errors marginalised as nuisance parameters the intervals hold them too;
    # otherwise (the older treatment) they are statistical and the systematic part stands apart.
    carried = any(is_nuisance_name(n) for n in fit["parameters"])
    interval = "median ± 68 % (all errors)" if carried else "median ± 68 % (statistical)"
    head = ["parameter", "unit", interval, "95 % interval", "MAP"]
    head += ["statistical σ", "systematic σ", "total σ"] if split else []
    head += ["truth", "truth in 95 %"]
    rows = []
    for name, p in fit["parameters"].items():
        t = truth.get(name)
        pm = format_pm(p["median"], p["p16"], p["p84"])
        wide = format_interval(p["median"], p["p2.5"], p["p97.5"])
        cells = [name, p.get("unit", ""), pm, wide, p["map"]]
        if split:
            cells += [_sigma(p.get(k)) for k in ("sd_stat", "sd_sys", "sd_total")]
        inside = None if t is None or p["p2.5"] is None else bool(p["p2.5"] <= t <= p["p97.5"])
        cells += [t, inside]
        rows.append("<tr>" + "".join(f"<td class='num'>{_cell(c)}</td>" for c in cells) + "</tr>")
    notes = [str(n) for n in (fit.get("diagnostics", {}).get("budget") or [])]
    if split and carried:
        notes.insert(
            0,
            "the intervals hold every error the samples' budget sizes: its shared errors were "
            "nuisance parameters of the fit; systematic σ is the part of each parameter's "
            "spread those nuisances explain, statistical σ the rest (total σ = statistical ⊕ "
            "systematic); the nuisances' own rows have no split",
        )
    elif split:
        notes.insert(
            0,
            "systematic σ: the shared errors of the samples' uncertainty budget (the "
            "radiometric scale moves kd and ks together and leaves the shape parameters), "
            "total σ = statistical ⊕ systematic; the intervals are statistical only",
        )
    elif not notes:
        notes.append(
            "no statistical / systematic split was recorded with this fit (made by an older "
            "gonio, or from samples without an uncertainty budget): intervals are statistical "
            "only, and shared errors such as the reference scale are not in them"
        )
    note = (
        "<p class='note'>Uncertainties are posterior quantiles: median with the 16–84 % "
        "interval, then the 2.5–97.5 % interval, shown to two significant digits of the "
        "uncertainty.</p>"
        + "".join(
            f"<p class='{'bad' if _is_warning(n) else 'note'}'>{html.escape(n)}.</p>" for n in notes
        )
    )
    header = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    return f"<table class='params'><tr>{header}</tr>{''.join(rows)}</table>{note}"


def mismatch_parts(fit: dict) -> list[str]:
    """How the model's mismatch shaped the intervals (fitting.mismatch): whether they were
    widened and by how much, what they cover, and the model error per (θ_h, θ_d) region."""
    info = fit.get("diagnostics", {}).get("mismatch")
    if not info:
        return []
    from fitting.mismatch import widening_words

    parts = ["<h3>Model mismatch</h3>", f"<p>{html.escape(widening_words(info))}.</p>"]
    factors = info.get("sd_factor") or {}
    if info.get("applied") and factors:
        parts.append(
            "<p class='note'>Widening per parameter (sd after / sd of the sampler's draws): "
            + html.escape(", ".join(f"{k} ×{v:.3g}" for k, v in factors.items()))
            + ". Where the model cannot describe the material, no parameter is 'true': the "
            "intervals are for the best approximation on the measured directions — what the "
            "same fit would give with every direction of that domain measured without noise — "
            "and widened to the sandwich estimate of their spread (HC3; Ribatet et al. 2012) "
            "where the residuals show the posterior is too narrow for it.</p>"
        )
    regions = info.get("regions") or []
    if regions:
        rows = [
            [r["label"], r["n"], f"{100 * r['median']:.3g} %"]
            + [f"{100 * r['p2.5']:.3g}–{100 * r['p97.5']:.3g} %"]
            for r in regions
        ]
        head = "<tr><th>region</th><th>samples</th><th>model error s</th><th>95 %</th></tr>"
        body = "".join(
            "<tr>" + "".join(f"<td class='num'>{_cell(c)}</td>" for c in row) + "</tr>"
            for row in rows
        )
        parts.append(
            f"<table class='params'>{head}{body}</table><p class='note'>Model error per region "
            "of the half and difference angles (θ_h, θ_d): the RMS fraction of f the model "
            "misses there, at the fitted parameters (uniform prior on [0, 1]). A prediction's "
            "95 % band uses its region's value.</p>"
        )
    return parts


def _is_warning(note: str) -> bool:
    """A budget note that says an interval leaves something out (shown in red)."""
    return any(w in note for w in ("statistical only", "not in any interval", "not propagated"))


def _sigma(x: Any) -> str:
    return "–" if x is None else f"{x:.2g}"


def _flag_counts(samples) -> list[tuple[str, int]]:
    from brdfdata.samples import Flags

    flags = np.asarray(samples.flags)
    names = ("SATURATED", "DARK", "BELOW_HORIZON", "MASKED", "NEGATIVE")
    out = [("good", int(np.count_nonzero(flags == 0)))]
    out += [(n.lower(), int(np.count_nonzero(flags & getattr(Flags, n)))) for n in names]
    return out


def calibration_evidence(samples) -> tuple[list[str], list[float]]:
    """HTML of the calibration evidence recorded in the samples metadata (dark levels, flat
    field, reference scale and its σ, flag counts, notes), and the light monitor per pose."""
    try:
        calib = json.loads(samples.metadata.get("gonio.calibration", "{}"))
    except json.JSONDecodeError:
        calib = {}
    ev = calib.get("evidence") or {}
    parts = ["<h2>Calibration evidence</h2>"]
    rows = [["radiometry", calib.get("radiometry", "not recorded")]]
    for t, d in (ev.get("dark") or {}).items():
        rows.append(
            [f"master dark at {t} s", f"{d['frames']} frames, mean {d['mean_dn']:.2f} DN, "
             f"temporal noise {d['noise_dn']:.2f} DN"]
        )  # fmt: skip
    if not ev.get("dark"):
        rows.append(["darks", "none recorded (dark level from the camera description)"])
    flat = ev.get("flat")
    rows.append(
        ["flat field", "none recorded (uniform response assumed)"]
        if not flat
        else ["flat field", f"{flat['frames']} frames, gain {flat['gain_min']:.3f}–"
              f"{flat['gain_max']:.3f} (sd {flat['gain_sd']:.3f}) relative to the centre"]
    )  # fmt: skip
    ref = calib.get("reference")
    if ref:
        for ch, k, rel, birge in zip(
            ref["channels"], ref["k_W_sr"], ref["rel_sigma"], ref["birge_ratio"], strict=False
        ):
            rows.append(
                [f"reference scale, channel {ch}",
                 f"k = {k:.5g} W/sr, σ = {100 * rel:.3g} % over {ref['n_poses']} poses "
                 f"(Birge ratio {birge:.2f})"]
            )  # fmt: skip
    elif calib.get("intensity_W_sr") is not None:
        rows.append(["scale", f"certified lamp intensity {calib['intensity_W_sr']} W/sr"])
    counts = ", ".join(f"{n} {c}" for n, c in _flag_counts(samples) if c or n == "good")
    rows.append(["samples by flag", counts])
    rows.append(["light drift", "corrected by the monitor" if calib.get("light_drift_corrected")
                 else "NOT corrected (no monitor, or switched off)"])  # fmt: skip
    body = "".join(
        f"<tr><td>{html.escape(a)}</td><td>{html.escape(str(b))}</td></tr>" for a, b in rows
    )
    parts.append(f"<table>{body}</table>")
    for note in calib.get("notes") or []:
        parts.append(f"<p class='bad'>{html.escape(str(note))}</p>")
    return parts, [float(x) for x in ev.get("monitor_per_pose") or []]


def provenance(samples, samples_path: Path, fits: list[tuple[str, dict]], version: str) -> str:
    """gonio version, the reduction options, the samples file's SHA-256 and each fit's
    model, options and sample count."""
    try:
        calib = json.loads(samples.metadata.get("gonio.calibration", "{}"))
    except json.JSONDecodeError:
        calib = {}
    reduction = {k: calib[k] for k in ("bin_px", "segment", "mode", "radiometry") if k in calib}
    rows = [
        ["gonio", version],
        ["samples file", f"{samples_path.name} (SHA-256 {_sha256(samples_path)})"],
        ["reduction options", json.dumps(reduction) if reduction else "not recorded"],
    ]
    for key in ("gonio.source.format", "gonio.source.file", "gonio.source.sha256"):
        if key in samples.metadata:
            rows.append([key.removeprefix("gonio."), samples.metadata[key]])
    for label, fit in fits:
        rows.append(
            [f"fit {label}", f"{fit.get('model')} {json.dumps(fit.get('options', {}))}, "
             f"channels {','.join(fit.get('channels', []))}, {fit.get('n_samples')} samples"]
        )  # fmt: skip
    body = "".join(
        f"<tr><td>{html.escape(str(a))}</td><td>{html.escape(str(b))}</td></tr>" for a, b in rows
    )
    return f"<h2>Provenance</h2><table class='prov'>{body}</table>"


def coverage_parts(samples, fit: dict) -> list[str]:
    """Which hemisphere regions the fitted model needs (brdfdata.coverage, the registry's
    `needs`) and how many of the good samples fall in each; a region left empty or sparse is
    named in red with what it means."""
    from fitting.models import model_coverage

    good = samples.good()
    if len(good) == 0:
        return []
    first = good.channel == good.channels[0]
    try:
        rep = model_coverage(str(fit.get("model")), good.wi[first], good.wo[first])
    except (KeyError, ValueError):
        return ["<p class='note'>No coverage check: this gonio does not know the model.</p>"]
    rows = "".join(f"<li>{html.escape(line)}</li>" for line in rep.lines())
    parts = [
        "<h3>Coverage: what this model needs of the hemisphere</h3>",
        f"<ul class='note'>{rows}</ul>",
    ]
    if rep.missing:
        parts.append(
            f"<p class='bad'>The samples leave {html.escape(', '.join(rep.missing))} empty or "
            "sparse: what those regions determine rests on the prior or is extrapolated; "
            "measure there (`gonio plan --plan FILE --model …` shows a plan's coverage).</p>"
        )
    return parts
