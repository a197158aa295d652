"""The structured run log (`log.jsonl`): every line parses, and its events match the manifest
— the SQLite rows are the ground truth for what was captured and why the run stopped."""

from __future__ import annotations

import json
from pathlib import Path

import tomli_w

from acquisition.config import PlanConfig, load_rig
from acquisition.plans import build_plan
from acquisition.protocols import DeviceFault
from acquisition.rig import build_rig
from acquisition.runlog import RunLog, read_log
from acquisition.runner import _StopFlag, run_acquisition
from acquisition.store import RunStore
from gonio.backends import prepare_backends
from gonio.pipeline import sample_levels_decoder
from tests.support.paths import REPO

PLAN = PlanConfig(
    name="log",
    theta_i_deg=(20.0, 50.0),
    theta_o_deg=(0.0, 40.0),
    delta_phi_deg=(180.0, 90.0),
    exposure_mode="auto",
)


def _lines(run: Path) -> list[dict]:
    text = (run / "log.jsonl").read_text()
    assert text.endswith("\n")
    out = []
    for line in text.splitlines():
        rec = json.loads(line)  # every line is one complete JSON object
        assert isinstance(rec, dict)
        assert {"ts", "level", "event"} <= rec.keys()
        assert rec["level"] in ("info", "warning", "error")
        out.append(rec)
    return out


def _session(tmp: Path, plan: PlanConfig):
    rig_cfg = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    world = prepare_backends(rig_cfg)
    rig = build_rig(rig_cfg)
    doc = {"rig": rig_cfg.model_dump(mode="json", exclude_none=True)}
    store = RunStore.create(tmp / "run", tomli_w.dumps(doc))
    levels = sample_levels_decoder(rig.camera.describe(), rig_cfg, world.scene.sample.size_m)
    return rig_cfg, rig, store, levels


def test_log_matches_manifest_across_an_interruption(tmp_path: Path) -> None:
    rig_cfg, rig, store, levels = _session(tmp_path, PLAN)
    plan = build_plan(rig_cfg, PLAN)
    flag = _StopFlag()
    out = run_acquisition(
        store,
        rig,
        plan,
        progress=False,
        stop=flag,
        frame_levels=levels,
        on_capture=lambda n: flag.set("interrupted (test)") if n == 4 else None,
    )
    rig.close()
    assert not out.complete
    first = {(c.pose_index, c.bracket_index): c.exposure_s for c in store.captures()}
    # Forget the stored sample-region stats, as for frames adopted after a kill -9 (their rows
    # never got metadata): the resume must recompute them from the frames on disk.
    import sqlite3

    with sqlite3.connect(store.root / "manifest.sqlite") as db:
        db.execute("UPDATE captures SET frame_meta = NULL")
    rig = build_rig(rig_cfg)
    out = run_acquisition(store, rig, plan, progress=False, frame_levels=levels)
    rig.close()
    assert out.complete, out.reason
    # The resume kept every first-session frame and only added frames: a pose interrupted
    # between brackets continued at its next bracket index instead of starting over.
    after = {(c.pose_index, c.bracket_index): c.exposure_s for c in store.captures()}
    assert {k: after[k] for k in first} == first
    # (The stop came between two brackets of one pose, so this case is really exercised.)
    assert {p for p, _ in first} & {p for p, _ in set(after) - set(first)}
    for pose in {p for p, _ in after}:
        assert sorted(b for p, b in after if p == pose) == list(
            range(sum(1 for p, _ in after if p == pose))
        )

    events = _lines(store.root)
    # Captures: the log's (pose, bracket, exposure, id, frame) are exactly the manifest's rows.
    logged = {
        (e["pose"], e["bracket"], e["exposure_s"], e["capture_id"], e["frame"])
        for e in events
        if e["event"] == "capture"
    }
    rows = {
        (c.pose_index, c.bracket_index, c.exposure_s, c.id, c.frame_path) for c in store.captures()
    }
    assert logged == rows and len(rows) >= 8
    # Each capture follows the exposure decision that asked for it.
    for i, e in enumerate(events):
        if e["event"] == "capture":
            d = events[i - 1]
            assert d["event"] == "exposure_decision"
            assert (d["pose"], d["bracket"], d["exposure_s"]) == (
                e["pose"],
                e["bracket"],
                e["exposure_s"],
            )
    # Stops: the same reasons, in the same order, as the manifest's stop events.
    assert (
        [e["reason"] for e in events if e["event"] == "stop"]
        == [m for _, k, m in store.events() if k == "stop"]
        == ["interrupted (test)", "complete"]
    )
    # The second session says it resumed, and every pose is finished exactly once overall.
    assert [e["event"] for e in events if e["event"] in ("session_start", "resume")] == [
        "session_start",
        "resume",
    ]
    done = [e["pose"] for e in events if e["event"] == "pose_done"]
    assert sorted(done) == sorted({c.pose_index for c in store.captures()})
    assert events[-1]["event"] == "session_end"


class _FailingCamera:
    """Wraps the sim camera; the third capture raises a device fault."""

    def __init__(self, cam) -> None:
        self.cam, self.n = cam, 0

    def capture(self, exposure_s):
        self.n += 1
        if self.n == 3:
            raise DeviceFault("camera stopped answering (test)")
        return self.cam.capture(exposure_s)

    def __getattr__(self, name):
        return getattr(self.cam, name)


def test_fault_is_logged_with_its_detail(tmp_path: Path) -> None:
    plan_cfg = PLAN.model_copy(update={"exposure_mode": "fixed", "exposures_s": (0.002,)})
    rig_cfg, rig, store, _ = _session(tmp_path, plan_cfg)
    rig.camera = _FailingCamera(rig.camera)
    out = run_acquisition(store, rig, build_plan(rig_cfg, plan_cfg), progress=False)
    rig.close()
    assert not out.complete and "camera stopped answering" in out.reason
    events = _lines(store.root)
    faults = [e for e in events if e["event"] == "fault"]
    assert len(faults) == 1 and faults[0]["level"] == "error"
    assert faults[0]["fault"] == "camera stopped answering (test)"
    # The fault happened at the pose the log last moved to.
    last_pose = [e["pose"] for e in events if e["event"] == "pose"][-1]
    assert faults[0]["pose"] == last_pose
    assert [e["reason"] for e in events if e["event"] == "stop"] == [
        m for _, k, m in store.events() if k == "stop"
    ]
    assert sum(e["event"] == "capture" for e in events) == store.count("done") == 2


def test_partial_last_line_is_cut_and_earlier_lines_are_kept(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    log = RunLog(path)
    for i in range(3):
        log.emit("capture", pose=i, exposure_s=float("nan") if i == 1 else 0.002)
    log.close()
    before = path.read_bytes()
    # A power cut mid-write leaves half a line.
    with open(path, "ab") as fh:
        fh.write(b'{"ts": "2026-11-23T00:00:00", "event": "capt')
    log = RunLog(path)
    log.emit("resume")
    log.close()
    after = path.read_bytes()
    assert after.startswith(before)  # earlier lines untouched, byte for byte
    events = [json.loads(line) for line in after.decode().splitlines()]
    assert [e["event"] for e in events] == ["capture"] * 3 + ["resume"]
    assert events[1]["exposure_s"] is None  # NaN is not JSON: written as null
    assert read_log(tmp_path) == events
