"""The fit result contract, ``fit-<model>.json`` (DESIGN §4).

::

    {"schema_version", "model", "options", "channels",
     "parameters": {NAME: {"unit", "map", "median", "p16", "p84", "p2.5", "p97.5"}},
     "diagnostics": {"tau": {NAME: …}, "ess": {NAME: …}, "acceptance", "converged",
                     "rhat": {NAME: …}, "stop_reason"},
     "goodness": {"chi2", "dof", "chi2_red", "aic", "bic", "n"},
     "n_samples", "wall_time_s"}

Values are natural units (not the log used for sampling). Non-finite numbers are written as
null (JSON has no NaN).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from fitting.atomic import atomic_write_bytes

__all__ = [
    "FIT_SCHEMA_VERSION",
    "PARAMETER_KEYS",
    "DIAGNOSTIC_KEYS",
    "GOODNESS_KEYS",
    "TOP_KEYS",
    "FitResult",
    "FitResultError",
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


class FitResultError(ValueError):
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
    # Not serialised: in-memory extras for callers (chain, LSQ result, likelihood).
    extras: dict = field(default_factory=dict, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("extras")
        return _clean({k: d[k] for k in TOP_KEYS})

    def value(self, name: str, key: str = "median") -> float:
        return float(self.parameters[name][key])

    def write(self, path: str | os.PathLike) -> Path:
        """Write atomically: temp file in the same directory, fsync, rename."""
        text = json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"
        return atomic_write_bytes(path, text.encode())


def read_fit(path: str | os.PathLike) -> FitResult:
    """Read and validate ``fit-<model>.json``."""
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
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
    for key, kind in (("options", dict), ("diagnostics", dict), ("goodness", dict)):
        if not isinstance(d[key], kind):
            raise FitResultError(f"{path}: {key}: expected a JSON object; refit to rewrite it")
    if not isinstance(d["channels"], list):
        raise FitResultError(f"{path}: channels: expected a list; refit to rewrite it")
    return FitResult(**{k: d[k] for k in TOP_KEYS})
