"""`gonio study real-materials`: the sweep (materials_sweep) into its CSVs and run record, then
the page and one plot per material from them (materials_document)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from gonio.studies.common import write_record
from gonio.studies.materials_document import write_document
from gonio.studies.materials_sweep import (
    CSV_COLUMNS,
    CSV_NAME,
    PARAM_COLUMNS,
    PARAMS_NAME,
    RECORD_NAME,
    SLICE_COLUMNS,
    SLICES_NAME,
    RealMaterialsConfig,
    run_sweep,
    write_csv,
)

__all__ = ["run_real_materials"]


def run_real_materials(
    out_dir: Path,
    cfg: RealMaterialsConfig,
    *,
    progress: bool = True,
    work_dir: Path | None = None,
    on_event: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Run the study; write its CSVs (one row per material × model, the parameters, the
    plotted slices) and run record into ``out_dir``, then the page and one PNG per material
    from them (gonio.studies.materials_document); return the rows."""
    from gonio.errors import UserError

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"{out_dir}: exists and is not a directory; choose another --out")
    rows, params, slices, record = run_sweep(
        cfg, progress=progress, work_dir=work_dir, on_event=on_event
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(out_dir / CSV_NAME, rows, CSV_COLUMNS)
    write_csv(out_dir / PARAMS_NAME, params, PARAM_COLUMNS)
    write_csv(out_dir / SLICES_NAME, slices, SLICE_COLUMNS)
    write_record(out_dir / RECORD_NAME, record)
    write_document(out_dir)
    return rows
