"""Inputs are regular files (issue 22 item 4): a FIFO, a device or a directory given where gonio
reads a file is refused in one line at once — never waited on — and a FIFO planted as a run's
pending frame makes the resume refuse, not hang.

Each command runs with a timeout: on the code before this change the FIFO cases block in
open() forever (a FIFO's open waits for a writer), so they fail by timing out.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import CONFIGS

GONIO = [sys.executable, "-m", "gonio.cli"]
RIG = CONFIGS / "rigs" / "sim.toml"
# Far longer than any of these one-line refusals takes (interpreter start ~2 s), far shorter
# than "forever".
TIMEOUT_S = 60


def _gonio(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*GONIO, *args], capture_output=True, text=True, timeout=TIMEOUT_S)


def _one_line_refusal(res: subprocess.CompletedProcess, path: Path, kind: str) -> None:
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("\n") == 1, res.stderr
    assert str(path) in res.stderr and kind in res.stderr, res.stderr
    assert "internal error" not in res.stderr


@pytest.fixture
def fifo(tmp_path: Path):
    def make(name: str) -> Path:
        p = tmp_path / name
        os.mkfifo(p)
        return p

    return make


def test_fifo_as_a_config(fifo, tmp_path: Path) -> None:
    rig = fifo("rig.toml")
    res = _gonio("acquire", "--rig", str(rig), "--plan", str(CONFIGS / "plans" / "demo.toml"),
                 "--out", str(tmp_path / "run"), "--no-progress")  # fmt: skip
    _one_line_refusal(res, rig, "FIFO")
    assert not (tmp_path / "run").exists()


def test_fifo_as_a_samples_table(fifo) -> None:
    samples = fifo("samples.parquet")
    _one_line_refusal(_gonio("fit", str(samples)), samples, "FIFO")


@pytest.mark.parametrize("fmt,name", [("rgl", "x.bsdf"), ("merl", "x.binary"), ("csv", "x.csv")])
def test_fifo_as_data_to_import(fifo, tmp_path: Path, fmt: str, name: str) -> None:
    src = fifo(name)
    res = _gonio("import", fmt, str(src), "--out", str(tmp_path / "s.parquet"))
    _one_line_refusal(res, src, "FIFO")


def test_fifo_as_a_fit_result(fifo, tmp_path: Path) -> None:
    fit = fifo("fit-ts.json")
    samples = tmp_path / "samples.parquet"
    samples.write_bytes(b"")  # never reached: the fit is read first or refused alike
    res = _gonio("report", "--samples", str(samples), "--fit", str(fit))
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "internal error" not in res.stderr


def test_device_as_data_to_import(tmp_path: Path) -> None:
    # /dev/zero never ends: read whole, it would fill memory.
    res = _gonio("import", "merl", "/dev/zero", "--out", str(tmp_path / "s.parquet"))
    _one_line_refusal(res, Path("/dev/zero"), "device")


def test_fifo_as_a_pending_frame_refuses_the_resume(tmp_path: Path) -> None:
    plan = tmp_path / "tiny.toml"
    plan.write_text(
        'name = "tiny"\ntype = "explicit"\n'
        "poses_deg = [[20.0, 0.0, 30.0, 180.0], [30.0, 0.0, 40.0, 180.0]]\n"
        "exposures_s = [0.002]\n"
    )
    run = tmp_path / "run"
    made = _gonio("acquire", "--rig", str(RIG), "--plan", str(plan), "--out", str(run),
                  "--no-progress")  # fmt: skip
    assert made.returncode == 0, made.stderr
    # As a crash between the frame write and the commit leaves it — the last capture pending,
    # the run incomplete — except that its frame is now a FIFO (someone sent us this run).
    db = sqlite3.connect(run / "manifest.sqlite", isolation_level=None)
    cid, rel = db.execute("SELECT id, frame_path FROM captures ORDER BY id DESC LIMIT 1").fetchone()
    db.execute("UPDATE captures SET status = 'pending', sha256 = NULL WHERE id = ?", (cid,))
    db.execute("UPDATE meta SET value = 'incomplete' WHERE key = 'status'")
    db.close()
    (run / rel).unlink()
    os.mkfifo(run / rel)
    res = _gonio("acquire", "--rig", str(RIG), "--plan", str(plan), "--out", str(run),
                 "--no-progress")  # fmt: skip
    assert res.returncode == 2, res.stdout + res.stderr
    assert "FIFO" in res.stderr and rel in res.stderr, res.stderr
    assert "internal error" not in res.stderr
