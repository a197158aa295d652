"""Lamp drift during a run is corrected from the light monitor recorded with each capture.

The simulated lamp loses output linearly with time since switch-on (scene `light.drift_per_hour`)
and its monitor photodiode reads the same relative output. Truth is Mitsuba's own BSDF.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acquisition.config import PlanConfig, load_rig
from brdfdata.directions import spherical_to_vector
from calibration.reduce import ReduceOptions, reduce_run
from gonio.pipeline import AcquireSpec, acquire
from simulator.render import Renderer
from simulator.scene import load_scene
from tests.support.paths import REPO

DRIFT_PER_HOUR = -0.10
WARMUP_S = 1800.0  # half an hour of (virtual) warm-up: the lamp is ~5% down at the first frame


@pytest.fixture(scope="module")
def drifting_run(tmp_path_factory: pytest.TempPathFactory):
    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    scene = scene.model_copy(
        update={"light": scene.light.model_copy(update={"drift_per_hour": DRIFT_PER_HOUR})}
    )
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    rig = rig.model_copy(update={"light": rig.light.model_copy(update={"warmup_s": WARMUP_S})})
    plan = PlanConfig(
        name="drift",
        theta_i_deg=(30.0,),
        theta_o_deg=(0.0, 20.0, 40.0),
        delta_phi_deg=(180.0, 90.0),
        exposures_s=(0.004,),
    )
    out = tmp_path_factory.mktemp("drift") / "run"
    res = acquire(out, AcquireSpec(rig=rig, plan=plan, scene=scene, progress=False, announce=False))
    assert res.outcome.complete
    return out, Renderer(scene)


def _ratio(table, renderer) -> np.ndarray:
    good = table.good()
    wi = spherical_to_vector(good.theta_i, good.phi_i)
    wo = spherical_to_vector(good.theta_o, good.phi_o)
    idx = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in good.channel])
    truth = renderer.truth_bsdf(wi, wo)[np.arange(idx.size), idx]
    return good.f / truth


def test_monitor_removes_lamp_drift(drifting_run, tmp_path: Path) -> None:
    out, renderer = drifting_run
    corrected = _ratio(
        reduce_run(out, ReduceOptions(bin_px=4, mode="center"), out=tmp_path / "a.parquet"),
        renderer,
    )
    raw = _ratio(
        reduce_run(
            out,
            ReduceOptions(bin_px=4, mode="center", light_monitor=False),
            out=tmp_path / "b.parquet",
        ),
        renderer,
    )
    # Without the monitor the BRDF inherits the lamp's loss: ≈ drift × (warm-up + run) / 1 h
    # (the run itself lasts well under a minute of lab time here).
    expected = 1.0 + DRIFT_PER_HOUR * WARMUP_S / 3600.0
    assert abs(np.median(raw) - expected) < 0.005, np.median(raw)
    # With it, the calibrated values are back on the truth: the residual median is pure noise
    # (per-sample SNR ≳ 50 over ~10³ samples → its standard error is ≪ 0.1%).
    assert abs(np.median(corrected) - 1.0) < 0.002, np.median(corrected)
