"""Mutation fuzz of gonio's readers (issue 47): every file a reader is given either reads or is
refused with a one-line error (a UserError, or pydantic's ValidationError the CLI prints as one
line); anything else is an internal error, and a read that takes longer than HANG_S is a hang.

    python tools/fuzz_readers.py 10000                 # every reader, 10⁴ mutants each
    python tools/fuzz_readers.py 2000 samples manifest # some readers

Each mutant is a valid file of the repository (or one built here) with one to three of: bytes
flipped, a truncation, a run deleted, duplicated or swapped, a token inserted (1e308, NaN, NUL,
200 brackets, a huge integer, bytes that are not UTF-8). Mutants are reproducible: reader
names seed the generator. docs/reliability.md gives the figures.
"""

from __future__ import annotations

import collections
import random
import shutil
import signal
import sys
import tempfile
import time
import traceback
import zlib
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORPUS = REPO / "tests" / "bad_inputs"
#: A read slower than this is counted as a hang (the slowest reader, RGL, takes ~0.05 s).
HANG_S = 10

_TOKENS = (b"1e308", b"-1", b"nan", b"inf", b"\x00", b"[" * 200, b'""', b"true",
           b"99999999999999999999", b"\xff\xfe", b"{", b"]", b"0")  # fmt: skip


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One random mutation of `data`."""
    b = bytearray(data)
    kind = rng.randrange(6)
    if kind == 0 and b:
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] = rng.randrange(256)
    elif kind == 1 and b:
        b = b[: rng.randrange(len(b))]
    elif kind == 2 and b:
        i = rng.randrange(len(b))
        del b[i : i + rng.randint(1, 64)]
    elif kind == 3 and b:
        i = rng.randrange(len(b))
        b[i:i] = b[i : min(len(b), i + rng.randint(1, 64))]
    elif kind == 4:
        i = rng.randrange(len(b) + 1)
        b[i:i] = rng.choice(_TOKENS)
    elif len(b) > 4:
        i, j = sorted(rng.sample(range(len(b)), 2))
        b[i], b[j] = b[j], b[i]
    return bytes(b)


def _samples(p: Path) -> None:
    from brdfdata.samples import read_samples

    read_samples(p)


def _rig(p: Path) -> None:
    from acquisition.config import load_rig

    load_rig(p)


def _plan(p: Path) -> None:
    from acquisition.config import load_plan

    load_plan(p)


def _fit(p: Path) -> None:
    from fitting.result import read_fit

    read_fit(p)


def _import(fmt: str, **options) -> Callable[[Path], None]:
    def read(p: Path) -> None:
        from brdfdata.formats.convert import ImportOptions, import_samples

        import_samples(fmt, p, ImportOptions(**options))

    return read


def _run(p: Path) -> None:
    from acquisition.store import RunStore

    with RunStore.open(p.parent) as store:
        store.run_config()
        store.verify()


def _csv_seed() -> bytes:
    rng = random.Random(0)
    rows = ["theta_i,phi_i,theta_o,phi_o,f"]
    for _ in range(60):
        rows.append(f"{rng.uniform(0, 80):.3f},0,{rng.uniform(0, 80):.3f},"
                    f"{rng.uniform(0, 360):.3f},{rng.uniform(0.05, 0.3):.5f}")  # fmt: skip
    return ("\n".join(rows) + "\n").encode()


def _fit_seed() -> bytes:
    """The corpus's fit JSON with its schema version put back (the corpus case says 99)."""
    text = (CORPUS / "run_dirs" / "fit_json_newer" / "fit-lambert.json").read_text()
    return text.replace('"schema_version": 99', '"schema_version": 1').encode()


def _merl_seed() -> bytes:
    """A MERL .binary of a Lambertian BRDF (33 MB: MERL's fixed grid), built here."""
    from brdfdata.formats import merl

    return merl.merl_bytes(merl.tabulate(lambda wi, wo: [[0.5 / 3.14159] * 3] * len(wi)))


