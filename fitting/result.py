"""The fit result contract, ``fit-<model>.json`` (docs/design.md §4).

::

    {"schema_version", "model", "options", "channels",
     "parameters": {NAME: {"unit", "map", "median", "p16", "p84", "p2.5", "p97.5"}},
     "diagnostics": {"tau": {NAME: …}, "ess": {NAME: …}, "acceptance", "converged", "budget",
                     "rhat": {NAME: …}, "stop_reason"},
       (since issue 43 "ess" is the bulk ESS and "rhat" the rank-normalised R̂ of
       fitting.convergence; "ess_tail" {NAME: …} and "steps_needed" — what the stopping rule
       would need when a cap stopped the chain, else null — are added)
     "goodness": {"chi2", "dof", "chi2_red", "aic", "bic", "n"},
       (and, where the exact rows were selected by reading above the detection limit — the
       samples have dark rows — "chi2_expected" and "chi2_sd": χ²'s mean and sd given that
       selection, fitting.likelihood.Likelihood.chi2_selected, which the χ² verdict uses)
     "n_samples", "wall_time_s",
     "fixed": {NAME: value},        (optional: parameters held fixed with --fix)
     "verdicts": [{"name", "status", "reason", "advice"}, …],   (optional, issue 18)
     "samples_sha256": HEX}         (optional, issue 22: SHA-256 of the samples file fitted)

``diagnostics`` also holds, in fits written since issue 18, ``converged_because`` (one line:
the criteria met, or "not converged: " and those that failed) and ``failed_criteria`` (their
names: "rhat", "ess", "length", "stuck", "lost", "mcmc"); ``converged`` is then true exactly
when every criterion of fitting.verdicts.mcmc_verdict holds. ``verdicts`` (fitting.verdicts):
status "ok" | "warning" | "fail", a one-line reason, a one-line advice ("" when ok). Files
without these keys (older fits) are read as before.

``diagnostics.mismatch`` (fits with the discrepancy term, issue 18 item 3; fitting.mismatch):
``applied`` (whether the intervals were widened for model mismatch, else ``reason``),
``variance_ratio`` (sandwich / model-based variance along its eigen-directions, clipped at 1),
``sd_factor`` {NAME: widened sd / sampler's sd}, ``transform`` {names, center, matrix} (the
linear map applied to the chain's draws, in the sampled space), and ``regions``: the model
error per (θ_h, θ_d) region — ``label``, ``regions`` (0…8), ``n``, ``median``, ``p2.5``,
``p16``, ``p84``, ``p97.5``, ``quantiles`` (at 0, 2.5, … 100 %).

``diagnostics.precision`` (fits with MCMC since issue 23): ``mcmc``, the precision the model was
evaluated in while sampling ("float32" or "float64", fitting.likelihood.choose_precision), and
``rounding_lnl``, the largest change of ln L float32 made at the points checked (float32 only
below 0.01; null for a model without float32 kernels or where float32 changed which points are
finite), and ``reason``, the choice in one line.

Values are natural units (not the log used for sampling). Non-finite numbers are written as
null (JSON has no NaN).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from plumbing.atomic import atomic_write_bytes
from plumbing.errors import UserError
from plumbing.inputs import MiB, check_nesting, read_input_text

__all__ = [
    "FIT_SCHEMA_VERSION",
    "PARAMETER_KEYS",
    "DIAGNOSTIC_KEYS",
    "GOODNESS_KEYS",
    "VERDICT_KEYS",
    "TOP_KEYS",
    "FitResult",
    "FitResultError",
    "check_samples_match",
    "read_fit",
]

FIT_SCHEMA_VERSION = 1
TOP_KEYS = (
    "schema_version",
    "model",
    "options",
    "channels",
    "parameters",
    "diagnostics",
    "goodness",
    "n_samples",
    "wall_time_s",
)
PARAMETER_KEYS = ("unit", "map", "median", "p16", "p84", "p2.5", "p97.5")
DIAGNOSTIC_KEYS = ("tau", "ess", "acceptance", "converged", "rhat", "stop_reason")
GOODNESS_KEYS = ("chi2", "dof", "chi2_red", "aic", "bic", "n")
VERDICT_KEYS = frozenset({"name", "status", "reason", "advice"})


class FitResultError(UserError, ValueError):
    """A fit result file is missing or malformed. The message is one line."""


def _clean(x):
    """NaN/inf → None recursively; numpy scalars → Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if hasattr(x, "item") and not isinstance(x, str):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


