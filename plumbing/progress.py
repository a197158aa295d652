"""One progress helper for every long step (acquisition, calibration, MCMC, studies).

    with progress("calibrating", total=len(poses), enabled=show) as bar:
        for pose in poses:
            ...
            bar.advance()

`enabled=False` gives the same object doing nothing, so callers never branch. A bar counts
done / total with the elapsed time and an estimate of the time left; `transient` bars vanish
when done (for sub-steps inside a larger command).
"""

from __future__ import annotations

from typing import Any

__all__ = ["Progress", "progress"]


class Progress:
    """A rich progress bar (see module doc); every method is a no-op when disabled."""

    def __init__(
        self,
        description: str,
        total: float | None,
        *,
        completed: float = 0,
        enabled: bool = True,
        transient: bool = False,
    ) -> None:
        self._bar: Any = None
        if not enabled:
            return
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as _Rich

        self._bar = _Rich(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            transient=transient,
        )
        self._task = self._bar.add_task(description, total=total, completed=completed)
        self._bar.start()

    def advance(self, n: float = 1) -> None:
        if self._bar is not None:
            self._bar.advance(self._task, n)

    def update(self, *, completed: float | None = None, description: str | None = None) -> None:
        if self._bar is not None:
            self._bar.update(self._task, completed=completed, description=description)

    def grow(self, n: float) -> None:
        """More work to come than first known (e.g. an adaptive plan's second phase)."""
        if self._bar is not None:
            total = self._bar.tasks[0].total or 0
            self._bar.update(self._task, total=total + n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress(description: str, total: float | None, **kwargs: Any) -> Progress:
    """A `Progress` (see the class) — the one way gonio shows progress."""
    return Progress(description, total, **kwargs)
