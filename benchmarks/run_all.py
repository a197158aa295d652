"""`make bench`: run every benchmarks/bench_*.py `main()` and print its figures.

Speed is measured here, never asserted in tests. Each benchmark prints its own table; the
figures quoted in docs/performance.md come from this command on a 2-core machine. Every
bench_*.py is picked up except the opt-in ones in OPT_IN, which run only when named;
`make bench BENCH=bench_soak` runs one (the soak, issue 9, takes a few minutes; its figures are in
docs/reliability.md). `make bench BENCH=bench_camera_scale` runs the real-camera-size reduce
(issue 23 item 4): about 2 h and ~16 GB of disk under /tmp the first time.

Each benchmark runs in a process of its own. A process's peak resident set (VmHWM) never goes
down, so in one shared process every memory figure after the first large benchmark reported
that benchmark's peak instead of its own: the soak printed 741 MiB peak RSS in one `make bench`
(issue 23, item 6) after bench_big_fit and bench_render had run before it, against 175–197 MiB
alone. A fresh interpreter per benchmark also keeps one benchmark's numba caches, thread pools
and imported libraries from timing another's.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# Too slow (or too large on disk) for every `make bench`: run only when named.
OPT_IN = frozenset({"bench_camera_scale"})


def main(argv: list[str]) -> int:
    names = argv or sorted(p.stem for p in HERE.glob("bench_*.py") if p.stem not in OPT_IN)
    failed = []
    for name in names:
        path = HERE / f"{name}.py"
        if not path.is_file():
            print(f"no benchmark named {name} in {HERE}", file=sys.stderr)
            failed.append(name)
            continue
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        # each benchmark parses its own (default) options; the child finds benchmarks/_common.py
        # because a script's own directory is first on its sys.path
        rc = subprocess.call([sys.executable, str(path)], cwd=HERE.parent)
        if rc != 0:
            failed.append(name)
        print(f"({name}: {time.perf_counter() - t0:.1f} s wall, exit {rc})", flush=True)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
