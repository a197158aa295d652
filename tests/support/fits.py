"""Fit results made by hand, as inputs for the commands that read them."""

from __future__ import annotations

from fitting.result import FitResult

__all__ = ["fit_json"]


def fit_json(tmp_path) -> FitResult:
    """A torrance-sparrow conductor fit (R, G, B) written as tmp_path/fit-torrance-sparrow.json,
    every quantile at its value: an input for the export commands."""
    params = {}
    for c, kd, ks in (("R", 0.30, 0.40), ("G", 0.20, 0.50), ("B", 0.10, 0.60)):
        params[f"kd_{c}"] = {"unit": "1", "map": kd, "median": kd}
        params[f"ks_{c}"] = {"unit": "1", "map": ks, "median": ks}
    params["m"] = {"unit": "1", "map": 0.3, "median": 0.3}
    for p in params.values():
        p.update({k: p["median"] for k in ("p16", "p84", "p2.5", "p97.5")})
    fit = FitResult(
        model="torrance-sparrow",
        options={"shadowing": "smith-rational", "fresnel": "conductor"},
        channels=["R", "G", "B"],
        parameters=params,
        diagnostics={},
        goodness={},
        n_samples=0,
        wall_time_s=0.0,
        fixed={"eta": 0.2, "k": 3.0},
    )
    fit.write(tmp_path / "fit-torrance-sparrow.json")
    return fit
