"""Small noise-free runs of the demo material with one instrument error switched on, and the
rows two such runs share: the measurement of what one effect does to the calibrated f."""

from __future__ import annotations

import numpy as np

from acquisition.operator import AutoOperator
from simulator.scene import GeometryTruth, load_scene
from tests.support.paths import REPO

__all__ = ["effect_run", "paired_rows"]


def effect_run(
    out,
    beta: float,
    geometry: GeometryTruth | None = None,
    flat_falloff: float | None = None,
    exposures_s: tuple[float, ...] = (0.016,),
    noise: bool = False,
    rig=None,
    **scene_update,
):
    """A small run of the demo material, noise off unless `noise` (so two runs differ only by β, the
    stated geometry error or the flat source's falloff). With ``flat_falloff`` the run records
    a flat field (8 frames) from a source of that falloff, and calibration uses it."""
    from acquisition.config import CalibrationPhasesConfig, FlatPhaseConfig, PlanConfig
    from gonio.pipeline import AcquireSpec, acquire

    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    sensor = scene.sensor.model_copy(update={"noise": noise, "nonlinearity": beta})
    plan = PlanConfig(
        name="linearity",
        type="isotropic",
        theta_i_deg=(30.0, 50.0),
        theta_o_deg=(0.0, 30.0, 50.0),
        delta_phi_deg=(180.0, 120.0),
        exposures_s=exposures_s,
        calibration=CalibrationPhasesConfig(
            flat=None if flat_falloff is None else FlatPhaseConfig(count=8)
        ),
    )
    spec = AcquireSpec(
        rig=REPO / "configs" / "rigs" / "sim.toml" if rig is None else rig,
        plan=plan,
        scene=scene.model_copy(
            update={
                "sensor": sensor,
                "geometry": geometry or GeometryTruth(),
                "flat_source_falloff": flat_falloff or 0.0,
                **scene_update,
            }
        ),
        progress=False,
        operator=AutoOperator(),
    )
    assert acquire(out, spec).outcome.complete
    from calibration.reduce import ReduceOptions, reduce_run

    return reduce_run(out, ReduceOptions(bin_px=4, radiometry="certified"), progress=False)


def paired_rows(base, other):
    """Row indices (a into ``base``, b into ``other``) of the samples both runs hold — the same
    capture, pixel block and channel — and where both are unflagged. Noise-free runs of one plan
    differ only by the effect under test, so ``other.f[b] / base.f[a]`` measures it."""
    key = lambda t: list(zip(t.extra["capture_id"], t.extra["pixel_x"], t.extra["pixel_y"],  # noqa: E731
                             t.channel.astype(str), strict=True))  # fmt: skip
    index = {k: i for i, k in enumerate(key(other))}
    pairs = [(i, index[k]) for i, k in enumerate(key(base)) if k in index]
    assert len(pairs) > 0.9 * len(base)
    a, b = np.array(pairs).T
    return a, b, (base.flags[a] == 0) & (other.flags[b] == 0)
