"""The ranges every rig and plan value must lie in, read from the config models themselves
(acquisition.config: each field states its bounds and, in its description, their reason), as the
Markdown table of docs/config-ranges.md. One place states the ranges — the models — and the
docs are generated from it; tests/house/test_config_ranges.py checks the file is current.

    python tools/config_ranges.py            # print the table
    python tools/config_ranges.py --write    # rewrite docs/config-ranges.md
"""

from __future__ import annotations

import sys
import types
import typing
from pathlib import Path

import annotated_types as at
from pydantic import BaseModel

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "config-ranges.md"

_HEADER = """# Config ranges

Every number a rig or plan file gives is checked against a range a real instrument can have
before anything runs; a value outside is refused in one line naming the key (issue 47). The
ranges are stated once, on the fields of `acquisition/config.py`, each with its reason in the
field's description; this page is generated from them by `tools/config_ranges.py --write`
(a test fails when it is out of date). A field without bounds is not listed.

| file | key | range | what it is |
| --- | --- | --- | --- |
"""


def _bounds(metadata: list) -> str:
    parts = []
    for m in metadata:
        for attr, sign in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
            value = getattr(m, attr, None)
            if value is not None and isinstance(m, at.BaseMetadata):
                parts.append(f"{sign} {value:g}" if isinstance(value, float) else f"{sign} {value}")
    return ", ".join(parts)


def _models(annotation) -> list[type[BaseModel]]:
    """The config models inside an annotation (X, X | None, tuple[X, ...], list[X])."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is not None:
        for arg in typing.get_args(annotation):
            out += _models(arg)
    return out


def _element_bounds(annotation) -> str:
    """Bounds on the elements of a tuple[Annotated[float, Field(...)], ...] field."""
    for arg in typing.get_args(annotation):
        if typing.get_origin(arg) is typing.Annotated:
            found = []
            for extra in typing.get_args(arg)[1:]:
                found += getattr(extra, "metadata", [])
            if found:
                return "each " + _bounds(found)
        inner = _element_bounds(arg)
        if inner:
            return inner
    return ""


def rows(model: type[BaseModel], prefix: str, file: str, seen: set) -> list[tuple[str, ...]]:
    """(file, key, range, description) of every bounded field of `model` and the models it
    holds; `seen`: the models on the way down (a model that holds itself is listed once)."""
    out = []
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        bounds = _bounds(field.metadata) or _element_bounds(field.annotation)
        if bounds:
            what = " ".join((field.description or "").split())
            out.append((file, f"`{key}`", bounds, what))
        for sub in _models(field.annotation):
            if sub not in seen:
                index = "[]" if typing.get_origin(field.annotation) in (tuple, list) else ""
                out += rows(sub, f"{key}{index}.", file, seen | {sub})
    return out


def table() -> str:
    sys.path.insert(0, str(REPO))
    from acquisition.config import PlanConfig, RigConfig

    lines = [_HEADER]
    for model, file in ((RigConfig, "rig"), (PlanConfig, "plan")):
        for row in rows(model, "", file, {model}):
            lines.append("| " + " | ".join(c.replace("|", "\\|") for c in row) + " |\n")
    return "".join(lines)


if __name__ == "__main__":
    text = table()
    if "--write" in sys.argv[1:]:
        DOC.write_text(text)
        print(f"{DOC.relative_to(REPO)}: {text.count(chr(10)) - _HEADER.count(chr(10))} rows")
    else:
        print(text, end="")
