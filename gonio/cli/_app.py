"""The `gonio` command line's application object and what its commands share: the help panels
and their order, the consoles (and how they print tables), --debug, the operator options (--yes,
--answers), --scene for simulated rigs, KEY=VALUE lists."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import (
    Console,
    ConsoleDimensions,
    ConsoleOptions,
    Group,
    RenderHook,
    RenderResult,
)
from rich.measure import Measurement
from rich.padding import Padding
from rich.table import Column, Table
from rich.text import Text
from typer.core import TyperGroup

__all__ = [
    "app",
    "LAB",
    "ANALYSIS",
    "DATA",
    "SCALE_OUT",
    "SIMULATION",
    "HELP_PANELS",
    "PIPE_WIDTH",
    "out",
    "err",
    "kv_pairs",
    "operator_for",
    "scene_for",
    "YES_OPTION",
    "ANSWERS_OPTION",
]

# `gonio --help` reads in the order a lab works (issue 42): each command names its panel
# (`rich_help_panel=` where it is registered); HELP_PANELS orders the panels and their commands.
LAB = "Lab"
ANALYSIS = "Analysis"
DATA = "Data"
SCALE_OUT = "Scale-out"
SIMULATION = "Simulation and studies"

HELP_PANELS = {
    LAB: ("rig", "acquire", "capture", "calibrate-rig", "calibrate-camera", "calibrate", "runs"),
    ANALYSIS: ("fit", "report", "plan", "models"),
    DATA: ("import", "export", "data"),
    SCALE_OUT: ("fit-texels", "fit-batch"),
    SIMULATION: ("demo", "simulate", "study"),
}


class _InHelpOrder(TyperGroup):
    """Lists the commands in the order of HELP_PANELS (one not in it last). Typer would list them
    as registered, sub-apps (`rig`, `runs`, `data`) after every command; its help shows the
    panels in the order their first command is listed."""

    def list_commands(self, ctx: typer.Context) -> list[str]:
        order = [name for names in HELP_PANELS.values() for name in names]
        rank = {name: i for i, name in enumerate(order)}
        return sorted(super().list_commands(ctx), key=lambda name: rank.get(name, len(rank)))


app = typer.Typer(
    cls=_InHelpOrder,
    add_completion=False,
    no_args_is_help=True,
    help="gonio: gonioreflectometer acquisition, calibration and BRDF fitting.",
    pretty_exceptions_enable=False,
)


# -- the consoles: tables stay readable in a pipe and in a narrow terminal (issue 42) ----------
# A table is drawn when it fits the width, or when only its widest column has to wrap and keeps
# at least _MIN_WRAPPED characters (and its longest word); otherwise its rows are printed as
# "header: value" records, so no cell is folded into a column a few characters wide. Cells are
# shown as the table would show them: a rich Text (gonio.plain_text.plain) as it is, never
# parsed for markup.

#: Width of output that is not a terminal (a pipe, a file) when COLUMNS does not say otherwise:
#: rich would assume 80 columns (or the width of the terminal stdin is on).
PIPE_WIDTH = 1000

_MIN_WRAPPED = 30


def _natural(
    table: Table, column: Column, console: Console, wide: ConsoleOptions
) -> tuple[int, int]:
    """(widest line, longest word) of `column`'s cells and header, unwrapped."""
    cells = [column.header, *column.cells] if table.show_header else list(column.cells)
    sizes = [Measurement.get(console, wide, cell) for cell in cells]
    return max((m.maximum for m in sizes), default=0), max((m.minimum for m in sizes), default=0)


def _fits(table: Table, console: Console, options: ConsoleOptions) -> bool:
    """True when `table` is readable at options.max_width (see above)."""
    wide = options.update_width(10 * PIPE_WIDTH)
    excess = Measurement.get(console, wide, table).maximum - options.max_width
    if excess <= 0:
        return True
    # Rich narrows the widest wrapping column first, down to the next widest: if the excess is
    # no more than that lead, that column alone wraps.
    spans = sorted(
        (
            _natural(table, column, console, wide)
            for column in table.columns
            if column.width is None and not column.no_wrap
        ),
        reverse=True,
    )
    if not spans:
        return False
    (widest, longest_word), next_widest = spans[0], (spans[1][0] if len(spans) > 1 else 0)
    return excess <= widest - next_widest and widest - excess >= max(_MIN_WRAPPED, longest_word)


