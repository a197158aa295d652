"""Read-only and busy runs (issue 22 item 6): a healthy run on read-only media is read, never
called damaged; nothing is written to it; outputs go elsewhere when asked; a locked manifest
says "in use by another process".

Read-only media are real: the run's folder is bind-mounted read-only onto itself in a private
mount namespace (`unshare -rm`, so the mount vanishes with the command), or, where user
namespaces are not allowed, with a plain bind mount as root, unmounted afterwards.
"""

from __future__ import annotations

import hashlib
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import CONFIGS

from acquisition import store as store_mod
from acquisition.store import RunStore, RunStoreError

GONIO = [sys.executable, "-m", "gonio.cli"]
PLAN = (
    'name = "tiny"\ntype = "explicit"\n'
    "poses_deg = [[20.0, 0.0, 30.0, 180.0], [30.0, 0.0, 40.0, 180.0], [40.0, 0.0, 20.0, 180.0]]\n"
    "exposures_s = [0.002]\n"
)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    media = tmp_path_factory.mktemp("media")
    plan = media.parent / "tiny.toml"
    plan.write_text(PLAN)
    res = subprocess.run(
        [*GONIO, "acquire", "--rig", str(CONFIGS / "rigs" / "sim.toml"), "--plan", str(plan),
         "--out", str(media / "run"), "--no-progress"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    return media / "run"


def _unshare_works() -> bool:
    try:
        return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0
    except FileNotFoundError:
        return False


@contextmanager
def read_only(folder: Path) -> Iterator[list[str]]:
    """A command prefix under which `folder` is a read-only mount of itself."""
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && shift && exec "$@"'
    if _unshare_works():
        yield ["unshare", "-rm", "sh", "-c", script, "sh", str(folder)]
        return
    subprocess.run(["mount", "--bind", str(folder), str(folder)], check=True)
    try:
        subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], check=True)
        yield []
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_a_run_on_read_only_media_is_read_and_left_untouched(run: Path, tmp_path: Path) -> None:
    media = run.parent
    before = _digests(media)
    # Closed cleanly, a WAL manifest has no -shm file; SQLite must create one to read it, which a
    # read-only medium forbids. This is the case the old code called "damaged".
    assert not (run / "manifest.sqlite-shm").exists()
    elsewhere = tmp_path / "samples.parquet"
    with read_only(media) as prefix:

        def gonio(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run(
                [*prefix, *GONIO, *args], capture_output=True, text=True, timeout=300
            )

        show = gonio("runs", "show", "--verify", str(run))
        listing = gonio("runs", "list", "--root", str(media))
        refused = gonio("calibrate", str(run))
        moved = gonio("calibrate", str(run), "--out", str(elsewhere))
        new_run = gonio(
            "acquire", "--rig", str(CONFIGS / "rigs" / "sim.toml"), "--plan",
            str(media.parent / "tiny.toml"), "--out", str(media / "run2"), "--no-progress",
        )  # fmt: skip
    assert show.returncode == 0, show.stderr
    assert "complete" in show.stdout and "damaged" not in show.stdout + show.stderr
    assert listing.returncode == 0 and "complete" in listing.stdout, listing.stderr
    # Writing into the run is refused before the reduction, in one line naming the way out.
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "read-only file system" in refused.stderr
    assert "--out" in refused.stderr
    assert moved.returncode == 0, moved.stderr
    assert elsewhere.stat().st_size > 0
    assert new_run.returncode == 2 and new_run.stderr.count("\n") == 1, new_run.stderr
    assert "internal error" not in new_run.stderr
    # Not a byte of the media changed, and no -shm/-wal or lock file appeared on it.
    assert _digests(media) == before


def test_a_locked_manifest_is_in_use_not_damaged(
    run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Another program (the sqlite3 shell, a backup tool) holds the manifest in exclusive locking
    # mode past the (here shortened) busy timeout: no other connection may even read it.
    monkeypatch.setattr(store_mod, "BUSY_TIMEOUT_S", 0.2)
    holder = sqlite3.connect(run / "manifest.sqlite", isolation_level=None)
    try:
        holder.execute("PRAGMA locking_mode=EXCLUSIVE")
        holder.execute("BEGIN EXCLUSIVE")
        for writable in (False, True):
            with pytest.raises(RunStoreError) as info:
                with RunStore.open(run, writable=writable, calibration_only=True) as store:
                    store.count()
            msg = str(info.value)
            assert "in use by another process" in msg, msg
            assert "damaged" not in msg and "restore" not in msg
        holder.execute("ROLLBACK")
    finally:
        holder.close()
    with RunStore.open(run) as store:  # released: readable again
        assert store.complete
