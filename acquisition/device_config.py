"""The settings of the real device backends, as rig-file subtables: `[camera.aravis]`,
`[camera.gphoto2]` and `[light.scpi]` (acquisition.config embeds them; a misspelt key is an error
naming it, like every other key).

Units in the names (µs where GenICam counts in µs is converted at the driver: the rig file says
seconds like everywhere else).
"""

from __future__ import annotations

import re
from typing import Literal

from pydantic import Field, field_validator, model_validator

from plumbing.config import Strict

__all__ = [
    "AravisConfig",
    "Gphoto2Config",
    "ScpiConfig",
    "ARAVIS_PIXEL_FORMATS",
    "pixel_format_bits",
    "pixel_format_cfa",
]

# GenICam PFNC names the Aravis backend can store untouched: 8-bit formats one byte per pixel,
# 10..16-bit ones unpacked in two little-endian bytes. Packed formats (Mono12Packed, ...) would
# need unpacking that no test here could check against a device: refused at load.
_BAYER = ("RG", "GR", "GB", "BG")
ARAVIS_PIXEL_FORMATS = (
    *(f"Mono{b}" for b in (8, 10, 12, 14, 16)),
    *(f"Bayer{p}{b}" for p in _BAYER for b in (8, 10, 12, 16)),
)


def pixel_format_bits(name: str) -> int:
    """Significant bits per pixel of a PFNC name: "Mono12" → 12, "BayerRG8" → 8."""
    return int(re.sub(r"^\D+", "", name))


def pixel_format_cfa(name: str) -> str:
    """The rig file's color_filter for a PFNC name: "BayerRG8" → "RGGB", "Mono16" → "mono"."""
    if name.startswith("Mono"):
        return "mono"
    a, b = name[5], name[6]  # BayerXY: X at (0, 0), Y at (0, 1); the other row is the rest
    other = {"RG": "GB", "GR": "BG", "GB": "RG", "BG": "GR"}[a + b]
    return a + b + other


class AravisConfig(Strict):
    """A GenICam camera (GigE Vision, USB3 Vision) through Aravis (`camera.backend = "aravis"`).

    The region of interest is `camera.resolution` (width, height), at `offset_px` or centred on
    the sensor. Exposure is set per frame from the plan; `gain` is the camera's own gain
    feature (GenICam `Gain`, in dB, or `GainRaw` where that is all the camera has) — measure
    `camera.gain_e_per_dn` at this setting.
    """

    device: str = Field(
        "first",
        description='GenICam device ID as `arv-tool-0.8` lists it (e.g. "Basler-21234567"), '
        'or "first": the first camera found',
    )
    pixel_format: str = Field("Mono16", description="PFNC name: Mono8..Mono16, Bayer*8..16")
    gain: float | None = Field(None, description="the camera's gain feature; None: as it is")
    offset_px: tuple[int, int] | None = Field(
        None, description="ROI top-left corner (x, y) on the sensor; None: centred"
    )
    packet_size: int | None = Field(
        None, ge=576, le=65_000, description="GigE Vision stream packet size (bytes); None: auto"
    )
    retries: int = Field(
        4, ge=0, le=50, description="new exposures after a lost or incomplete buffer"
    )

    @field_validator("pixel_format")
    @classmethod
    def _format(cls, v: str) -> str:
        if v not in ARAVIS_PIXEL_FORMATS:
            raise ValueError(
                f"unsupported pixel_format {v!r}; one of {', '.join(ARAVIS_PIXEL_FORMATS)} "
                "(packed formats are not read)"
            )
        return v


