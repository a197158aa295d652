"""The camera's response measured from the run's own brackets and taken out before the merge
(calibration.linearity, issue 43 item 3).

Truth is the simulated sensor's stated bend e·(1 + β e/FW) (simulator.sensor), which the
calibration never reads: it sees only the frames. Calibration's β is relative to its clip
Y = white − black (DN); the world's to its full well FW (e⁻), so the world's β reads as
β·(Y·gain)/FW in calibration's terms (0.9994 of β on the simulated camera).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from simulator.scene import load_scene
from tests.support.effect_runs import effect_run, paired_rows
from tests.support.paths import REPO

BRACKETS = (0.002, 0.016)


def _measured(table) -> dict:
    budget = json.loads(table.metadata["gonio.budget"])
    (comp,) = [c for c in budget if c["component"].startswith("linearity")]
    return comp["measured"]


def _beta_in_calibration_terms(beta: float) -> float:
    sensor = load_scene(REPO / "configs" / "scenes" / "demo.toml").sensor
    from acquisition.config import load_rig

    cam = load_rig(REPO / "configs" / "rigs" / "sim.toml").camera
    return beta * (cam.white_level_dn - cam.black_level_dn) * cam.gain_e_per_dn / sensor.full_well_e


def test_a_bent_response_is_measured_and_taken_out(tmp_path) -> None:
    """Noise-free, β = 5 % (large, so DN rounding is < 1 % of the effect): the brackets give
    β within 5 % of the world's (what is left is the estimator's own approximation: the
    neighbours' mean stands for the pixel's level, off by the image's curvature over 3×3
    pixels), and the corrected f of the bent run equals the linear run's to within a tenth of
    the bend the run had (the bend's effect on f is β·ū ≤ 2 %; rounding 0.05 %)."""
    beta = 0.05
    linear = effect_run(tmp_path / "linear", 0.0, exposures_s=BRACKETS)
    bent = effect_run(tmp_path / "bent", beta, exposures_s=BRACKETS)
    got = _measured(bent)
    assert got["corrected"] and got["poses"] >= 8
    assert got["beta"] == pytest.approx(_beta_in_calibration_terms(beta), rel=0.05)
    assert not _measured(linear)["corrected"]
    a, b, good = paired_rows(linear, bent)
    good &= linear.f[a] > 0
    rel = bent.f[b][good] / linear.f[a][good] - 1.0
    print(f"corrected: |f_bent/f_linear − 1| max {np.abs(rel).max():.2e}, rms "
          f"{np.sqrt(np.mean(rel**2)):.2e} (β {got['beta']:.4f})")  # fmt: skip
    assert np.sqrt(np.mean(rel**2)) < 0.1 * beta * 0.2  # a tenth of β at a 20 % well fill


@pytest.mark.parametrize("beta", [0.0, 0.005])
def test_a_datasheet_sized_bend_is_found_in_noise_and_a_straight_one_is_not(tmp_path, beta) -> None:
    """With shot and read noise, β = 0.5 % (the realistic scene's, EMVA 1288 linearity errors
    of 0.1–1 %) is found within 3 of its own σ and corrected; a linear camera's β is within 3σ
    of 0 and left alone (3σ: the correction's detection rule, calibration.linearity)."""
    table = effect_run(tmp_path / "run", beta, exposures_s=BRACKETS, noise=True)
    got = _measured(table)
    truth = _beta_in_calibration_terms(beta)
    print(f"β world {truth:.4%}: measured {got['beta']:+.4%} ± {got['sigma']:.4%} "
          f"({got['pixels']} pixels, corrected {got['corrected']})")  # fmt: skip
    assert abs(got["beta"] - truth) < 3 * got["sigma"]
    assert got["corrected"] == (beta > 0)


def test_each_samples_bend_level_is_where_the_worlds_bend_acts(tmp_path, monkeypatch) -> None:
    """The fit carries the bend calibration leaves in as 1 + b · level per sample (fitting.nuisance,
    ``linearity_pct``), level the samples' ``bend_level`` column (calibration.linearity.bend_level:
    the fraction of the clip at which the merge read the sample, from the merge's own weights).
    Against the world: a 2 % bend left in the samples (the 3σ test switched off, here only, so
    that calibration does not take it out), noise-free and paired with the straight run, moves
    each f by the factor 1 + β·level with the world's β (in calibration's terms). Tolerance: the
    first-order model misses (β·level)² ≤ 4e-4, 2 % of the effect at the top; a 4×4 block's mean
    of f·level differs from f·mean(level) by the image's curvature (< 1 %); DN rounding is
    < 2 % of the effect where level > 0.1 (the rows compared). The level is read from the eight
    blocks around the sample's own (calibration.reduce._around, so that it carries none of the
    sample's noise); against the level of the block's own noise-free flux it differs by
    0.972–1.028 (5–95 %) in this run, which these bounds, unchanged, absorb as measured
    (0.957–1.029; 0.977–1.015 when the level was read from the sample itself)."""
    import calibration.linearity

    monkeypatch.setattr(calibration.linearity, "DETECT_Z", np.inf)
    beta = 0.02
    linear = effect_run(tmp_path / "linear", 0.0, exposures_s=BRACKETS)
    bent = effect_run(tmp_path / "bent", beta, exposures_s=BRACKETS)
    assert not _measured(bent)["corrected"]
    a, b, good = paired_rows(linear, bent)
    level = np.asarray(linear.extra["bend_level"])[a]
    good &= (linear.f[a] > 0) & (level > 0.1)
    slope = (bent.f[b][good] / linear.f[a][good] - 1.0) / (
        _beta_in_calibration_terms(beta) * level[good]
    )
    q05, q95 = np.quantile(slope, [0.05, 0.95])
    print(f"bend level: rows {good.sum()}, level up to {level[good].max():.2f}; effect over "
          f"β·level median {np.median(slope):.3f}, 5–95 % {q05:.3f}–{q95:.3f}")  # fmt: skip
    assert level[good].max() > 0.5  # the run reaches well into the bend
    assert abs(np.median(slope) - 1.0) < 0.03
    assert abs(q05 - 1.0) < 0.05 and abs(q95 - 1.0) < 0.05
