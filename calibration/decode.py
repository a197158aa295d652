"""Decode camera frames (DNG/NEF/... RAW through rawpy, linear EXR through OpenEXR) to DN arrays.

RAW follows docs/design.md §7 (rawpy 0.28 / LibRaw 0.22): we take ``raw_image_visible`` (the sensor
values with the masked border cropped, no demosaic, no scaling) and LibRaw's per-colour black level,
``black_level_per_channel``, which is indexed by *colour index* (``raw_colors_visible``), not by
position in the 2×2 pattern. The linear value is

    linear = (DN − black[colour_index]) / (white − black[colour_index])        (docs/design.md §7)

and no postprocess/auto-brightness is ever applied, so absolute values survive. The white level
reported by LibRaw is the nominal one; the real clip level can be lower — calibration measures it.

Exposure time: from the gonio JSON metadata (DNG ImageDescription / EXR ``gonio`` attribute) when
present (exact), else LibRaw's EXIF shutter speed (float32), else NaN.

Every failure raises ``FrameError`` (a ``ValueError``) with a one-line message naming the file.
What the C libraries print on the process's stderr while reading a file (OpenEXR's "corrupt
chunk leader", LibRaw's I/O complaints, tifffile's log) is collected instead: it becomes the
reason in that one line when the read fails, and is passed on unchanged when it succeeds.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plumbing.errors import UserError
from plumbing.hashing import sha256_file
from plumbing.inputs import FRAME_MAX_BYTES, NotAnInputFile, check_input

__all__ = [
    "DecodedFrame",
    "FrameError",
    "FrameIntegrityError",
    "decode_frame",
    "linear",
    "demosaic_to_rgb",
    "RAW_SUFFIXES",
    "EXR_SUFFIXES",
    "MONO_SUFFIXES",
]

RAW_SUFFIXES = frozenset(
    {".dng", ".nef", ".nrw", ".cr2", ".cr3", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw"}
)
EXR_SUFFIXES = frozenset({".exr"})
# Monochrome 8/16-bit TIFF (a GenICam camera's Mono8/Mono16 frames, acquisition.frame_files).
MONO_SUFFIXES = frozenset({".tif", ".tiff"})
_TIFF_RAW_SUFFIXES = frozenset({".dng", ".nef", ".nrw", ".arw", ".pef", ".srw"})
METADATA_ATTRIBUTE = "gonio"


class FrameError(UserError, ValueError):
    """A frame that cannot be decoded; the message is one line and names the file."""


class FrameIntegrityError(FrameError):
    """A frame whose SHA-256 is not the one the manifest recorded at capture (changed, swapped
    or replaced since): never used as if it were that capture."""


@dataclass
class DecodedFrame:
    """One decoded frame.

    dn : float32 (H, W, C) for RGB frames, (H, W) for a CFA mosaic.
    channels : "RGB" | "Y" | "CFA".
    cfa_pattern : e.g. "RGGB" (letters of the top-left 2×2 tile, row-major) or None.
    black_level : float32 array broadcastable to ``dn`` (per pixel for a mosaic: the black of
        each site's colour index; (C,) or scalar for RGB).
    white_level : nominal white (DN).
    exposure_s : exposure time (s), NaN if unknown.
    metadata : the gonio JSON metadata if present, else {}.
    """

    dn: np.ndarray
    channels: str
    cfa_pattern: str | None
    black_level: np.ndarray
    white_level: float
    exposure_s: float
    metadata: dict = field(default_factory=dict)
    path: str = ""


def linear(frame: DecodedFrame) -> np.ndarray:
    """(DN − black) / (white − black), float32, same shape as ``frame.dn`` (docs/design.md §7)."""
    black = np.asarray(frame.black_level, dtype=np.float32)
    return ((frame.dn - black) / (np.float32(frame.white_level) - black)).astype(np.float32)


def demosaic_to_rgb(mosaic: np.ndarray, pattern: str = "RGGB") -> np.ndarray:
    """2×2 superpixel demosaic: (H, W) → (H//2, W//2, 3), the two greens averaged.

    No interpolation, so every output value is a plain (average of) measured site(s): the
    radiometrically honest choice, at half resolution. Odd trailing rows/columns are dropped.
    """
    if len(pattern) != 4 or sorted(pattern) != ["B", "G", "G", "R"]:
        raise ValueError(f"pattern must be a 2×2 Bayer pattern like 'RGGB' (got {pattern!r})")
    m = np.asarray(mosaic, dtype=np.float32)
    h, w = (m.shape[0] // 2) * 2, (m.shape[1] // 2) * 2
    sites = {}
    for k, letter in enumerate(pattern):
        dy, dx = divmod(k, 2)
        sites.setdefault(letter, []).append(m[dy:h:2, dx:w:2])
    return np.stack([sites["R"][0], 0.5 * (sites["G"][0] + sites["G"][1]), sites["B"][0]], axis=-1)


class _NativeStderr:
    """File descriptor 2 redirected to one temp file while any decode runs, in any thread.

    fd 2 belongs to the whole process, and the frames are decoded on background threads
    (plumbing.prefetch): two decodes each saving and restoring fd 2 on their own could restore
    it in the wrong order and leave it pointing at a deleted temp file, so that every later line
    on stderr — the command's one-line error included — vanished (seen: `gonio calibrate` exit 2
    with an empty stderr). So the first decode to enter redirects, the last to leave restores,
    under one lock; each decode reads what was written while it ran (a message another thread's
    decode wrote meanwhile may come with it: C libraries rarely say anything)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._depth = 0
        self._saved: int | None = None
        self._file = None
        self._tifffile_was_disabled = False

    def enter(self) -> int | None:
        """Redirect (if first); returns the offset this decode's text starts at, None when
        there is no usable fd 2."""
        with self._lock:
            if self._depth == 0:
                try:
                    sys.stderr.flush()
                    saved = os.dup(2)
                except (OSError, ValueError):
                    return None
                self._file = tempfile.TemporaryFile()
                os.dup2(self._file.fileno(), 2)
                self._saved = saved
                # tifffile logs its complaints (Python's logging, not fd 2): quiet too
                quiet = logging.getLogger("tifffile")
                self._tifffile_was_disabled, quiet.disabled = quiet.disabled, True
            self._depth += 1
            return os.fstat(self._file.fileno()).st_size

    def leave(self, start: int) -> str:
        """Restore (if last); returns the text written since ``start``."""
        with self._lock:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            text = os.pread(self._file.fileno(), 1 << 20, start).decode("utf-8", "replace")
            self._depth -= 1
            if self._depth == 0:
                os.dup2(self._saved, 2)
                os.close(self._saved)
                self._file.close()
                self._saved = self._file = None
                logging.getLogger("tifffile").disabled = self._tifffile_was_disabled
            return text


_NATIVE_STDERR = _NativeStderr()


@contextmanager
def _native_stderr(collected: list[str]) -> Iterator[None]:
    """Redirect file descriptor 2 (where C libraries write) for the duration (shared with the
    other threads' decodes, _NativeStderr); its text is appended to ``collected``. Without a
    usable fd 2 nothing is redirected."""
    start = _NATIVE_STDERR.enter()
    if start is None:
        yield
        return
    try:
        yield
    finally:
        collected.append(_NATIVE_STDERR.leave(start))


def _first_line(collected: list[str]) -> str:
    for text in collected:
        for line in text.splitlines():
            if line.strip():
                return line.strip()
    return ""


def _pass_on(collected: list[str]) -> None:
    """A successful read keeps whatever the library said (it may be a real warning)."""
    text = "".join(collected)
    if text:
        sys.stderr.write(text)


def decode_frame(path, sha256: str | None = None) -> DecodedFrame:
    """Decode a RAW (DNG, NEF, ...) or EXR file. Raises ``FrameError`` with a one-line message.

    ``sha256``: the digest the manifest recorded at capture; the file is checked against it
    before it is decoded (``FrameIntegrityError``), so a swapped or edited frame is never taken
    for its capture. Costs one read of the file (~50 ms for a 25 MB RAW)."""
    p = Path(path)
    suffix = p.suffix.lower()
    try:
        check_input(p, "frame", FRAME_MAX_BYTES)
    except FileNotFoundError:
        raise FrameError(f"{p}: no such file") from None
    except NotAnInputFile as exc:  # a FIFO or device in frames/ would block the reduction
        raise FrameError(str(exc)) from None
    if sha256 is not None and sha256_file(p) != sha256:
        changed = "SHA-256 differs from the manifest's (changed or swapped since capture)"
        try:
            decode_frame(p)
        except FrameError as exc:  # say what is wrong with it, too (truncated, not a RAW...)
            raise FrameIntegrityError(f"{exc}; its {changed}") from None
        raise FrameIntegrityError(f"{p}: {changed}")
    if suffix in EXR_SUFFIXES:
        return _decode_exr(p)
    if suffix in RAW_SUFFIXES:
        return _decode_raw(p)
    if suffix in MONO_SUFFIXES:
        return _decode_mono_tiff(p)
    raise FrameError(
        f"{p}: unknown frame suffix {p.suffix!r} (expected .exr, .tif or a RAW such as .dng/.nef)"
    )


@contextmanager
def _tifffile_quiet() -> Iterator[None]:
    """tifffile logs a warning for a file that is not TIFF; here that is a question we ask,
    and the answer goes into the FrameError (or LibRaw's), not onto the terminal."""
    log = logging.getLogger("tifffile")
    was, log.disabled = log.disabled, True
    try:
        yield
    finally:
        log.disabled = was


def _tiff_metadata(p: Path) -> tuple[dict, float]:
    """gonio JSON from ImageDescription and EXIF ExposureTime of a TIFF-based RAW, if any."""
    import tifffile

    md: dict = {}
    exposure = float("nan")
    try:
        with _tifffile_quiet(), tifffile.TiffFile(p) as tif:
            page = tif.pages[0]
            desc = page.tags.get(270)
            if desc is not None:
                try:
                    obj = json.loads(desc.value)
                    md = obj if isinstance(obj, dict) else {}
                except (ValueError, TypeError):
                    md = {}
            et = page.tags.get(33434)
            if et is None and page.tags.get(34665) is not None:  # EXIF IFD
                et_val = page.tags[34665].value.get("ExposureTime")
            else:
                et_val = et.value if et is not None else None
            if et_val is not None:
                num, den = et_val if isinstance(et_val, tuple) else (et_val, 1)
                exposure = num / den if den else float("nan")
    except Exception:  # not TIFF-based (CR3, RAF): metadata is optional
        pass
    return md, exposure


def _check_tiff_complete(p: Path) -> None:
    """Raise FrameError if a TIFF-based RAW's image strips/tiles run past the end of the file.

    LibRaw would also fail (LibRawIOError) but only after printing to stderr; this names the cause.
    """
    import tifffile

    size = p.stat().st_size
    try:
        with _tifffile_quiet(), tifffile.TiffFile(p) as tif:
            need = 0
            for page in tif.pages:
                offs, counts = page.dataoffsets, page.databytecounts
                if offs and counts:
                    need = max(need, max(o + c for o, c in zip(offs, counts, strict=False)))
    except Exception:  # unreadable as TIFF: leave the diagnosis to LibRaw
        return
    if need > size:
        raise FrameError(f"{p}: truncated RAW (file has {size} bytes, image data needs {need})")


def _decode_raw(p: Path) -> DecodedFrame:
    import rawpy

    if p.suffix.lower() in _TIFF_RAW_SUFFIXES:
        _check_tiff_complete(p)

    native: list[str] = []
    try:
        with _native_stderr(native), rawpy.imread(str(p)) as raw:
            if raw.raw_type != rawpy.RawType.Flat:
                raise FrameError(f"{p}: not a Bayer sensor raw ({raw.raw_type})")
            dn = np.array(raw.raw_image_visible, dtype=np.float32)
            colors = np.array(raw.raw_colors_visible)
            black_per_colour = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = float(raw.white_level)
            desc = raw.color_desc.decode("ascii", "replace")
            pattern_idx = np.asarray(raw.raw_pattern)
            shutter = float(raw.other.shutter_speed)
    except FrameError:
        raise
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        msg = str(exc).strip("b'\"")
        said = _first_line(native)
        detail = f"{type(exc).__name__}: {msg}" + (f"; {said}" if said else "")
        raise FrameError(f"{p}: cannot decode RAW ({detail})") from None
    _pass_on(native)
    if pattern_idx.shape != (2, 2):
        raise FrameError(f"{p}: unsupported CFA repeat {pattern_idx.shape} (only 2×2 Bayer)")
    cfa = "".join(desc[i] for i in pattern_idx.ravel())
    if sorted(cfa) != ["B", "G", "G", "R"]:
        raise FrameError(f"{p}: unsupported CFA colours {cfa!r} (only R/G/B Bayer)")
    # Per-pixel black: indexed by colour index (not by pattern position) — docs/design.md §7.
    black = black_per_colour[colors]
    if p.suffix.lower() in _TIFF_RAW_SUFFIXES:
        md, tiff_exposure = _tiff_metadata(p)
    else:
        md, tiff_exposure = {}, float("nan")
    exposure = md.get("exposure_s")
    if exposure is None:  # exact rational EXIF value first, LibRaw's float32 copy last
        if np.isfinite(tiff_exposure):
            exposure = tiff_exposure
        else:
            exposure = shutter if shutter > 0 else float("nan")
    return DecodedFrame(
        dn=dn,
        channels="CFA",
        cfa_pattern=cfa,
        black_level=black,
        white_level=white,
        exposure_s=float(exposure),
        metadata=md,
        path=str(p),
    )


def _decode_exr(p: Path) -> DecodedFrame:
    import OpenEXR

    native: list[str] = []
    try:
        with _native_stderr(native), OpenEXR.File(str(p)) as f:
            # Copy: the binding clears the header dict in place when the file is closed.
            header = dict(f.header())
            chans = f.channels()
            if "RGB" in chans:
                dn = np.array(chans["RGB"].pixels, dtype=np.float32)
                kind = "RGB"
            elif "Y" in chans:
                dn = np.array(chans["Y"].pixels, dtype=np.float32)
                kind = "Y"
            else:
                names = ", ".join(sorted(chans)) or "none"
                raise FrameError(f"{p}: EXR has no R,G,B or Y channels (found: {names})")
    except FrameError:
        raise
    except Exception as exc:  # OpenEXR raises plain RuntimeError/Exception
        # The library's own complaint (e.g. "corrupt leader ... file offset N") says more than
        # the exception the binding raises afterwards; drop the repeated path from it.
        said = _first_line(native).replace(f"{p}: ", "")
        detail = said or f"{type(exc).__name__}: {exc}"
        raise FrameError(f"{p}: cannot read EXR ({detail})") from None
    _pass_on(native)
    if kind == "RGB" and (dn.ndim != 3 or dn.shape[-1] != 3):
        raise FrameError(f"{p}: EXR RGB channels have unexpected shape {dn.shape}")
    md: dict = {}
    raw_md = header.get(METADATA_ATTRIBUTE)
    if raw_md is not None:
        try:
            md = json.loads(raw_md)
        except (ValueError, TypeError):
            raise FrameError(f"{p}: EXR attribute {METADATA_ATTRIBUTE!r} is not JSON") from None
    black = np.float32(md.get("black_level", 0.0))
    white = float(md.get("white_level", 1.0))
    return DecodedFrame(
        dn=dn,
        channels=kind,
        cfa_pattern=None,
        black_level=np.asarray(black, dtype=np.float32),
        white_level=white,
        exposure_s=float(md.get("exposure_s", float("nan"))),
        metadata=md,
        path=str(p),
    )


def _decode_mono_tiff(p: Path) -> DecodedFrame:
    """A monochrome uint8/uint16 TIFF (acquisition.frame_files.encode_mono_tiff): DN as they are,
    black/white level and exposure from the gonio JSON in ImageDescription (exact), else the
    EXIF ExposureTime, else NaN; without metadata the black level is 0 and white the dtype's max.
    """
    import tifffile

    _check_tiff_complete(p)
    try:
        with _tifffile_quiet(), tifffile.TiffFile(p) as tif:
            page = tif.pages[0]
            arr = page.asarray()
    except Exception as exc:  # tifffile raises many kinds; one line for all
        raise FrameError(f"{p}: cannot read TIFF ({type(exc).__name__}: {exc})") from None
    if arr.ndim != 2 or arr.dtype not in (np.uint8, np.uint16):
        raise FrameError(
            f"{p}: not a monochrome 8/16-bit frame (shape {arr.shape}, dtype {arr.dtype})"
        )
    md, tiff_exposure = _tiff_metadata(p)
    exposure = md.get("exposure_s", tiff_exposure)
    return DecodedFrame(
        dn=arr.astype(np.float32),
        channels="Y",
        cfa_pattern=None,
        black_level=np.asarray(np.float32(md.get("black_level", 0.0))),
        white_level=float(md.get("white_level", np.iinfo(arr.dtype).max)),
        exposure_s=float(exposure),
        metadata=md,
        path=str(p),
    )
