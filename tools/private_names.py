"""An import-linter contract: a ``_name`` stays inside the module that defines it.

``from pkg.mod import _helper`` and ``mod._helper`` (with ``mod`` one of our modules) are broken
imports unless the importer is ``pkg.mod`` itself. A private *module* (``pkg/_app.py``) is not a
private name: import-linter's ``private_modules`` contract keeps those inside their package, and
its public names may be used by its siblings. Dunder names are not private.

Why a rule: a private name used elsewhere is an interface nobody declared — 19 of the 28 such
imports the house once had came from one module, whose base class and helpers three model
families depended on without its knowing (docs/architecture.md).

Configured in pyproject.toml::

    [tool.importlinter]
    contract_types = ["private_names: tools.private_names.PrivateNamesContract"]

    [[tool.importlinter.contracts]]
    type = "private_names"
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import grimp
from importlinter.application import output
from importlinter.domain.contract import Contract, ContractCheck

from tools.house_stats import private_uses

__all__ = ["PrivateNamesContract"]


def _source(module: str) -> Path | None:
    """The file of ``module``, found from its top-level package's folder without importing (and
    so running) anything of it."""
    top, *rest = module.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(next(iter(spec.submodule_search_locations))).joinpath(*rest)
    for path in (folder / "__init__.py", folder.with_suffix(".py")):
        if path.is_file():
            return path
    return None


class PrivateNamesContract(Contract):
    """No module of the root packages uses another module's private names (module docstring)."""

    type_name = "private_names"

    def check(self, graph: grimp.ImportGraph, verbose: bool) -> ContractCheck:
        known = set(graph.modules)
        broken = []
        for module in sorted(known):
            path = _source(module)
            if path is None:
                continue
            for line, text in private_uses(module, path.read_text(), known):
                broken.append({"importer": module, "line": line, "text": text})
        return ContractCheck(kept=not broken, warnings=[], metadata={"broken": broken})

    def render_broken_contract(self, check: ContractCheck) -> None:
        output.print_error("Private names used outside their module:", bold=False)
        output.new_line()
        for b in check.metadata["broken"]:
            output.print_error(f"- {b['importer']} (l.{b['line']}): {b['text']}", bold=False)
            output.new_line()
