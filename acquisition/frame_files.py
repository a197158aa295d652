"""Frame files a camera driver writes itself: Bayer DNG and 16-bit monochrome TIFF, as bytes.

Used by real drivers that receive bare pixels (a GenICam camera through Aravis) and by the
simulated camera (simulator.frames), so there is one writer; `calibration.decode` reads both.

DNG (written with tifffile, read by rawpy/LibRaw, docs/design.md §7): one uncompressed 16-bit CFA
IFD with the tags LibRaw needs — PhotometricInterpretation 32803 (CFA), CFARepeatPatternDim 33421,
CFAPattern 33422, DNGVersion 50706, UniqueCameraModel 50708, CFAPlaneColor 50710, CFALayout 50711,
BlackLevelRepeatDim 50713, BlackLevel 50714, WhiteLevel 50717, ColorMatrix1 50721 (identity: "raw
RGB"), AsShotNeutral 50728, CalibrationIlluminant1 50778, ExposureTime 33434 — plus the gonio
metadata JSON in ImageDescription (270).

Monochrome TIFF: one uncompressed uint16 (or uint8) plane, PhotometricInterpretation
BlackIsZero, ExposureTime 33434 and the same JSON in ImageDescription. LibRaw does not read
monochrome TIFF as a raw, so `calibration.decode` reads it with tifffile.
"""

from __future__ import annotations

import io
import json
from fractions import Fraction

import numpy as np

__all__ = [
    "encode_dng",
    "encode_mono_tiff",
    "metadata_json",
    "rational",
    "CFA_CODES",
    "MIN_DNG_SIDE",
]

# LibRaw 0.22 answers "Unsupported file format" below 22 px a side (measured: 21 fails, 22 reads).
MIN_DNG_SIDE = 22
# TIFF/EP CFA colour codes: 0 = red, 1 = green, 2 = blue.
CFA_CODES = {"R": 0, "G": 1, "B": 2}


def metadata_json(metadata: dict) -> str:
    """The capture metadata as JSON; floats are written with repr → exact float64 round trip."""
    return json.dumps(metadata, sort_keys=True, default=_json_default)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"metadata value of type {type(obj).__name__} is not JSON serialisable")


def rational(x: float, max_den: int = 1_000_000) -> tuple[int, int]:
    """(numerator, denominator) of the closest fraction with a bounded denominator."""
    fr = Fraction(float(x)).limit_denominator(max_den)
    return fr.numerator, fr.denominator


def _exposure_tag(exposure_s: float | None) -> list[tuple]:
    if exposure_s is None:
        return []
    return [(33434, "2I", 1, rational(exposure_s, 1_000_000_000), True)]  # ExposureTime


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
    bl_num, bl_den = rational(black_level)
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
        (50728, "2I", 3, sum((rational(v) for v in as_shot_neutral), ()), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1 = D65
        *_exposure_tag(exposure_s),
    ]
    buf = io.BytesIO()
    tifffile.imwrite(
        buf,
        arr,
        photometric=32803,  # CFA
        compression=None,
        planarconfig="contig",
        subfiletype=0,
        description=metadata_json(md),
        software="gonio",
        metadata=None,
        extratags=extratags,
    )
    return buf.getvalue()


def encode_mono_tiff(
    image: np.ndarray,
    metadata: dict | None = None,
    *,
    black_level: float = 0.0,
    white_level: int | None = None,
    exposure_s: float | None = None,
) -> bytes:
    """uint8 or uint16 (H, W) monochrome frame → TIFF bytes with the gonio JSON metadata
    (black_level, white_level, exposure_s and whatever else the driver reported)."""
    import tifffile

    arr = np.ascontiguousarray(np.asarray(image))
    if arr.ndim != 2 or arr.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"a mono frame must be uint8/uint16 (H, W), got {arr.dtype} {arr.shape}")
    md = dict(metadata or {})
    if white_level is None:
        white_level = int(md.get("white_level", np.iinfo(arr.dtype).max))
    if exposure_s is None and "exposure_s" in md:
        exposure_s = float(md["exposure_s"])
    md.setdefault("black_level", float(black_level))
    md.setdefault("white_level", int(white_level))
    if exposure_s is not None:
        md.setdefault("exposure_s", float(exposure_s))
    buf = io.BytesIO()
    tifffile.imwrite(
        buf,
        arr,
        photometric="minisblack",
        compression=None,
        description=metadata_json(md),
        software="gonio",
        metadata=None,
        extratags=_exposure_tag(exposure_s),
    )
    return buf.getvalue()
