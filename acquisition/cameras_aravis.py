"""A GenICam camera (GigE Vision, USB3 Vision) through Aravis 0.8 (`camera.backend = "aravis"`).

Aravis is reached through its GObject-introspection bindings (Debian `gir1.2-aravis-0.8`, and
PyGObject in the virtualenv: `pip install "gonio[aravis]"`, which `make setup` does). The import
happens only when the backend is asked for; without the libraries that is one line saying how
to install them (a `DeviceFault`, so the CLI prints it without a traceback).

What one capture does (GenICam SFNC feature names; Aravis picks ExposureTime or ExposureTimeAbs,
Gain or GainRaw, whichever the camera has):
1. the exposure (µs in GenICam, s in gonio) is written when it changes and read back: the
   camera rounds it to its own step (a line period, or whole µs), and the value it reports is
   what the frame's metadata says (`exposure_s`; the plan's value is `exposure_commanded_s`);
2. buffers already waiting in the stream (a late frame of an earlier, failed attempt) are
   returned to the pool unread, then one software trigger (TriggerMode On, TriggerSource
   Software, TriggerSelector FrameStart) exposes one frame;
3. the buffer is taken within `camera.timeout_s`; it must be complete (status SUCCESS, the
   payload of the set width × height × bytes per pixel, a frame id not seen before). A lost,
   incomplete or late buffer — on GigE Vision a lost packet the camera did not resend — is
   counted and the frame is exposed again, at most `camera.aravis.retries` more times; then
   the capture is a `DeviceFault` naming what happened to each attempt, and the runner stops
   safely (the run resumes).
Frames are stored as the camera gave them: Bayer formats as DNG (the CFA mosaic, 16-bit
container), Mono formats as 16-bit (or 8-bit) monochrome TIFF, both with exposure, gain, device
ID and frame id in the JSON metadata that `calibration.decode` reads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from acquisition.device_config import AravisConfig, pixel_format_bits, pixel_format_cfa
from acquisition.frame_files import MIN_DNG_SIDE, encode_dng, encode_mono_tiff
from acquisition.protocols import DeviceFault, Frame

__all__ = ["AravisCamera", "AravisOptions", "aravis_camera", "load_aravis", "INSTALL_HINT"]

INSTALL_HINT = (
    'camera.backend "aravis" needs Aravis 0.8 and PyGObject: as root `apt-get install '
    "aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev`, then "
    "`pip install 'gonio[aravis]'` (`make setup` does both)"
)


def load_aravis() -> tuple[Any, Any]:
    """(Aravis, GLib) from gi.repository, or a DeviceFault with the install hint."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:  # no PyGObject / no Aravis typelib
        raise DeviceFault(f"{INSTALL_HINT} ({exc})") from None
    return Aravis, GLib


@dataclass
class AravisOptions:
    """Everything the driver needs, from the rig file (`aravis_camera` builds it)."""

    settings: AravisConfig
    resolution: tuple[int, int]  # ROI width, height (px)
    timeout_s: float = 5.0  # wait for one buffer after the trigger (wall time)
    exposure_range_s: tuple[float, float] = (1e-5, 30.0)  # the rig file's range
    black_level_dn: float = 0.0  # written into each file (the rig file's description)
    white_level_dn: float | None = None  # default: 2^bits − 1 of the pixel format
    info: dict[str, Any] = field(default_factory=dict)  # extra describe() entries


