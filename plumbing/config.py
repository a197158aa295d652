"""Data-only config files into strict pydantic models, with one-line errors.

Configs are data: TOML (or JSON), never code — other formats (YAML can construct objects,
Python would run) are refused by suffix. Every mistake a user can type becomes a `ConfigError`
with one line naming the file, the key and what is allowed (`format_validation_error`), with a
hint when the mistake is about units (units live in key names, SI and degrees).
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from plumbing.errors import UserError
from plumbing.inputs import MiB, NotAnInputFile, check_nesting, open_input

__all__ = [
    "ConfigError",
    "Strict",
    "CONFIG_SUFFIXES",
    "load_config_data",
    "format_validation_error",
    "load_model",
]

M = TypeVar("M", bound=BaseModel)


class ConfigError(UserError, ValueError):
    """A config file is wrong. The message is one line: file, key, what is allowed."""


class Strict(BaseModel):
    """The base of every config model: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# Units live in key names (`distance_m`, `exposure_s`, `min_deg`), never in values: a value
# is a plain number in the key's unit. These suffixes name the unit, longest first.
_UNIT_SUFFIXES = (
    ("_W_sr", "W/sr"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_mm", "mm"),
    ("_cm", "cm"),
    ("_um", "µm"),
    ("_ms", "ms"),
    ("_us", "µs"),
    ("_m", "m"),
    ("_s", "s"),
)
_SI_SUFFIX = {"_rad": "_deg", "_mm": "_m", "_cm": "_m", "_um": "_m", "_ms": "_s", "_us": "_s"}
_NUMBER_WITH_UNIT = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*([^\d\s].*?)\s*$")
_RANGE_TYPES = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")


def _unit_of(key: str) -> tuple[str, str] | None:
    """(suffix, unit name) of a unit-carrying key, e.g. "min_deg" → ("_deg", "deg")."""
    for suffix, unit in _UNIT_SUFFIXES:
        if key.endswith(suffix) and len(key) > len(suffix):
            return suffix, unit
    return None


def _fields_at(model: type[BaseModel] | None, loc: tuple) -> set[str] | None:
    """Field names of the (nested) model that holds the last key of `loc`, if known."""
    for part in loc[:-1]:
        if model is None:
            return None
        if isinstance(part, int):
            continue
        info = model.model_fields.get(str(part))
        model = _submodel(info.annotation) if info is not None else None
    return set(model.model_fields) if model is not None else None


def _submodel(annotation: object) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = _submodel(arg)
        if found is not None:
            return found
    return None


def _unit_hint(e: dict, loc: tuple, model: type[BaseModel] | None) -> str | None:
    """A one-line explanation when the mistake is about units, else None."""
    keys = [p for p in loc if isinstance(p, str)]
    if not keys:
        return None
    key = keys[-1]
    unit = _unit_of(key)
    got = e.get("input")
    if e["type"] == "extra_forbidden" and unit is not None and unit[0] in _SI_SUFFIX:
        want = key[: -len(unit[0])] + _SI_SUFFIX[unit[0]]
        fields = _fields_at(model, loc)
        if fields is None or want in fields:
            return (
                f"unknown key; gonio configs use SI units and degrees: write {want} "
                f"(in {dict(_UNIT_SUFFIXES)[_SI_SUFFIX[unit[0]]]}) instead of {key}"
            )
    if unit is not None and e["type"] in ("tuple_type", "list_type"):
        return f"{key} is a list of numbers in {unit[1]}, e.g. [30.0] (got {got!r})"
    if unit is not None and isinstance(got, str):
        m = _NUMBER_WITH_UNIT.match(got)
        if m:
            return (
                f"{key} is in {unit[1]} (the unit is in the key name); write a plain number "
                f"in {unit[1]}, without a unit string (got {got!r})"
            )
        return f"{key} is a number in {unit[1]}; write it without quotes (got {got!r})"
    if unit is not None and e["type"] in _RANGE_TYPES:
        return f"{e['msg']}; {key} is in {unit[1]} (got {got!r})"
    return None


def format_validation_error(
    path: Path | str, err: ValidationError, model: type[BaseModel] | None = None
) -> str:
    """First pydantic error as one line: `file: key.path: message (got value)`.

    `model` (the validated class) lets an unknown key like `distance_mm` be answered with the
    real key (`distance_m`) when it exists.
    """
    e = err.errors()[0]
    loc = tuple(e["loc"])
    where = ".".join(str(p) for p in loc)
    msg = e["msg"].removeprefix("Value error, ").removeprefix("Assertion failed, ")
    hint = _unit_hint(e, loc, model)
    if hint is not None:
        return f"{path}: {where}: {hint}"
    if e["type"] == "extra_forbidden":
        msg = "unknown key (check the spelling; see the commented example configs in configs/)"
    elif e["type"] == "missing":
        msg = "required key is missing"
    got = e.get("input")
    tail = (
        f" (got {got!r})"
        if e["type"] not in ("missing", "extra_forbidden") and loc and _short(got)
        else ""
    )
    if not loc:  # a whole-file check (duplicate ids, missing roles): its message names the key
        return f"{path}: {msg}{tail}"
    return f"{path}: {where}: {msg}{tail}"


def _short(v: object) -> bool:
    return not isinstance(v, dict | list | tuple) or len(repr(v)) < 60


CONFIG_SUFFIXES = (".toml", ".json")


def load_config_data(path: Path | str) -> dict:
    """Parse a config file. Configs are data: TOML (or JSON), never code, so other formats
    (YAML can construct objects, Python would run) are refused by suffix."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such file")
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory; give a .toml config file")
    if path.suffix.lower() not in CONFIG_SUFFIXES:
        raise ConfigError(
            f"{path}: configs must be TOML (.toml) or JSON (.json) files, not "
            f"{path.suffix or 'files without a suffix'!r}; convert it to TOML"
        )
    try:
        with open_input(path, "config file", 16 * MiB) as fh:
            text = fh.read().decode("utf-8")
        check_nesting(text, path, "config file")
        if path.suffix.lower() == ".json":
            data = json.loads(text)
            if not isinstance(data, dict):
                raise ConfigError(f"{path}: a JSON config must be an object {{...}}")
            return data
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except NotAnInputFile as exc:
        raise ConfigError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None


def load_model(path: Path | str, model: type[M], error: type[Exception] = ConfigError) -> M:
    """Parse a data-only config file into `model`; every mistake is one `error` line."""
    data = load_config_data(path)
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise error(format_validation_error(path, err, model)) from None
