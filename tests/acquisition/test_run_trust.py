"""A run directory is data, never instructions (issue 22, item 1): resuming a run someone sent
needs this machine's rig file, and a run whose frozen rig names other devices or commands is
refused in one line — the command stored in it is never run. Real parts: the gonio CLI in a
subprocess, a real SQLite manifest, the real simulated rig."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from acquisition.config import load_plan, load_rig
from acquisition.run_document import RunDocument, device_difference
from acquisition.store import RunStore
from tests.support.paths import REPO

SIM_RIG = REPO / "configs" / "rigs" / "sim.toml"
PLAN = REPO / "configs" / "plans" / "demo.toml"


def _hostile_run(tmp_path: Path, **camera) -> tuple[Path, Path]:
    """An unfinished run whose run.toml swaps the simulated camera for a tethered-folder camera
    that runs a shell command per frame (the attack), and the file that command would make."""
    rig = load_rig(SIM_RIG)
    proof = tmp_path / "PWNED"
    drop = tmp_path / "drop"
    drop.mkdir()
    bad = rig.camera.model_copy(
        update={
            "backend": "folder",
            "folder": str(drop),
            "trigger_command": ("sh", "-c", f"touch {proof}"),
            **camera,
        }
    )
    doc = RunDocument.new(
        rig.model_copy(update={"camera": bad}), load_plan(PLAN), version="test", device={}
    )
    out = tmp_path / "sent-run"
    RunStore.create(out, doc.toml()).close()
    return out, proof


def _gonio(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "gonio.cli", "acquire", *args, "--no-progress", "--yes"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=cwd)


def test_resuming_a_sent_run_never_runs_its_command(tmp_path: Path) -> None:
    out, proof = _hostile_run(tmp_path)
    # Without the rig file: refused, nothing run.
    res = _gonio("--out", str(out), cwd=tmp_path)
    assert res.returncode != 0 and "needs --rig" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    # With this machine's rig file: the difference is named, in one line, nothing run.
    res = _gonio("--out", str(out), "--rig", str(SIM_RIG), "--plan", str(PLAN), cwd=tmp_path)
    assert res.returncode != 0, res.stdout
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "camera.backend" in lines[0], res.stderr
    assert not proof.exists()
    assert RunStore.open(out).count("done") == 0  # nothing was captured either


@pytest.mark.parametrize(
    ("section", "change"),
    [
        (
            "bus.url",
            lambda r: r.model_copy(
                update={"bus": r.bus.model_copy(update={"url": "/dev/ttyUSB0"})}
            ),
        ),
        (
            "light.url",
            lambda r: r.model_copy(
                update={"light": r.light.model_copy(update={"url": "/dev/ttyACM0"})}
            ),
        ),
        (
            "axes[2].id",
            lambda r: r.model_copy(
                update={"axes": (*r.axes[:2], r.axes[2].model_copy(update={"id": 9}), *r.axes[3:])}
            ),
        ),
        ("clock", lambda r: r.model_copy(update={"clock": "system"})),
    ],
)
def test_every_device_section_is_compared(section: str, change) -> None:
    rig = load_rig(SIM_RIG)
    found = device_difference(change(rig), rig)
    assert found is not None and found[0] == section, found
    assert device_difference(rig, load_rig(SIM_RIG)) is None  # the same file agrees with itself
