"""A camera libgphoto2 drives — DSLRs and mirrorless cameras over USB or PTP/IP
(`camera.backend = "gphoto2"`, settings in `[camera.gphoto2]`).

python-gphoto2 (`pip install "gonio[gphoto2]"`; its wheels bundle libgphoto2 and the camera
drivers) is imported only here. What a capture does:
1. the shutter speed is the camera's choice nearest the plan's exposure in log space (the frame's
   metadata says the one taken, `exposure_s`, and the plan's, `exposure_commanded_s`); an
   exposure longer than the camera's longest timed speed is a bulb exposure: shutter "Bulb",
   the bulb control pressed, held for the exposure on the rig's clock, released;
2. the camera writes its file(s) to the card; with `image_format = "raw+jpeg"` it writes two,
   and the JPEG is discarded (deleted unread): gonio keeps raw data only;
3. the RAW file is downloaded untouched (its suffix kept: .nef, .cr2, .arw, ...), then deleted
   from the card (`delete_after_download`), so a long run never fills the card.
ISO, aperture and the image format are set once when the camera is opened; the camera's own
description (model, serial number, manufacturer, lens, port) goes to run.toml [camera_device].
Every libgphoto2 failure is a `DeviceFault` naming the step, so the runner stops safely.
"""

from __future__ import annotations

import math
import re
import time
from pathlib import PurePosixPath
from typing import Any

from acquisition.clock import Clock, SystemClock
from acquisition.device_config import Gphoto2Config
from acquisition.protocols import DeviceFault, Frame

__all__ = [
    "Gphoto2Camera",
    "gphoto2_camera",
    "open_gphoto2",
    "parse_shutter",
    "pick_raw_choice",
    "INSTALL_HINT",
]

INSTALL_HINT = (
    "camera.backend \"gphoto2\" needs python-gphoto2: pip install 'gonio[gphoto2]' "
    "(its wheel bundles libgphoto2 and the camera drivers)"
)
# Config widget names across drivers (ptp2 Nikon/Canon/Sony, and older ones), first found wins.
WIDGETS = {
    "shutter": ("shutterspeed", "shutterspeed2", "eos-shutterspeed"),
    "iso": ("iso", "isospeed"),
    "aperture": ("f-number", "aperture"),
    "format": ("imagequality", "imageformat", "imageformatsd"),
    "serial": ("serialnumber", "eosserialnumber"),
    "model": ("cameramodel", "model"),
    "manufacturer": ("manufacturer",),
    "lens": ("lensname",),
}
_RAW_WORDS = re.compile(r"raw|nef|cr2|cr3|arw|orf|rw2|pef|raf|dng", re.IGNORECASE)
_JPEG_WORDS = re.compile(r"jpe?g|fine|normal|basic|\+|large|medium|small", re.IGNORECASE)
_JPEG_SUFFIXES = (".jpg", ".jpeg")


def _gp() -> Any:
    try:
        import gphoto2 as gp  # type: ignore[import-not-found]
    except ImportError:
        raise DeviceFault(INSTALL_HINT) from None
    return gp


def parse_shutter(text: str) -> float:
    """gphoto2 shutter choices: "1/250", "0.5", "2", "30s", "0.0002s", '1/3"' → seconds;
    anything else (Bulb, Time, x 1/200) → -1."""
    t = text.strip().rstrip('s"').strip()
    try:
        if "/" in t:
            num, den = t.split("/", 1)
            return float(num) / float(den)
        return float(t)
    except ValueError:
        return -1.0


def pick_raw_choice(choices: list[str], image_format: str) -> str | None:
    """The image-format choice meaning RAW only ("raw") or RAW + a JPEG ("raw+jpeg")."""
    raw = [c for c in choices if _RAW_WORDS.search(c)]
    if image_format == "raw":
        only = [c for c in raw if not _JPEG_WORDS.search(_RAW_WORDS.sub("", c))]
        return only[0] if only else None
    both = [c for c in raw if _JPEG_WORDS.search(_RAW_WORDS.sub("", c))]
    return both[0] if both else None


