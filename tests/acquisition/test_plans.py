"""Plan expansion, kinematics round trip, and travel-optimal ordering."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from acquisition.config import PlanConfig, load_rig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.motion import trapezoid_time_s
from acquisition.plans import build_plan
from tests.support.paths import REPO

RIG = load_rig(REPO / "configs" / "rigs" / "sim.toml")


def test_trapezoid_matches_kinematics_by_integration() -> None:
    # Independent check: integrate the velocity profile numerically.
    v, a = 1.5, 4.0
    for d in (0.1, 0.5, 3.0):
        t_total = float(trapezoid_time_s(d, v, a))
        ts = np.linspace(0.0, t_total, 200001)
        vel = np.minimum.reduce([a * ts, np.full_like(ts, v), a * (t_total - ts)])
        travelled = np.trapezoid(vel, ts)
        # Trapezoid rule on a piecewise-linear profile with 2e5 steps: error ≪ 1e-6 rad.
        assert abs(travelled - d) < 1e-6


@given(
    st.floats(0.0, math.radians(80)),
    st.floats(0.0, 2 * math.pi - 1e-9),
    st.floats(0.0, math.radians(80)),
    st.floats(0.0, 2 * math.pi - 1e-9),
)
def test_pose_round_trip(ti: float, pi: float, to: float, po: float) -> None:
    kin = Kinematics(RIG)
    pose = Pose(ti, pi, to, po)
    try:
        targets = kin.targets(pose)
    except Unreachable:
        return
    back = kin.pose(targets)
    # Directions, not angles, are compared: φ is undefined at θ = 0.
    assert np.allclose(back.wi, pose.wi, atol=1e-12)
    assert np.allclose(back.wo, pose.wo, atol=1e-12)


def test_ordering_beats_raster() -> None:
    cfg = PlanConfig(
        theta_i_deg=(10, 30, 50, 70),
        theta_o_deg=(0, 15, 30, 45, 60, 75),
        delta_phi_deg=(180, 135, 90, 45),
        order="nearest",
    )
    plan = build_plan(RIG, cfg)
    raster = build_plan(RIG, cfg.model_copy(update={"order": "raster"}))
    assert raster.move_time_s == raster.raster_move_time_s
    # Same set of poses either way.
    assert sorted(p.index for p in plan.poses) == sorted(p.index for p in raster.poses)
    assert plan.move_time_s < raster.move_time_s
