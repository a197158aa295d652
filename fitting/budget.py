"""The samples' uncertainty budget (Parquet metadata ``gonio.budget``, written by calibration)
and the systematic part it gives each fitted parameter.

A budget is a list of components (GUM, JCGM 100:2008 §4–5): ``component``, ``type`` (A: from
these data's scatter; B: from elsewhere, e.g. a certificate), ``relative_sigma`` ({channel:
σ/value} or None when unknown), ``size`` (words) and ``shared_by``. The ``sigma`` column holds
only the statistical component; every other component is one error shared by the samples it
names. Treated per sample in quadrature, a shared error would average away as 1/√N — the
mistake this module exists to avoid.

The shared radiometric scale s (f_measured = s · f_true, s = 1 ± σ_s) is propagated exactly
for the parameters it acts on: when the model is homogeneous of degree one in its amplitude
parameters A (f(c·A, shape) = c · f(A, shape) — true of every lobe sum kd·D + ks·S here, and
checked numerically for the model at hand, never assumed), a scale error moves each amplitude
by the same factor and leaves the shape parameters where they are, so the fit of s·f has
amplitudes s·Â. Marginalising s ~ N(1, σ_s) then adds a systematic σ_sys = |Â| σ_s to each
amplitude (first order in σ_s, which is ≪ 1) and nothing to the shape parameters. A model that
is not homogeneous in its amplitudes gets no systematic part and a warning in words.
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = [
    "read_budget",
    "scale_sigma",
    "amplitude_parameters",
    "add_systematic",
    "budget_words",
    "left_out_words",
]

#: Parameter-name prefixes tried as amplitudes (diffuse and lobe weights); the homogeneity
#: check below decides.
_AMPLITUDE_PREFIXES = ("kd", "ks")


def read_budget(metadata: dict) -> list[dict] | None:
    """The budget from a samples table's metadata, or None if the table has none (written
    before budgets existed, or imported from another instrument)."""
    text = metadata.get("gonio.budget")
    if not text:
        return None
    try:
        budget = json.loads(text)
    except json.JSONDecodeError:
        return None
    return budget if isinstance(budget, list) else None


def scale_sigma(budget: list[dict] | None, channel: str) -> float | None:
    """Relative σ of the shared scale for `channel`: every ``scale…`` component of the budget
    (the certificate, the lamp's distance, …) in quadrature — independent errors that each
    multiply every f of the channel. None when the budget states none with a size."""
    parts = []
    for comp in budget or []:
        rel = comp.get("relative_sigma")
        if str(comp.get("component", "")).startswith("scale") and isinstance(rel, dict):
            value = rel.get(channel)
            if value is None and rel:
                value = float(np.sqrt(np.mean(np.square(list(rel.values())))))
            if value is not None:
                parts.append(float(value))
    return float(np.sqrt(np.sum(np.square(parts)))) if parts else None


def amplitude_parameters(model, params: dict[str, float]) -> tuple[str, ...]:
    """The model's amplitude parameters if f is homogeneous of degree one in them (checked at
    `params` on 64 random direction pairs to 1e-9 relative); () otherwise."""
    amps = tuple(n for n in model.parameter_names if n.startswith(_AMPLITUDE_PREFIXES))
    if not amps:
        return ()
    from brdfdata.directions import uniform_hemisphere

    rng = np.random.default_rng(0)
    wi, wo = uniform_hemisphere(64, rng), uniform_hemisphere(64, rng)
    base = {k: np.asarray(v, float) for k, v in params.items()}
    scaled = {k: (1.01 * v if k in amps else v) for k, v in base.items()}
    with np.errstate(all="ignore"):
        f0 = np.asarray(model.evaluate(base, wi, wo), float)
        f1 = np.asarray(model.evaluate(scaled, wi, wo), float)
    ok = np.isfinite(f0) & (f0 > 0)
    if not ok.any() or not np.allclose(f1[ok], 1.01 * f0[ok], rtol=1e-9, atol=0.0):
        return ()
    return amps


def _channel_of(name: str, channels: list[str]) -> tuple[str, str | None]:
    base, _, ch = name.rpartition("_")
    return (base, ch) if base and ch in channels else (name, None)


def add_systematic(
    parameters: dict[str, dict], model, channels: list[str], budget: list[dict] | None
) -> tuple[dict[str, dict], list[str]]:
    """Each parameter's summary with ``sd_stat`` (half the 16–84 % width), ``sd_sys`` (from the
    shared scale, see module docstring) and ``sd_total`` (their quadrature sum: the two errors
    are independent), and the words the user must read. Without a budget nothing is added."""
    if budget is None:
        return parameters, [
            "no uncertainty budget with these samples: intervals are statistical only"
        ]
    missing = left_out_words(budget)
    per_channel = {ch: scale_sigma(budget, ch) for ch in channels}
    if all(v is None for v in per_channel.values()):
        return parameters, [
            "the samples' budget states no size for the shared scale: intervals are "
            "statistical only and kd, ks are less certain than they show",
            *missing,
        ]
    values = {}
    for name, p in parameters.items():
        base, ch = _channel_of(name, channels)
        values.setdefault(base, p.get("median"))
    amps = amplitude_parameters(model, {k: v for k, v in values.items() if v is not None})
    words = []
    if not amps:
        words.append(
            f"{model.name}: not homogeneous in its amplitudes, so the shared scale's error is "
            "not propagated; intervals are statistical only"
        )
    out = {}
    for name, p in parameters.items():
        q = dict(p)
        base, ch = _channel_of(name, channels)
        lo, hi, med = p.get("p16"), p.get("p84"), p.get("median")
        sd_stat = None if lo is None or hi is None else 0.5 * (hi - lo)
        rels = [v for c, v in per_channel.items() if v is not None and (ch is None or c == ch)]
        # a shared amplitude (no channel suffix) sees every channel's scale: the rms, i.e.
        # the scale errors taken as fully correlated across channels (one reference target)
        rel = float(np.sqrt(np.mean(np.square(rels)))) if rels else None
        sd_sys = abs(med) * rel if base in amps and rel is not None and med is not None else 0.0
        q["sd_stat"] = sd_stat
        q["sd_sys"] = sd_sys
        q["sd_total"] = None if sd_stat is None else math.hypot(sd_stat, sd_sys)
        out[name] = q
    return out, words + missing


def left_out_words(budget: list[dict] | None, carried: tuple[str, ...] = ()) -> list[str]:
    """The words naming the budget's components no interval holds (every time): those marked
    not propagated and the arms' angle errors, unless among the `carried` ones
    (fitting.nuisance)."""
    left_out = [
        f"{c.get('component')} ({c.get('size')})"
        for c in budget or []
        if c.get("component") not in carried
        and (c.get("propagated") is False or str(c.get("component", "")).startswith("arm angles"))
    ]
    if not left_out:
        return []
    return ["not in any interval here, though shared by the samples: " + "; ".join(left_out)]


def budget_words(budget: list[dict] | None) -> list[tuple[str, str, str, str]]:
    """Rows (component, type, size, shared by) for printing the budget as a table."""
    return [
        (
            str(c.get("component", "?")),
            str(c.get("type", "?")),
            str(c.get("size", "?")),
            str(c.get("shared_by", "?")),
        )
        for c in budget or []
    ]
