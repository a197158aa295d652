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

# numba's threads likewise: each worker runs the kernels' serial twins (plumbing.numba_policy's
# "serial" policy). With two workers on two cores a parallel twin's threads only wait for each other
# (numba's spin-waits: ~10 % more CPU, tests/support/repeats.py), and every parallel twin a process
# calls is one more compile of its kernel: ~36 CPU-s of a fresh checkout's suite went to compiling
# them (measured with numba's compile events, 2026-12-07). The tests of the parallel twins and of
# the "auto" policy set the policy they test themselves (tests/fitting/models/test_models.py,
# tests/calibration/test_hdr_fused.py). Processes the tests start run as a user's would.
from plumbing.numba_policy import set_threading  # noqa: E402

set_threading("serial")

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from tests.support.paths import REPO  # noqa: E402

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


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "heavy(seconds): a module that takes about this long on one worker; the longest run "
        "first (pytest_collection_modifyitems)",
    )
    config.addinivalue_line(
        "markers",
        "waits: a module that spends most of its wall time waiting on emulated hardware's real "
        "time (a camera's frame period, a serial link, a timeout); it starts beside the longest "
        "modules, whose repeat pools then have the cores (pytest_collection_modifyitems)",
    )
    if "PYTEST_XDIST_WORKER" not in os.environ:
        # Probe Mitsuba's variant once, in the process that starts the workers: its answer is
        # in the environment every worker, pool process and `gonio` subprocess inherits
        # (simulator.variant), instead of ~50 probes of ~0.5 CPU-s each across the suite.
        from simulator.variant import choose_variant

        choose_variant()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest test files first, longest first, each of the files that mostly wait right
    after one of them; the rest in their usual order. The suite runs a file at a time on each of
    two workers (make test: --dist loadfile, with xdist's own reordering by number of tests
    switched off), taking files in this order: started last, a 5-minute file kept one worker
    busy long after the other had run out of work (measured: the workers ended 340 s apart).
    Longest first, the short files fill in around the long ones. A waiting file beside another
    waiting file left both cores ~70 % idle for a minute (the Aravis and pretend-lab files,
    measured with a per-second CPU trace of a fresh clone's make test); beside a file whose
    repeats run in a pool of two processes (tests/support/repeats.py), the pool takes the core
    the waiting file leaves."""

    def cost(item: pytest.Item) -> float:
        mark = item.get_closest_marker("heavy")
        return float(mark.args[0]) if mark is not None else 0.0

    def waits(item: pytest.Item) -> bool:
        return item.get_closest_marker("waits") is not None

    first: dict[str, pytest.Item] = {}  # file → its first item, in collection order
    for item in items:
        first.setdefault(item.nodeid.split("::")[0], item)
    files = sorted(first, key=lambda f: -cost(first[f]))  # stable: the rest keep their order
    waiting = [f for f in files if waits(first[f])]
    working = [f for f in files if not waits(first[f])]
    rank: dict[str, int] = {}
    for i, f in enumerate(working):
        rank[f] = len(rank)
        if i < len(waiting):
            rank[waiting[i]] = len(rank)
    for f in waiting[len(working) :]:
        rank[f] = len(rank)
    order = {id(item): i for i, item in enumerate(items)}
    items.sort(key=lambda item: (rank[item.nodeid.split("::")[0]], order[id(item)]))
