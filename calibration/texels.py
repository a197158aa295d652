"""Per-texel samples: which texel of the sample plane each pixel's surface point falls in.

A square sample of side s (m) is cut into n × n texels of side t (n = ⌈s/t⌉ − the last row and
column are partial when t does not divide s). The grid starts at the sample's (−s/2, −s/2) corner;
texel (ix, iy) covers x ∈ [−s/2 + ix·t, −s/2 + (ix+1)·t), y likewise, and its index is iy·n + ix (+x
across, +y up: the sample frame of docs/design.md §3, and the layout of the simulator's textured
sample). The `texel` column of a samples table holds that index (int32); the grid is in the Parquet
metadata key ``gonio.texels`` = {"texel_mm", "n_x", "n_y", "size_m"}.

A samples file is never silently replaced by one made with other options: `check_replace`
compares the calibration record of an existing file with the new one (the atomic-write rule of
plumbing.atomic: nothing is overwritten by accident).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plumbing.errors import UserError

__all__ = ["TexelGrid", "TEXELS_KEY", "check_replace"]

TEXELS_KEY = "gonio.texels"


@dataclass(frozen=True)
class TexelGrid:
    texel_m: float
    size_m: float

    @property
    def n_side(self) -> int:
        # A tolerance of 1e-9 texel keeps s/t = 32.000000001 from growing a 33rd column.
        return max(1, math.ceil(self.size_m / self.texel_m - 1e-9))

    def index(self, point_m: np.ndarray) -> np.ndarray:
        """Texel index (…,) int32 of surface points (…, 3); −1 off the grid."""
        n = self.n_side
        ix = np.floor((point_m[..., 0] + self.size_m / 2.0) / self.texel_m)
        iy = np.floor((point_m[..., 1] + self.size_m / 2.0) / self.texel_m)
        inside = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
        out = np.where(inside, iy * n + ix, -1)
        return np.nan_to_num(out, nan=-1).astype(np.int32)

    def metadata(self) -> dict[str, str]:
        n = self.n_side
        record = {"texel_mm": self.texel_m * 1e3, "n_x": n, "n_y": n, "size_m": self.size_m}
        return {TEXELS_KEY: json.dumps(record)}


def check_replace(path: Path, new_metadata: dict[str, str]) -> None:
    """Refuse (UserError) to replace ``path`` when it holds samples made with other options
    (calibration record or texel grid); the same options may be re-made in place."""
    if not path.exists():
        return
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
    except Exception:  # pyarrow raises several types for a damaged file
        raise UserError(
            f"{path}: exists and is not a samples table; move it away or choose another --out"
        ) from None
    old = {k.decode(): v.decode() for k, v in meta.items()}
    for key in ("gonio.calibration", TEXELS_KEY):
        if _options(old.get(key)) != _options(new_metadata.get(key)):
            raise UserError(
                f"{path}: exists and was made with other calibration options ({key}); "
                "move it away or choose another --out"
            )


def _options(text: str | None):
    return None if text is None else json.loads(text)
