"""The run's structured log: `log.jsonl` in the run directory, one JSON object per line.

Each event is appended with a single `write` on an O_APPEND descriptor, so lines never
interleave or overwrite one another, and flushed to the OS at once (a killed process loses
nothing already written). A power cut can leave the last line partial; on the next open that
partial tail is cut off, so every line of the file always parses and earlier lines are never
touched. Fields: `ts` (UTC, ISO 8601), `lab_s` (rig clock since the session began), `level`,
`event`, and whatever the event carries (`pose`, `bracket`, `exposure_s`, `reason`, `fault`,
`timings_s`, ...).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from acquisition.store import now_iso
from plumbing.inputs import GiB, read_input_text

__all__ = ["LOG_NAME", "RunLog", "read_log"]

LOG_NAME = "log.jsonl"


def _clean(v: Any) -> Any:
    """JSON has no NaN/inf (json.dumps would write the non-standard `NaN`): use null."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    return v


class RunLog:
    """Append-only JSON-lines log. `lab_clock` gives the rig clock's time in seconds."""

    def __init__(self, path: Path | str, lab_clock: Callable[[], float] | None = None) -> None:
        self.path = Path(path)
        self._clock = lab_clock
        self._t0 = lab_clock() if lab_clock else 0.0
        self._fd: int | None = None
        self._repair()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def _repair(self) -> None:
        """Cut a partial last line (a crash mid-write), keeping every complete line."""
        try:
            with open(self.path, "rb+") as fh:
                data = fh.read()
                if data and not data.endswith(b"\n"):
                    fh.truncate(data.rfind(b"\n") + 1)
        except FileNotFoundError:
            pass

    def emit(self, event: str, level: str = "info", **fields: Any) -> None:
        rec: dict[str, Any] = {"ts": now_iso(), "level": level, "event": event}
        if self._clock is not None:
            rec["lab_s"] = round(self._clock() - self._t0, 6)
        rec.update(fields)
        line = (json.dumps(_clean(rec), default=str, allow_nan=False) + "\n").encode()
        if self._fd is None:
            return
        try:
            os.write(self._fd, line)
        except OSError:
            # Disk full: the log is a convenience beside the manifest; losing a line must not
            # stop the hardware from being made safe.
            pass

    def close(self) -> None:
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            except OSError:
                pass
            os.close(self._fd)
            self._fd = None


def read_log(path: Path | str) -> list[dict[str, Any]]:
    """Every event of a run's log (a missing log is an empty list)."""
    p = Path(path)
    if p.is_dir():
        p = p / LOG_NAME
    if not p.exists():
        return []
    text = read_input_text(p, "run log", GiB)
    return [json.loads(line) for line in text.splitlines() if line.strip()]
