"""A few-pose simulated run for tests of the calibration: one θ_i, a few θ_o, Δφ = 180°, two
brackets, through the real acquisition (gonio.pipeline.acquire) on the sim rig."""

from __future__ import annotations

from pathlib import Path

from acquisition.config import PlanConfig, RigConfig
from gonio.pipeline import AcquireSpec, acquire
from tests.support.paths import REPO


def small_run(
    out: Path,
    scene: str,
    *,
    theta_i_deg: float = 30.0,
    theta_o_deg: tuple[float, ...] = (0.0, 30.0),
    rig: RigConfig | Path | None = None,
) -> Path:
    """Acquire the run into `out` with configs/scenes/`scene` (raw.toml: RGGB DNG; demo.toml:
    RGB EXR) on `rig` (default configs/rigs/sim.toml); returns `out`."""
    plan = PlanConfig.model_validate(
        {
            "name": "tiny",
            "type": "isotropic",
            "theta_i_deg": [theta_i_deg],
            "theta_o_deg": list(theta_o_deg),
            "delta_phi_deg": [180.0],
            "exposures_s": [0.002, 0.016],
        }
    )
    spec = AcquireSpec(
        rig=REPO / "configs" / "rigs" / "sim.toml" if rig is None else rig,
        scene=REPO / "configs" / "scenes" / scene,
        progress=False,
        plan=plan,
    )
    assert acquire(out, spec).outcome.complete
    return out