def open_gphoto2(settings: Gphoto2Config) -> Any:
    """An initialised gphoto2.Camera: the model and port named in the settings, or the one
    camera found (`gphoto2 --auto-detect`). Raises DeviceFault with what was found."""
    gp = _gp()
    cam = gp.Camera()
    try:
        model, port = settings.camera, settings.port
        if model is not None and port is None:
            found = [(n, p) for n, p in _autodetect(gp) if n == model]
            if not found:
                raise DeviceFault(f"gphoto2: no {model!r} connected ({_found(gp)})")
            port = found[0][1]
        if model is not None:
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            index = _lookup(gp, abilities.lookup_model, model)
            if index < 0:
                raise DeviceFault(f"gphoto2: libgphoto2 knows no camera model {model!r}")
            cam.set_abilities(abilities[index])
        if port is not None:
            ports = gp.PortInfoList()
            ports.load()
            index = _lookup(gp, ports.lookup_path, port)
            if index < 0:
                raise DeviceFault(f"gphoto2: no port {port!r}")
            cam.set_port_info(ports[index])
        cam.init()
    except gp.GPhoto2Error as exc:
        raise DeviceFault(f"gphoto2: cannot open the camera ({exc}; {_found(gp)})") from exc
    return cam


def _lookup(gp: Any, fn: Any, key: str) -> int:
    """libgphoto2's index of `key`, or −1 (python-gphoto2 raises where C returns < 0)."""
    try:
        return int(fn(key))
    except gp.GPhoto2Error:
        return -1


def _autodetect(gp: Any) -> list[tuple[str, str]]:
    try:
        found = gp.Camera.autodetect()
        return [(str(found.get_name(i)), str(found.get_value(i))) for i in range(found.count())]
    except gp.GPhoto2Error:
        return []


def _found(gp: Any) -> str:
    found = _autodetect(gp)
    return "found: " + ", ".join(f"{n} at {p}" for n, p in found) if found else "none found"


