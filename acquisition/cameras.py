"""Real cameras: a tethered-folder camera (the gphoto2 and Aravis cameras have modules of their
own, acquisition.cameras_gphoto2 and acquisition.cameras_aravis).

Tethered folder: vendor software (or a tethering tool) writes each frame into a folder. After
a trigger, the camera waits for a file that was not there before, waits until its size stops
changing (the writer may still be streaming it), and returns its bytes untouched with its
suffix (".nef", ".dng", ".exr"...). No frame within `timeout_s` is a DeviceFault, so the
runner stops safely instead of hanging or recording a stale frame.
"""

from __future__ import annotations

import shlex
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from acquisition.protocols import DeviceFault, Frame
from plumbing.inputs import FRAME_MAX_BYTES, read_input_bytes

__all__ = ["FolderCamera", "folder_camera"]

# Names vendor tools use while a file is still being written; never picked up.
_PARTIAL = (".tmp", ".part", ".crdownload", ".download", "~")


class FolderCamera:
    """Implements `Camera` on a folder that receives one new file per capture.

    Parameters
    ----------
    folder: where the frames land.
    trigger: called with the exposure (s) to take one frame (a shell command, a serial
        shutter release...); None when something else triggers (e.g. the vendor software's
        interval timer, or a test).
    timeout_s: wall time to wait for the new file.
    stable_s: the file's size must be unchanged (and non-zero) for this long.
    poll_s: how often the folder is listed.
    info: what `describe()` reports (resolution, pixel pitch... from the rig config).
    """

    def __init__(
        self,
        folder: Path | str,
        *,
        trigger: Callable[[float], None] | None = None,
        timeout_s: float = 30.0,
        stable_s: float = 0.2,
        poll_s: float = 0.02,
        exposure_range_s: tuple[float, float] = (1e-5, 60.0),
        info: dict[str, Any] | None = None,
    ) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DeviceFault(f"camera folder {self.folder} does not exist")
        self.trigger = trigger
        self.timeout_s = timeout_s
        self.stable_s = stable_s
        self.poll_s = poll_s
        self.exposure_range_s = exposure_range_s
        self.info = dict(info or {})
        self._seen = set(self._listing())  # files already there are never "new"

    def _listing(self) -> dict[str, int]:
        out = {}
        for p in self.folder.iterdir():
            if p.name.startswith(".") or p.name.endswith(_PARTIAL) or not p.is_file():
                continue
            try:
                out[p.name] = p.stat().st_size
            except FileNotFoundError:  # renamed away between listing and stat
                continue
        return out

    def capture(self, exposure_s: float) -> Frame:
        lo, hi = self.exposure_range_s
        if not lo <= exposure_s <= hi:
            raise ValueError(f"exposure {exposure_s} s outside the camera's range {lo}..{hi} s")
        self._seen |= set(self._listing())
        t0 = time.monotonic()
        if self.trigger is not None:
            self.trigger(exposure_s)
        name, size, since = None, -1, 0.0
        while True:
            now = time.monotonic()
            listing = self._listing()
            if name is None:
                new = sorted(n for n in listing if n not in self._seen)
                if new:
                    name, size, since = new[0], listing[new[0]], now
            elif name not in listing:  # the writer renamed or removed it: start over
                name = None
            elif listing[name] != size or size == 0:
                size, since = listing[name], now
            elif now - since >= self.stable_s:
                break
            if now - t0 > self.timeout_s:
                what = "no new file" if name is None else f"{name} still growing"
                raise DeviceFault(
                    f"camera folder {self.folder}: {what} within {self.timeout_s:g} s "
                    f"of the trigger (exposure {exposure_s:g} s)"
                )
            time.sleep(self.poll_s)
        path = self.folder / name
        data = read_input_bytes(path, "frame", FRAME_MAX_BYTES)
        self._seen.add(name)
        if len(data) != size:  # changed between the stability check and the read
            raise DeviceFault(f"camera folder {self.folder}: {name} changed while being read")
        return Frame(
            data=data,
            suffix=path.suffix.lower(),
            metadata={"exposure_s": exposure_s, "source_file": name},
        )

    def supported_exposures(self) -> tuple[float, float]:
        return self.exposure_range_s

    def describe(self) -> dict[str, Any]:
        return {"backend": "folder", "folder": str(self.folder), **self.info}


def _command_trigger(argv: Sequence[str]) -> Callable[[float], None]:
    """A trigger that runs a command; `{exposure_s}` in an argument is replaced."""

    def trigger(exposure_s: float) -> None:
        cmd = [a.replace("{exposure_s}", f"{exposure_s:g}") for a in argv]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        if res.returncode != 0:
            msg = (res.stderr or res.stdout).strip().splitlines()
            raise DeviceFault(
                f"camera trigger {shlex.join(cmd)} failed ({res.returncode}): "
                f"{msg[0] if msg else 'no output'}"
            )

    return trigger


def folder_camera(config: Any, clock: Any = None) -> FolderCamera:
    """Factory for `CAMERA_BACKENDS["folder"]` from a RigConfig."""
    cam = config.camera
    if not cam.folder:
        raise DeviceFault('camera.backend "folder" needs camera.folder (the tethering folder)')
    trigger = _command_trigger(cam.trigger_command) if cam.trigger_command else None
    return FolderCamera(cam.folder, trigger=trigger, timeout_s=cam.timeout_s)
