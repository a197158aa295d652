"""Shared test setup. Tests run on 2 cores within CI's budget; no timing assertions here."""

from __future__ import annotations

import os
import subprocess
import warnings
from collections.abc import Callable
from pathlib import Path

# The suite runs on two worker processes, one per core (make test). OpenBLAS's own threads
# (numpy and scipy: least squares, SVDs) then only oversubscribe the cores — its threads spin
# while they wait: measured, one realistic coverage repeat took 20 CPU-s and 10 s with them, 10
# CPU-s and 8.5 s without, so beside the other worker it runs twice as fast. So each worker's BLAS
# is single-threaded unless the developer says otherwise; set before numpy is first imported
# (the Makefile sets it too, for the workers and every subprocess). Results differ from a
# multi-threaded BLAS only in rounding (a summation order), which no test depends on.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from tests.support.paths import REPO

os.environ.setdefault("MPLBACKEND", "Agg")
warnings.filterwarnings("ignore", category=FutureWarning)

# Hypothesis: derandomised in CI so a failure reproduces; deadline off because numba kernels
# compile on first call.
settings.register_profile(
    "ci", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

CONFIGS = REPO / "configs"


@pytest.fixture
def configs() -> Path:
    return CONFIGS


def data_file(relpath: str) -> Path:
    """A real data file through the one resolver (brdfdata.data_paths: $GONIO_DATA, the
    repository's data/, an installed wheel, the download cache). A shipped file that is missing
    is a test failure, never a skip; a file not shipped for licence reasons (data/README.md)
    skips with the command that fetches it."""
    from brdfdata.data_paths import FETCHED, DataNotFound, find_data

    try:
        return find_data(relpath)
    except DataNotFound as exc:
        if relpath in FETCHED:
            pytest.skip(str(exc))
        pytest.fail(str(exc))


def data_dir(group: str) -> Path:
    """The folder holding a data group (``rgl_brdf``, ``calibration_chessboard``, …), found
    through one of its files (see data_file)."""
    from brdfdata.data_paths import FETCHED, manifest

    files = sorted(p for p in {**manifest(), **FETCHED} if p.split("/", 1)[0] == group)
    if not files:
        pytest.fail(f"no data group {group!r} in data/SHA256SUMS or brdfdata.data_paths.FETCHED")
    return data_file(files[0]).parent


@pytest.fixture
def tmpfs():
    """`mount(path, size)`: a real tmpfs over `path`; returns a function that grows it to
    8 MiB (the operator frees space), or None where mounting is not permitted. Unmounted at
    teardown."""
    mounted: list[Path] = []

    def mount(path: Path, size: str) -> Callable[[], None] | None:
        cmd = ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)]
        try:
            if os.geteuid() != 0 or subprocess.run(cmd, capture_output=True).returncode != 0:
                return None
        except OSError:  # no mount binary
            return None
        mounted.append(path)
        return lambda: subprocess.run(["mount", "-o", "remount,size=8m", str(path)], check=True)

    yield mount
    for path in mounted:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)
