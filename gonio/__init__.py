"""gonio's front door: the command line (gonio.cli), the spine (gonio.pipeline), the report, the
studies, and the one door to the simulator (gonio.backends). docs/architecture.md draws it."""

from __future__ import annotations

__all__ = ["version"]


def version() -> str:
    """gonio's installed version ("0+unknown" when run from a source tree without an install);
    recorded in every run.toml and printed in every report."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("gonio")
    except PackageNotFoundError:
        return "0+unknown"
