"""The ``tensor_file`` container of the RGL material database (Dupuy & Jakob 2018, "An adaptive
parameterization for efficient material acquisition and rendering", ACM TOG 37(6); file layout
as read by RGL's reference loader ``powitacq_rgb.inl``, class ``Tensor``, and Mitsuba 3's
``TensorFile``).

Layout (little endian)::

    12 bytes   b"tensor_file\\0"
    2 bytes    version (major, minor) = (1, 0)
    uint32     number of fields
    per field: uint16 name length, name (ASCII), uint16 rank, uint8 dtype, uint64 offset,
               rank × uint64 shape
    then each field's data, C order, at its offset (8-byte aligned in the published files).

dtype codes: 1 uint8, 2 int8, 3 uint16, 4 int16, 5 uint32, 6 int32, 7 uint64, 8 int64,
9 float16, 10 float32, 11 float64.

:func:`read_tensor_file` keeps the fields in file order and :func:`write_tensor_file` writes
them back with the same layout, so read → write reproduces a published file byte for byte.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

import numpy as np

from brdfdata.formats.common import FormatError
from plumbing.atomic import atomic_write_bytes
from plumbing.inputs import DATA_MAX_BYTES, read_input_bytes

__all__ = ["MAGIC", "read_tensor_file", "write_tensor_file", "tensor_file_bytes", "is_tensor_file"]

MAGIC = b"tensor_file\0"
_DTYPES = {
    1: "u1",
    2: "i1",
    3: "<u2",
    4: "<i2",
    5: "<u4",
    6: "<i4",
    7: "<u8",
    8: "<i8",
    9: "<f2",
    10: "<f4",
    11: "<f8",
}
_CODES = {np.dtype(v).str.lstrip("|<"): k for k, v in _DTYPES.items()}


def is_tensor_file(path: str | os.PathLike) -> bool:
    """True when the file starts with the tensor_file magic."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def read_tensor_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All fields of a tensor file, in file order, as read-only numpy arrays of their dtype and
    shape. FormatError (one line, naming the file) for anything that is not a valid file."""
    path = Path(path)
    data = read_input_bytes(path, "RGL .bsdf file", DATA_MAX_BYTES)
    if len(data) < 18 or data[:12] != MAGIC:
        raise FormatError(
            f"{path}: not an RGL tensor file (no 'tensor_file' header); RGL materials are the "
            "*_rgb.bsdf / *_spec.bsdf files of https://rgl.epfl.ch/materials"
        )
    if data[12:14] != b"\x01\x00":
        raise FormatError(
            f"{path}: tensor file version {data[12]}.{data[13]}, this reader knows 1.0"
        )
    (n_fields,) = struct.unpack_from("<I", data, 14)
    pos, fields = 18, {}
    try:
        for _ in range(n_fields):
            (name_len,) = struct.unpack_from("<H", data, pos)
            name = data[pos + 2 : pos + 2 + name_len].decode("ascii")
            pos += 2 + name_len
            ndim, code, offset = struct.unpack_from("<HBQ", data, pos)
            pos += 11
            shape = struct.unpack_from(f"<{ndim}Q", data, pos)
            pos += 8 * ndim
            if code not in _DTYPES:
                raise FormatError(f"{path}: field {name!r} has unknown dtype code {code}")
            # Python's integers: an int64 product of a hostile shape wrapped round (to a small
            # or negative count) and reached numpy as an internal error
            count = math.prod(int(n) for n in shape)
            dt = np.dtype(_DTYPES[code])
            if offset + count * dt.itemsize > len(data):
                raise FormatError(f"{path}: field {name!r} runs past the end (truncated file?)")
            fields[name] = np.frombuffer(data, dt, count, offset).reshape(shape)
    except (struct.error, UnicodeDecodeError):
        raise FormatError(f"{path}: damaged tensor file header (truncated?)") from None
    return fields


def tensor_file_bytes(fields: dict[str, np.ndarray]) -> bytes:
    """The bytes of a tensor file holding ``fields`` (in dict order), data 8-byte aligned."""
    arrays = {name: np.ascontiguousarray(a) for name, a in fields.items()}
    header = bytearray(MAGIC + b"\x01\x00" + struct.pack("<I", len(arrays)))
    header_len = len(header) + sum(2 + len(n) + 11 + 8 * a.ndim for n, a in arrays.items())
    offset = _align(header_len)
    offsets = []
    for a in arrays.values():
        offsets.append(offset)
        offset = _align(offset + a.nbytes)
    for (name, a), off in zip(arrays.items(), offsets, strict=True):
        key = a.dtype.str.lstrip("|<")
        if key not in _CODES or a.dtype.byteorder == ">":
            raise ValueError(f"field {name!r}: dtype {a.dtype} has no tensor_file code")
        header += struct.pack("<H", len(name)) + name.encode("ascii")
        header += struct.pack("<HBQ", a.ndim, _CODES[key], off)
        header += struct.pack(f"<{a.ndim}Q", *a.shape)
    out = bytearray(offset)
    out[: len(header)] = header
    for a, off in zip(arrays.values(), offsets, strict=True):
        out[off : off + a.nbytes] = a.tobytes()
    return bytes(out)


def write_tensor_file(path: str | os.PathLike, fields: dict[str, np.ndarray]) -> Path:
    """Write ``fields`` as a tensor file (atomically)."""
    return atomic_write_bytes(path, tensor_file_bytes(fields), overwrite=True)


def _align(n: int, to: int = 8) -> int:
    return (n + to - 1) // to * to
