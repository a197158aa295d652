"""The one resolver for gonio's real data files (measured BRDFs, published fits, calibration
images): ``find_data("rgl_brdf/paper_white_rgb.bsdf")`` → an existing path, and the ``data:``
scheme scene files use (``filename = "data:rgl_brdf/…"``). Provenance, licences and hashes:
``data/README.md``.

It lives in ``fitting`` because it is plain file lookup every layer may use (``fitting`` imports
nothing else of ours), with no domain logic. Search order, first hit wins:

1. ``$GONIO_DATA`` — a folder with the same layout (``rgl_brdf/``, ``brdf_fits/``, …);
2. ``data/`` beside the packages — the source checkout;
3. ``<prefix>/share/gonio/data`` (``sys.prefix``, then the user base) — an installed wheel;
4. the download cache ``$GONIO_CACHE/data`` (default ``$XDG_CACHE_HOME/gonio`` or
   ``~/.cache/gonio``) — groups not shipped for licence reasons, filled by :func:`fetch`.

A missing file is a :class:`DataNotFound` (a ``FileNotFoundError``, so the CLI prints one line
and exits 2) naming every place looked and, for fetchable data, the command that gets it.
"""

from __future__ import annotations

import os
import shutil
import site
import sys
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from plumbing.errors import UserError
from plumbing.hashing import sha256_file as _sha256

__all__ = [
    "DATA_ENV",
    "CACHE_ENV",
    "SCHEME",
    "DataNotFound",
    "DataFile",
    "FETCHED",
    "manifest",
    "data_roots",
    "cache_dir",
    "find_data",
    "resolve_data_uri",
    "fetch",
    "verify",
]

DATA_ENV = "GONIO_DATA"
CACHE_ENV = "GONIO_CACHE"
SCHEME = "data:"


class DataNotFound(UserError, FileNotFoundError):
    """A data file is in none of the data roots. The message is one line with the fix."""


@dataclass(frozen=True)
class DataFile:
    """One known file: its path under a data root, SHA-256, whether the repository ships it,
    and (for fetched files) where it is downloaded from."""

    path: str
    sha256: str
    shipped: bool = True
    url: str | None = None


_IMAGEIO = (
    "https://raw.githubusercontent.com/imageio/test_images/f676c96b1af7e04bb1eed1e4551e058eb2f14acd"
)
#: Shipped files and their SHA-256 are listed in ``data/SHA256SUMS`` (``sha256sum -c`` format);
#: files not shipped (no redistribution licence) are known here, with their source.
FETCHED: dict[str, DataFile] = {
    "camera_raw/Blackmagic.dng": DataFile(
        "camera_raw/Blackmagic.dng",
        "adb7beb2753978d8e2bb1a868057ce373f103957908a6d36b2c4da714e211e25",
        shipped=False,
        url=f"{_IMAGEIO}/Blackmagic.dng",
    ),
    "camera_raw/Nikon_uncompressed.nef": DataFile(
        "camera_raw/Nikon_uncompressed.nef",
        "268d9a98920a9f3ea3ebf6a2b9ff68b956df74ac0e46b980bee69e7ef3ebc172",
        shipped=False,
        url=f"{_IMAGEIO}/Nikon_uncompressed.nef",
    ),
}


def manifest() -> dict[str, DataFile]:
    """Every file gonio knows, by path under a data root: ``SHA256SUMS`` of the first root
    that has one, plus :data:`FETCHED`."""
    out: dict[str, DataFile] = {}
    for root in data_roots():
        sums = root / "SHA256SUMS"
        if sums.is_file():
            for line in sums.read_text().splitlines():
                digest, _, rel = line.strip().partition("  ")
                if rel:
                    out[rel] = DataFile(rel, digest)
            break
    out.update(FETCHED)
    return out