class Gphoto2Camera:
    """Implements `Camera` on an initialised gphoto2 camera (see the module docstring).

    Parameters
    ----------
    device: a `gphoto2.Camera` (from `open_gphoto2`), or an object with its methods.
    settings: the `[camera.gphoto2]` table.
    clock: times bulb exposures (the rig's clock).
    timeout_s: wall time to wait for the camera's file after the shutter.
    info: extra `describe()` entries.
    """

    def __init__(
        self,
        device: Any,
        settings: Gphoto2Config,
        clock: Clock | None = None,
        *,
        timeout_s: float = 30.0,
        info: dict[str, Any] | None = None,
    ) -> None:
        self._gp = _gp()
        self.device = device
        self.settings = settings
        self.clock: Clock = clock if clock is not None else SystemClock()
        self.timeout_s = timeout_s
        self.info = dict(info or {})
        self.discarded: list[str] = []  # files deleted unread (the JPEG of RAW+JPEG)
        try:
            self._config = device.get_config()
        except self._gp.GPhoto2Error as exc:
            self._config = None
            if any(getattr(settings, k) is not None for k in ("iso", "aperture")):
                raise DeviceFault(f"gphoto2: the camera has no settings to change ({exc})") from exc
        self._apply_settings()
        self._speeds = self._timed_speeds()

    # -- settings -------------------------------------------------------------------------
    def _widget(self, kind: str) -> Any | None:
        if self._config is None:
            return None
        for name in WIDGETS[kind]:
            try:
                return self._config.get_child_by_name(name)
            except self._gp.GPhoto2Error:
                continue
        return None

    def _choices(self, widget: Any) -> list[str]:
        return [widget.get_choice(i) for i in range(widget.count_choices())]

    def _set_choice(self, kind: str, value: str) -> None:
        widget = self._widget(kind)
        if widget is None:
            names = "/".join(WIDGETS[kind])
            raise DeviceFault(f"gphoto2: the camera has no {kind} setting ({names})")
        choices = self._choices(widget)
        want = value.strip().lower().removeprefix("f/")
        match = [c for c in choices if c.strip().lower().removeprefix("f/") == want]
        if not match:
            raise DeviceFault(
                f"gphoto2: {widget.get_name()} has no choice {value!r}; it offers: "
                + ", ".join(choices)
            )
        widget.set_value(match[0])

    def _push(self, what: str) -> None:
        try:
            self.device.set_config(self._config)
        except self._gp.GPhoto2Error as exc:
            raise DeviceFault(f"gphoto2: the camera refused {what} ({exc})") from exc

    def _apply_settings(self) -> None:
        s = self.settings
        if s.iso is not None:
            self._set_choice("iso", s.iso)
        if s.aperture is not None:
            self._set_choice("aperture", s.aperture)
        fmt = self._widget("format")
        if fmt is not None:
            choice = s.raw_choice or pick_raw_choice(self._choices(fmt), s.image_format)
            if choice is None:
                raise DeviceFault(
                    f"gphoto2: no {s.image_format.upper()} choice among {fmt.get_name()}: "
                    f"{', '.join(self._choices(fmt))} (set camera.gphoto2.raw_choice)"
                )
            self._set_choice("format", choice)
        if self._config is not None:
            self._push("the ISO / aperture / image format")

    def _timed_speeds(self) -> list[tuple[float, str]]:
        widget = self._widget("shutter")
        if widget is None:
            return []
        return sorted((parse_shutter(c), c) for c in self._choices(widget) if parse_shutter(c) > 0)

    # -- Camera protocol ------------------------------------------------------------------
    def supported_exposures(self) -> list[float] | tuple[float, float]:
        speeds = [t for t, _ in self._speeds]
        if self.settings.bulb != "none" and speeds:
            return (speeds[0], 3600.0)  # bulb covers everything above the longest speed
        return speeds

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"backend": "gphoto2", **self.info}
        try:
            out["driver_model"] = str(self.device.get_abilities().model)
        except (self._gp.GPhoto2Error, AttributeError):
            pass
        for key in ("model", "serial", "manufacturer", "lens", "iso", "aperture", "format"):
            widget = self._widget(key)
            if widget is not None:
                out[key if key != "format" else "image_format"] = str(widget.get_value())
        out.setdefault("model", out.get("driver_model", "?"))
        if self._speeds:
            out["shutter_speeds_s"] = [self._speeds[0][0], self._speeds[-1][0]]
        out["bulb"] = self.settings.bulb
        return out

    def capture(self, exposure_s: float) -> Frame:
        gp = self._gp
        try:
            if self._speeds and exposure_s > self._speeds[-1][0] * 1.01:
                taken_s, paths = exposure_s, self._bulb(exposure_s)
            else:
                taken_s, choice = self._nearest(exposure_s)
                if choice is not None:
                    self._widget("shutter").set_value(choice)
                    self._push(f"shutter speed {choice}")
                paths = [self.device.capture(gp.GP_CAPTURE_IMAGE)]
            paths += self._more_files()
            return self._download(paths, exposure_s, taken_s)
        except gp.GPhoto2Error as exc:
            raise DeviceFault(f"gphoto2 capture failed: {exc}") from exc

    def _nearest(self, exposure_s: float) -> tuple[float, str | None]:
        if not self._speeds:
            return exposure_s, None  # a camera without a speed setting: as it is set
        t, choice = min(self._speeds, key=lambda tc: abs(math.log(tc[0] / exposure_s)))
        return t, choice

    def _bulb(self, exposure_s: float) -> list[Any]:
        """Bulb: shutter to "Bulb", hold the release for the exposure, wait for the file."""
        mode = self.settings.bulb
        if mode == "none":
            raise DeviceFault(
                f"exposure {exposure_s:g} s is beyond the longest shutter speed "
                f'{self._speeds[-1][1]} and camera.gphoto2.bulb = "none"'
            )
        shutter = self._widget("shutter")
        bulb = [c for c in self._choices(shutter) if c.strip().lower() == "bulb"]
        if bulb:
            shutter.set_value(bulb[0])
            self._push("shutter speed Bulb")
        try:
            control = self._config.get_child_by_name(mode)
        except self._gp.GPhoto2Error:
            raise DeviceFault(f"gphoto2: the camera has no {mode!r} control for bulb") from None
        press, release = (1, 0) if mode == "bulb" else ("Press Full", "Release Full")
        control.set_value(press)
        self._push("bulb press")
        self.clock.sleep(exposure_s)
        control.set_value(release)
        self._push("bulb release")
        return self._wait_files(first=True)

    def _wait_files(self, *, first: bool) -> list[Any]:
        """Files the camera announces (GP_EVENT_FILE_ADDED): wait up to `timeout_s` for the
        first one when `first`, then take what comes within a short quiet time."""
        gp = self._gp
        found: list[Any] = []
        deadline = time.monotonic() + (self.timeout_s if first else 0.0)
        while True:
            left_ms = int((deadline - time.monotonic()) * 1e3)
            wait_ms = 200 if found or not first else max(left_ms, 1)
            kind, data = self.device.wait_for_event(wait_ms)
            if kind == gp.GP_EVENT_FILE_ADDED:
                found.append(data)
                continue
            if kind == gp.GP_EVENT_TIMEOUT and (found or not first or time.monotonic() > deadline):
                break
            if time.monotonic() > deadline + 5.0:  # a camera that never stops talking
                break
        if first and not found:
            raise DeviceFault(f"gphoto2: no file within {self.timeout_s:g} s of the exposure")
        return found

    def _more_files(self) -> list[Any]:
        """RAW+JPEG: the second file arrives as an event after capture() returned the first."""
        if self.settings.image_format != "raw+jpeg":
            return []
        return self._wait_files(first=False)

    def _download(self, paths: list[Any], exposure_s: float, taken_s: float) -> Frame:
        gp = self._gp
        names = [(p.folder, p.name) for p in paths]
        raws = [fn for fn in names if PurePosixPath(fn[1]).suffix.lower() not in _JPEG_SUFFIXES]
        if not raws:
            raise DeviceFault(
                f"gphoto2: the camera wrote {', '.join(n for _, n in names)}, no RAW file "
                "(set the camera to RAW: camera.gphoto2.image_format / raw_choice)"
            )
        folder, name = raws[0]
        cam_file = self.device.file_get(folder, name, gp.GP_FILE_TYPE_NORMAL)
        data = bytes(memoryview(cam_file.get_data_and_size()))
        if self.settings.delete_after_download:
            for f, n in names:
                self.device.file_delete(f, n)
                if (f, n) != (folder, name):
                    self.discarded.append(n)
        return Frame(
            data=data,
            suffix=PurePosixPath(name).suffix.lower(),
            metadata={
                "exposure_s": taken_s,
                "exposure_commanded_s": exposure_s,
                "bulb": bool(self._speeds) and exposure_s > self._speeds[-1][0] * 1.01,
                "source_file": f"{folder.rstrip('/')}/{name}",
                "discarded": [n for f, n in names if (f, n) != (folder, name)],
            },
        )

    def close(self) -> None:
        try:
            self.device.exit()
        except Exception:  # a camera that went away: nothing to undo
            pass


def gphoto2_camera(config: Any, clock: Clock | None = None) -> Gphoto2Camera:
    """Factory for `CAMERA_BACKENDS["gphoto2"]` from a RigConfig."""
    settings = config.camera.gphoto2
    return Gphoto2Camera(open_gphoto2(settings), settings, clock, timeout_s=config.camera.timeout_s)
