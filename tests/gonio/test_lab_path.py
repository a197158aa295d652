"""The lab path (issue 14): the rig file describes the instrument, the scene only the emulated
world, calibration captures are phases of a run, and calibration reads nothing from a scene.

Where a test needs the truth it comes from the scene file or the camera irradiance equation
written out here, never from the calibration code under test.
"""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from acquisition.config import (
    CameraConfig,
    PlanConfig,
    RigConfig,
    SampleConfig,
    load_rig,
)
from acquisition.operator import AutoOperator, OperatorDeclined, ScriptedOperator
from acquisition.store import RunStore
from calibration.darks import calibration_frames
from calibration.reduce import ReduceOptions, reduce_run
from gonio.pipeline import AcquireSpec, acquire, capture_calibration
from simulator.dxl import get_bus
from simulator.scene import load_scene
from simulator.world import axis_ticks
from tests.support.paths import REPO

SIM_RIG = REPO / "configs" / "rigs" / "sim.toml"
LAB_RIG = REPO / "configs" / "rigs" / "lab-example.toml"
DEMO = REPO / "configs" / "scenes" / "demo.toml"
SMALL = PlanConfig.model_validate(
    {
        "name": "lab-path",
        "type": "isotropic",
        "theta_i_deg": [30.0, 50.0],
        "theta_o_deg": [10.0, 40.0],
        "delta_phi_deg": [180.0, 120.0],
        "exposures_s": [0.002, 0.016],
    }
)
WITH_CALIBRATION = SMALL.model_copy(
    update={
        "calibration": PlanConfig.model_validate(
            {**SMALL.model_dump(), "calibration": {"dark": {"count": 3}, "reference": {}}}
        ).calibration
    }
)


# -- the rig file ------------------------------------------------------------------------------
def test_lab_example_states_every_key_a_real_rig_needs() -> None:
    rig = load_rig(LAB_RIG)
    raw = tomllib.loads(LAB_RIG.read_text())
    # Every description key of the camera and sample is written out (not left to defaults),
    # so the example teaches what a lab must know about its instrument.
    # (trigger_command: the folder backend's; aravis / gphoto2: those backends' own tables,
    # documented in docs/lab-setup.md §7 and checked by their tests)
    backend_only = {"trigger_command", "intrinsics", "aravis", "gphoto2"}
    for model, section in ((CameraConfig, "camera"), (SampleConfig, "sample")):
        missing = set(model.model_fields) - set(raw[section]) - backend_only
        assert not missing, (section, sorted(missing))
    for section in ("bus", "light", "reference", "calibration", "geometry", "axes"):
        assert section in raw, section
    assert rig.clock == "system" and not rig.bus.url.startswith("dxlsim")
    assert rig.camera.backend == "folder" and rig.reference is not None


def test_sim_rig_states_the_same_keys_as_a_lab_rig() -> None:
    sim, lab = tomllib.loads(SIM_RIG.read_text()), tomllib.loads(LAB_RIG.read_text())
    for section in ("camera", "sample", "reference", "calibration"):
        assert section in sim, section
    description = set(lab["camera"]) - {"folder", "timeout_s", "backend"}
    assert description <= set(sim["camera"]), sorted(description - set(sim["camera"]))


