"""The model library's front door: every BRDF model, registered once, behind one dispatcher.

``models.get(name, **options) -> Model``, ``models.names()``, ``models.entry(name)``, … The
pattern of colour-science's method mappings: the registry sits at the package face, *above* the
implementations it dispatches to (:mod:`fitting.models.catalogue` lists the entries and imports
the model modules; this module imports the catalogue), so nothing is filled lazily and no import
runs back up. Each entry holds the class that builds the model, its options with allowed values
and defaults, aliases, the published reference, the hemisphere regions it needs and the
parameter sets its properties are checked with. *Named variants* (``cook-torrance``,
``ts-ggx-smith``, …) are entries too: a base model with some options fixed.

Errors are one line and say what is allowed: an unknown model is :class:`UnknownModelError`
(a KeyError and a ValueError); an unknown option name or value is a ValueError naming the
allowed ones (the CLI prints it as one line and exits 2).

=====================  ========================================================================
module                 what it holds
=====================  ========================================================================
``base``               ``Model``, ``Parameter`` and the helpers every model builds on
``seed``               the seed lecture's Lambert, Phong family and Torrance-Sparrow
``anisotropic``        anisotropic Torrance-Sparrow (GGX/Beckmann) and Ward
``oren_nayar``         Oren-Nayar rough diffuse
``multilobe``          two microfacet lobes
``abc_lobe``           the ABC model's lobe (Löw et al. 2012)
``microfacet``         the numpy reference of D, G (docs/design.md §5)
``fresnel``            the numpy reference of F: dielectric, conductor, Schlick
``kernel_math``        exp(−x) and log-add-exp for the numba kernels
``microfacet_kernels`` the fused microfacet kernels (numba)
``lobe_kernels``       the fused Phong-family and Lambert kernels (numba)
``entries``            ``ModelEntry``, ``OptionSpec``: what a registry entry holds
``catalogue``          every entry, once
``properties``         reciprocity, albedo and the other checks every model must pass
=====================  ========================================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from brdfdata.coverage import CoverageReport, coverage_report
from fitting.models import catalogue
from fitting.models.base import PRECISIONS, Model, Parameter
from fitting.models.entries import ModelEntry, OptionSpec, UnknownModelError

__all__ = [
    "PRECISIONS",
    "Model",
    "Parameter",
    "OptionSpec",
    "ModelEntry",
    "UnknownModelError",
    "register",
    "entry",
    "resolve",
    "get",
    "names",
    "aliases",
    "applicable_options",
    "full_options",
    "describe",
    "model_coverage",
]


_ENTRIES: dict[str, ModelEntry] = {}
_ALIASES: dict[str, str] = {}


def register(e: ModelEntry) -> ModelEntry:
    """Add an entry; names and aliases must be new (one registry, no silent overrides).
    The catalogue's entries are added when this package is imported."""
    for key in (e.name, *e.aliases):
        if key in _ENTRIES or key in _ALIASES:
            raise ValueError(f"model name {key!r} is already registered")
    _ENTRIES[e.name] = e
    for a in e.aliases:
        _ALIASES[a] = e.name
    return e


for _entry in catalogue.ENTRIES:
    register(_entry)
del _entry


def resolve(name: str) -> str:
    """The registered name for ``name`` or one of its aliases."""
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
    return [n for n, e in _ENTRIES.items() if variants or e.base is None]


def aliases() -> dict[str, str]:
    """alias → registered name."""
    return dict(_ALIASES)


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


def model_coverage(name: str, wi, wo) -> CoverageReport:
    """:func:`brdfdata.coverage.coverage_report` for the regions the registered model ``name``
    needs."""
    return coverage_report(entry(name).needs, wi, wo)
