"""The `gonio fit` command's longer options, as annotated types (gonio.cli.fit uses them)."""

from __future__ import annotations

from typing import Annotated

import typer

__all__ = ["ModelOption", "BinOption", "NoWidenOption", "SamplerOption", "TemperaturesOption"]

ModelOption = Annotated[
    str,
    typer.Option(
        "--model",
        help="Model (see `gonio models`), several by commas, or all; several are ranked where "
        "their PSIS-LOO is reliable (all lists any model it leaves out, and why).",
    ),
]
BinOption = Annotated[
    float | None,
    typer.Option(
        "--bin",
        help="Bin samples into cells of DEG (0: every row; default: 0.1 for tables over "
        "1,000,000 rows, streamed in bounded memory; a verdict bounds what it moved).",
    ),
]

NoWidenOption = Annotated[
    bool,
    typer.Option(
        "--no-widen",
        help="Keep the sampler's intervals: do not widen them for model mismatch (they then "
        "hold only if the model describes the material).",
    ),
]

SamplerOption = Annotated[
    str,
    typer.Option(
        help="ensemble (emcee) | tempered (parallel tempering: for posteriors with several "
        "modes or long ridges; reports the modes and their masses; costs --temperatures × "
        "the steps)."
    ),
]

TemperaturesOption = Annotated[
    int,
    typer.Option(
        help="Temperatures of --sampler tempered: β from 1 down by exp(−√(2/D)) each "
        "(D parameters), so neighbours swap; more reach hotter and cross deeper valleys."
    ),
]
