"""Frame encoders for the simulated camera: linear OpenEXR and Bayer DNG, returned as bytes.

EXR (OpenEXR 3.5 Python API): float32 pixels in an "RGB" (or single "Y") channel group, and the
capture metadata as a JSON string header attribute ``gonio`` — a Python float attribute would be
stored as float32 and lose precision (docs/design.md §7), a JSON string is exact.

DNG: `acquisition.frame_files.encode_dng`, the one DNG writer, shared with the real drivers that
receive bare pixels (re-exported here); the simulated sensor is "raw RGB" (identity colour
matrix).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from acquisition.frame_files import CFA_CODES, MIN_DNG_SIDE, encode_dng
from acquisition.frame_files import metadata_json as _json

__all__ = [
    "encode_exr",
    "encode_dng",
    "encode_capture",
    "CFA_CODES",
    "METADATA_ATTRIBUTE",
    "MIN_DNG_SIDE",
]

METADATA_ATTRIBUTE = "gonio"


def encode_exr(image: np.ndarray, metadata: dict | None = None) -> bytes:
    """float32 (H, W, 3) → EXR with channels R, G, B; (H, W) → channel Y. Returns the file bytes."""
    import OpenEXR

    arr = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if arr.ndim == 3 and arr.shape[-1] == 3:
        channels = {"RGB": arr}
    elif arr.ndim == 2:
        channels = {"Y": arr}
    else:
        raise ValueError(f"EXR image must be (H, W, 3) or (H, W), got {arr.shape}")
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        METADATA_ATTRIBUTE: _json(metadata or {}),
    }
    # The OpenEXR binding writes to a path only: go through a private temp file.
    fd, path = tempfile.mkstemp(suffix=".exr")
    os.close(fd)
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(path)
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.unlink(path)


def encode_capture(
    dn: np.ndarray, spec, fmt: str, metadata: dict | None = None
) -> tuple[bytes, str]:
    """Encode one sensor capture in the scene's format; returns (bytes, file suffix).

    ``spec`` is the scene's ``SensorSpec``: its black level and ADC white level (2^bits − 1) go
    into the file. "dng" needs a Bayer mosaic (H, W) uint16; "exr" stores the DN as float32
    (exact below 2^24) with ``black_level``/``white_level`` in the JSON metadata, so
    ``calibration.decode.linear`` works the same way for both.
    """
    md = dict(metadata or {})
    md.setdefault("black_level", float(spec.black_level_dn))
    md.setdefault("white_level", int(2**spec.adc_bits - 1))
    if fmt == "dng":
        if np.ndim(dn) != 2:
            raise ValueError("DNG output needs a Bayer sensor (sensor.bayer = 'RGGB')")
        return encode_dng(
            np.asarray(dn, dtype=np.uint16),
            md,
            cfa_pattern=spec.bayer or "RGGB",
            black_level=float(spec.black_level_dn),
            white_level=int(2**spec.adc_bits - 1),
        ), ".dng"
    if fmt == "exr":
        return encode_exr(np.asarray(dn, dtype=np.float32), md), ".exr"
    raise ValueError(f"unknown frame format {fmt!r} (expected 'exr' or 'dng')")
