"""Shared test setup. Tests run on 2 cores within CI's budget; no timing assertions here."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

os.environ.setdefault("MPLBACKEND", "Agg")
warnings.filterwarnings("ignore", category=FutureWarning)

# Hypothesis: derandomised in CI so a failure reproduces; deadline off because numba kernels
# compile on first call.
settings.register_profile(
    "ci", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "configs"


@pytest.fixture
def configs() -> Path:
    return CONFIGS


def find_shared_data() -> Path:
    """The shared real-data directory: $GONIO_SHARED_DATA, else a `shared/data` beside the
    clone or one of its parents (CI clones beside shared/), else /work/shared/data.
    Missing data is a test failure, never a skip."""
    candidates = []
    if os.environ.get("GONIO_SHARED_DATA"):
        candidates.append(Path(os.environ["GONIO_SHARED_DATA"]))
    candidates += [p / "shared" / "data" for p in (REPO, *REPO.parents)]
    candidates.append(Path("/work/shared/data"))
    for c in candidates:
        if (c / "SOURCES.md").is_file():
            return c
    pytest.fail(
        "shared data not found (looked in "
        + ", ".join(str(c) for c in candidates)
        + "); set GONIO_SHARED_DATA to the shared/data directory"
    )


@pytest.fixture
def shared_data() -> Path:
    return find_shared_data()
