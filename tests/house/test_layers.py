"""The house's import rules (docs/design.md §2, docs/architecture.md) are import-linter contracts
in pyproject.toml — and every one of them can fail.

Two linter runs on a copy of the tree prove it for every contract the file declares (read from
pyproject.toml, so a new contract without a way to break it fails here): one copy where each
contract gets one import that breaks it — an existing module of a low layer reaching a module of
the highest layer of its container, a forbidden or private import — and one where every
exhaustive contract's container gets a module no layer lists.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.support.paths import REPO

PACKAGES = ("plumbing", "brdfdata", "fitting", "acquisition", "calibration", "simulator", "gonio")
LINT = Path(sys.executable).with_name("lint-imports")
CONTRACTS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"][
    "contracts"
]


def _lint(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(LINT), "--config", str(root / "pyproject.toml")],
        cwd=root,
        capture_output=True,
        text=True,
        env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"},
        timeout=300,
    )


def _copy_tree(dst: Path) -> None:
    shutil.copy(REPO / "pyproject.toml", dst / "pyproject.toml")
    for pkg in (*PACKAGES, "tools"):
        shutil.copytree(REPO / pkg, dst / pkg, ignore=shutil.ignore_patterns("__pycache__"))


def _append(root: Path, module: str, line: str) -> None:
    """Add ``line`` at the end of ``module``'s file in the copy at ``root``."""
    path = root.joinpath(*module.split("."))
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")


def _first(layer: str) -> str:
    return layer.split("|")[0].split(":")[0].strip()


def _break(root: Path, contract: dict) -> None:
    """One import in the copy that breaks ``contract`` (and is meant to break only it, where
    the other contracts allow)."""
    kind = contract["type"]
    if kind == "layers" and "containers" in contract:
        container = contract["containers"][0]
        top, bottom = _first(contract["layers"][0]), _first(contract["layers"][-1])
        _append(root, f"{container}.{bottom}", f"import {container}.{top}")
    elif kind == "layers":  # the root packages: the ground floor imports the top one
        top, bottom = _first(contract["layers"][0]), _first(contract["layers"][-1])
        _append(root, f"{bottom}.errors", f"import {top}.cli")
    elif kind == "forbidden":
        source = contract["source_modules"][0]
        target = contract["forbidden_modules"][0]
        module = {"calibration": "calibration.radiometry", "plumbing": "plumbing.progress"}.get(
            source, source
        )
        _append(
            root,
            module,
            f"import {target}.scene" if target == "simulator" else f"import {target}.fit",
        )
    elif kind == "independence":
        a, b = contract["modules"][:2]
        _append(root, f"{a}.texels", f"import {b}.scene")
    elif kind == "private_modules":
        _append(root, "gonio.runs", "import gonio.cli._app")
    elif kind == "private_names":
        _append(root, "gonio.errors", "from plumbing.numba_policy import _policy")
    else:
        pytest.fail(f"no way to break a {kind!r} contract is written here: add one")


def test_contracts_hold_on_the_repository(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    res = _lint(tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_contract_can_fail(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    for contract in CONTRACTS:
        _break(tmp_path, contract)
    res = _lint(tmp_path)
    kept = [c["name"] for c in CONTRACTS if f"{c['name']} BROKEN" not in res.stdout]
    assert res.returncode != 0 and kept == [], res.stdout[-3000:]


def test_every_exhaustive_contract_fails_on_a_module_no_layer_lists(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    exhaustive = [c for c in CONTRACTS if c.get("exhaustive")]
    assert len(exhaustive) >= 10  # each package and sub-package with floors of its own
    for contract in exhaustive:
        folder = tmp_path.joinpath(*contract["containers"][0].split("."))
        (folder / "unlisted_room.py").write_text('"""A module no layer lists."""\n')
    res = _lint(tmp_path)
    kept = [c["name"] for c in exhaustive if f"{c['name']} BROKEN" not in res.stdout]
    assert kept == [], res.stdout[-3000:]
    # ... and the layered contracts without containers (the root packages) list every root
    layered = [c for c in CONTRACTS if c["type"] == "layers" and "containers" not in c]
    for contract in layered:
        listed = {m.strip() for layer in contract["layers"] for m in layer.split("|")}
        assert listed == set(PACKAGES), contract["name"]


def test_every_package_has_an_exhaustive_contract() -> None:
    """Every package and sub-package of ours (a folder with modules of its own) has its floors
    written down, so no module can sit in a package without a place in its layers."""
    containers = {c["containers"][0] for c in CONTRACTS if c.get("exhaustive")}
    packages = {
        ".".join(p.parent.relative_to(REPO).parts)
        for pkg in PACKAGES
        for p in (REPO / pkg).rglob("__init__.py")
        if len([m for m in p.parent.glob("*.py") if m.name != "__init__.py"]) > 1
        or any(d.is_dir() and (d / "__init__.py").exists() for d in p.parent.iterdir())
    }
    assert packages <= containers, sorted(packages - containers)
