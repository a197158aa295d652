"""Frame encoders for the simulated camera: linear OpenEXR and Bayer DNG, returned as bytes.

EXR (OpenEXR 3.5 Python API): float32 pixels in an "RGB" (or single "Y") channel group, and the
capture metadata as a JSON string header attribute ``gonio`` — a Python float attribute would be
stored as float32 and lose precision (DESIGN §7), a JSON string is exact.

DNG (written with tifffile, read by rawpy/LibRaw): one uncompressed 16-bit CFA IFD with the tags
LibRaw needs — PhotometricInterpretation 32803 (CFA), CFARepeatPatternDim 33421,
CFAPattern 33422, DNGVersion 50706, UniqueCameraModel 50708, CFAPlaneColor 50710,
CFALayout 50711, BlackLevelRepeatDim 50713, BlackLevel 50714, WhiteLevel 50717,
ColorMatrix1 50721 (identity: the simulated sensor is "raw RGB"), AsShotNeutral 50728,
CalibrationIlluminant1 50778, ExposureTime 33434 — plus the gonio metadata JSON in
ImageDescription (270).
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from fractions import Fraction

import numpy as np

__all__ = [
    "encode_exr",
    "encode_dng",
    "encode_capture",
    "CFA_CODES",
    "METADATA_ATTRIBUTE",
    "MIN_DNG_SIDE",
]

METADATA_ATTRIBUTE = "gonio"
# LibRaw 0.22 answers "Unsupported file format" below 22 px a side (measured: 21 fails, 22 reads).
MIN_DNG_SIDE = 22
# TIFF/EP CFA colour codes: 0 = red, 1 = green, 2 = blue.
CFA_CODES = {"R": 0, "G": 1, "B": 2}


def _json(metadata: dict) -> str:
    # json writes floats with repr → exact float64 round trip.
    return json.dumps(metadata, sort_keys=True, default=_json_default)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"metadata value of type {type(obj).__name__} is not JSON serialisable")


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


def _rational(x: float, max_den: int = 1_000_000) -> tuple[int, int]:
    fr = Fraction(float(x)).limit_denominator(max_den)
    return fr.numerator, fr.denominator


def encode_dng(
    mosaic: np.ndarray,
    metadata: dict | None = None,
    *,
    cfa_pattern: str = "RGGB",
    black_level: float = 0.0,
    white_level: int | None = None,
    exposure_s: float | None = None,
    as_shot_neutral=(1.0, 1.0, 1.0),
    camera_model: str = "gonio simulated camera",
) -> bytes:
    """uint16 (H, W) Bayer mosaic → DNG 1.4 bytes readable by rawpy.

    ``black_level``, ``white_level`` (default from ``metadata["white_level"]`` or 65535) and
    ``exposure_s`` fall back to the same keys in ``metadata``; the full metadata dict is stored
    as JSON in ImageDescription.
    """
    import tifffile

    md = dict(metadata or {})
    if black_level == 0.0 and "black_level" in md:
        black_level = float(md["black_level"])
    if white_level is None:
        white_level = int(md.get("white_level", 65535))
    if exposure_s is None and "exposure_s" in md:
        exposure_s = float(md["exposure_s"])
    md.setdefault("black_level", black_level)
    md.setdefault("white_level", white_level)
    md.setdefault("cfa_pattern", cfa_pattern)
    if exposure_s is not None:
        md.setdefault("exposure_s", exposure_s)

    arr = np.ascontiguousarray(np.asarray(mosaic))
    if arr.ndim != 2:
        raise ValueError(f"DNG mosaic must be 2-D (H, W), got {arr.shape}")
    if arr.dtype != np.uint16:
        raise ValueError(f"DNG mosaic must be uint16, got {arr.dtype}")
    if min(arr.shape) < MIN_DNG_SIDE:
        raise ValueError(
            f"LibRaw rejects DNGs smaller than {MIN_DNG_SIDE} px a side (got {arr.shape})"
        )
    if len(cfa_pattern) != 4 or set(cfa_pattern) - set("RGB"):
        raise ValueError(
            f"cfa_pattern must be 4 letters of R/G/B, e.g. 'RGGB' (got {cfa_pattern!r})"
        )

    # BlackLevel as a RATIONAL keeps non-integer black levels; one value for the whole 1×1 tile.
    bl_num, bl_den = _rational(black_level)
    extratags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(CFA_CODES[c] for c in cfa_pattern), True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, camera_model, True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, "H", 1, 1, True),  # CFALayout: rectangular
        (50713, "H", 2, (1, 1), True),  # BlackLevelRepeatDim
        (50714, "2I", 1, (bl_num, bl_den), True),  # BlackLevel (RATIONAL)
        (50717, "I", 1, int(white_level), True),  # WhiteLevel
        # ColorMatrix1 = identity (camera RGB ≡ XYZ): LibRaw needs one to accept the DNG.
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
        (50728, "2I", 3, sum((_rational(v) for v in as_shot_neutral), ()), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1 = D65
    ]
    if exposure_s is not None:
        extratags.append((33434, "2I", 1, _rational(exposure_s, 1_000_000_000), True))
    buf = io.BytesIO()
    tifffile.imwrite(
        buf,
        arr,
        photometric=32803,  # CFA
        compression=None,
        planarconfig="contig",
        subfiletype=0,
        description=_json(md),
        software="gonio",
        metadata=None,
        extratags=extratags,
    )
    return buf.getvalue()


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