class _Readable:
    """A table drawn when it fits (`_fits`), else its rows as records:

        title
        - header: value
          header: value
          header:
            a value of
            several lines
        - header: value (the next row)

    Empty cells are left out; a table without a header shows a row as `first: other cells`."""

    def __init__(self, table: Table) -> None:
        self.table = table

    def __rich_measure__(self, console: Console, options: ConsoleOptions) -> Measurement:
        return Measurement.get(console, options, self.table)

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        table = self.table
        if _fits(table, console, options):
            yield table
            return

        def text(cell: Any) -> Any:  # a str cell is markup to a table, and so here
            return console.render_str(cell) if isinstance(cell, str) else cell

        def lines(value: Text, first: str, rest: str) -> Iterable[Text]:
            wrapped = value.wrap(console, max(options.max_width - len(rest), 1), overflow="fold")
            for i, line in enumerate(wrapped):
                line.rstrip()
                yield Text(first if i == 0 else rest) + line

        def blank(cell: Any) -> bool:
            return isinstance(cell, str | Text) and not str(cell).strip()

        if table.title:
            yield from lines(Text.assemble(text(table.title), style="table.title"), "", "")
        for row in zip(*(column.cells for column in table.columns), strict=True):
            if table.show_header:
                heads = [column.header for column in table.columns]
                fields = [(h, c) for h, c in zip(heads, row, strict=True) if not blank(c)]
                marks = ("- ", "  ")
            else:
                others = [text(c) for c in row[1:] if not blank(c)]
                if not others:
                    yield text(row[0])
                    continue
                fields = [(row[0], Text("  ").join(others))]
                marks = ("", "  ")
            for i, (head, cell) in enumerate(fields):
                mark = marks[0] if i == 0 else marks[1]
                key, value = text(head), text(cell)
                if not isinstance(key, Text):  # a renderable header: shown without it
                    key = Text()
                key = Text.assemble(key, ":", style="table.header")
                if not isinstance(value, Text):
                    yield Text(mark) + key
                    yield Padding(value, (0, 0, 0, 4), expand=False)
                elif "\n" in value.plain:
                    yield Text(mark) + key
                    for part in value.split("\n"):
                        yield from lines(part, "    ", "      ")
                else:
                    yield from lines(key + Text(" ") + value, mark, "    ")
        if table.caption:
            yield from lines(Text.assemble(text(table.caption), style="table.caption"), "", "")


class _ReadableTables(RenderHook):
    """Prints every table (also in a Group, as `gonio runs show` and `gonio rig check` print) as
    a `_Readable`."""

    def process_renderables(self, renderables: list[Any]) -> list[Any]:
        return [self._readable(r) for r in renderables]

    def _readable(self, renderable: Any) -> Any:
        if isinstance(renderable, Table):
            return _Readable(renderable)
        if isinstance(renderable, Group):
            return Group(*map(self._readable, renderable.renderables), fit=renderable.fit)
        return renderable


class _Console(Console):
    """A rich Console that keeps tables readable: output that is not a terminal is PIPE_WIDTH
    wide (unless COLUMNS or `width=` says otherwise), and tables print as `_Readable`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.push_render_hook(_ReadableTables())

    @property
    def size(self) -> ConsoleDimensions:
        size = super().size
        if self._width is None and not self.is_terminal:  # _width: width= or COLUMNS
            return ConsoleDimensions(PIPE_WIDTH, size.height)
        return size

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        Console.size.fset(self, new_size)


# Never parsed for markup: what gonio prints carries paths, run and material names, channel names
# and device replies, which are data ("teflon[v2]" would print as "teflon", "[bold red]R" as a
# red "R", "[/dev/ttyUSB0]" is a closing tag that crashed a command). Styling is rich Text's.
out = _Console(markup=False)


err = _Console(stderr=True, markup=False)


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
