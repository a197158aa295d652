"""The Aravis camera path on loopback: frames and bytes per second through the real Aravis 0.8
against `arv-fake-gv-camera-0.8` on 127.0.0.1 (GigE Vision, 1400-byte GVSP packets).

Two figures per region of interest and pixel format:
* `capture()`: what the runner gets — exposure check, software trigger, one complete buffer,
  the frame file encoded (TIFF or DNG);
* `stream only`: software trigger and buffer, no file (what the wire and Aravis cost).
The fake camera's acquisition loop serves at most one software trigger per frame period
(≈ 40 ms), so small frames measure that loop, large ones the GVSP wire and Aravis.
Needs `make setup` (Aravis); prints what is missing otherwise. `make bench BENCH=bench_aravis`.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from acquisition.cameras_aravis import AravisCamera, AravisOptions
from acquisition.device_config import AravisConfig

CASES = [
    ("Mono8", 512, 512),
    ("Mono16", 512, 512),
    ("BayerRG8", 512, 512),
    ("Mono16", 1024, 1024),
    ("Mono16", 64, 64),
]
N_FRAMES = 60
EXPOSURE_S = 0.001


def _run(cam: AravisCamera, n: int, encode: bool) -> tuple[float, int]:
    w, h = cam.options.resolution
    bpp = 1 if cam.settings.pixel_format.endswith("8") else 2
    t0 = time.perf_counter()
    for _ in range(n):
        if encode:
            cam.capture(EXPOSURE_S)
        else:
            got = cam._one_attempt()
            assert not isinstance(got, str), got
    return time.perf_counter() - t0, n * w * h * bpp


def main() -> None:
    if shutil.which("arv-fake-gv-camera-0.8") is None:
        print("arv-fake-gv-camera-0.8 missing: `make setup` as root installs aravis-tools")
        return
    proc = subprocess.Popen(
        ["arv-fake-gv-camera-0.8", "-i", "127.0.0.1", "-s", "BENCH"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(0.3)
        print(f"{N_FRAMES} frames per row; exposure {EXPOSURE_S * 1e3:g} ms; software trigger")
        print(f"{'format':>9} {'ROI':>9} {'path':>12} {'fps':>7} {'MB/s':>7}")
        for fmt, w, h in CASES:
            cam = AravisCamera(
                AravisOptions(AravisConfig(device="Aravis-Fake-BENCH", pixel_format=fmt), (w, h))
            )
            try:
                cam.capture(EXPOSURE_S)  # warm up: exposure set, first buffer
                for encode in (True, False):
                    dt, nbytes = _run(cam, N_FRAMES, encode)
                    print(
                        f"{fmt:>9} {w:>4}×{h:<4} {'capture()' if encode else 'stream only':>12} "
                        f"{N_FRAMES / dt:7.1f} {nbytes / dt / 1e6:7.2f}"
                    )
                print(f"{'':>9} failed attempts retried: {cam.failed_attempts}")
            finally:
                cam.close()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


if __name__ == "__main__":
    main()
