"""`make bench`: run every benchmarks/bench_*.py `main()` and print its figures.

Speed is measured here, never asserted in tests. Each benchmark prints its own table; the
figures quoted in docs/performance.md come from this command on a 2-core machine. Every
bench_*.py is picked up; `make bench BENCH=bench_soak` runs one (the soak, issue 9, takes a few
minutes; its figures are in docs/reliability.md).
"""

from __future__ import annotations

import importlib.util
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # the benchmarks' shared helpers (benchmarks/_common.py)


def main(argv: list[str]) -> int:
    names = argv or sorted(p.stem for p in HERE.glob("bench_*.py"))
    failed = 0
    for name in names:
        path = HERE / f"{name}.py"
        print(f"\n=== {name} ===", flush=True)
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        t0 = time.perf_counter()
        saved = sys.argv
        sys.argv = [str(path)]  # each benchmark parses its own (default) options
        try:
            spec.loader.exec_module(module)
            module.main()
        except (Exception, SystemExit):
            traceback.print_exc()
            failed += 1
        finally:
            sys.argv = saved
        print(f"({name}: {time.perf_counter() - t0:.1f} s wall)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