def readers() -> dict[str, tuple[Callable[[], bytes], str, Callable[[Path], None], Path | None]]:
    """name → (the valid file's bytes, its name, the reader, a run directory it lives in)."""
    run = CORPUS / "run_dirs" / "bin_px_huge"  # a good one-capture run
    rgl = REPO / "data" / "rgl_brdf" / "paper_white_rgb.bsdf"
    return {
        "samples": (lambda: (CORPUS / "samples" / "fix_outside_range.parquet").read_bytes(),
                    "s.parquet", _samples, None),
        "rig": (lambda: (REPO / "configs" / "rigs" / "lab-example.toml").read_bytes(),
                "rig.toml", _rig, None),
        "plan": (lambda: (REPO / "configs" / "plans" / "demo.toml").read_bytes(),
                 "plan.toml", _plan, None),
        "fit": (_fit_seed, "fit-lambert.json", _fit, None),
        "csv": (_csv_seed, "x.csv", _import("csv", angles="deg", sigma="rel=0.02"), None),
        "rgl": (lambda: rgl.read_bytes(), "x.bsdf", _import("rgl", grid="measured"), None),
        "merl": (_merl_seed, "x.binary", _import("merl", grid="theta_i=10:70:30,theta_o=0:80:20,"
                                                   "phi_o=0:180:45"), None),
        "run.toml": (lambda: (run / "run.toml").read_bytes(), "run.toml", _run, run),
        "manifest": (lambda: (run / "manifest.sqlite").read_bytes(), "manifest.sqlite", _run, run),
    }  # fmt: skip


class _Hang(Exception):
    pass


def _alarm(*_args) -> None:
    raise _Hang


def fuzz(name: str, n: int) -> tuple[collections.Counter, dict[str, str]]:
    """(counts of ok / user / internal / hang, one example per internal error's place) over
    `n` mutants of reader `name`."""
    from pydantic import ValidationError

    from plumbing.errors import UserError

    seed_bytes, file_name, read, run = readers()[name]
    data = seed_bytes()
    rng = random.Random(zlib.crc32(name.encode()))
    counts: collections.Counter = collections.Counter()
    examples: dict[str, str] = {}
    tmp = Path(tempfile.mkdtemp(prefix="gonio-fuzz-"))
    work = tmp / "run" if run is not None else tmp
    if run is not None:
        shutil.copytree(run, work)
    target = work / file_name
    previous = signal.signal(signal.SIGALRM, _alarm)
    try:
        for k in range(n):
            mutant = data
            for _ in range(rng.randint(1, 3)):
                mutant = mutate(mutant, rng)
            target.write_bytes(mutant)
            for side in ("-wal", "-shm"):
                (work / f"{file_name}{side}").unlink(missing_ok=True)
            signal.alarm(HANG_S)
            try:
                read(target)
                counts["read"] += 1
            except (UserError, ValidationError):
                counts["one line"] += 1
            except _Hang:
                counts["hang"] += 1
                examples.setdefault("hang", f"mutant {k}")
            except Exception as exc:  # the finding: an internal error
                frames = traceback.extract_tb(exc.__traceback__)
                ours = [f for f in frames if str(REPO) in f.filename and ".venv" not in f.filename]
                where = (
                    f"{Path(ours[-1].filename).relative_to(REPO)}:{ours[-1].lineno}"
                    if ours
                    else "?"
                )
                counts["internal error"] += 1
                examples.setdefault(f"{type(exc).__name__} at {where}", f"mutant {k}: {exc!s:.80}")
            finally:
                signal.alarm(0)
    finally:
        signal.signal(signal.SIGALRM, previous)
        shutil.rmtree(tmp, ignore_errors=True)
    return counts, examples


def main(argv: list[str]) -> int:
    import warnings

    warnings.simplefilter("ignore")  # numpy's floating-point warnings on mutated values
    n = int(argv[0]) if argv else 1000
    names = argv[1:] or list(readers())
    bad = 0
    for name in names:
        t0 = time.perf_counter()
        counts, examples = fuzz(name, n)
        print(f"{name}: {n} mutants in {time.perf_counter() - t0:.0f} s: {dict(counts)}")
        for where, what in examples.items():
            print(f"    {where} ({what})")
        bad += counts["internal error"] + counts["hang"]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main(sys.argv[1:]))
