"""The whole spine, timed: `gonio demo --quick` into a temp dir, per stage (wall seconds),
plus the lab time the simulated rig accounted on its virtual clock.

Issue #2 asks for `gonio demo --quick` ≤ 2 min on 2 cores once set up; this prints the figure.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

__all__ = ["main"]


def main() -> None:
    from acquisition.store import RunStore
    from gonio.pipeline import demo

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        t0 = time.perf_counter()
        demo(out, None, quick=True, progress=False)
        total = time.perf_counter() - t0
        timings = json.loads((out / "timings.json").read_text())
        lab = float(RunStore.open(out).meta("lab_time_s") or "nan")
    print(f"{'stage':<24}{'wall s':>10}")
    for stage, seconds in timings.items():
        print(f"{stage:<24}{seconds:>10.2f}")
    print(f"{'total (in process)':<24}{total:>10.2f}")
    print(f"lab time on the rig's clock: {lab:.1f} s")


if __name__ == "__main__":
    main()
