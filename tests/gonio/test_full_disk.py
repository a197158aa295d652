"""A full disk is said as such (issue 47): on a 1 MB tmpfs filled to its last block, `runs
show`, `report` and `calibrate` of a healthy run said its manifest was damaged and advised
restoring it from a backup — advice that, followed, overwrites a good manifest. SQLite needs a
few kB beside the file to open it. Real parts: a real tmpfs (mounted as root, as CI runs; where
this machine allows no mount the test is skipped and says why), the CLI in subprocesses, a good
one-capture run from the bad-input corpus's generator (tests/bad_inputs/make_corpus.py)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO


@pytest.fixture
def full_disk(tmp_path: Path):
    mnt = tmp_path / "full"
    mnt.mkdir()
    res = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True, text=True
    )
    if res.returncode != 0:
        pytest.skip(f"no tmpfs can be mounted here ({res.stderr.strip() or 'not root'})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_a_full_disk_is_said_never_called_damage(full_disk: Path) -> None:
    run = full_disk / "run"
    shutil.copytree(REPO / "tests" / "bad_inputs" / "run_dirs" / "bin_px_huge", run)
    try:
        with open(full_disk / "fill", "wb", buffering=0) as fh:
            while True:
                fh.write(b"\0" * 4096)
    except OSError:
        pass  # the disk is full
    for args in (["runs", "show", str(run)], ["report", str(run)], ["calibrate", str(run)]):
        res = subprocess.run([sys.executable, "-m", "gonio.cli", *args], capture_output=True,
                             text=True, timeout=120, cwd=REPO)  # fmt: skip
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1, (args, res.stderr)
        assert "no space left" in lines[0] and "not known to be damaged" in lines[0], lines
        assert "restore" not in lines[0], lines
