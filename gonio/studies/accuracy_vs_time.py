"""`gonio study accuracy-vs-time`: the sweep (accuracy_sweep) into its CSV and run record, then
the page and plots from them (accuracy_document)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gonio.studies.accuracy_document import write_document
from gonio.studies.accuracy_sweep import (
    CSV_NAME,
    RECORD_NAME,
    StudyConfig,
    run_sweep,
    write_csv,
)
from gonio.studies.common import write_record

__all__ = ["run_study"]


def run_study(
    out_dir: Path,
    cfg: StudyConfig,
    *,
    scene_path: Path | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Run the sweep; write its CSV and run record, then the page and plots from them
    (gonio.studies.accuracy_document); return the rows."""
    rows, record = run_sweep(cfg, scene_path=scene_path, progress=progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(out_dir / CSV_NAME, rows)
    write_record(out_dir / RECORD_NAME, record)
    write_document(out_dir)
    return rows
