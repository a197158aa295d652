"""The `gonio` command line's application object and what its commands share: the consoles,
--debug, the operator options (--yes, --answers), --scene for simulated rigs, KEY=VALUE lists."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

__all__ = [
    "app",
    "out",
    "err",
    "kv_pairs",
    "operator_for",
    "scene_for",
    "YES_OPTION",
    "ANSWERS_OPTION",
]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="gonio: gonioreflectometer acquisition, calibration and BRDF fitting.",
    pretty_exceptions_enable=False,
)


out = Console()


err = Console(stderr=True)


_DEBUG = {"on": False}


def _version_cb(value: bool) -> None:
    if value:
        from gonio import version

        out.print(f"gonio {version()}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_cb, is_eager=True, help="Show version.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
) -> None:
    _DEBUG["on"] = debug


YES_OPTION = typer.Option("--yes", help="Operator steps are prepared: do not ask (unattended).")


ANSWERS_OPTION = typer.Option(
    "--answers", help="TOML file answering the operator steps ([answers] STEP = yes|no)."
)


def scene_for(path: Path | None):
    """--scene for a simulated rig: the emulated world (None: the rig file's own scene)."""
    if path is None:
        return None
    from gonio.backends import load_scene

    return load_scene(path)


def operator_for(yes: bool, answers: Path | None):
    """The operator for steps that need hands: --yes, an answers file, or the console."""
    from acquisition.operator import AutoOperator, ConsoleOperator, ScriptedOperator
    from gonio.errors import UserError

    if yes and answers is not None:
        raise UserError("give --yes or --answers, not both")
    if yes:
        return AutoOperator(log=sys.stderr)
    if answers is not None:
        return ScriptedOperator.from_file(answers)
    return ConsoleOperator()


def kv_pairs(items: list[str], what: str) -> dict[str, str]:
    from gonio.errors import UserError

    result = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UserError(f"{what} {item!r}: expected KEY=VALUE")
        result[key.strip()] = value.strip()
    return result
