"""The model registry: every BRDF model registered once, with one dispatcher (issue 21 item 5).

Pattern of colour's method registries: a table name → entry (the class that builds the model,
its options with allowed values and defaults, aliases, the published reference, the coverage
of the hemisphere it needs and the parameter sets its properties are checked with), and one
dispatcher :func:`get`. *Named variants* (``cook-torrance``, ``ts-ggx-smith``, …) are entries
too: a base model with some options fixed, so a study or the model comparison refers to a
variant by name instead of keeping its own table of option sets.

Errors are one line and say what is allowed: an unknown model is :class:`UnknownModelError`
(a KeyError and a ValueError); an unknown option name or value is a ValueError naming the
allowed ones (the CLI prints it as one line and exits 2).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = [
    "OptionSpec",
    "ModelEntry",
    "UnknownModelError",
    "register",
    "entry",
    "resolve",
    "get",
    "names",
    "aliases",
    "group",
    "applicable_options",
    "full_options",
    "describe",
]


class UnknownModelError(KeyError, ValueError):
    """A model name that is neither registered nor an alias. ``str()`` is the plain message."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "unknown model"


@dataclass(frozen=True)
class OptionSpec:
    """One string option of a model: its allowed values (the first-listed default unless
    ``default`` says otherwise) and what it selects."""

    name: str
    allowed: tuple[str, ...]
    default: str
    doc: str = ""

    def __post_init__(self) -> None:
        if self.default not in self.allowed:
            raise ValueError(f"option {self.name}: default {self.default!r} not allowed")

    def describe(self) -> str:
        """``name: a* | b | c`` with the default starred."""
        vals = " | ".join(v + ("*" if v == self.default else "") for v in self.allowed)
        return f"{self.name}: {vals}"


@dataclass(frozen=True)
class ModelEntry:
    """One registered model or named variant.

    ``build(**options)`` returns the model for a complete, validated option set. A variant has
    ``base`` (the entry it specialises) and ``fixed`` (the options it fixes); its ``options``
    are the base's remaining ones. ``needs`` names the regions of the hemisphere the model's
    parameters are determined by (:mod:`fitting.coverage`). ``checks`` are (options, parameter
    sets) on which ``gonio models --check`` measures the properties. ``groups`` are named sets
    ("all": what ``gonio fit --model all`` fits).
    """

    name: str
    build: Callable[..., object]
    options: tuple[OptionSpec, ...] = ()
    aliases: tuple[str, ...] = ()
    summary: str = ""
    reference: str = ""
    base: str | None = None
    fixed: Mapping[str, str] = field(default_factory=dict)
    needs: tuple[str, ...] = ()
    checks: tuple[tuple[Mapping[str, str], tuple[Mapping[str, float], ...]], ...] = ()
    groups: frozenset[str] = frozenset()

    def option(self, name: str) -> OptionSpec | None:
        return next((o for o in self.options if o.name == name), None)


_ENTRIES: dict[str, ModelEntry] = {}
_ALIASES: dict[str, str] = {}


def register(e: ModelEntry) -> ModelEntry:
    """Add an entry; names and aliases must be new (one registry, no silent overrides)."""
    for key in (e.name, *e.aliases):
        if key in _ENTRIES or key in _ALIASES:
            raise ValueError(f"model name {key!r} is already registered")
    _ENTRIES[e.name] = e
    for a in e.aliases:
        _ALIASES[a] = e.name
    return e


def _ensure_loaded() -> None:
    if not _ENTRIES:
        from fitting import catalogue  # noqa: F401  (registers every model on import)


def resolve(name: str) -> str:
    """The registered name for ``name`` or one of its aliases."""
    _ensure_loaded()
    if name in _ENTRIES:
        return name
    if name in _ALIASES:
        return _ALIASES[name]
    raise UnknownModelError(f"unknown model {name!r}; known: {', '.join(names())}")


def entry(name: str) -> ModelEntry:
    """The entry of a model, variant or alias."""
    return _ENTRIES[resolve(name)]


def names(*, variants: bool = True) -> list[str]:
    """Registered names in registration order (base models first within each family)."""
    _ensure_loaded()
    return [n for n, e in _ENTRIES.items() if variants or e.base is None]


def aliases() -> dict[str, str]:
    """alias → registered name."""
    _ensure_loaded()
    return dict(_ALIASES)


def group(label: str) -> list[str]:
    """The names in a named group, e.g. ``group("all")``."""
    _ensure_loaded()
    return [n for n, e in _ENTRIES.items() if label in e.groups]


def _choices(e: ModelEntry) -> str:
    if not e.options:
        return "it takes no options"
    return "options: " + "; ".join(o.describe() for o in e.options)


def full_options(name: str, options: Mapping[str, object] | None = None) -> dict[str, str]:
    """Validated options of ``name`` with defaults filled in, *including* a variant's fixed
    ones (what the model is built with). Raises ValueError naming the allowed names/values."""
    e = entry(name)
    given = {str(k): str(v) for k, v in (options or {}).items()}
    out: dict[str, str] = {}
    for key, value in given.items():
        if key in e.fixed:
            if value != e.fixed[key]:
                raise ValueError(
                    f"model {e.name!r} fixes {key}={e.fixed[key]!r} (got {value!r}); "
                    f"use {e.base!r} to choose it"
                )
            continue
        spec = e.option(key)
        if spec is None:
            raise ValueError(f"model {e.name!r}: unknown option {key!r}; {_choices(e)}")
        if value not in spec.allowed:
            raise ValueError(
                f"model {e.name!r}: {key}={value!r}; choose one of {', '.join(spec.allowed)}"
            )
        out[key] = value
    for spec in e.options:
        out.setdefault(spec.name, spec.default)
    out.update(e.fixed)
    return out


def get(name: str, **options):
    """The model ``name`` (registered name, variant or alias) built with ``options``.

    ``get("torrance-sparrow", distribution="ggx")``; ``get("cook-torrance")`` (a variant);
    unknown names and options raise with the allowed ones listed.
    """
    e = entry(name)
    opts = full_options(e.name, options)
    if e.base is None:
        return e.build(**opts)
    model = _ENTRIES[e.base].build(**opts)
    model.name = e.name  # a variant is addressed (and reported) by its own name
    return model


def applicable_options(name: str, options: Mapping[str, object] | None) -> dict[str, str]:
    """The subset of ``options`` that ``name`` accepts with an allowed value (for fitting
    several models with one --option list: each takes what applies to it)."""
    e = entry(name)
    out = {}
    for k, v in (options or {}).items():
        spec = e.option(str(k))
        if spec is not None and str(v) in spec.allowed and k not in e.fixed:
            out[str(k)] = str(v)
    return out


def describe(name: str) -> Mapping[str, object]:
    """What ``gonio models`` lists for one entry: summary, reference, aliases, options
    (allowed values, default), fixed options of a variant, the parameters and declared
    properties of the default build, and the hemisphere regions the model needs."""
    e = entry(name)
    model = get(e.name)
    return MappingProxyType(
        {
            "name": e.name,
            "base": e.base,
            "aliases": e.aliases,
            "summary": e.summary,
            "reference": e.reference,
            "options": e.options,
            "fixed": dict(e.fixed),
            "parameters": model.parameters,
            "flags": dict(model.flags),
            "needs": e.needs,
        }
    )
