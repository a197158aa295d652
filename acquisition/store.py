"""Crash-safe run store (docs/design.md §4): `run.toml`, `manifest.sqlite` (WAL), `frames/`.

Invariants:
- A frame is written to a temp file, fsync'd, then linked into place with `os.link`, which
  fails rather than overwrite; the directory is fsync'd. Only then is its row marked done.
- A capture row is inserted as `pending` (with everything known about it) *before* the frame is
  written. A crash between "frame in place" and "row done" leaves a pending row whose frame
  exists: resume verifies and adopts it, so no captured frame is ever lost.
- A run directory is never overwritten: opening a complete run for writing is refused.
- Opening a run to read it never changes it: no schema is created, the journal mode is left
  alone, and a run written by a newer gonio (manifest `meta.schema_version` or run.toml
  `schema_version` above `SCHEMA_VERSION`) is refused before anything else is touched.
- A manifest is data, not trusted code: every frame path it lists must stay inside the run
  directory (relative, no `..`, not through a symlink that leaves it), or the run is refused.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import re
import sqlite3
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plumbing.atomic import atomic_write_bytes
from plumbing.errors import UserError
from plumbing.hashing import sha256_file
from plumbing.inputs import MiB, NotAnInputFile, check_nesting, open_input

__all__ = [
    "SCHEMA_VERSION",
    "RunStoreError",
    "RunStore",
    "CaptureRecord",
    "CaptureStart",
    "CalibrationRecord",
    "CALIBRATION_KINDS",
    "exposure_taken",
    "sha256_file",
    "now_iso",
]

# 2: calibration captures (darks, flats, reference target) in the manifest's own table.
SCHEMA_VERSION = 2


def _check_values(exposure_s, angles_rad, lab_time_s) -> None:
    """Values of a manifest row, not only types (issue 22): a finite positive exposure, finite
    angles with θ in [0°, 180°], a finite non-negative lab time. SQLite stores whatever it is
    given, and an exposure of 0 would divide every radiance of that frame by zero."""
    if not (_real(exposure_s) and 0 < exposure_s < 1e6):
        raise ValueError(f"exposure_s {exposure_s!r} is not a positive number of seconds")
    for k, v in zip(("theta_i", "phi_i", "theta_o", "phi_o"), angles_rad, strict=False):
        if not _real(v) or (k.startswith("theta") and not 0 <= v <= math.pi):
            raise ValueError(f"{k} {v!r} is not an angle in radians")
    if lab_time_s is not None and not (_real(lab_time_s) and lab_time_s >= 0):
        raise ValueError(f"lab_time_s {lab_time_s!r} is not a non-negative time")


def _real(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


#: The sections of run.toml gonio writes, each a table (acquisition.run_document).
_RUN_TOML_SECTIONS = ("gonio", "rig", "plan", "camera", "camera_device", "sample", "scene")


class RunStoreError(UserError, RuntimeError):
    """A run directory cannot be used as asked. One-line message."""


def _newer(what: str, version: object) -> str:
    return (
        f"{what}: schema version {version} was written by a newer gonio (this one reads up to "
        f"{SCHEMA_VERSION}); upgrade gonio to read this run"
    )


def _unreadable(db: Path, exc: Exception) -> str:
    if isinstance(exc, sqlite3.OperationalError) and _busy(exc):
        # Another process holds a write lock past the bounded wait: the run is fine, and the
        # advice for a damaged file (restore it) would overwrite a live manifest.
        return (
            f"{db}: in use by another process (the database stayed locked for "
            f"{BUSY_TIMEOUT_S:.0f} s); try again when it has finished"
        )
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
    if _no_space(db.parent):
        # SQLite needs a few kB beside the file to open it (its -shm): a full disk is not damage
        return (
            f"{db}: no space left on the device ({exc}); free some space and run the command "
            "again — the manifest is not known to be damaged: do not replace it"
        )
    if code in (sqlite3.SQLITE_IOERR, sqlite3.SQLITE_FULL, sqlite3.SQLITE_CANTOPEN):
        return (
            f"{db}: the disk refused to read or write it ({exc}); check the medium (full, "
            "read-only, failing) and run the command again — the manifest is not known to be "
            "damaged: do not replace it"
        )
    return (
        f"{db}: unreadable, damaged or not an SQLite manifest ({exc}); restore it from a "
        "backup (frames/ is untouched)"
    )


def _utf8_text(raw: bytes) -> str:
    """A TEXT value of the manifest: gonio writes UTF-8; other bytes are a damaged manifest
    (an error SQLite's readers turn into one line), not a UnicodeDecodeError."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise sqlite3.DataError("a text value is not UTF-8") from None


def _no_space(folder: Path) -> bool:
    """Whether the file system of `folder` has (almost) no space left for an unprivileged
    writer: less than 64 KiB."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 64 * 1024


def _busy(exc: sqlite3.OperationalError) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED)
    return "locked" in str(exc) or "busy" in str(exc)


# How long an open or a statement waits for another process's write lock before saying the run
# is in use (SQLite's busy timeout; a capture's transaction holds it for milliseconds).
BUSY_TIMEOUT_S = 30.0


def now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS captures (
    id INTEGER PRIMARY KEY,
    pose_index INTEGER NOT NULL,
    bracket_index INTEGER NOT NULL,
    exposure_s REAL NOT NULL,
    theta_i REAL NOT NULL, phi_i REAL NOT NULL, theta_o REAL NOT NULL, phi_o REAL NOT NULL,
    axes_commanded TEXT NOT NULL,
    axes_measured TEXT NOT NULL,
    light_dir TEXT NOT NULL,
    camera_dir TEXT NOT NULL,
    frame_path TEXT NOT NULL UNIQUE,
    sha256 TEXT,
    status TEXT NOT NULL CHECK (status IN ('pending', 'done')),
    started_at TEXT NOT NULL,
    finished_at TEXT,
    lab_time_s REAL,
    devices TEXT,
    frame_meta TEXT,
    note TEXT,
    UNIQUE (pose_index, bracket_index)
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY,
    at TEXT NOT NULL,
    kind TEXT NOT NULL,
    message TEXT NOT NULL
);
"""

# Calibration captures (schema 2): the same pending → frame → done protocol as `captures`.
# `take` counts recordings of one kind: 1 for the run's own phases, +1 for each retake by
# `gonio capture KIND RUN`; calibration uses the newest complete take, older takes stay on
# disk and in the manifest. `meta` (JSON) holds what the kind needs (reference: pose index,
# measured axis angles, light monitor reading).
_CALIBRATION_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibration_captures (
    id INTEGER PRIMARY KEY,
    kind TEXT NOT NULL,
    take INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    exposure_s REAL NOT NULL,
    frame_path TEXT NOT NULL UNIQUE,
    sha256 TEXT,
    status TEXT NOT NULL CHECK (status IN ('pending', 'done')),
    started_at TEXT NOT NULL,
    finished_at TEXT,
    meta TEXT,
    frame_meta TEXT,
    note TEXT,
    UNIQUE (kind, take, seq)
);
CREATE TABLE IF NOT EXISTS calibration_takes (
    kind TEXT NOT NULL,
    take INTEGER NOT NULL,
    expected INTEGER NOT NULL,
    started_at TEXT NOT NULL,
    description TEXT,
    PRIMARY KEY (kind, take)
);
"""
CALIBRATION_KINDS = ("dark", "flat", "reference")


def exposure_taken(frame_meta: dict[str, Any], commanded_s: float) -> float:
    """The exposure a frame had: what the camera reported it took (frame metadata
    ``exposure_s`` — Aravis reads the camera's rounded value back, gphoto2 takes the nearest
    shutter speed, the simulated camera quantises as a sensor does), else the commanded one
    (a camera that reports nothing). Calibration uses this for every frame: the HDR merge, the
    darks' matching, the flat and the reference scale."""
    reported = frame_meta.get("exposure_s") if isinstance(frame_meta, dict) else None
    if isinstance(reported, int | float) and math.isfinite(reported) and reported > 0:
        return float(reported)
    return float(commanded_s)


@dataclass(frozen=True)
class CaptureStart:
    """Everything known about a capture before its frame exists (its pending manifest row):
    the pose and bracket, the exposure, the directions (rad) and axis angles commanded and
    measured, the frame's suffix, the devices' status and the lab time since the session."""

    pose_index: int
    bracket_index: int
    exposure_s: float
    pose: tuple[float, float, float, float]
    axes_commanded: dict[str, float]
    axes_measured: dict[str, float]
    light_dir: list[float]
    camera_dir: list[float]
    suffix: str
    devices: dict[str, Any]
    lab_time_s: float


@dataclass
class CalibrationRecord:
    """One calibration capture (a dark, flat or reference-target frame)."""

    id: int
    kind: str
    take: int
    seq: int
    exposure_s: float
    frame_path: str
    sha256: str | None
    status: str
    meta: dict[str, Any]
    frame_meta: dict[str, Any]

    @property
    def exposure_taken_s(self) -> float:
        """The exposure the frame had (`exposure_taken`)."""
        return exposure_taken(self.frame_meta, self.exposure_s)

    def entry(self) -> dict[str, Any]:
        """As a plain dict: kind, exposure_s (the exposure the frame had: `exposure_taken`),
        exposure_commanded_s, path, sha256, and the kind's own keys (meta)."""
        return {
            **self.meta,
            "kind": self.kind,
            "take": self.take,
            "exposure_s": self.exposure_taken_s,
            "exposure_commanded_s": self.exposure_s,
            "path": self.frame_path,
            "sha256": self.sha256,
        }


@dataclass
class CaptureRecord:
    id: int
    pose_index: int
    bracket_index: int
    exposure_s: float  # as commanded (the plan's); the frame had `exposure_taken_s`
    theta_i: float
    phi_i: float
    theta_o: float
    phi_o: float
    axes_commanded: dict[str, float]
    axes_measured: dict[str, float]
    frame_path: str
    sha256: str | None
    status: str
    devices: dict[str, Any]
    frame_meta: dict[str, Any]
    lab_time_s: float | None

    @property
    def exposure_taken_s(self) -> float:
        """The exposure the frame had (`exposure_taken`)."""
        return exposure_taken(self.frame_meta, self.exposure_s)


class RunStore:
    """One run directory. Use `create` for a new run, `open` for an existing one; a context
    manager (`with RunStore.open(run) as store:`) closes it."""

    def __init__(self, root: Path, conn: sqlite3.Connection) -> None:
        self.root = root
        self.frames = root / "frames"
        self._db = conn

    # -- lifecycle ---------------------------------------------------------------------------
    @classmethod
    def create(cls, root: Path | str, run_toml: str) -> RunStore:
        root = Path(root)
        if root.exists() and any(root.iterdir()):
            raise RunStoreError(f"{root}: exists and is not empty; choose a new directory")
        if not re.search(r"^schema_version\s*=", run_toml, flags=re.MULTILINE):
            # Top-level keys must precede the first [table]: prepend, so readers can refuse a
            # run.toml from a newer gonio before interpreting anything else in it.
            run_toml = f"schema_version = {SCHEMA_VERSION}\n" + run_toml
        root.mkdir(parents=True, exist_ok=True)
        (root / "frames").mkdir()
        atomic_write_bytes(root / "run.toml", run_toml.encode())
        store = cls._connect(root, create=True)
        with store._db:
            store._db.executemany(
                "INSERT INTO meta VALUES (?, ?)",
                [
                    ("schema_version", str(SCHEMA_VERSION)),
                    ("status", "incomplete"),
                    ("created_at", now_iso()),
                ],
            )
        return store

    @classmethod
    def open(
        cls, root: Path | str, *, writable: bool = False, calibration_only: bool = False
    ) -> RunStore:
        """Open a run. `writable` refuses a complete run — except with `calibration_only`,
        for adding a calibration take (`gonio capture`) to a finished run: that adds frames
        and rows, and never changes a measurement capture."""
        root = Path(root)
        if not (root / "manifest.sqlite").exists() or not (root / "run.toml").exists():
            raise RunStoreError(
                f"{root}: not a run directory (no run.toml + manifest.sqlite); give a run "
                "directory (see `gonio runs list`)"
            )
        if not (root / "manifest.sqlite").is_file():
            raise RunStoreError(f"{root}/manifest.sqlite: not a file; not a gonio run")
        store = cls._connect(root, create=False, writable=writable)
        try:
            version = store.meta("schema_version")
            if version is None:
                raise RunStoreError(f"{root}/manifest.sqlite: no schema version; not a gonio run")
            if not re.fullmatch(r"[0-9]{1,9}", str(version)):  # "²" passes isdigit, not int()
                raise RunStoreError(
                    f"{root}/manifest.sqlite: schema version {version!r} is not a whole number "
                    "as gonio writes it; not a manifest of this gonio (a newer one, or another "
                    "tool, wrote it)"
                )
            if int(version) > SCHEMA_VERSION:
                raise RunStoreError(_newer(f"{root}/manifest.sqlite", version))
            if writable and store.complete and not calibration_only:
                raise RunStoreError(f"{root}: run is complete; refusing to modify it")
            if writable:
                # A schema-1 run being written to gains the calibration tables (additive).
                store._db.executescript(_CALIBRATION_SCHEMA)
                if int(version) < SCHEMA_VERSION:
                    store.set_meta("schema_version", str(SCHEMA_VERSION))
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:  # locked, or damaged
            store.close()
            raise RunStoreError(_unreadable(root / "manifest.sqlite", exc)) from None
        except BaseException:
            store.close()
            raise
        return store

    @classmethod
    def _connect(cls, root: Path, *, create: bool, writable: bool = True) -> RunStore:
        db = root / "manifest.sqlite"
        try:
            conn = cls._sqlite(db, read_only=not (create or writable))
        except sqlite3.Error as exc:
            raise RunStoreError(f"{db}: cannot open ({exc})") from None
        conn.text_factory = _utf8_text
        try:
            if create or writable:
                conn.execute("PRAGMA journal_mode=WAL")
                # FULL: a committed 'done' row survives power loss, matching the fsync'd frame.
                conn.execute("PRAGMA synchronous=FULL")
            if create:
                conn.executescript(_SCHEMA)
                conn.executescript(_CALIBRATION_SCHEMA)
            else:
                # A reader must not create tables in someone else's file: check instead.
                names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
                missing = {"meta", "captures", "events"} - names
                if missing:
                    raise RunStoreError(
                        f"{db}: not a gonio manifest (no table {sorted(missing)[0]!r})"
                    )
        except (sqlite3.Error, UnicodeDecodeError) as exc:
            conn.close()
            raise RunStoreError(_unreadable(db, exc)) from None
        conn.isolation_level = "DEFERRED"
        return cls(root, conn)

    @staticmethod
    def _sqlite(db: Path, *, read_only: bool) -> sqlite3.Connection:
        """A connection. A reader never writes to the manifest, whatever the mode; on media it
        cannot write to (read-only mount, no permission) it opens `mode=ro`.

        Why not `mode=ro` everywhere: a read-only connection cannot remove SQLite's -wal and
        -shm side files on close, so every `runs show` would leave two new files in the run.
        A WAL database closed cleanly has no -shm file, and SQLite must create one to read it —
        impossible on a read-only medium; there the file cannot change under us, so it is opened
        `immutable=1` (no locking, no -shm). Where another connection has the -shm open, it is
        read with locking, as usual.
        """
        if not read_only or os.access(db.parent, os.W_OK):
            return sqlite3.connect(db, timeout=BUSY_TIMEOUT_S, isolation_level=None)
        uri = f"{db.resolve().as_uri()}?mode=ro"
        if not (db.parent / f"{db.name}-shm").exists():
            uri += "&immutable=1"
        return sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S, isolation_level=None)

    @contextmanager
    def _reading(self):
        """Translate SQLite failures (a damaged or truncated manifest) into one-line errors."""
        try:
            yield
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            raise RunStoreError(_unreadable(self.root / "manifest.sqlite", exc)) from None

    def _rel_path(self, rel: str, capture_id: int) -> Path:
        """`rel` as a path inside the run directory; anything else means a tampered manifest."""
        where = f"{self.root}/manifest.sqlite: capture {capture_id} frame_path {rel!r:.80}"
        if not isinstance(rel, str) or "\0" in rel or len(rel) > 1024:
            # a NUL byte or 5000 characters failed inside open() (ValueError, ENAMETOOLONG)
            raise RunStoreError(
                f"{where} is not a frame path gonio writes (frames/NAME, no NUL byte, under "
                "1024 characters); refusing to read this run (the manifest was edited or damaged)"
            )
        p = Path(rel)
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise RunStoreError(
                f"{where} is not a path inside the run directory; refusing to read this run "
                "(the manifest was edited or damaged)"
            )
        full = self.root / p
        try:
            resolved = full.resolve()
        except (RuntimeError, OSError):  # a link to itself: Python 3.11 raises RuntimeError
            raise RunStoreError(
                f"{where} is a symbolic link that loops; refusing to read it (the run was edited)"
            ) from None
        if not resolved.is_relative_to(self.root.resolve()):
            raise RunStoreError(
                f"{where} resolves outside the run directory (symlink); refusing to read it"
            )
        return full

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- meta --------------------------------------------------------------------------------
    def meta(self, key: str) -> str | None:
        with self._reading():
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def set_meta(self, key: str, value: str) -> None:
        with self._db:
            self._db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (key, value))

    @property
    def complete(self) -> bool:
        return self.meta("status") == "complete"

    def mark_complete(self) -> None:
        self.set_meta("status", "complete")
        self.set_meta("completed_at", now_iso())

    def run_config(self) -> dict[str, Any]:
        """The frozen configs of run.toml; refused when written by a newer gonio."""
        path = self.root / "run.toml"
        try:
            with open_input(path, "run.toml", 16 * MiB) as fh:
                text = fh.read().decode("utf-8")
            check_nesting(text, path, "run.toml")
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise RunStoreError(
                f"{path}: damaged, not valid TOML ({exc}); restore it from a backup"
            ) from None
        except NotAnInputFile as exc:
            raise RunStoreError(str(exc)) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise RunStoreError(f"{path}: cannot read ({exc})") from None
        for key, value in doc.items():  # gonio's sections are tables
            if key in _RUN_TOML_SECTIONS and not isinstance(value, dict):
                raise RunStoreError(
                    f"{path}: {key}: expected a table ([{key}]), not {type(value).__name__} "
                    f"{value!r:.40}; not a run.toml gonio wrote — restore it from a backup"
                )
        version = doc.get("schema_version", doc.get("gonio", {}).get("schema_version"))
        if version is not None:
            if not isinstance(version, int) or isinstance(version, bool):
                raise RunStoreError(
                    f"{path}: schema_version: expected an integer (got {version!r})"
                )
            if version > SCHEMA_VERSION:
                raise RunStoreError(_newer(str(path), version))
        return doc

    def event(self, kind: str, message: str) -> None:
        with self._db:
            self._db.execute(
                "INSERT INTO events (at, kind, message) VALUES (?, ?, ?)",
                (now_iso(), kind, message),
            )

    def events(self) -> list[tuple[str, str, str]]:
        with self._reading():
            return list(self._db.execute("SELECT at, kind, message FROM events ORDER BY id"))

    # -- captures ----------------------------------------------------------------------------
    def done_keys(self) -> set[tuple[int, int]]:
        with self._reading():
            rows = self._db.execute(
                "SELECT pose_index, bracket_index FROM captures WHERE status = 'done'"
            ).fetchall()
        return {(int(a), int(b)) for a, b in rows}

    def frame_name(self, pose_index: int, bracket_index: int, suffix: str) -> str:
        return f"frames/p{pose_index:05d}_b{bracket_index:02d}{suffix}"

    def begin_capture(self, c: CaptureStart) -> int:
        """Insert (or refresh) the pending row for a capture; returns its id."""
        rel = self.frame_name(c.pose_index, c.bracket_index, c.suffix)
        with self._db:
            self._db.execute(
                "DELETE FROM captures WHERE pose_index = ? AND bracket_index = ? "
                "AND status = 'pending'",
                (c.pose_index, c.bracket_index),
            )
            cur = self._db.execute(
                "INSERT INTO captures (pose_index, bracket_index, exposure_s, theta_i, phi_i, "
                "theta_o, phi_o, axes_commanded, axes_measured, light_dir, camera_dir, frame_path, "
                "status, started_at, devices, lab_time_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending', ?, ?, ?)",
                (
                    c.pose_index,
                    c.bracket_index,
                    c.exposure_s,
                    *c.pose,
                    json.dumps(c.axes_commanded),
                    json.dumps(c.axes_measured),
                    json.dumps(c.light_dir),
                    json.dumps(c.camera_dir),
                    rel,
                    now_iso(),
                    json.dumps(c.devices, default=str),
                    c.lab_time_s,
                ),
            )
        return int(cur.lastrowid)

    def _write_frame(self, table: str, row_id: int, data: bytes, frame_meta: dict) -> str:
        """Write the frame of a pending row of `table` safely, then mark the row done.

        A frame from an interrupted attempt already in place is kept (it is data that was
        captured), and the new one is stored beside it rather than over it."""
        (rel,) = self._db.execute(
            f"SELECT frame_path FROM {table} WHERE id = ?", (row_id,)
        ).fetchone()
        path = self._rel_path(rel, row_id)
        digest = hashlib.sha256(data).hexdigest()
        try:
            atomic_write_bytes(path, data, overwrite=False)
        except FileExistsError:
            if sha256_file(path) != digest:
                k = 1
                while (alt := path.with_name(f"{path.stem}.r{k}{path.suffix}")).exists():
                    k += 1
                atomic_write_bytes(alt, data)
                rel = str(alt.relative_to(self.root))
        with self._db:
            self._db.execute(
                f"UPDATE {table} SET status = 'done', sha256 = ?, finished_at = ?, "
                "frame_meta = ?, frame_path = ? WHERE id = ?",
                (digest, now_iso(), json.dumps(frame_meta, default=str), rel, row_id),
            )
        return digest

    def finish_capture(self, capture_id: int, data: bytes, frame_meta: dict[str, Any]) -> str:
        """Write the frame safely, then mark the row done. Returns the SHA-256."""
        return self._write_frame("captures", capture_id, data, frame_meta)

    def adopt_orphans(self) -> int:
        """Pending rows (measurement and calibration) whose frame made it to disk are adopted
        (marked done with the checksum of the file on disk). Returns how many were adopted."""
        tables = ["captures"] + (["calibration_captures"] if self._has_calibration_table() else [])
        adopted = 0
        for table in tables:
            with self._reading():
                rows = list(
                    self._db.execute(f"SELECT id, frame_path FROM {table} WHERE status = 'pending'")
                )
            for cid, rel in rows:
                path = self._rel_path(rel, cid)
                if path.exists():
                    with self._db:
                        self._db.execute(
                            f"UPDATE {table} SET status = 'done', sha256 = ?, finished_at = ?, "
                            "note = 'adopted on resume' WHERE id = ?",
                            (sha256_file(path), now_iso(), cid),
                        )
                    adopted += 1
        return adopted

    def captures(self, status: str | None = "done") -> Iterator[CaptureRecord]:
        q = (
            "SELECT id, pose_index, bracket_index, exposure_s, theta_i, phi_i, theta_o, phi_o, "
            "axes_commanded, axes_measured, frame_path, sha256, status, devices, frame_meta, "
            "lab_time_s FROM captures"
        )
        args: tuple = ()
        if status is not None:
            q += " WHERE status = ?"
            args = (status,)
        with self._reading():
            rows = self._db.execute(q + " ORDER BY pose_index, bracket_index", args).fetchall()
        records = []
        # Every row is checked before the first is handed out, so a consumer never acts on
        # part of a tampered manifest.
        for r in rows:
            self._rel_path(r[10], r[0])
            try:
                records.append(self._record(r))
            except (TypeError, ValueError) as exc:  # a damaged JSON column
                raise RunStoreError(
                    f"{self.root}/manifest.sqlite: capture {r[0]} is damaged ({exc}); "
                    "restore the manifest from a backup"
                ) from None
        yield from records

    @staticmethod
    def _record(r: tuple) -> CaptureRecord:
        _check_values(r[3], r[4:8], r[15])
        return CaptureRecord(
            id=r[0],
            pose_index=r[1],
            bracket_index=r[2],
            exposure_s=r[3],
            theta_i=r[4],
            phi_i=r[5],
            theta_o=r[6],
            phi_o=r[7],
            axes_commanded=json.loads(r[8]),
            axes_measured=json.loads(r[9]),
            frame_path=r[10],
            sha256=r[11],
            status=r[12],
            devices=json.loads(r[13] or "{}"),
            frame_meta=json.loads(r[14] or "{}"),
            lab_time_s=r[15],
        )

    def count(self, status: str = "done") -> int:
        with self._reading():
            (n,) = self._db.execute(
                "SELECT COUNT(*) FROM captures WHERE status = ?", (status,)
            ).fetchone()
        return int(n)

    def verify(self) -> list[str]:
        """Check every done frame (measurement and calibration) against its SHA-256; return a
        list of problems."""
        problems = []
        done = [(r.frame_path, r.sha256) for r in self.captures("done")]
        done += [(r.frame_path, r.sha256) for r in self.calibration_captures()]
        for rel, sha in done:
            path = self.root / rel  # checked to be inside the run when listed
            if not path.exists():
                problems.append(f"{rel}: missing")
            elif sha256_file(path) != sha:
                problems.append(f"{rel}: checksum mismatch")
        return problems

    # -- calibration captures (darks, flats, reference target) ------------------------------
    def _has_calibration_table(self) -> bool:
        with self._reading():
            row = self._db.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'calibration_captures'"
            ).fetchone()
        return row is not None

    def calibration_take(self, kind: str) -> int:
        """The newest take of `kind` (0 when none was started)."""
        if not self._has_calibration_table():
            return 0
        with self._reading():
            (n,) = self._db.execute(
                "SELECT COALESCE(MAX(take), 0) FROM calibration_takes WHERE kind = ?", (kind,)
            ).fetchone()
        return int(n)

    def start_calibration_take(
        self, kind: str, expected: int, description: dict[str, Any] | None = None
    ) -> int:
        """Open a new take of `kind` expecting `expected` frames; returns its number."""
        if kind not in CALIBRATION_KINDS:
            raise ValueError(f"calibration kind must be one of {CALIBRATION_KINDS}")
        take = self.calibration_take(kind) + 1
        with self._db:
            self._db.execute(
                "INSERT INTO calibration_takes VALUES (?, ?, ?, ?, ?)",
                (kind, take, int(expected), now_iso(), json.dumps(description or {})),
            )
        return take

    def set_take_description(self, kind: str, take: int, description: dict[str, Any]) -> None:
        with self._db:
            self._db.execute(
                "UPDATE calibration_takes SET description = ? WHERE kind = ? AND take = ?",
                (json.dumps(description, default=str), kind, take),
            )

    def calibration_take_info(self, kind: str, take: int) -> dict[str, Any] | None:
        """{"expected": n, "done": k, "description": {...}} of a take, or None."""
        if not self._has_calibration_table():
            return None
        with self._reading():
            row = self._db.execute(
                "SELECT expected, description FROM calibration_takes WHERE kind = ? AND take = ?",
                (kind, take),
            ).fetchone()
            if row is None:
                return None
            (done,) = self._db.execute(
                "SELECT COUNT(*) FROM calibration_captures WHERE kind = ? AND take = ? "
                "AND status = 'done'",
                (kind, take),
            ).fetchone()
        return {"expected": int(row[0]), "done": int(done), "description": json.loads(row[1])}

    def calibration_frame_name(self, kind: str, take: int, seq: int, suffix: str) -> str:
        return f"calibration/{kind}/t{take:02d}_{seq:04d}{suffix}"

    def begin_calibration(
        self,
        kind: str,
        take: int,
        seq: int,
        exposure_s: float,
        suffix: str,
        meta: dict[str, Any] | None = None,
    ) -> int:
        """Insert (or refresh) the pending row of one calibration frame; returns its id."""
        rel = self.calibration_frame_name(kind, take, seq, suffix)
        (self.root / rel).parent.mkdir(parents=True, exist_ok=True)
        with self._db:
            self._db.execute(
                "DELETE FROM calibration_captures WHERE kind = ? AND take = ? AND seq = ? "
                "AND status = 'pending'",
                (kind, take, seq),
            )
            cur = self._db.execute(
                "INSERT INTO calibration_captures (kind, take, seq, exposure_s, frame_path, "
                "status, started_at, meta) VALUES (?, ?, ?, ?, ?, 'pending', ?, ?)",
                (kind, take, seq, exposure_s, rel, now_iso(), json.dumps(meta or {}, default=str)),
            )
        return int(cur.lastrowid)

    def finish_calibration(self, row_id: int, data: bytes, frame_meta: dict[str, Any]) -> str:
        """Write the calibration frame safely (never over an existing file), mark it done."""
        return self._write_frame("calibration_captures", row_id, data, frame_meta)

    def calibration_captures(
        self, kind: str | None = None, take: int | None = None, status: str = "done"
    ) -> list[CalibrationRecord]:
        """Calibration frames (all kinds, or one kind; all takes, or one), in take/seq order."""
        if not self._has_calibration_table():
            return []
        q = (
            "SELECT id, kind, take, seq, exposure_s, frame_path, sha256, status, meta, "
            "frame_meta FROM calibration_captures WHERE status = ?"
        )
        args: list[Any] = [status]
        if kind is not None:
            q += " AND kind = ?"
            args.append(kind)
        if take is not None:
            q += " AND take = ?"
            args.append(take)
        with self._reading():
            rows = self._db.execute(q + " ORDER BY kind, take, seq", args).fetchall()
        out = []
        for r in rows:
            self._rel_path(r[5], r[0])
            try:
                meta, fmeta = json.loads(r[8] or "{}"), json.loads(r[9] or "{}")
            except ValueError as exc:
                raise RunStoreError(
                    f"{self.root}/manifest.sqlite: calibration capture {r[0]} is damaged "
                    f"({exc}); restore the manifest from a backup"
                ) from None
            try:
                _check_values(r[4], (), None)
            except ValueError as exc:
                raise RunStoreError(
                    f"{self.root}/manifest.sqlite: calibration capture {r[0]} is damaged "
                    f"({exc}); restore the manifest from a backup"
                ) from None
            out.append(CalibrationRecord(*r[:8], meta, fmeta))
        return out

    def usable_calibration_take(self, kind: str) -> tuple[int, str | None]:
        """The newest *complete* take of `kind` (0 if none) and a note when a newer take is
        incomplete (an interrupted retake: the older complete one is used)."""
        newest = self.calibration_take(kind)
        for take in range(newest, 0, -1):
            info = self.calibration_take_info(kind, take)
            if info is not None and info["done"] >= info["expected"]:
                note = None
                if take != newest:
                    note = (
                        f"{kind} take {newest} is incomplete; using take {take} (resume with "
                        f"`gonio capture {kind}`)"
                    )
                return take, note
        if newest:
            return 0, f"{kind} frames incomplete (take {newest}); resume the run or retake"
        return 0, None

    def calibration_done_seqs(self, kind: str, take: int) -> set[int]:
        return {r.seq for r in self.calibration_captures(kind, take)}
