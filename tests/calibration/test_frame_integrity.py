"""Integrity where data is used (issue 22, item 2): calibration checks every frame against the
SHA-256 the manifest recorded at capture. Two swapped pose frames are skipped with a counted
warning (or stop the calibration with --strict), never calibrated as each other's pose; a
changed dark frame stops it. Real parts: a simulated run (real EXR frames, SQLite manifest)
and the gonio CLI in a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from acquisition.config import load_plan, load_rig
from acquisition.operator import AutoOperator
from acquisition.store import RunStore
from gonio.pipeline import AcquireSpec, acquire
from tests.support.paths import REPO

PLAN = """
name = "integrity"
theta_i_deg = [30.0]
theta_o_deg = [0.0, 30.0, 50.0]
delta_phi_deg = [180.0]
exposures_s = [0.004]
[calibration.dark]
count = 2
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("integrity")
    (root / "plan.toml").write_text(PLAN)
    out = root / "run"
    spec = AcquireSpec(
        rig=load_rig(REPO / "configs" / "rigs" / "sim.toml"),
        plan=load_plan(root / "plan.toml"),
        operator=AutoOperator(),
        progress=False,
        announce=False,
    )
    assert acquire(out, spec).outcome.complete
    return out


def _copy_run(run: Path, dest: Path) -> Path:
    subprocess.run(["cp", "-a", str(run), str(dest)], check=True)
    return dest


def _calibrate(run: Path, *extra: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "gonio.cli", "calibrate", str(run), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def _swap(a: Path, b: Path) -> None:
    tmp = a.with_name(a.name + ".swap")
    os.replace(a, tmp)
    os.replace(b, a)
    os.replace(tmp, b)


def test_swapped_pose_frames_are_never_calibrated_as_each_other(run: Path, tmp_path: Path) -> None:
    good = _copy_run(run, tmp_path / "good")
    res = _calibrate(good)
    assert res.returncode == 0, res.stderr
    n_good = pq.read_metadata(good / "samples.parquet").num_rows

    bad = _copy_run(run, tmp_path / "bad")
    with RunStore.open(bad) as store:
        caps = list(store.captures("done"))
    first, second = caps[0], caps[-1]  # two different poses
    assert first.pose_index != second.pose_index
    _swap(bad / first.frame_path, bad / second.frame_path)

    res = _calibrate(bad)
    assert res.returncode == 0, res.stderr
    assert "SHA-256 differs" in res.stderr and "2 capture(s) skipped" in res.stderr, res.stderr
    meta = pq.read_schema(bad / "samples.parquet").metadata
    skipped = json.loads(meta[b"gonio.skipped_captures"])
    assert skipped["count"] == 2
    assert {c["capture_id"] for c in skipped["captures"]} == {first.id, second.id}
    # Fewer samples than the intact run: the two poses' samples are left out, not mislabelled.
    assert pq.read_metadata(bad / "samples.parquet").num_rows < n_good

    strict = _copy_run(run, tmp_path / "strict")
    _swap(strict / first.frame_path, strict / second.frame_path)
    res = _calibrate(strict, "--strict")
    assert res.returncode == 2, res.stdout
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "SHA-256 differs" in lines[0] and "--strict" in lines[0], lines
    assert not (strict / "samples.parquet").exists()


def test_a_changed_dark_frame_stops_calibration(run: Path, tmp_path: Path) -> None:
    bad = _copy_run(run, tmp_path / "dark")
    with RunStore.open(bad) as store:
        take, _ = store.usable_calibration_take("dark")
        darks = list(store.calibration_captures("dark", take))
    assert len(darks) >= 2
    victim, other = bad / darks[0].frame_path, bad / darks[1].frame_path
    assert victim.read_bytes() != other.read_bytes()  # independent read noise in each dark
    victim.chmod(0o644)
    victim.write_bytes(other.read_bytes())  # a valid frame, but not the capture recorded
    res = _calibrate(bad)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    # stdout too in the message: this failed once with an empty stderr (stop 40), cause unknown
    assert len(lines) == 1 and "dark frame unusable" in lines[0] and "SHA-256" in lines[0], (
        lines,
        res.stdout[-2000:],
    )
