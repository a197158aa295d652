"""Aravis test helpers: the real `arv-fake-gv-camera-0.8` (Debian aravis-tools) as a process on
127.0.0.1, the check that Aravis is installed, and the fake camera's test pattern computed
independently, so a frame's every pixel can be checked.

Installation policy: `make setup` installs Aravis (as root, like libllvm19). Where it is missing
these tests *fail* with one line saying how to install it — unless the Makefile itself could
not install it, which it records in `<venv>/.aravis-unavailable`; only then do they skip, with
that reason.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

__all__ = ["FAKE_CAMERA", "require_aravis", "FakeCamera", "expected_mono", "fake_serial"]

FAKE_CAMERA = "arv-fake-gv-camera-0.8"
UNAVAILABLE = Path(sys.prefix) / ".aravis-unavailable"
HOW = (
    "run `make setup` as root (apt-get install aravis-tools gir1.2-aravis-0.8 "
    "libgirepository1.0-dev libcairo2-dev; pip install -e '.[aravis]')"
)


def require_aravis() -> None:
    """Fail (or, where the Makefile could not install it, skip) without Aravis."""
    from acquisition.cameras_aravis import load_aravis
    from acquisition.protocols import DeviceFault

    missing = []
    if shutil.which(FAKE_CAMERA) is None:
        missing.append(f"{FAKE_CAMERA} (Debian aravis-tools)")
    try:
        load_aravis()
    except DeviceFault as exc:
        missing.append(f"the Aravis GI bindings ({str(exc).rsplit('(', 1)[-1].rstrip(')')})")
    if not missing:
        return
    if UNAVAILABLE.exists():
        reason = UNAVAILABLE.read_text().strip()
        pytest.skip(f"the Makefile could not install Aravis here: {reason}")
    pytest.fail(f"missing {' and '.join(missing)}: {HOW}")


def fake_serial() -> str:
    """A serial number of this test process: another fake camera on the machine is not ours."""
    return f"T{os.getpid() % 100000:05d}"


class FakeCamera:
    """`arv-fake-gv-camera-0.8 -i 127.0.0.1 -s SERIAL [-r LOST‰]` as a child process."""

    def __init__(self, serial: str, lost_per_thousand: float = 0.0) -> None:
        self.serial = serial
        self.device_id = f"Aravis-Fake-{serial}"
        self.lost_per_thousand = lost_per_thousand
        self.proc: subprocess.Popen | None = None

    def start(self) -> FakeCamera:
        argv = [FAKE_CAMERA, "-i", "127.0.0.1", "-s", self.serial]
        if self.lost_per_thousand:
            argv += ["-r", f"{self.lost_per_thousand:g}"]
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(0.3)  # its sockets are bound within milliseconds; discovery then finds it
        if self.proc.poll() is not None:
            raise RuntimeError(f"{FAKE_CAMERA} exited: {self.proc.stderr.read().decode()}")
        return self

    def kill(self) -> None:
        """SIGKILL: the camera vanishes mid-stream, as when its cable is pulled."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=10)

    def __enter__(self) -> FakeCamera:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.kill()


def expected_mono(
    pixel_format: str, width: int, height: int, frame_id: int, gain: int, exposure_us: float
) -> np.ndarray:
    """The fake camera's diagonal ramp (Aravis 0.8 src/arvfakecamera.c,
    arv_fake_camera_diagonal_ramp), computed here from its formula:

        scale = 1 + gain + log10(exposure_µs / 10⁴)
        Mono8:  DN = clamp(((x + frame_id + y) mod 255) · scale, 0, 255)
        Mono16: DN = clamp(((256 x + 256 frame_id + 256 y) mod 65535) · scale, 0, 65535)

    truncated to an integer as C converts a double; (x, y) count from the ROI's corner. At
    exposures of 10 ms and 100 ms with an integer gain, scale is an exact integer, so the
    frame is known exactly (log10 of a power of ten is exact)."""
    scale = 1.0 + gain + math.log10(exposure_us / 10000.0)
    y, x = np.mgrid[0:height, 0:width].astype(np.int64)
    if pixel_format == "Mono8":
        v, top = ((x + frame_id + y) % 255) * scale, 255
    elif pixel_format == "Mono16":
        v, top = ((256 * x + 256 * frame_id + 256 * y) % 65535) * scale, 65535
    else:
        raise ValueError(pixel_format)
    return np.clip(v, 0, top).astype(np.int64)
