"""The bad-input corpus (tests/bad_inputs/, cases in cases.toml): one test per corpus file.

Each case copies its file (or run directory) into a fresh temporary directory, records the
SHA-256 and mtime of every file there, runs the gonio command on it in a subprocess, and checks:

- the exit status is 2 (a user error, not 1 = internal error, not 0);
- stderr has no traceback and is exactly one ``error:`` line, which names the file, the key
  where there is one, and what to do (the case's ``expect`` words) — no warning before it;
- every file is byte-identical with the same mtime, and no file or directory appeared (no
  temp files, no half-written outputs);
- with ``--debug`` the same command re-raises, so a traceback is shown (run in-process here:
  ``main`` re-raising is what makes Python print it; one case is also run end to end).
"""

from __future__ import annotations

import gc
import hashlib
import os
import shutil
import subprocess
import sys
import tomllib
import traceback
from pathlib import Path

import pytest

from tests.support.paths import REPO

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(80)

CORPUS = REPO / "tests" / "bad_inputs"
CASES = tomllib.loads((CORPUS / "cases.toml").read_text())["case"]
MAX_BYTES = 50_000


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "GONIO_DEBUG"}
    env["MPLBACKEND"] = "Agg"
    return env


def _snapshot(root: Path) -> dict[str, tuple[str, int] | None]:
    """Every file (SHA-256, mtime in ns) and every directory (None) under root."""
    snap: dict[str, tuple[str, int] | None] = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_dir() and not p.is_symlink():
            snap[rel + "/"] = None
        else:
            snap[rel] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
    return snap


def _diff(before: dict, after: dict) -> list[str]:
    out = [f"new: {k}" for k in after.keys() - before.keys()]
    out += [f"gone: {k}" for k in before.keys() - after.keys()]
    out += [f"changed: {k}" for k in before.keys() & after.keys() if before[k] != after[k]]
    return sorted(out)


def _prepare(case: dict, tmp_path: Path) -> tuple[Path, list[str]]:
    src = CORPUS / case["file"]
    work = tmp_path / "work"
    work.mkdir()
    dst = work / src.name
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    args = [a.format(path=dst, tmp=work, repo=REPO) for a in case["args"]]
    return work, args


def _gonio(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=_env(),
        timeout=300,
    )


def _in_process_debug(args: list[str], cwd: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run `gonio --debug ARGS` in this process; return the traceback it raises."""
    from gonio import cli

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", ["gonio", "--debug", *args])
    monkeypatch.delenv("GONIO_DEBUG", raising=False)
    try:
        cli.main()
    except SystemExit as exc:  # main turned the error into an exit code: --debug ignored
        pytest.fail(f"--debug: exited with {exc.code} instead of re-raising")
    except Exception as exc:  # any error type; that it propagates is the point
        return "".join(traceback.format_exception(exc))
    pytest.fail("--debug: the command succeeded on bad input")


@pytest.mark.parametrize("case", CASES, ids=[c["file"] for c in CASES])
def test_bad_input(case: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    work, args = _prepare(case, tmp_path)
    before = _snapshot(tmp_path)

    res = _gonio(args, work)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, (res.returncode, res.stderr)
    assert "Traceback" not in res.stderr, res.stderr
    errors = [ln for ln in lines if ln.startswith("error: ")]
    assert len(errors) == 1 and len(lines) == 1, res.stderr  # one line, nothing else
    line = errors[0].lower()
    missing = [w for w in case["expect"] if w.lower() not in line]
    assert not missing, f"{errors[0]!r} lacks {missing}"
    assert _diff(before, _snapshot(tmp_path)) == []
    # The cases with a command in them (rig_python_code, runtoml_trigger_command) touch PWNED.
    assert not (work / "PWNED").exists() and not (REPO / "PWNED").exists()

    tb = _in_process_debug(args, work, monkeypatch)
    assert tb.startswith("Traceback (most recent call last)")
    # The traceback kept the failed command's frames (and any SQLite connection in them, whose
    # -wal/-shm files exist while it is open) alive; a process exits here, so collect them.
    gc.collect()
    assert _diff(before, _snapshot(tmp_path)) == []


def test_debug_shows_the_traceback_end_to_end(tmp_path: Path) -> None:
    """The same bad samples file: one line without --debug, a traceback with it."""
    case = next(c for c in CASES if c["file"] == "samples/partial_nan.parquet")
    work, args = _prepare(case, tmp_path)
    plain = _gonio(args, work)
    debug = _gonio(["--debug", *args], work)
    assert plain.returncode == 2 and "Traceback" not in plain.stderr
    assert debug.returncode != 0
    assert "Traceback (most recent call last)" in debug.stderr
    assert "SamplesError" in debug.stderr


def test_corpus_is_complete_and_small() -> None:
    """Every corpus item has exactly one case, every case's file exists, every file < 50 kB."""
    listed = [c["file"] for c in CASES]
    assert len(listed) == len(set(listed))
    items = {
        f"{group}/{p.name}"
        for group in ("configs", "run_dirs", "samples", "studies")
        for p in (CORPUS / group).iterdir()
    }
    assert items == set(listed)
    sizes = {p: p.stat().st_size for p in CORPUS.rglob("*") if p.is_file()}
    assert max(sizes.values()) < MAX_BYTES, max(sizes, key=sizes.get)
