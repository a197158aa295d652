"""Plans for the new models (issue 19 item 4): the anisotropic plan turns the sample through ≥ 4
orientations, the retro-reflection plan reaches as close to the light as the rig's
min_separation_deg allows and records the gap, and the coverage report says which regions a
model needs and which a plan left empty."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquisition.config import load_plan, load_rig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.plans import (
    anisotropic_plan_config,
    anisotropic_poses,
    build_plan,
    expand_grid,
    plan_coverage,
    retro_plan_config,
    retro_poses,
)
from brdfdata import coverage
from brdfdata.directions import spherical_to_vector
from fitting import models
from tests.support.paths import REPO

INPLANE = load_rig(REPO / "configs" / "rigs" / "inplane.toml")
TWO_ARM = load_rig(REPO / "configs" / "rigs" / "sim.toml")
THETA_O = [float(x) for x in range(0, 81, 5)]


def _sep_deg(pose_deg) -> float:
    ti, pi, to, po = np.radians(pose_deg)
    a, b = spherical_to_vector(ti, pi), spherical_to_vector(to, po)
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


@pytest.mark.parametrize("rig", [INPLANE, TWO_ARM], ids=["inplane-turntable", "two-arm"])
def test_anisotropic_plan_turns_the_sample_through_four_orientations(rig):
    cfg = anisotropic_plan_config("a", (30.0, 50.0), THETA_O, (0.0, 45.0, 90.0, 135.0))
    plan = build_plan(rig, cfg)
    assert len(plan.poses) == len(expand_grid(cfg)) == 2 * 4 * len(THETA_O) and not plan.skipped
    # the orientation of the plane of incidence in the sample frame takes 4 values mod 180°
    psi = {round(math.degrees(p.pose.phi_i) % 180.0, 6) for p in plan.poses}
    assert psi == {0.0, 45.0, 90.0, 135.0}
    if rig is INPLANE:  # ... which the turntable makes: sample_azimuth = −ψ
        turns = {round(math.degrees(p.targets["sample_azimuth"]), 6) for p in plan.poses}
        assert turns == {0.0, -45.0, -90.0, -135.0}
    # every pose is in its plane of incidence on the specular side
    for p in plan.poses:
        dphi = math.degrees(p.pose.phi_o - p.pose.phi_i) % 360.0
        assert p.pose.theta_o == 0.0 or abs(dphi - 180.0) < 1e-6
    with pytest.raises(ValueError, match="4 sample orientations"):
        anisotropic_poses((30.0,), THETA_O, (0.0, 90.0, 180.0, 270.0))  # only 2 mod 180°


@pytest.mark.parametrize("rig", [INPLANE, TWO_ARM], ids=["inplane", "two-arm"])
def test_retro_plan_reaches_the_occlusion_limit_and_records_the_gap(rig):
    sep = rig.geometry.min_separation_deg
    cfg, gap = retro_plan_config(rig, (20.0, 40.0, 60.0))
    plan = build_plan(rig, cfg)
    assert gap == sep and plan.retro_gap_deg == pytest.approx(sep, abs=1e-9)
    assert not plan.skipped  # every pose of the rings is reachable
    seps = np.array([_sep_deg(p.pose.deg()) for p in plan.poses])
    assert np.min(seps) == pytest.approx(sep, abs=1e-9)  # as close as the rig allows ...
    assert np.all(seps >= sep - 1e-9)
    # ... and no closer: the same ring at half the gap is occluded
    kin = Kinematics(rig)
    with pytest.raises(Unreachable, match="min_separation_deg"):
        closer, _ = retro_poses((40.0,), sep / 2, (0.0,), ring_angles_deg=(0.0,))
        kin.check(Pose.from_deg(*closer[0]))
    n_rings = 2 if rig.geometry.preset == "inplane" else 4
    assert len(plan.poses) == 3 * 7 * n_rings - sum(
        1 for ti in (20.0, 40.0, 60.0) for off in (0, 1, 2, 4, 8, 15, 25) if ti + sep + off > 85
    )
    report = plan_coverage(expand_grid(cfg, rig), models.entry("oren-nayar").needs)
    assert report.retro_gap_deg == pytest.approx(sep, abs=1e-9)
    assert "retro" not in report.missing


def test_shipped_model_plans_load_and_build_on_both_rigs():
    for name in ("anisotropic", "retro"):
        cfg = load_plan(REPO / "configs" / "plans" / f"{name}.toml")
        for rig in (INPLANE, TWO_ARM):
            plan = build_plan(rig, cfg)
            assert len(plan.poses) == len(expand_grid(cfg, rig)) and not plan.skipped
    # the shipped files lay out what their comments say
    a = load_plan(REPO / "configs" / "plans" / "anisotropic.toml")
    gen = anisotropic_poses((30.0, 50.0), THETA_O, (0.0, 45.0, 90.0, 135.0))
    np.testing.assert_allclose(np.array(expand_grid(a)), np.array(gen), atol=1e-6)
    r = load_plan(REPO / "configs" / "plans" / "retro.toml")
    gen_r, gap = retro_poses((20.0, 40.0, 60.0), 5.0, ring_angles_deg=(0.0, 180.0))
    np.testing.assert_allclose(np.array(expand_grid(r, INPLANE)), np.array(gen_r), atol=1e-6)
    assert build_plan(INPLANE, r).retro_gap_deg == pytest.approx(gap) == 5.0
    with pytest.raises(ValueError, match="4 sample orientations"):
        a.model_validate({**a.model_dump(), "orientations_deg": (0.0, 90.0)})


def test_coverage_says_what_a_model_needs_and_the_plan_left_empty():
    iso_inplane = build_plan(TWO_ARM, load_plan(REPO / "configs" / "plans" / "inplane.toml"))
    poses = [p.pose.deg() for p in iso_inplane.poses]
    aniso_needs = models.entry("torrance-sparrow-anisotropic").needs
    assert "orientations" in aniso_needs
    # an in-plane plan at one sample orientation cannot determine an anisotropic lobe ...
    rep = plan_coverage(poses, aniso_needs)
    assert rep.missing == ["orientations"]
    assert any("orientations: 1 orientation bins" in line for line in rep.lines())
    # ... the anisotropic plan can; it leaves the retro region empty, which Oren-Nayar needs
    cfg = expand_grid(load_plan(REPO / "configs" / "plans" / "anisotropic.toml"))
    assert plan_coverage(cfg, aniso_needs).missing == []
    on = plan_coverage(cfg, models.entry("oren-nayar").needs)
    assert "retro" in on.missing
    assert {r.region: r.status for r in on.regions}["retro"] == "empty"
    # every registered model's needs are known regions
    for name in models.names():
        assert set(models.entry(name).needs) <= set(coverage.REGIONS), name
    with pytest.raises(ValueError, match="unknown coverage region"):
        coverage.coverage_report(["everywhere"], np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]))


def test_coverage_regions_count_what_they_say():
    # hand-made pairs, one per region: the mirror direction (θ_h = 0), 17.5° off it in plane
    # (θ_h = 17.5°), grazing on the light's side (θ_h = 45°), 5° from retro (θ_h = 42.5°), and out
    # of the plane (θ_h = 42.6°)
    wi = spherical_to_vector(np.radians([30, 30, 80, 40, 50]), np.radians([0, 0, 0, 0, 0]))
    wo = spherical_to_vector(np.radians([30, 65, 10, 45, 55]), np.radians([180, 180, 0, 0, 90]))
    rep = coverage.coverage_report(coverage.REGIONS, wi, wo)
    counts = {r.region: r.count for r in rep.regions}
    assert counts["specular"] == 1 and counts["off-specular"] == 1
    assert counts["grazing"] == 1 and counts["retro"] == 1 and counts["out-of-plane"] == 1
    assert rep.retro_gap_deg == pytest.approx(5.0, abs=1e-9)
    assert all(r.status in ("sparse", "empty") for r in rep.regions)  # < 8 pairs each


def test_gonio_plan_describes_a_plan_and_what_a_model_needs_of_it():
    import subprocess
    import sys

    def gonio(*args):
        cmd = [sys.executable, "-m", "gonio.cli", "plan", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=REPO)

    # an in-plane plan at one orientation: an anisotropic model's orientations are missing
    res = gonio("--plan", "configs/plans/inplane.toml", "--model", "ward")
    assert res.returncode == 0, res.stderr
    text = " ".join(res.stdout.split())  # rich wraps at the terminal width
    assert "orientations: 1 orientation bins (need ≥ 4): sparse" in text
    assert "warning: this plan leaves orientations sparse" in text
    # the anisotropic plan has them: no warning
    res = gonio("--plan", "configs/plans/anisotropic.toml", "--model", "ward")
    assert res.returncode == 0 and "warning" not in res.stdout
    # the retro plan reports how close it gets to the light
    res = gonio("--plan", "configs/plans/retro.toml", "--model", "oren-nayar")
    assert "gap 5.00 deg" in " ".join(res.stdout.split())
    # an unknown model is one line
    res = gonio("--plan", "configs/plans/retro.toml", "--model", "nope")
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert [ln for ln in res.stderr.splitlines() if ln.strip()][0].startswith(
        "error: unknown model"
    )
