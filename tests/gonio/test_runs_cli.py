"""`gonio runs list`, `gonio runs show` and `gonio rig check` against runs and a rig whose truth is
known independently: capture counts from the plan grid, stop reasons from faults injected
here, corrupted frames made here, servo registers read straight from the emulator."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from acquisition.config import PlanConfig, load_rig
from acquisition.plans import build_plan
from acquisition.rig import build_rig
from acquisition.run_document import RunDocument
from acquisition.runner import run_acquisition
from acquisition.store import RunStore
from gonio.backends import prepare_backends
from gonio.pipeline import AcquireSpec, acquire
from gonio.rig_check import check_rig
from gonio.runs import find_runs, summarize_run
from simulator.dxl import ReplyFaults
from tests.support.paths import REPO

SIM_RIG = REPO / "configs" / "rigs" / "sim.toml"
# 2 × 2 × 2 = 8 poses (all reachable), 1 bracket → 8 captures planned.
PLAN = PlanConfig(
    name="tiny",
    theta_i_deg=(20.0, 50.0),
    theta_o_deg=(0.0, 30.0),
    delta_phi_deg=(180.0, 90.0),
    exposures_s=(0.002,),
)
PLANNED = 2 * 2 * 2
ENV = {**os.environ, "COLUMNS": "400"}  # rich would truncate cells in a narrow pipe


def gonio(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )


@pytest.fixture(scope="module")
def runs_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("runs")
    rig = load_rig(SIM_RIG)
    acquire(root / "done-run", AcquireSpec(rig=rig, plan=PLAN, progress=False))
    # An incomplete run: the lamp dies after 3 captures.
    world = prepare_backends(rig)
    doc = RunDocument.new(rig, PLAN, version="test", device={})
    store = RunStore.create(root / "lamp-died", doc.toml())
    dev = build_rig(rig)

    def lamp_dies(n: int) -> None:
        if n == 3:
            world.light.is_on, world.light.fault = False, "LAMP_FAIL"

    try:
        run_acquisition(store, dev, build_plan(rig, PLAN), progress=False, on_capture=lamp_dies)
    finally:
        dev.close()
        store.close()
    return root


def test_summaries_match_the_runs(runs_root: Path) -> None:
    assert {p.name for p in find_runs(runs_root)} == {"done-run", "lamp-died"}
    done = summarize_run(runs_root / "done-run")
    assert (done.status, done.done, done.total) == ("complete", PLANNED, PLANNED)
    died = summarize_run(runs_root / "lamp-died")
    assert (died.status, died.done, died.total) == ("incomplete", 3, PLANNED)
    assert "LAMP_FAIL" in (died.last_stop or "")


def test_runs_list_cli(runs_root: Path) -> None:
    res = gonio("runs", "list", "--root", str(runs_root))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    done = next(ln for ln in lines if "done-run" in ln)
    died = next(ln for ln in lines if "lamp-died" in ln)
    assert " complete " in done and f"{PLANNED}/{PLANNED}" in done
    assert "incomplete" in died and f"3/{PLANNED}" in died and "LAMP_FAIL" in died


def test_runs_show_cli_reports_stop_reason_and_checksums(runs_root: Path, tmp_path: Path) -> None:
    res = gonio("runs", "show", "lamp-died", "--root", str(runs_root))
    assert res.returncode == 0, res.stderr
    assert "LAMP_FAIL" in res.stdout and "all 3 verify" in res.stdout
    assert f"3 done / {PLANNED} planned" in res.stdout
    # Corrupt one frame of a copy: show must find it and exit non-zero.
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(runs_root / "done-run", copy)
    frame = sorted((copy / "frames").iterdir())[0]
    data = bytearray(frame.read_bytes())
    data[-1] ^= 0xFF
    frame.write_bytes(bytes(data))
    res = gonio("runs", "show", str(copy))
    assert res.returncode == 4
    assert "1 problem(s)" in res.stdout and "checksum mismatch" in res.stdout


def test_runs_show_unknown_run_is_one_line(tmp_path: Path) -> None:
    res = gonio("runs", "show", str(tmp_path / "nope"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert len([ln for ln in res.stderr.splitlines() if ln.strip()]) == 1


def test_rig_check_reads_the_emulator_registers() -> None:
    rig = load_rig(SIM_RIG)
    world = prepare_backends(rig)
    sick, dead = rig.axes[1].id, rig.axes[2].id
    world.bus.inject_alert(sick, "overload")
    world.bus.set_reply_faults(ReplyFaults(drop_p=1.0), servo_id=dead)
    rows = {r.servo_id: r for r in check_rig(rig)}
    assert set(rows) == {a.id for a in rig.axes}
    for a in rig.axes:
        r, servo = rows[a.id], world.bus.servo(a.id)
        if a.id == dead:
            assert not r.ok and f"{dead}" in r.problem and r.firmware is None
            continue
        assert r.firmware == servo.register("firmware_version")
        assert r.voltage_V == servo.register("present_input_voltage") / 10.0
        assert r.temperature_C == servo.register("present_temperature")
        assert r.limits_ticks == (
            servo.register("min_position_limit"),
            servo.register("max_position_limit"),
        )
        assert r.model == a.model  # the emulator was built from the config's model names
        if a.id == sick:
            assert not r.ok and r.hardware_error == ["overload"]
        else:
            assert r.ok and r.hardware_error == []
    # Read-only: the tripped servo was not rebooted by the check.
    assert world.bus.servo(sick).register("hardware_error_status") != 0


def test_rig_check_cli() -> None:
    res = gonio("rig", "check", "--rig", str(SIM_RIG))
    assert res.returncode == 0, res.stderr
    rows = [ln for ln in res.stdout.splitlines() if "XM430-W350" in ln]
    assert len(rows) == 4 and all(" OK " in ln for ln in rows)
