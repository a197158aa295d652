"""Run store invariants: atomic frames, no overwrite, adoption of orphans, complete = frozen."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from acquisition.store import CaptureStart, RunStore, RunStoreError
from plumbing.atomic import atomic_write_bytes


def _begin(store: RunStore, pose: int, bracket: int = 0) -> int:
    return store.begin_capture(
        CaptureStart(
            pose_index=pose,
            bracket_index=bracket,
            exposure_s=0.01,
            pose=(0.1, 0.0, 0.2, 3.1),
            axes_commanded={"a": 0.1},
            axes_measured={"a": 0.1001},
            light_dir=[0.0, 0.0, 1.0],
            camera_dir=[0.0, 0.0, 1.0],
            suffix=".exr",
            devices={},
            lab_time_s=1.0,
        )
    )


def test_atomic_write_refuses_overwrite(tmp_path: Path) -> None:
    p = tmp_path / "x.bin"
    atomic_write_bytes(p, b"first")
    with pytest.raises(FileExistsError):
        atomic_write_bytes(p, b"second")
    assert p.read_bytes() == b"first"
    assert [q.name for q in tmp_path.iterdir()] == ["x.bin"]  # no temp file left behind


def test_capture_lifecycle_and_verify(tmp_path: Path) -> None:
    store = RunStore.create(tmp_path / "run", 'name = "t"\n')
    cid = _begin(store, 0)
    assert store.count("pending") == 1 and store.count("done") == 0
    digest = store.finish_capture(cid, b"frame-bytes", {"exposure_s": 0.01})
    assert digest == hashlib.sha256(b"frame-bytes").hexdigest()
    assert store.done_keys() == {(0, 0)}
    assert store.verify() == []
    # Corrupt the frame on disk: verify must notice.
    rec = next(store.captures())
    (tmp_path / "run" / rec.frame_path).write_bytes(b"tampered")
    assert store.verify() == [f"{rec.frame_path}: checksum mismatch"]


def test_orphan_frame_is_adopted_not_lost(tmp_path: Path) -> None:
    store = RunStore.create(tmp_path / "run", 'name = "t"\n')
    cid = _begin(store, 3)
    rel = store.frame_name(3, 0, ".exr")
    # Simulate a crash after the frame landed but before the row was marked done.
    atomic_write_bytes(tmp_path / "run" / rel, b"captured")
    store.close()
    store = RunStore.open(tmp_path / "run", writable=True)
    assert store.adopt_orphans() == 1
    rec = next(store.captures())
    assert rec.id == cid and rec.sha256 == hashlib.sha256(b"captured").hexdigest()


def test_retry_keeps_both_frames_when_different(tmp_path: Path) -> None:
    store = RunStore.create(tmp_path / "run", 'name = "t"\n')
    _begin(store, 1)
    rel = store.frame_name(1, 0, ".exr")
    atomic_write_bytes(tmp_path / "run" / rel, b"old attempt")
    cid = _begin(store, 1)  # a retry replaces the pending row, not the file
    store.finish_capture(cid, b"new attempt", {})
    frames = sorted(p.name for p in (tmp_path / "run" / "frames").iterdir())
    assert len(frames) == 2
    assert (tmp_path / "run" / rel).read_bytes() == b"old attempt"


def test_new_run_refuses_non_empty_dir_and_complete_run_is_frozen(tmp_path: Path) -> None:
    d = tmp_path / "busy"
    d.mkdir()
    (d / "notes.txt").write_text("keep me")
    with pytest.raises(RunStoreError, match="not empty"):
        RunStore.create(d, "")
    store = RunStore.create(tmp_path / "run", 'name = "t"\n')
    store.mark_complete()
    store.close()
    with pytest.raises(RunStoreError, match="complete"):
        RunStore.open(tmp_path / "run", writable=True)
    assert RunStore.open(tmp_path / "run").complete


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    store = RunStore.create(tmp_path / "run", 'name = "t"\n')
    store.set_meta("schema_version", "99")
    store.close()
    with pytest.raises(RunStoreError, match="newer"):
        RunStore.open(tmp_path / "run")


def test_wal_mode(tmp_path: Path) -> None:
    store = RunStore.create(tmp_path / "run", "")
    (mode,) = store._db.execute("PRAGMA journal_mode").fetchone()
    assert mode == "wal"
    assert os.path.exists(tmp_path / "run" / "manifest.sqlite")