class AravisCamera:
    """Implements `Camera` on one GenICam device (see the module docstring)."""

    def __init__(self, options: AravisOptions) -> None:
        self.options = options
        self.settings = options.settings
        self._Aravis, self._GLib = load_aravis()
        self.device_id = self._find_device(self.settings.device)
        self.frames = 0  # complete frames delivered
        self.failed_attempts = 0  # lost / incomplete / late buffers, retried
        self._last_frame_id: int | None = None
        self._exposure_set_us: float | None = None
        self._requested_us: float | None = None
        self._camera = None
        self._stream = None
        try:
            self._camera = self._Aravis.Camera.new(self.device_id)
            self._configure()
        except self._GLib.Error as exc:
            self.close()
            raise DeviceFault(f"camera {self.device_id}: cannot configure: {exc.message}") from exc
        except BaseException:
            self.close()
            raise

    # -- opening ------------------------------------------------------------------------------
    def _find_device(self, wanted: str) -> str:
        Aravis = self._Aravis
        Aravis.update_device_list()  # discovery; also makes the GigE stream address right
        found = [Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())]
        if not found:
            raise DeviceFault(
                "no GenICam camera found (is it powered and on this network? `arv-tool-0.8` "
                "lists what Aravis sees)"
            )
        if wanted == "first":
            return found[0]
        if wanted not in found:
            raise DeviceFault(
                f"camera.aravis.device {wanted!r} not found; Aravis sees: {', '.join(found)}"
            )
        return wanted

    def _configure(self) -> None:
        cam, s = self._camera, self.settings
        Aravis = self._Aravis
        cam.set_pixel_format_from_string(s.pixel_format)
        w, h = self.options.resolution
        sensor = cam.get_sensor_size()
        sw, sh = int(sensor.width), int(sensor.height)
        x, y = s.offset_px if s.offset_px is not None else ((sw - w) // 2, (sh - h) // 2)
        if w > sw or h > sh or x < 0 or y < 0 or x + w > sw or y + h > sh:
            raise DeviceFault(
                f"camera {self.device_id}: ROI {w}×{h} at ({x}, {y}) does not fit its "
                f"{sw}×{sh} sensor (camera.resolution, camera.aravis.offset_px)"
            )
        cam.set_region(x, y, w, h)
        region = cam.get_region()
        got = (int(region.x), int(region.y), int(region.width), int(region.height))
        if got != (x, y, w, h):
            raise DeviceFault(
                f"camera {self.device_id}: asked for ROI {w}×{h} at ({x}, {y}), the camera set "
                f"{got[2]}×{got[3]} at ({got[0]}, {got[1]}) (its step constraints): change "
                "camera.resolution or camera.aravis.offset_px"
            )
        if cam.is_exposure_auto_available():
            cam.set_exposure_time_auto(Aravis.Auto.OFF)
        if s.gain is not None:
            if cam.is_gain_auto_available():
                cam.set_gain_auto(Aravis.Auto.OFF)
            cam.set_gain(float(s.gain))
        cam.set_trigger("Software")
        if cam.is_gv_device():
            if s.packet_size is not None:
                cam.gv_set_packet_size(int(s.packet_size))
            else:
                cam.gv_auto_packet_size()
        self._bytes_pp = 1 if pixel_format_bits(s.pixel_format) <= 8 else 2
        self._payload = int(cam.get_payload())
        self._stream = cam.create_stream(None, None)
        for _ in range(4):  # a few buffers: a late frame must not starve the next one
            self._stream.push_buffer(Aravis.Buffer.new_allocate(self._payload))
        self._device_facts = self._read_facts(sw, sh, got)
        cam.start_acquisition()

    def _read_facts(self, sw: int, sh: int, region: tuple[int, int, int, int]) -> dict[str, Any]:
        """The device's own description, from GenICam features (for run.toml [camera_device])."""
        cam = self._camera
        dev = cam.get_device()
        exp = cam.get_exposure_time_bounds()
        facts: dict[str, Any] = {
            "backend": "aravis",
            "device_id": self.device_id,
            "vendor": cam.get_vendor_name(),
            "model": f"{cam.get_vendor_name()} {cam.get_model_name()}".strip(),
            "serial": cam.get_device_serial_number(),
            "protocol": "GigE Vision" if cam.is_gv_device() else "USB3 Vision/other",
            "sensor_px": [sw, sh],
            "resolution": [region[2], region[3]],
            "offset_px": [region[0], region[1]],
            "pixel_format": cam.get_pixel_format_as_string(),
            "bit_depth": pixel_format_bits(self.settings.pixel_format),
            "color_filter": pixel_format_cfa(self.settings.pixel_format),
            "exposure_range_s": [float(exp.min) * 1e-6, float(exp.max) * 1e-6],
            "gain": float(cam.get_gain()) if cam.is_gain_available() else None,
        }
        if cam.is_gv_device():
            facts["packet_size_bytes"] = int(cam.gv_get_packet_size())
        for key, feature in (("firmware", "DeviceFirmwareVersion"), ("version", "DeviceVersion")):
            if dev.get_feature(feature) is not None:
                try:
                    facts[key] = dev.get_string_feature_value(feature)
                except self._GLib.Error:
                    pass
        return facts

    # -- Camera protocol ----------------------------------------------------------------------
    def supported_exposures(self) -> tuple[float, float]:
        lo, hi = self.options.exposure_range_s
        dlo, dhi = self._device_facts["exposure_range_s"]
        return max(lo, dlo), min(hi, dhi)

    def describe(self) -> dict[str, Any]:
        out = {**self.options.info, **self._device_facts}
        if self._exposure_set_us is not None:
            out["exposure_s"] = self._exposure_set_us / 1e6  # the last one read back
        out["frames"] = self.frames
        out["failed_attempts"] = self.failed_attempts
        return out

    def capture(self, exposure_s: float) -> Frame:
        lo, hi = self.supported_exposures()
        if not lo <= exposure_s <= hi:
            raise ValueError(f"exposure {exposure_s} s outside the camera's range {lo}..{hi} s")
        if self._stream is None:
            raise DeviceFault(f"camera {self.device_id} is closed")
        try:
            actual_us = self._set_exposure(exposure_s * 1e6)
            notes: list[str] = []
            for attempt in range(self.settings.retries + 1):
                got = self._one_attempt()
                if isinstance(got, str):
                    notes.append(f"attempt {attempt + 1}: {got}")
                    self.failed_attempts += 1
                    continue
                pixels, frame_id, timestamp_ns = got
                self.frames += 1
                return self._frame(pixels, exposure_s, actual_us, frame_id, timestamp_ns, attempt)
        except self._GLib.Error as exc:
            raise DeviceFault(f"camera {self.device_id}: {exc.message}") from exc
        raise DeviceFault(
            f"camera {self.device_id}: no complete frame in {self.settings.retries + 1} "
            f"attempt(s) ({'; '.join(notes)})"
        )

    def _set_exposure(self, exposure_us: float) -> float:
        cam = self._camera
        if self._requested_us is None or abs(exposure_us - self._requested_us) > 1e-9:
            cam.set_exposure_time(exposure_us)
            self._requested_us = exposure_us
            self._exposure_set_us = float(cam.get_exposure_time())
        return self._exposure_set_us

    def _drain(self) -> None:
        """Return buffers that arrived after an earlier attempt gave up on them."""
        while (buf := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buf)

    def _one_attempt(self) -> tuple[np.ndarray, int, int] | str:
        """Trigger one frame; its pixels, frame id and timestamp, or what went wrong."""
        Aravis = self._Aravis
        self._drain()
        self._camera.software_trigger()
        deadline = time.monotonic() + self.options.timeout_s
        while (left_s := deadline - time.monotonic()) > 0:
            buf = self._stream.timeout_pop_buffer(max(int(left_s * 1e6), 1))
            if buf is None:
                break
            try:
                status = buf.get_status()
                frame_id = int(buf.get_frame_id())
                if frame_id == self._last_frame_id:  # a stale copy of the previous frame
                    continue
                if status != Aravis.BufferStatus.SUCCESS:
                    return f"buffer {status.value_nick} (frame {frame_id})"
                pixels = self._pixels(buf)
                if isinstance(pixels, str):
                    return pixels
                self._last_frame_id = frame_id
                return pixels, frame_id, int(buf.get_timestamp())
            finally:
                self._stream.push_buffer(buf)
        return f"no buffer within {self.options.timeout_s:g} s"

    def _pixels(self, buf: Any) -> np.ndarray | str:
        w, h = self.options.resolution
        if (int(buf.get_image_width()), int(buf.get_image_height())) != (w, h):
            return f"frame of {buf.get_image_width()}×{buf.get_image_height()}, not {w}×{h}"
        data = buf.get_data()
        need = w * h * self._bytes_pp
        if len(data) < need:
            return f"incomplete payload ({len(data)} of {need} bytes)"
        dtype = np.uint8 if self._bytes_pp == 1 else np.dtype("<u2")
        return np.frombuffer(data, dtype=dtype, count=w * h).reshape(h, w).copy()

    def _frame(
        self,
        pixels: np.ndarray,
        exposure_s: float,
        actual_us: float,
        frame_id: int,
        timestamp_ns: int,
        retries: int,
    ) -> Frame:
        s, facts = self.settings, self._device_facts
        bits = pixel_format_bits(s.pixel_format)
        white = self.options.white_level_dn
        white = int(white) if white is not None else 2**bits - 1
        md = {
            "exposure_s": actual_us / 1e6,
            "exposure_commanded_s": exposure_s,
            "gain": facts["gain"],
            "device_id": self.device_id,
            "camera_model": facts["model"],
            "serial": facts["serial"],
            "pixel_format": s.pixel_format,
            "frame_id": frame_id,
            "timestamp_ns": timestamp_ns,
            "retries": retries,
            "black_level": float(self.options.black_level_dn),
            "white_level": white,
        }
        cfa = pixel_format_cfa(s.pixel_format)
        if cfa == "mono":
            data = encode_mono_tiff(pixels, md)
            return Frame(data=data, suffix=".tif", metadata=md)
        mosaic = pixels.astype(np.uint16)
        data = encode_dng(mosaic, md, cfa_pattern=cfa, camera_model=facts["model"])
        return Frame(data=data, suffix=".dng", metadata=md)

    def close(self) -> None:
        cam, self._camera = self._camera, None
        self._stream = None
        if cam is not None:
            try:
                cam.stop_acquisition()
            except Exception:  # a camera that went away cannot be stopped; nothing to undo
                pass


def aravis_camera(config: Any, clock: Any = None) -> AravisCamera:
    """Factory for `CAMERA_BACKENDS["aravis"]` from a RigConfig."""
    cam = config.camera
    s = cam.aravis
    if pixel_format_cfa(s.pixel_format) != "mono" and min(cam.resolution) < MIN_DNG_SIDE:
        raise DeviceFault(
            f"camera.resolution {list(cam.resolution)}: Bayer frames are stored as DNG, which "
            f"LibRaw reads from {MIN_DNG_SIDE} px a side"
        )
    return AravisCamera(
        AravisOptions(
            settings=s,
            resolution=tuple(cam.resolution),
            timeout_s=cam.timeout_s,
            exposure_range_s=(cam.exposure_min_s, cam.exposure_max_s),
            black_level_dn=cam.black_level_dn,
            white_level_dn=cam.white_level_dn,
        )
    )