class Gphoto2Config(Strict):
    """A camera libgphoto2 drives (DSLRs and mirrorless cameras over USB or PTP/IP,
    `camera.backend = "gphoto2"`). Settings left out stay as the camera has them."""

    camera: str | None = Field(
        None, description="model as `gphoto2 --auto-detect` lists it; None: the only one found"
    )
    port: str | None = Field(None, description='e.g. "usb:001,004"; None: wherever it is')
    iso: str | None = Field(None, description='an ISO choice of the camera, e.g. "100"')
    aperture: str | None = Field(None, description='an aperture choice, e.g. "8" (f/8)')
    image_format: Literal["raw", "raw+jpeg"] = Field(
        "raw", description='"raw+jpeg": the camera writes both, the JPEG is discarded'
    )
    raw_choice: str | None = Field(
        None,
        description="the imageformat/imagequality choice meaning RAW (or RAW+JPEG) on this "
        'camera, e.g. "NEF (Raw)"; None: the first choice naming RAW/NEF/CR2/ARW',
    )
    bulb: Literal["bulb", "eosremoterelease", "none"] = Field(
        "bulb",
        description="how exposures longer than the longest shutter speed are taken: the "
        '"bulb" toggle (Nikon, Sony...), Canon\'s "eosremoterelease", or "none" (refused)',
    )
    delete_after_download: bool = Field(True, description="free the card after each frame")


class ScpiConfig(Strict):
    """A SCPI lamp power supply or LED driver through PyVISA (`light.backend = "scpi"`,
    `light.url` = the VISA resource, e.g. "ASRL/dev/ttyUSB1::INSTR", "TCPIP::10.0.0.5::INSTR",
    "USB0::0x2A8D::0x1002::MY1234::INSTR").

    Level l ∈ [0, 1] of the run is the output `mode` quantity l · `full_scale` (A or V); the
    drift monitor is `monitor_query` (e.g. the measured current) divided by the full-scale
    value of the monitored quantity. Every command is followed by `error_query`; a non-zero
    error is a device fault. The command texts default to the SCPI-99 power-supply subsystem
    and can be replaced for a supply that spells them otherwise.
    """

    visa_library: str = Field(
        "@py",
        description='"@py" (pyvisa-py), "" (the system\'s VISA, e.g. NI-VISA), or '
        '"FILE.yaml@sim" (a pyvisa-sim definition, relative to the rig file)',
    )
    mode: Literal["current", "voltage"] = "current"
    full_scale: float = Field(gt=0, le=1e4, description="A or V at level 1")
    monitor_full_scale: float | None = Field(
        None, gt=0, description="monitor reading at level 1 (default: full_scale)"
    )
    channel: int | None = Field(None, ge=1, le=16, description="output of a multi-output supply")
    timeout_s: float = Field(2.0, gt=0, le=60, description="wait for each reply")
    retries: int = Field(1, ge=0, le=10, description="re-sent queries after a timeout")
    settle_s: float = Field(0.0, ge=0, le=600, description="after switching or a level change")
    output_on: str = "OUTP ON"
    output_off: str = "OUTP OFF"
    output_query: str = "OUTP?"
    set_level: str | None = Field(
        None, description='e.g. "CURR {value:.4f}"; default from mode (CURR or VOLT)'
    )
    monitor_query: str | None = Field(
        None, description='default from mode: "MEAS:CURR?" or "MEAS:VOLT?"'
    )
    error_query: str = "SYST:ERR?"
    clear: str = Field("*CLS", description="sent once when the supply is opened")
    select_channel: str = Field("INST:NSEL {channel}", description="with `channel`")
    read_termination: str = "\n"
    write_termination: str = "\n"

    @model_validator(mode="after")
    def _templates(self) -> ScpiConfig:
        if self.set_level is not None and "{value" not in self.set_level:
            raise ValueError(f"set_level {self.set_level!r} must contain {{value}}")
        return self

    @property
    def level_command(self) -> str:
        return self.set_level or ("CURR" if self.mode == "current" else "VOLT") + " {value:.6f}"

    @property
    def monitor_command(self) -> str:
        return self.monitor_query or ("MEAS:CURR?" if self.mode == "current" else "MEAS:VOLT?")
