"""Where things are, for every test module wherever it sits under tests/."""

from __future__ import annotations

from pathlib import Path

__all__ = ["REPO", "TESTS", "CONFIGS"]

#: The repository's root (the folder holding pyproject.toml).
REPO = Path(__file__).resolve().parents[2]
#: tests/: the test data folders (scenes/, instruments/, bad_inputs/) are here.
TESTS = REPO / "tests"
CONFIGS = REPO / "configs"
