"""Faults on the simulated rig: the run completes through transient faults and stops safely on
real ones, recording why, and resumes once the fault is cleared.

Real parts throughout: the real dynamixel_sdk talks to the Protocol 2.0 emulator over a
pseudo-terminal (simulator.dxl.transport.PtyTransport), as on a lab rig's /dev/ttyUSB0; the
light is driven by the real SerialLight against the light emulator; frames are real files in
a real SQLite manifest. The expected (pose, bracket) keys come from the plan's grid
(θ_i × θ_o × Δφ × brackets), counted here independently of the runner.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import tomli_w

from acquisition.config import load_rig
from acquisition.dynamixel import HardwareAlert
from acquisition.plans import build_plan, park_targets
from acquisition.rig import build_rig
from acquisition.runner import _StopFlag, run_acquisition
from acquisition.store import RunStore
from gonio.backends import prepare_backends
from simulator.dxl import ReplyFaults
from tests.support.faults import (
    ARRIVAL_RAD,
    EXPECTED_KEYS,
    PLAN,
    REPO,
    TICK_RAD,
    assert_recorded,
    expected_keys,
    sim_session,
)
from tests.support.faults import assert_all_data as _assert_all_data
from tests.support.faults import assert_safe as _safe_state

# 3 × 6 × 2 = 36 poses, all reachable: ≈ 500 status packets, so 1 % faults
# occur (the test checks that retries happened).
BIG_PLAN = PLAN.model_copy(update={"theta_o_deg": (0.0, 10.0, 30.0, 45.0, 65.0, 80.0)})
_expected_keys = expected_keys


def test_one_percent_packet_faults_complete_with_all_data(tmp_path: Path) -> None:
    with sim_session(tmp_path, plan=BIG_PLAN) as s:
        # 0.5 % dropped + 0.5 % corrupted status packets, on every servo.
        s.world.bus.set_reply_faults(ReplyFaults(drop_p=0.005, bad_crc_p=0.005))
        rig = s.rig()
        try:
            outcome = run_acquisition(s.store, rig, s.plan, progress=False)
            retries = rig.axes["light_theta"].bus.stats["retries"]
        finally:
            rig.close()
        assert outcome.complete, outcome.reason
        _assert_all_data(s.store, _expected_keys(BIG_PLAN))
        # The faults really happened and were retried (else this test proves nothing).
        assert retries > 0, retries
        # Every capture's measured axes are where the plan commanded, within arrival tolerance.
        for c in s.store.captures():
            for role, target in c.axes_commanded.items():
                assert abs(c.axes_measured[role] - target) <= ARRIVAL_RAD + 1e-12, role


def test_overload_alert_stops_safely_then_resumes(tmp_path: Path) -> None:
    with sim_session(tmp_path, on_alert="stop") as s:
        sick = s.config.axis("camera_theta").id
        stop_at = 4

        def inject(n: int) -> None:
            if n == stop_at:  # mid-run: the servo trips at once and stays tripped
                s.world.bus.inject_alert(sick, "overload", persistent=True)

        out = s.run(on_capture=inject)
        assert not out.complete
        assert "overload" in out.reason and f"servo {sick}" in out.reason
        assert ("stop", out.reason) in s.events()
        assert s.store.count("done") == stop_at  # nothing captured after the alert
        _safe_state(s.world, s.config)
        # The healthy arms were parked; the tripped servo (torque off) stays where it stopped.
        park = park_targets(s.config)
        true = s.world.true_axes_rad()
        for a in s.config.axes:
            if a.id != sick:
                assert abs(true[a.role] - park[a.role]) <= ARRIVAL_RAD + TICK_RAD, (
                    a.role,
                    s.events(),
                )
        # Fault not cleared: the rig refuses to start, naming the servo.
        with pytest.raises(HardwareAlert, match=f"servo {sick}.*overload"):
            s.rig()
        # Cause removed: the resumed run reboots the tripped servo and completes.
        s.world.bus.clear_fault(sick)
        out = s.run()
        assert out.complete, out.reason
        assert any(k == "recover" and f"servo {sick}" in m for k, m in s.events())
        _assert_all_data(s.store)
        _safe_state(s.world, s.config)


def test_light_that_fails_to_turn_on_stops_safely(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        s.world.light.fail_to_turn_on = True
        out = s.run()
        assert not out.complete and "LAMP_FAIL" in out.reason
        assert_recorded(s.store, out.reason)
        assert s.store.count("done") == 0
        _safe_state(s.world, s.config)
        s.world.light.fail_to_turn_on = False  # lamp replaced; the latched fault stays until CLR
        s.resume_and_check()


def test_light_failing_mid_run_stops_before_the_next_pose(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:

        def lamp_dies(n: int) -> None:
            if n == 3:
                s.world.light.is_on = False
                s.world.light.fault = "LAMP_FAIL"

        out = s.run(on_capture=lamp_dies)
        assert not out.complete and "light is off" in out.reason and "LAMP_FAIL" in out.reason
        assert s.store.count("done") == 3
        assert_recorded(s.store, out.reason)
        _safe_state(s.world, s.config)
        s.resume_and_check()  # the lamp strikes again on resume


def test_servo_that_stops_answering_stops_safely(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        dead = s.config.axis("light_phi").id

        def unplug(n: int) -> None:
            if n == 2:
                s.world.bus.set_reply_faults(ReplyFaults(drop_p=1.0), servo_id=dead)

        out = s.run(on_capture=unplug)
        assert not out.complete
        assert f"servo {dead}" in out.reason or f"ID {dead}" in out.reason
        assert ("stop", out.reason) in s.events()
        assert s.store.count("done") == 2
        # Every other servo is safe; the dead one could not be told, and the manifest says so.
        _safe_state(s.world, s.config, skip_torque=frozenset({dead}))
        assert any(k == "safe-stop" and "torque off failed" in m for k, m in s.events())
        # Reconnected: the resume completes with nothing lost, and all four end unpowered.
        s.world.bus.set_reply_faults(ReplyFaults(), servo_id=dead)
        s.resume_and_check()


def test_interrupt_then_resume_over_pty(tmp_path: Path) -> None:
    """A Ctrl-C stop (flag) finishes the capture in progress; the resume completes."""
    with sim_session(tmp_path) as s:
        flag = _StopFlag()
        out = s.run(
            stop=flag, on_capture=lambda n: flag.set("interrupted (test)") if n == 5 else None
        )
        assert out.reason == "interrupted (test)" and s.store.count("done") == 5
        _safe_state(s.world, s.config)
        out = s.run()
        assert out.complete and out.captured == len(EXPECTED_KEYS) - 5
        _assert_all_data(s.store)


# -- tethered-folder camera ---------------------------------------------------------------------
def _drop_later(folder: Path, name: str, payload: bytes, delay_s: float, chunks: int = 4) -> None:
    """Play vendor software: after `delay_s`, write the file in slow chunks (the camera must
    wait until the size is stable, not return a half-written file)."""
    import threading
    import time

    def run() -> None:
        time.sleep(delay_s)
        step = max(1, len(payload) // chunks)
        with open(folder / name, "wb") as fh:
            for k in range(0, len(payload), step):
                fh.write(payload[k : k + step])
                fh.flush()
                time.sleep(0.05)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_folder_camera_returns_the_new_file_untouched(tmp_path: Path) -> None:
    from acquisition.cameras import FolderCamera
    from acquisition.protocols import Camera

    (tmp_path / "old.nef").write_bytes(b"stale frame")  # already there: never picked up
    (tmp_path / "x.nef.part").write_bytes(b"partial")  # a writer's temp name: ignored
    payload = bytes(range(256)) * 40
    triggered = []
    cam = FolderCamera(tmp_path, trigger=triggered.append, timeout_s=5.0, stable_s=0.15)
    assert isinstance(cam, Camera)
    t = _drop_later(tmp_path, "IMG_0001.NEF", payload, delay_s=0.1)
    frame = cam.capture(0.01)
    t.join()
    assert triggered == [0.01]
    assert frame.data == payload and frame.suffix == ".nef"
    assert frame.metadata["source_file"] == "IMG_0001.NEF"
    # The next capture waits for the next new file, not the one already returned.
    t = _drop_later(tmp_path, "IMG_0002.NEF", b"second", delay_s=0.05, chunks=1)
    assert cam.capture(0.02).data == b"second"
    t.join()


def test_folder_camera_times_out_with_a_device_fault(tmp_path: Path) -> None:
    from acquisition.cameras import FolderCamera
    from acquisition.protocols import DeviceFault

    cam = FolderCamera(tmp_path, timeout_s=0.3)
    with pytest.raises(DeviceFault, match="no new file within 0.3 s"):
        cam.capture(0.01)


def test_folder_backend_in_a_run_stores_vendor_bytes(tmp_path: Path) -> None:
    """The "folder" backend from CAMERA_BACKENDS, triggered by a command, in a real run; a
    missing frame stops the run safely."""
    import sys

    folder = tmp_path / "tether"
    folder.mkdir()
    script = tmp_path / "shutter.py"
    # Writes one file per trigger whose content names the exposure: the test can check that
    # each stored frame is the vendor's file for that capture, byte for byte.
    script.write_text(
        "import sys, time, pathlib\n"
        "d = pathlib.Path(sys.argv[1])\n"
        "n = len(list(d.iterdir()))\n"
        "(d / f'DSC{n:04d}.ARW').write_bytes(f'raw frame {n} at {sys.argv[2]} s'.encode())\n"
    )
    base = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    cam = base.camera.model_copy(
        update={
            "backend": "folder",
            "folder": str(folder),
            "trigger_command": (sys.executable, str(script), str(folder), "{exposure_s}"),
            "timeout_s": 5.0,
        }
    )
    cfg = base.model_copy(update={"camera": cam})
    world = prepare_backends(cfg)
    plan_cfg = PLAN.model_copy(update={"theta_i_deg": (20.0,), "delta_phi_deg": (180.0,)})
    plan = build_plan(cfg, plan_cfg)
    store = RunStore.create(tmp_path / "run", tomli_w.dumps({"note": "folder"}))
    rig = build_rig(cfg)
    try:
        out = run_acquisition(store, rig, plan, progress=False)
    finally:
        rig.close()
    assert out.complete, out.reason
    got = sorted((store.root / c.frame_path).read_bytes() for c in store.captures())
    assert got == [b"raw frame 0 at 0.002 s", b"raw frame 1 at 0.002 s"]
    assert all(c.frame_path.endswith(".arw") for c in store.captures())
    store.close()
    # A camera that produces nothing: the run stops safely with the reason.
    cfg2 = cfg.model_copy(
        update={"camera": cam.model_copy(update={"trigger_command": ("true",), "timeout_s": 0.3})}
    )
    world = prepare_backends(cfg2)
    store = RunStore.create(tmp_path / "run2", tomli_w.dumps({"note": "folder"}))
    rig = build_rig(cfg2)
    try:
        out = run_acquisition(store, rig, build_plan(cfg2, plan_cfg), progress=False)
    finally:
        rig.close()
    assert not out.complete and "no new file" in out.reason
    assert ("stop", out.reason) in [(k, m) for _, k, m in store.events()]
    _safe_state(world, cfg2)
    store.close()


def test_overload_with_on_alert_reboot_recovers_and_completes(tmp_path: Path) -> None:
    """on_alert = "reboot": the driver reboots the servo, restores torque and goal, and the
    run goes on (a transient overload, e.g. a cable snag)."""
    with sim_session(tmp_path, on_alert="reboot") as s:
        sick = s.config.axis("light_phi").id

        def inject(n: int) -> None:
            if n == 4:
                s.world.bus.inject_alert(sick, "overload")  # not persistent: REBOOT clears it

        rig = s.rig()
        try:
            out = run_acquisition(s.store, rig, s.plan, progress=False, on_capture=inject)
            reboots = rig.axes["light_phi"].bus.stats["reboots"]
        finally:
            rig.close()
        assert out.complete, out.reason
        assert reboots == 1
        _assert_all_data(s.store)
        # Profile registers are RAM: after the reboot the axis must still move at the
        # configured profile (the emulator's register is the truth).
        ax = s.config.axis("light_phi")
        assert s.world.bus.servo(sick).register("profile_velocity") == ax.profile_velocity


def test_dead_servo_at_start_is_named_and_the_port_is_released(tmp_path: Path) -> None:
    from acquisition.protocols import DeviceFault

    with sim_session(tmp_path) as s:
        dead = s.config.axis("camera_theta")
        s.world.bus.set_reply_faults(ReplyFaults(drop_p=1.0), servo_id=dead.id)
        with pytest.raises(DeviceFault, match=f"axis camera_theta: servo {dead.id} does not"):
            s.rig()
        # Reconnected: the pty was opened exclusively, so this also proves it was closed.
        s.world.bus.set_reply_faults(ReplyFaults(), servo_id=dead.id)
        out = s.run()
        assert out.complete, out.reason
        _assert_all_data(s.store)