def cache_dir() -> Path:
    """``$GONIO_CACHE/data``, else ``$XDG_CACHE_HOME/gonio/data``, else ``~/.cache/gonio/data``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]) / "data"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "gonio" / "data"


def data_roots() -> list[Path]:
    """The folders searched, in order (module docstring)."""
    roots = []
    if os.environ.get(DATA_ENV):
        roots.append(Path(os.environ[DATA_ENV]))
    roots.append(Path(__file__).resolve().parent.parent / "data")
    for prefix in dict.fromkeys([sys.prefix, site.getuserbase()]):
        roots.append(Path(prefix) / "share" / "gonio" / "data")
    roots.append(cache_dir())
    return roots


def _group(relpath: str) -> str:
    return relpath.strip("/").split("/", 1)[0]


def find_data(relpath: str) -> Path:
    """The first existing ``root/relpath`` (module docstring), or DataNotFound."""
    relpath = relpath.strip().lstrip("/")
    if not relpath or ".." in Path(relpath).parts:
        raise DataNotFound(f"data path {relpath!r}: give a path under a data root, without '..'")
    roots = data_roots()
    for root in roots:
        candidate = root / relpath
        if candidate.is_file():
            return candidate
    entry = FETCHED.get(relpath)
    hint = f"set {DATA_ENV} to a folder holding it"
    if entry is not None and not entry.shipped:
        hint = f"get it with `gonio data fetch {_group(relpath)}` (see data/README.md), or {hint}"
    raise DataNotFound(
        f"data file {relpath} not found (looked in {', '.join(str(r) for r in roots)}); {hint}"
    )


def resolve_data_uri(value: str) -> str:
    """``data:REL`` → the resolved absolute path (as a string); anything else unchanged."""
    if isinstance(value, str) and value.startswith(SCHEME):
        return str(find_data(value[len(SCHEME) :]))
    return value


def verify(relpath: str) -> tuple[Path, bool]:
    """(where the file is, whether its SHA-256 matches the manifest)."""
    path = find_data(relpath)
    entry = manifest().get(relpath)
    return path, entry is None or _sha256(path) == entry.sha256


def fetch(group: str, source_dir: str | os.PathLike | None = None) -> list[Path]:
    """Put the not-shipped files of ``group`` (e.g. ``camera_raw``) into the cache: copied from
    ``source_dir`` when given (a folder holding them, or their group folder), else downloaded
    from the source in ``data/README.md``. Every file's SHA-256 is checked before it is kept;
    a mismatch or a failed download is DataNotFound (one line)."""
    files = [e for e in FETCHED.values() if _group(e.path) == group]
    if not files:
        known = sorted({_group(e.path) for e in FETCHED.values()})
        raise DataNotFound(f"no fetchable data group {group!r} (known: {', '.join(known)})")
    out = []
    for entry in files:
        dest = cache_dir() / entry.path
        if dest.is_file() and _sha256(dest) == entry.sha256:
            out.append(dest)
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".{dest.name}.part")
        name = Path(entry.path).name
        try:
            if source_dir is not None:
                places = (Path(source_dir) / name, Path(source_dir) / entry.path)
                src = next((p for p in places if p.is_file()), None)
                if src is None:
                    raise DataNotFound(f"{source_dir}: no {name} there (or under {group}/)")
                shutil.copyfile(src, tmp)
            else:
                with urllib.request.urlopen(entry.url, timeout=60) as resp, open(tmp, "wb") as fh:
                    shutil.copyfileobj(resp, fh)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if isinstance(exc, DataNotFound):
                raise
            raise DataNotFound(
                f"{entry.url}: download failed ({exc}); copy the file with "
                f"`gonio data fetch {group} --from DIR` instead"
            ) from None
        got = _sha256(tmp)
        if got != entry.sha256:
            tmp.unlink(missing_ok=True)
            raise DataNotFound(
                f"{name}: SHA-256 {got[:16]}… does not match the expected {entry.sha256[:16]}… "
                "(data/README.md); the copy is not the published file"
            )
        os.replace(tmp, dest)
        out.append(dest)
    return out
