"""Outputs never replace what is not a plain file (issue 22, item 4): an output path that is a
symbolic link, a FIFO, a device or a directory is refused in one line before a byte is
written — through the real CLI (`gonio export merl`) and at the one place every write goes
through (plumbing.atomic)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from plumbing.atomic import NotARegularFile, atomic_write_bytes
from tests.support.fits import fit_json


def _export(fit: Path, out: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "gonio.cli", "export", "merl", str(fit), "--out", str(out)]
    # A FIFO opened for writing blocks until a reader comes: the timeout turns a hang into a
    # failure instead of a stuck suite.
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _one_line(res: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, (res.returncode, res.stderr)
    return lines[0]


def test_cli_refuses_a_symlink_and_a_fifo_as_output(tmp_path: Path) -> None:
    fit_json(tmp_path)
    fit = tmp_path / "fit-torrance-sparrow.json"
    precious = tmp_path / "precious.binary"
    precious.write_bytes(b"someone else's data")
    link = tmp_path / "link.binary"
    link.symlink_to(precious)
    assert "symbolic link" in _one_line(_export(fit, link))
    assert link.is_symlink() and precious.read_bytes() == b"someone else's data"

    fifo = tmp_path / "pipe.binary"
    os.mkfifo(fifo)
    assert "not a regular file" in _one_line(_export(fit, fifo))
    assert fifo.exists() and not fifo.is_file()
    # A plain path still works (the refusal is about the target, not the command).
    ok = _export(fit, tmp_path / "plain.binary")
    assert ok.returncode == 0 and (tmp_path / "plain.binary").stat().st_size > 0, ok.stderr


@pytest.mark.parametrize("overwrite", [False, True])
def test_atomic_write_refuses_special_targets(tmp_path: Path, overwrite: bool) -> None:
    target = tmp_path / "target"
    target.write_bytes(b"kept")
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "nowhere")
    (tmp_path / "adir").mkdir()
    for path, words in (
        (tmp_path / "link", "symbolic link"),
        (dangling, "symbolic link"),
        (Path("/dev/null"), "not a regular file"),
        (tmp_path / "adir", "a directory"),
    ):
        if path.name == "link":
            path.symlink_to(target)
        with pytest.raises(NotARegularFile, match=words):
            atomic_write_bytes(path, b"new", overwrite=overwrite)
    assert target.read_bytes() == b"kept"
    assert not list(tmp_path.glob(".*.tmp-*"))  # nothing half-written left behind


def test_a_killed_writers_temp_file_is_removed_by_the_next_write(tmp_path: Path, caplog) -> None:
    """Issue 47: a killed `calibrate` left `.samples.parquet.tmp-PID` forever. A real process
    that has exited stands for the killed writer (its PID is then free); the next write of the
    same file removes its temp file and says so, and leaves a live process's temp file alone."""
    import logging

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    stale = tmp_path / f".samples.parquet.tmp-{int(dead.stdout)}"
    stale.write_bytes(b"half a table")
    live = tmp_path / f".samples.parquet.tmp-{os.getppid()}"
    live.write_bytes(b"another writer's")
    with caplog.at_level(logging.WARNING, logger="gonio"):
        atomic_write_bytes(tmp_path / "samples.parquet", b"whole", overwrite=True)
    assert not stale.exists() and live.exists()
    assert (tmp_path / "samples.parquet").read_bytes() == b"whole"
    assert any(str(stale) in r.getMessage() for r in caplog.records), caplog.text