# -- calibration reads nothing from the scene -------------------------------------------------
def test_no_simulator_shortcut_in_calibration_or_the_spine() -> None:
    """No simulator-only recording, and no code in calibration/ or gonio/pipeline.py that looks
    at a scene or the simulator, apart from building the emulated devices (prepare_backends),
    giving the operator the world's hands, and freezing the scene for a resume."""
    for path in [*sorted((REPO / "calibration").glob("*.py")), REPO / "gonio" / "pipeline.py"]:
        text = path.read_text()
        assert "_record_sim_calibration_frames" not in text, path
    for path in sorted((REPO / "calibration").glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom | ast.Import):
                names = [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                names += [a.name for a in node.names]
                assert not any(n.startswith("simulator") for n in names), (path, names)
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert '"scene"' not in repr(node.value) and node.value != "scene", path
            if isinstance(node, ast.Attribute | ast.Name):
                ident = node.attr if isinstance(node, ast.Attribute) else node.id
                assert "scene" not in ident.lower() and "sim" != ident.lower(), (path, ident)
    tree = ast.parse((REPO / "gonio" / "pipeline.py").read_text())
    uses = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.value.id == "world":
                uses.add(node.attr)
    assert uses <= {"hands", "scene"}, uses


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lab") / "run"
    rig = load_rig(SIM_RIG)
    res = acquire(
        out,
        AcquireSpec(
            rig=rig,
            plan=WITH_CALIBRATION,
            scene=load_scene(DEMO),
            progress=False,
            operator=AutoOperator(),
        ),
    )
    assert res.outcome.complete
    return out


def test_calibration_is_the_same_without_the_scene(demo_run: Path, tmp_path: Path) -> None:
    """run.toml keeps the scene only to rebuild the emulators on resume: with it removed the
    samples are bit for bit the same."""
    bare = tmp_path / "bare"
    shutil.copytree(demo_run, bare)
    doc = tomllib.loads((bare / "run.toml").read_text())
    assert "scene" in doc
    del doc["scene"]
    doc["rig"].pop("scene", None)
    (bare / "run.toml").write_text(tomli_w.dumps(doc))
    a = reduce_run(demo_run, ReduceOptions(bin_px=4), out=tmp_path / "a.parquet")
    b = reduce_run(bare, ReduceOptions(bin_px=4), out=tmp_path / "b.parquet")
    assert np.array_equal(a.f, b.f) and np.array_equal(a.sigma, b.sigma)
    meta = json.loads(a.metadata["gonio.calibration"])
    assert meta["radiometry"] == "reference" and meta["dark"] == {"0.002": 3, "0.016": 3}


def test_run_records_the_rig_files_description(demo_run: Path) -> None:
    doc = tomllib.loads((demo_run / "run.toml").read_text())
    rig = load_rig(SIM_RIG)
    intr = json.loads((REPO / "configs" / "rigs" / "sim-camera.json").read_text())
    assert doc["camera"]["fx"] == intr["fx"] and doc["camera"]["resolution"] == [64, 64]
    assert doc["camera"]["white_level_dn"] == rig.camera.white_level_dn
    assert doc["camera"]["intrinsics_source"].startswith("file ")
    assert doc["sample"]["size_m"] == rig.sample.size_m
    # What the camera device reported about itself is kept apart from the description.
    assert doc["camera_device"]["model"].startswith("gonio simulated camera")


# -- a misstated description: radiometry and segmentation follow the rig file ------------------
def _pitch_run(root: Path, pitch_m: float) -> Path:
    rig = load_rig(SIM_RIG)
    rig = rig.model_copy(
        update={"camera": rig.camera.model_copy(update={"pixel_pitch_m": pitch_m})}
    )
    # The world states its true pixel pitch, so only the lab's belief differs between runs;
    # the pinhole comes from the rig's calibrated intrinsics file, so the geometry is right.
    scene = load_scene(DEMO)
    scene = scene.model_copy(
        update={"sensor": scene.sensor.model_copy(update={"pixel_pitch_m": 5e-6})}
    )
    out = root / f"pitch-{pitch_m:g}"
    res = acquire(
        out,
        AcquireSpec(
            rig=rig, plan=WITH_CALIBRATION, scene=scene, progress=False, operator=AutoOperator()
        ),
    )
    assert res.outcome.complete
    return out


def test_a_misstated_pixel_pitch_moves_certified_f_by_the_irradiance_equation(tmp_path) -> None:
    right, wrong = _pitch_run(tmp_path, 5e-6), _pitch_run(tmp_path, 10e-6)
    ra, rb = RunStore.open(right), RunStore.open(wrong)
    # Same world, same seed: the same frames; only the lab's description differs.
    assert [c.sha256 for c in ra.captures()] == [c.sha256 for c in rb.captures()]
    opts = {"bin_px": 4}

    def f(run: Path, method: str) -> np.ndarray:
        return reduce_run(run, ReduceOptions(radiometry=method, **opts), out=tmp_path / "x.pq").f

    # Camera irradiance equation: L = e·(hc/λ)·4N²/(π·QE·p²·t), so f ∝ 1/p²: stating twice the
    # true pitch makes the certified f four times too small, exactly (same frames, same σ).
    ratio = f(wrong, "certified") / f(right, "certified")
    assert np.allclose(ratio, 0.25, rtol=1e-12, atol=0), (ratio.min(), ratio.max())
    # The reference-target method measures the same nominal conversion on the target: p² is
    # common to reference and sample and cancels (to float rounding).
    ref = f(wrong, "reference") / f(right, "reference")
    assert np.allclose(ref, 1.0, rtol=1e-9, atol=0), (ref.min(), ref.max())


# -- operator, retakes, manual lamp ------------------------------------------------------------
def _servo_state(name: str, rig: RigConfig) -> dict:
    """Per servo, from the emulator: (goal, park ticks, true position, torque enable)."""
    bus = get_bus(name)
    out = {}
    for a in rig.axes:
        park = axis_ticks(a, np.radians(a.park_deg if a.park_deg is not None else a.min_deg))
        sv = bus.servo(a.id)
        out[a.id] = (sv.register("goal_position"), park, sv.true_position_ticks(),
                     sv.register("torque_enable"))  # fmt: skip
    return out


def test_an_operator_who_says_no_stops_before_any_servo_moves(tmp_path: Path) -> None:
    rig = load_rig(SIM_RIG)
    out = tmp_path / "run"
    scene = load_scene(DEMO)
    with pytest.raises(OperatorDeclined, match="cap on the camera lens"):
        acquire(
            out,
            AcquireSpec(
                rig=rig,
                plan=WITH_CALIBRATION,
                scene=scene,
                progress=False,
                operator=ScriptedOperator({"cap_lens": False}),
            ),
        )
    # Read from the emulator: every goal is still the park position it started at, the horns
    # are there, and no servo holds torque.
    state = _servo_state("sim-two-arm", rig)
    for goal, park, pos, torque in state.values():
        assert goal == park and abs(pos - park) < 0.5 and torque == 0, state
    store = RunStore.open(out)
    assert store.count("done") == 0 and store.calibration_captures() == []
    assert any("operator" in m for _, k, m in store.events() if k == "stop")


def test_cli_operator_no_is_one_line_exit_2(tmp_path: Path) -> None:
    answers = tmp_path / "answers.toml"
    answers.write_text('[answers]\ncap_lens = "no"\n')
    res = subprocess.run(
        [sys.executable, "-m", "gonio.cli", "acquire", "--rig", str(SIM_RIG), "--plan",
         str(REPO / "configs" / "plans" / "demo.toml"), "--out", str(tmp_path / "run"),
         "--answers", str(answers), "--no-progress"],
        capture_output=True, text=True, cwd=REPO, timeout=300,
    )  # fmt: skip
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and "declined" in lines[0] and "Traceback" not in res.stderr
    log = [json.loads(ln) for ln in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert not any(e["event"] in ("pose", "calibration_capture") for e in log)


def test_capture_retake_keeps_the_old_take(demo_run: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(demo_run, run)
    old = calibration_frames(run, "dark")
    assert {e["take"] for e in old} == {1}
    n = capture_calibration(run, "dark", rig_path=SIM_RIG, scene_path=DEMO,
                            operator=AutoOperator())  # fmt: skip
    assert n == 3 * 2  # the plan's count per exposure × its two exposures
    new = calibration_frames(run, "dark")
    assert {e["take"] for e in new} == {2} and len(new) == n
    assert all((run / e["path"]).exists() for e in old)  # the earlier take is kept
    store = RunStore.open(run)
    assert store.complete and store.verify() == []  # a finished run stays finished and whole


def test_manual_lamp_is_asked_for_and_drift_is_reported_uncorrected(tmp_path: Path) -> None:
    rig = load_rig(SIM_RIG)
    rig = rig.model_copy(update={"light": rig.light.model_copy(update={"url": "manual"})})
    op = AutoOperator()
    out = tmp_path / "run"
    spec = AcquireSpec(rig=rig, plan=SMALL, scene=load_scene(DEMO), progress=False, operator=op)
    res = acquire(out, spec)
    assert res.outcome.complete and op.asked == ["lamp_on"]
    meta = json.loads(reduce_run(out).metadata["gonio.calibration"])
    assert meta["light_drift_corrected"] is False
    assert any("drift is uncorrected" in n for n in meta["notes"])


def test_rig_validation_needs_optics() -> None:
    doc = tomllib.loads(LAB_RIG.read_text())
    del doc["camera"]["focal_length_m"]
    with pytest.raises(ValueError, match="focal_length_m is missing"):
        RigConfig.model_validate(doc)
