"""Issue 9, fault scenarios: each one ends SAFE (torque off on every emulated servo, lamp off —
read from the emulators, not from the driver), RECORDED (the stop reason is in the manifest) and
RESUMABLE with nothing lost (the resume completes; the keys equal the plan's grid, none twice;
every SHA-256 verifies). The checks live in tests/support/faults.py.

Where each scenario is tested (the real dynamixel_sdk over a pty in all of them):

| scenario                  | test                                                         |
|---------------------------|--------------------------------------------------------------|
| servo stops answering     | test_acquisition_faults::test_servo_that_stops_answering_... |
| hardware alert mid-move   | here: test_overload_alert_mid_move_...                       |
| light fails to turn on    | test_acquisition_faults::test_light_that_fails_to_turn_on_...|
| light dies mid-run        | test_acquisition_faults::test_light_failing_mid_run_...      |
| camera returns no frame   | here: test_camera_that_returns_no_frame_...                  |
| disk full (frames)        | here: test_disk_full_for_frames_... (injected; real tmpfs)   |
| disk full (manifest)      | here: test_disk_full_for_the_manifest_... (SQLITE_FULL)      |
| SIGTERM, SIGINT           | here: test_signal_to_gonio_acquire_... (CLI subprocess)      |
| kill -9                   | test_crash_safety (10 kills over 200 poses, CLI subprocess)  |
| a bug (any other error)   | here: test_a_bug_in_the_loop_... (safe first, then raised)   |

A servo that stops answering cannot be told to drop torque; its test shows the other three
are unpowered and that the failed torque-off is recorded. After kill -9 nothing can make the
rig safe (the host is gone); the test shows the resumed runs lose nothing.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import time
import warnings
from pathlib import Path

import pytest

from acquisition.store import RunStore
from simulator.faults import full_disk
from tests.support.faults import (
    ARRIVAL_RAD,
    EXPECTED_KEYS,
    PLAN,
    TICK_RAD,
    acquire_cmd,
    assert_all_data,
    assert_recorded,
    assert_safe,
    done_count,
    read_state,
    sim_session,
    write_plan,
    write_pty_rig,
)


def _most_moving_role(plan, n: int) -> str:
    """The axis that travels furthest from pose n-1 to pose n (the move after capture n, one
    exposure per pose): an alert armed for it is sure to find it mid-move."""
    a, b = plan.poses[n - 1].targets, plan.poses[n].targets
    return max(a, key=lambda r: abs(b[r] - a[r]))


def test_overload_alert_mid_move_stops_safely_and_resumes(tmp_path: Path) -> None:
    with sim_session(tmp_path, on_alert="stop") as s:
        n = 5
        role = _most_moving_role(s.plan, n)
        sick = s.config.axis(role).id

        def arm(k: int) -> None:
            if k == n:  # the next packet that finds the servo travelling trips it
                s.world.bus.inject_alert(sick, "overload", while_moving=True, persistent=True)

        out = s.run(on_capture=arm)
        # The alert fired during the move — not at its start, not on arrival — per the
        # emulator's own motion state (more than the 8-tick arrival tolerance from its goal).
        (fired,) = s.world.bus.fired_alerts
        assert fired.servo_id == sick and fired.moving
        assert fired.ticks_to_goal > ARRIVAL_RAD / TICK_RAD
        # And the arm really stopped short: the emulator's horn is not at the goal.
        goal = s.plan.poses[n].targets[role]
        assert abs(s.world.true_axes_rad()[role] - goal) > ARRIVAL_RAD
        assert not out.complete and "overload" in out.reason and f"servo {sick}" in out.reason
        assert s.store.count("done") == n  # nothing captured at the pose it never reached
        assert s.store.count("pending") == 0
        assert_recorded(s.store, out.reason)
        assert_safe(s.world, s.config)
        # The cause removed (the arm freed), the resume reboots the servo and completes.
        s.world.bus.clear_fault(sick)
        s.resume_and_check()


def test_camera_that_returns_no_frame_stops_safely_and_resumes(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        n = 3

        def miss(k: int) -> None:
            if k == n:
                s.world.camera_faults.fail_next(1)

        out = s.run(on_capture=miss)
        assert s.world.camera_faults.counts["camera_miss"] == 1
        assert not out.complete and "camera: no frame returned" in out.reason
        assert s.store.count("done") == n and s.store.count("pending") == 0
        assert_recorded(s.store, out.reason)
        assert_safe(s.world, s.config)
        out = s.resume_and_check()  # the camera answers again: the missed pose is re-shot
        assert out.captured == len(EXPECTED_KEYS) - n


# A frame is an EXR of ~21 kB (64×64 RGB half + header, page-rounded to 24 kB on tmpfs), so
# 64 kB of disk holds 2–3 frames and the next write fails part-way, as write(2) does.
FREE_BYTES = 64_000


@pytest.mark.parametrize("disk", ["injected", "tmpfs"])
def test_disk_full_for_frames_stops_safely_and_resumes(tmp_path: Path, disk: str, tmpfs) -> None:
    """The disk holding the frames fills up mid-run. "injected": the frame writer gets ENOSPC
    once FREE_BYTES are used (runs everywhere). "tmpfs": a real 64 KiB tmpfs mounted over the
    run's frames/ directory, so the kernel says ENOSPC; where mounting is not permitted it
    falls back to the injected disk (never a skip)."""
    with sim_session(tmp_path) as s:
        grow = tmpfs(s.store.frames, "64k") if disk == "tmpfs" else None
        if disk == "tmpfs" and grow is None:
            warnings.warn(
                "mount not permitted: the tmpfs case runs on the injected disk", stacklevel=1
            )
        if grow is not None:
            out = s.run()
        else:
            with full_disk(FREE_BYTES) as budget:
                out = s.run()
            assert budget.refused == 1
        assert not out.complete, out.reason
        assert out.reason.startswith("storage: ") and os.strerror(errno.ENOSPC) in out.reason
        assert 0 < s.store.count("done") < len(EXPECTED_KEYS)
        assert_safe(s.world, s.config)
        assert_recorded(s.store, out.reason)
        assert s.store.verify() == []  # the frames already done are intact
        if grow is not None:
            grow()  # the operator frees space
        s.resume_and_check()


def test_disk_full_for_the_manifest_stops_safely_and_resumes(tmp_path: Path) -> None:
    """SQLite itself finds the disk full ("database or disk is full", SQLITE_FULL) — on a real
    full disk it often fails before the frame writer does. Made real with SQLite's own
    `max_page_count` limit: the runner must treat it like ENOSPC, not crash past the safe
    stop."""
    with sim_session(tmp_path) as s:
        db = s.store._db  # the manifest's own connection: the limit applies to its writes
        (pages,) = db.execute("PRAGMA page_count").fetchone()
        # A capture row (pending insert, then done update with device status JSON) takes
        # about one 4 KiB page; 3 more pages let a few captures through, then SQLITE_FULL.
        db.execute(f"PRAGMA max_page_count = {pages + 3}")
        out = s.run()
        assert not out.complete and out.reason.startswith("storage: "), out.reason
        assert "full" in out.reason
        assert 0 < s.store.count("done") < len(EXPECTED_KEYS)
        assert_safe(s.world, s.config)
        # The stop event still fits in a page the events table already has; nothing reserves
        # that room, so on a disk full to the last byte the reason may reach only stderr.
        assert_recorded(s.store, out.reason)
        db.execute("PRAGMA max_page_count = 1073741823")  # space freed
        assert s.store.verify() == []
        s.resume_and_check()


# -- signals to the real CLI process --------------------------------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_to_gonio_acquire_stops_safely_and_resumes(tmp_path: Path, sig) -> None:
    """`gonio acquire` in its own process (emulators on ptys in that process); the signal
    arrives after N frames, counted by polling the manifest. The capture in progress is
    finished, the rig made safe, the reason recorded; a second `gonio acquire` completes."""
    tty, state = tmp_path / "tty", tmp_path / "state.json"
    rig = write_pty_rig(tmp_path / "rig.toml", tty)
    plan = write_plan(tmp_path / "plan.toml", PLAN)
    out = tmp_path / "run"
    cmd = acquire_cmd(rig, plan, out, tty, state)
    n = 4
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while done_count(out) < n and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        assert proc.poll() is None, proc.stderr.read()  # still running: the signal is mid-run
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    reason = f"interrupted ({sig.name})"
    assert proc.returncode == 3, err  # the CLI's "incomplete run" exit code
    st = read_state(state)
    assert st["pty_errors"] == []
    # SAFE, from the emulators in the acquisition process at its exit.
    assert set(st["torque_enable"].values()) == {0}, st
    assert st["light_on"] is False
    store = RunStore.open(out)
    try:
        assert_recorded(store, reason)
        assert n <= store.count("done") < len(EXPECTED_KEYS)
        assert store.count("pending") == 0  # the capture in progress was finished, not cut
    finally:
        store.close()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    st = read_state(state)
    assert set(st["torque_enable"].values()) == {0} and st["light_on"] is False
    store = RunStore.open(out)
    try:
        assert_all_data(store)
    finally:
        store.close()


def test_a_bug_in_the_loop_still_makes_the_rig_safe_then_surfaces(tmp_path: Path) -> None:
    # Not a device fault but a programming error (here: the camera wrapper raises a
    # RuntimeError): the runner must not guess, so the exception propagates — but only after
    # the lamp is off and torque is off, and the reason is in the manifest.
    with sim_session(tmp_path) as s:
        n = 2

        def bug(k: int) -> None:
            if k == n:
                raise RuntimeError("simulated bug")

        with pytest.raises(RuntimeError, match="simulated bug"):
            s.run(on_capture=bug)
        assert s.store.count("done") == n and s.store.count("pending") == 0
        assert_recorded(s.store, "internal error: RuntimeError: simulated bug")
        assert_safe(s.world, s.config)
        s.resume_and_check()
