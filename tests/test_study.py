"""The accuracy-vs-time study: its published results show the expected trends, and the
planner picks from them correctly. The CSV is the artefact `gonio study accuracy-vs-time`
regenerates (docs/accuracy-vs-time.csv); these checks are on what the study measured."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gonio.study import pareto, pick_plan, read_csv, summarise

REPO = Path(__file__).resolve().parent.parent
CSV = REPO / "docs" / "accuracy-vs-time.csv"


@pytest.fixture(scope="module")
def rows() -> list[dict]:
    assert CSV.exists(), "run `gonio study accuracy-vs-time --quick --out docs` to create it"
    return read_csv(CSV)


def test_error_falls_with_poses(rows) -> None:
    for material in ("rough", "glossy"):
        # Short exposures: shot noise dominates, as the trend is about statistics.
        s = [
            x
            for x in summarise(rows, "m")
            if x["material"] == material and x["exposures"] == "short" and x["mcmc_steps"] == 300
        ]
        by_poses = sorted(s, key=lambda x: x["poses"])
        assert len(by_poses) >= 3
        # The largest plan beats the smallest (medians over seeds).
        assert by_poses[-1]["rel_error"] < by_poses[0]["rel_error"], by_poses


def test_width_shrinks_like_inverse_sqrt_samples(rows) -> None:
    # Where noise dominates, the 68% half-width scales as 1/√(samples). Plans here differ in
    # geometry as well as count, so "roughly": the measured ratio is within a factor 2 of it.
    for material in ("rough", "glossy"):
        for param in ("m", "kd"):
            s = [
                x
                for x in summarise(rows, param)
                if x["material"] == material
                and x["exposures"] == "short"
                and x["mcmc_steps"] == 300
            ]
            lo, hi = min(s, key=lambda x: x["samples"]), max(s, key=lambda x: x["samples"])
            measured = hi["rel_half_width_68"] / lo["rel_half_width_68"]
            expected = math.sqrt(lo["samples"] / hi["samples"])
            assert 0.5 < measured / expected < 2.0, (material, param, measured, expected)


def test_coverage_of_the_68_percent_interval(rows) -> None:
    covered = np.array([r["covered_68"] for r in rows])
    frac = covered.mean()
    print(f"68% interval coverage over {covered.size} (parameter, run) pairs: {frac:.3f}")
    assert 0.55 <= frac <= 0.80


def test_pareto_and_pick_plan_on_synthetic_rows() -> None:
    # Independent toy data: the cheapest configuration meeting the target must be chosen.
    assert pareto([(1, 5), (2, 3), (3, 4), (4, 1)]) == [0, 1, 3]
    rows = []
    for plan, lab, err in (("A", 60, 0.10), ("B", 120, 0.04), ("C", 300, 0.01)):
        for seed in range(3):
            rows.append(
                {
                    "material": "rough",
                    "plan": plan,
                    "exposures": "single",
                    "mcmc_steps": 300,
                    "poses": 10,
                    "samples": 100,
                    "lab_time_s": lab,
                    "compute_s": 1.0,
                    "param": "m",
                    "rel_error": err,
                    "rel_half_width_68": err,
                    "covered_68": 1,
                    "seed": seed,
                }
            )
    assert pick_plan(rows, "m", 0.05, "rough")["plan"] == "B"
    assert pick_plan(rows, "m", 0.02, "rough")["plan"] == "C"
    assert pick_plan(rows, "m", 0.001, "rough") is None


def test_gonio_plan_prints_the_cheapest_plan(rows) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "gonio.cli", "plan", "--target", "m=0.05", "--results", str(CSV)],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert res.returncode == 0, res.stderr
    best = pick_plan(rows, "m", 0.05, "rough")
    assert best["plan"] in res.stdout and "lab time" in res.stdout
