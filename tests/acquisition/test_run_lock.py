"""One writer per run directory (issue 22, item 6): while `gonio acquire --out RUN` runs, a
second one on the same RUN is refused in one line naming the first one's PID, before it opens
a device; after the first is killed with -9 the kernel has dropped its lock and the same command
resumes the run. Real parts: two gonio CLI processes, flock, the simulated rig."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from acquisition.store import RunStore
from tests.support.paths import REPO


def _cmd(out: Path) -> list[str]:
    return [
        sys.executable, "-m", "gonio.cli", "acquire",
        "--rig", str(REPO / "configs" / "rigs" / "sim.toml"),
        # isotropic.toml (≈ 308 poses × 2 brackets), not the demo plan: the first writer must
        # outlast the second command's start-up and refusal on a slow, loaded machine (with the
        # demo plan it finished in between once, under the full suite).
        "--plan", str(REPO / "configs" / "plans" / "isotropic.toml"),
        "--out", str(out), "--no-progress", "--yes",
    ]  # fmt: skip


def test_second_writer_is_refused_and_a_killed_one_leaves_no_lock(tmp_path: Path) -> None:
    out = tmp_path / "run"
    first = subprocess.Popen(_cmd(out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if (out / "frames").exists() and len(list((out / "frames").iterdir())) >= 5:
                break
            time.sleep(0.05)
        assert first.poll() is None, "the first acquisition ended before the test could race it"
        second = subprocess.run(_cmd(out), capture_output=True, text=True, timeout=120)
        lines = [ln for ln in second.stderr.splitlines() if ln.strip()]
        assert second.returncode == 2 and len(lines) == 1, second.stderr
        assert f"in use by another gonio process (PID {first.pid})" in lines[0], lines[0]
        assert first.poll() is None, "the first acquisition ended before it could be killed"
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
    with RunStore.open(out) as store:
        assert not store.complete
    again = subprocess.run(_cmd(out), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    with RunStore.open(out) as store:
        assert store.complete and store.verify() == []
