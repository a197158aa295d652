"""What the model registry holds: one :class:`ModelEntry` per model or named variant, its string
options (:class:`OptionSpec`), and the error an unknown name raises.

The entries themselves are in :mod:`fitting.models.catalogue`; the registry and its one
dispatcher (``get``, ``names``, …) are the package's face, :mod:`fitting.models`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

__all__ = ["OptionSpec", "ModelEntry", "UnknownModelError"]


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
    parameters are determined by (:mod:`brdfdata.coverage`). ``checks`` are (options, parameter
    sets) on which ``gonio models --check`` measures the properties.
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

    def option(self, name: str) -> OptionSpec | None:
        return next((o for o in self.options if o.name == name), None)