@dataclass
class FitResult:
    model: str
    options: dict
    channels: list[str]
    parameters: dict[str, dict]
    diagnostics: dict
    goodness: dict
    n_samples: int
    wall_time_s: float
    schema_version: int = FIT_SCHEMA_VERSION
    #: Parameters held fixed (natural units, fitted names such as ``eta`` or ``kd_R``): not in
    #: ``parameters`` but needed to evaluate or export the model.
    fixed: dict[str, float] = field(default_factory=dict)
    #: The fit's verdicts (fitting.verdicts), None for a file written before they existed.
    verdicts: list[dict] | None = None
    #: SHA-256 of the samples file the fit was made from (None: fitted from memory, or a fit
    #: written before issue 22); `check_samples_match` compares it with a file.
    samples_sha256: str | None = None
    # Not serialised: in-memory extras for callers (chain, LSQ result, likelihood).
    extras: dict = field(default_factory=dict, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("extras")
        out = {k: d[k] for k in TOP_KEYS}
        if self.fixed:
            out["fixed"] = {str(k): float(v) for k, v in self.fixed.items()}
        if self.verdicts is not None:
            out["verdicts"] = [dict(v) for v in self.verdicts]
        if self.samples_sha256 is not None:
            out["samples_sha256"] = self.samples_sha256
        return _clean(out)

    def value(self, name: str, key: str = "median") -> float:
        return float(self.parameters[name][key])

    def predict(self, wi, wo, channels=None, *, x=None, estimate: str = "map"):
        """f̂ (N, C) in sr⁻¹ of the fitted model at direction pairs `wi`, `wo` (N, 3), per
        channel (default: the fitted ones): at the `estimate` of every parameter ("map",
        "median", ...; fixed parameters at their values), or at `x`, a point of the fit's
        sampled space (e.g. the least-squares optimum; needs the in-memory fit)."""
        import numpy as np

        from fitting import models

        model = models.get(self.model, **dict(self.options))
        channels = list(channels or self.channels)
        space = self.extras.get("space")
        if space is not None and (x is not None or estimate == "map"):
            if x is None:
                x = space.to_internal(np.array([self.parameters[n]["map"] for n in space.names]))
            nat = space.natural_dict(np.asarray(x)[None, :])
            per = [
                {k: v[0, 0] for k, v in space.channel_params(nat, ch).items()} for ch in channels
            ]
        elif x is not None:
            raise ValueError("predict(x=...) needs the fit's parameter space (an in-memory fit)")
        else:
            values = {n: float(p[estimate]) for n, p in self.parameters.items()}
            values.update({str(k): float(v) for k, v in self.fixed.items()})
            names = model.parameter_names
            per = [
                {n: values[f"{n}_{ch}"] if f"{n}_{ch}" in values else values[n] for n in names}
                for ch in channels
            ]
        cols = [np.asarray(model.evaluate(p, wi, wo)) for p in per]
        return np.stack(cols, axis=-1)

    def write(self, path: str | os.PathLike) -> Path:
        """Write atomically: temp file in the same directory, fsync, rename."""
        text = json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"
        return atomic_write_bytes(path, text.encode(), overwrite=True)


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def read_fit(path: str | os.PathLike) -> FitResult:
    """Read and validate ``fit-<model>.json``."""
    path = Path(path)
    try:
        text = read_input_text(path, "fit result", 256 * MiB)
        check_nesting(text, path, "fit result")
        d = json.loads(text)
    except FileNotFoundError:
        raise FitResultError(f"{path}: no such fit result") from None
    except json.JSONDecodeError as exc:
        raise FitResultError(
            f"{path}: not JSON ({exc.msg} at line {exc.lineno}); refit to rewrite it"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FitResultError(f"{path}: cannot read ({exc})") from None
    if not isinstance(d, dict):
        raise FitResultError(f"{path}: not a fit result (expected a JSON object)")
    missing = [k for k in TOP_KEYS if k not in d]
    if missing:
        raise FitResultError(f"{path}: not a fit result, missing {', '.join(missing)}")
    version = d["schema_version"]
    if not isinstance(version, int) or isinstance(version, bool):
        raise FitResultError(f"{path}: schema_version: expected an integer (got {version!r})")
    if version > FIT_SCHEMA_VERSION:
        raise FitResultError(
            f"{path}: fit schema version {version} was written by a newer gonio (this one reads "
            f"up to {FIT_SCHEMA_VERSION}); upgrade gonio"
        )
    params = d["parameters"]
    if not isinstance(params, dict) or not all(isinstance(v, dict) for v in params.values()):
        raise FitResultError(f"{path}: parameters: expected {{NAME: {{...}}}}; refit to rewrite it")
    for name, p in params.items():
        gaps = [k for k in PARAMETER_KEYS if k != "unit" and k not in p]
        if gaps:
            raise FitResultError(
                f"{path}: parameters.{name}: missing {', '.join(gaps)}; refit to rewrite it"
            )
        for k in PARAMETER_KEYS[1:]:  # numbers, or null where a value was not finite
            v = p[k]
            if v is not None and not (_is_number(v) and math.isfinite(v)):
                raise FitResultError(
                    f"{path}: parameters.{name}.{k}: expected a finite number or null "
                    f"(got {v!r}); refit to rewrite it"
                )
    for key, kind in (("options", dict), ("diagnostics", dict), ("goodness", dict)):
        if not isinstance(d[key], kind):
            raise FitResultError(f"{path}: {key}: expected a JSON object; refit to rewrite it")
    if not isinstance(d["channels"], list) or not all(
        isinstance(c, str) and c for c in d["channels"]
    ):
        raise FitResultError(f"{path}: channels: expected a list of names; refit to rewrite it")
    n = d["n_samples"]
    if not (_is_number(n) and float(n).is_integer() and n >= 0):
        raise FitResultError(
            f"{path}: n_samples: expected a count (got {n!r}); refit to rewrite it"
        )
    fixed = d.get("fixed", {})
    if not isinstance(fixed, dict) or not all(
        _is_number(v) and math.isfinite(v) for v in fixed.values()
    ):
        raise FitResultError(
            f"{path}: fixed: expected {{NAME: finite number}}; refit to rewrite it"
        )
    verdicts = d.get("verdicts")
    if verdicts is not None and (
        not isinstance(verdicts, list)
        or not all(isinstance(v, dict) and VERDICT_KEYS <= set(v) for v in verdicts)
    ):
        raise FitResultError(
            f"{path}: verdicts: expected a list of {{{', '.join(sorted(VERDICT_KEYS))}}}; "
            "refit to rewrite it"
        )
    sha = d.get("samples_sha256")
    if sha is not None and not (
        isinstance(sha, str) and len(sha) == 64 and all(c in "0123456789abcdef" for c in sha)
    ):
        raise FitResultError(
            f"{path}: samples_sha256: expected 64 lowercase hex digits; refit to rewrite it"
        )
    return FitResult(
        **{k: d[k] for k in TOP_KEYS}, fixed=dict(fixed), verdicts=verdicts, samples_sha256=sha
    )


def check_samples_match(fit_path, fit: dict | FitResult, samples_path, samples_sha256) -> None:
    """Refuse, in one line, a samples file other than the one the fit was made from (issue 22:
    a report of fit F drawn over other data would show residuals that mean nothing). Fits that
    recorded no hash (older files, in-memory fits) pass."""
    want = fit.get("samples_sha256") if isinstance(fit, dict) else fit.samples_sha256
    if want is None or samples_sha256 is None or want == samples_sha256:
        return
    raise FitResultError(
        f"{fit_path}: was fitted to a samples file with SHA-256 {want[:16]}…, but "
        f"{samples_path} has {samples_sha256[:16]}… (recalibrated or replaced since); refit it "
        "or give the samples it was made from"
    )
