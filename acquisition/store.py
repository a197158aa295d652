"""Crash-safe run store (DESIGN §4): `run.toml`, `manifest.sqlite` (WAL), `frames/`.

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
import re
import sqlite3
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fitting.atomic import atomic_write_bytes as _atomic_write_bytes

__all__ = [
    "SCHEMA_VERSION",
    "RunStoreError",
    "RunStore",
    "CaptureRecord",
    "atomic_write_bytes",
    "sha256_file",
    "now_iso",
]

SCHEMA_VERSION = 1


class RunStoreError(RuntimeError):
    """A run directory cannot be used as asked. One-line message."""


def _newer(what: str, version: object) -> str:
    return (
        f"{what}: schema version {version} was written by a newer gonio (this one reads up to "
        f"{SCHEMA_VERSION}); upgrade gonio to read this run"
    )


def _unreadable(db: Path, exc: Exception) -> str:
    return (
        f"{db}: unreadable, damaged or not an SQLite manifest ({exc}); restore it from a "
        "backup (frames/ is untouched)"
    )


def now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def atomic_write_bytes(path: Path, data: bytes, *, overwrite: bool = False) -> None:
    """Temp file in the same directory, fsync, then link (no overwrite, the default for run
    data) or replace."""
    _atomic_write_bytes(path, data, overwrite=overwrite)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


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


@dataclass
class CaptureRecord:
    id: int
    pose_index: int
    bracket_index: int
    exposure_s: float
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


class RunStore:
    """One run directory. Use `create` for a new run, `open` for an existing one."""

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
    def open(cls, root: Path | str, *, writable: bool = False) -> RunStore:
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
            if version is None or not version.isdigit():
                raise RunStoreError(f"{root}/manifest.sqlite: no schema version; not a gonio run")
            if int(version) > SCHEMA_VERSION:
                raise RunStoreError(_newer(f"{root}/manifest.sqlite", version))
            if writable and store.complete:
                raise RunStoreError(f"{root}: run is complete; refusing to modify it")
        except BaseException:
            store.close()
            raise
        return store

    @classmethod
    def _connect(cls, root: Path, *, create: bool, writable: bool = True) -> RunStore:
        db = root / "manifest.sqlite"
        try:
            conn = sqlite3.connect(db, timeout=30, isolation_level=None)
        except sqlite3.Error as exc:
            raise RunStoreError(f"{db}: cannot open ({exc})") from None
        try:
            if create or writable:
                conn.execute("PRAGMA journal_mode=WAL")
                # FULL: a committed 'done' row survives power loss, matching the fsync'd frame.
                conn.execute("PRAGMA synchronous=FULL")
            if create:
                conn.executescript(_SCHEMA)
            else:
                # A reader must not create tables in someone else's file: check instead.
                names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
                missing = {"meta", "captures", "events"} - names
                if missing:
                    raise RunStoreError(
                        f"{db}: not a gonio manifest (no table {sorted(missing)[0]!r})"
                    )
        except sqlite3.Error as exc:
            conn.close()
            raise RunStoreError(_unreadable(db, exc)) from None
        conn.isolation_level = "DEFERRED"
        return cls(root, conn)

    @contextmanager
    def _reading(self):
        """Translate SQLite failures (a damaged or truncated manifest) into one-line errors."""
        try:
            yield
        except sqlite3.DatabaseError as exc:
            raise RunStoreError(_unreadable(self.root / "manifest.sqlite", exc)) from None

    def _rel_path(self, rel: str, capture_id: int) -> Path:
        """`rel` as a path inside the run directory; anything else means a tampered manifest."""
        p = Path(rel)
        where = f"{self.root}/manifest.sqlite: capture {capture_id} frame_path {rel!r}"
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise RunStoreError(
                f"{where} is not a path inside the run directory; refusing to read this run "
                "(the manifest was edited or damaged)"
            )
        full = self.root / p
        if not full.resolve().is_relative_to(self.root.resolve()):
            raise RunStoreError(
                f"{where} resolves outside the run directory (symlink); refusing to read it"
            )
        return full

    def close(self) -> None:
        self._db.close()

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
            with open(path, "rb") as fh:
                doc = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise RunStoreError(
                f"{path}: damaged, not valid TOML ({exc}); restore it from a backup"
            ) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise RunStoreError(f"{path}: cannot read ({exc})") from None
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

    def begin_capture(
        self,
        *,
        pose_index: int,
        bracket_index: int,
        exposure_s: float,
        pose: tuple[float, float, float, float],
        axes_commanded: dict[str, float],
        axes_measured: dict[str, float],
        light_dir: list[float],
        camera_dir: list[float],
        suffix: str,
        devices: dict[str, Any],
        lab_time_s: float,
    ) -> int:
        """Insert (or refresh) the pending row for a capture; returns its id."""
        rel = self.frame_name(pose_index, bracket_index, suffix)
        with self._db:
            self._db.execute(
                "DELETE FROM captures WHERE pose_index = ? AND bracket_index = ? "
                "AND status = 'pending'",
                (pose_index, bracket_index),
            )
            cur = self._db.execute(
                "INSERT INTO captures (pose_index, bracket_index, exposure_s, theta_i, phi_i, "
                "theta_o, phi_o, axes_commanded, axes_measured, light_dir, camera_dir, frame_path, "
                "status, started_at, devices, lab_time_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending', ?, ?, ?)",
                (
                    pose_index,
                    bracket_index,
                    exposure_s,
                    *pose,
                    json.dumps(axes_commanded),
                    json.dumps(axes_measured),
                    json.dumps(light_dir),
                    json.dumps(camera_dir),
                    rel,
                    now_iso(),
                    json.dumps(devices, default=str),
                    lab_time_s,
                ),
            )
        return int(cur.lastrowid)

    def finish_capture(self, capture_id: int, data: bytes, frame_meta: dict[str, Any]) -> str:
        """Write the frame safely, then mark the row done. Returns the SHA-256."""
        (rel,) = self._db.execute(
            "SELECT frame_path FROM captures WHERE id = ?", (capture_id,)
        ).fetchone()
        path = self._rel_path(rel, capture_id)
        digest = hashlib.sha256(data).hexdigest()
        try:
            atomic_write_bytes(path, data, overwrite=False)
        except FileExistsError:
            # A frame from an interrupted attempt is already in place: keep it (it is data
            # that was captured), and store the new one beside it rather than overwrite.
            if sha256_file(path) != digest:
                k = 1
                while (alt := path.with_name(f"{path.stem}.r{k}{path.suffix}")).exists():
                    k += 1
                atomic_write_bytes(alt, data)
                rel = str(alt.relative_to(self.root))
        with self._db:
            self._db.execute(
                "UPDATE captures SET status = 'done', sha256 = ?, finished_at = ?, "
                "frame_meta = ?, frame_path = ? WHERE id = ?",
                (digest, now_iso(), json.dumps(frame_meta, default=str), rel, capture_id),
            )
        return digest

    def adopt_orphans(self) -> int:
        """Pending rows whose frame made it to disk are adopted (marked done with the
        checksum of the file on disk). Returns how many were adopted."""
        with self._reading():
            rows = list(
                self._db.execute("SELECT id, frame_path FROM captures WHERE status = 'pending'")
            )
        adopted = 0
        for cid, rel in rows:
            path = self._rel_path(rel, cid)
            if path.exists():
                with self._db:
                    self._db.execute(
                        "UPDATE captures SET status = 'done', sha256 = ?, finished_at = ?, "
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
        """Check every done frame against its SHA-256; return a list of problems."""
        problems = []
        for rec in self.captures("done"):
            path = self.root / rec.frame_path  # checked to be inside the run by captures()
            if not path.exists():
                problems.append(f"{rec.frame_path}: missing")
            elif sha256_file(path) != rec.sha256:
                problems.append(f"{rec.frame_path}: checksum mismatch")
        return problems
