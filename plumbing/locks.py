"""One writer per run directory: an advisory lock (flock) on a hidden file beside the run,
`.NAME.lock` in its parent, holding the writer's PID.

Why beside, not inside: a new run's directory must be empty when the store creates it, and a
complete run is refused without a byte of it changing. Why flock: the kernel drops the lock when
its holder dies (kill -9 included), so a crashed acquisition never leaves a run locked and the
same command resumes it. The file stays beside a run that exists (a few bytes; removing it could
let a second writer lock a fresh file while the first still holds the old one), and is removed
when the command made no run at all.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from plumbing.errors import UserError

__all__ = ["RunLock", "RunLocked"]


class RunLocked(UserError):
    """Another process holds the run directory."""


class RunLock:
    """`with RunLock(run_dir):` — refuse (RunLocked, one line naming the holder's PID) while
    another process writes to `run_dir`."""

    def __init__(self, run_dir: str | os.PathLike) -> None:
        run_dir = Path(run_dir)
        self.run_dir = run_dir
        self.path = run_dir.parent / f".{run_dir.name}.lock"
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            # A read-only medium, a folder without write permission, or a planted symlink: the
            # run cannot be written there, whatever the lock says.
            raise UserError(
                f"{self.run_dir}: cannot write beside it ({self.path}: {exc.strerror}); "
                "give an --out on a writable disk"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunLocked(
                f"{self.run_dir}: in use by another gonio process (PID {holder}); wait for it "
                "to finish or stop it (Ctrl-C, or kill PID), then run the command again"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            if not (self.run_dir / "manifest.sqlite").exists():
                # No run was made (a device failed to open): leave nothing beside it. Unlinked
                # while still held, so no other process can have locked this file meanwhile.
                self.path.unlink(missing_ok=True)
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
