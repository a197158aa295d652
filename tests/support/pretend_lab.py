"""The pretend lab for tests: configs/rigs/lab-example.toml with only its device paths pointed at
a pretend lab's ptys (simulator.pretend_lab, a separate process, as a USB adapter appears to the
host) and its camera backend set to the simulated camera, which takes its world from --scene.

Everything else is the lab's: wall clock, its servo profiles, its camera description (a
256 × 256 RGGB region of interest, 12 bit), its reference target, and the unmodified `gonio`
command line in a process of its own.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.support.paths import REPO

LAB_RIG = REPO / "configs" / "rigs" / "lab-example.toml"
DEMO_SCENE = REPO / "configs" / "scenes" / "demo.toml"

# ≤ 6 poses; the exposures keep the demo material's specular peak below the lab camera's clip
# (256 × 256 px of 4.8 µm at f/8 under the demo's 1 W/sr lamp reach the full well in ≈ 4 ms).
PLAN_TOML = """name = "pretend-lab"
type = "isotropic"
theta_i_deg = [30.0, 50.0]
theta_o_deg = [10.0, 40.0, 60.0]
delta_phi_deg = [180.0]
exposures_s = [0.0005, 0.002]

[calibration.dark]
count = 4

[calibration.flat]
count = 4

[calibration.reference]
"""

ANSWERS_TOML = """# the operator's answers, scripted for an unattended run
[answers]
cap_lens = "yes"
uncap_lens = "yes"
mount_flat = "yes"
unmount_flat = "yes"
mount_reference = "yes"
mount_sample = "yes"
"""


def lab_rig_text(lab_dir: Path) -> str:
    """lab-example.toml with its bus and light on the lab's ptys and the simulated camera."""
    text = LAB_RIG.read_text()
    for old, new in (
        (
            'url = "/dev/serial/by-id/usb-FTDI_USB__-__Serial_Converter_FT4TJ8ZQ-if00-port0"',
            f'url = "{lab_dir / "dxl"}"',
        ),
        (
            'url = "/dev/serial/by-id/usb-gonio_light_controller-if00"',
            f'url = "{lab_dir / "light"}"',
        ),
        ('backend = "folder"', 'backend = "sim"'),
    ):
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def write_lab_files(tmp: Path, lab_dir: Path) -> tuple[Path, Path, Path]:
    rig, plan, answers = tmp / "rig.toml", tmp / "plan.toml", tmp / "answers.toml"
    rig.write_text(lab_rig_text(lab_dir))
    plan.write_text(PLAN_TOML)
    answers.write_text(ANSWERS_TOML)
    return rig, plan, answers


@contextmanager
def pretend_lab(rig: Path, lab_dir: Path, scene: Path = DEMO_SCENE) -> Iterator[subprocess.Popen]:
    """Run the pretend lab as its own process until the block ends (then SIGTERM: it writes
    lab_dir/state.json, the emulators' final state)."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "simulator.pretend_lab",
            "--rig",
            str(rig),
            "--scene",
            str(scene),
            "--dir",
            str(lab_dir),
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not (lab_dir / "ready").exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"pretend lab did not start: {proc.stderr.read()}")
        time.sleep(0.05)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def gonio(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """The real command line in a process of its own."""
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )
