"""The house rules (docs/architecture.md), measured on the source: no import cycle, even through
an import written inside a function; no module in gonio/ over 650 lines, no function over 100
lines, no public function with more than 8 parameters outside an *Options constructor; and every
"you can fix this" error derives from plumbing.errors.UserError, the one class the command line
turns into a one-line message."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest

from plumbing.errors import UserError
from tests.support.paths import REPO

PACKAGES = ("plumbing", "brdfdata", "fitting", "acquisition", "calibration", "simulator", "gonio")
MAX_MODULE_LINES = 650  # gonio/ only
MAX_FUNCTION_LINES = 100
MAX_PARAMETERS = 8
# A typer command takes one parameter per command-line option (that is how typer declares the
# options); the command builds the options objects from them.
PARAMETER_EXCEPTIONS = {
    ("gonio/cli/fit.py", "fit"),
    ("gonio/cli/fit.py", "import_cmd"),
    ("gonio/cli/texels.py", "fit_texels_cmd"),
    ("gonio/cli/texels.py", "fit_batch_cmd"),
}


def _sources():
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            yield path.relative_to(REPO).as_posix(), path.read_text()


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node


def test_no_module_of_the_front_door_is_too_long() -> None:
    long = {p: len(s.splitlines()) for p, s in _sources() if p.startswith("gonio/")}
    assert {p: n for p, n in long.items() if n > MAX_MODULE_LINES} == {}


def test_no_function_is_too_long() -> None:
    too_long = [
        (p, f.name, f.end_lineno - f.lineno + 1)
        for p, src in _sources()
        for f in _functions(ast.parse(src))
        if f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert too_long == []


def test_no_public_function_takes_too_many_parameters() -> None:
    bad = []
    for p, src in _sources():
        for f in _functions(ast.parse(src)):
            if f.name.startswith("_") or (p, f.name) in PARAMETER_EXCEPTIONS:
                continue
            a = f.args
            names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
            n = len([x for x in names if x not in ("self", "cls")])
            if n > MAX_PARAMETERS:
                bad.append((p, f.name, n))
    assert bad == []


def test_no_import_cycle_anywhere() -> None:
    """Every import counts, top-level or inside a function (tools/house_stats.py): an import
    moved into a function to break a cycle still closes it here."""
    from tools.house_stats import cycles, imports, modules

    assert cycles(imports(modules())) == []


def test_the_cycle_finder_finds_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A cycle closed only by a function-level import is seen (so a pass means something)."""
    from tools import house_stats

    pkg = tmp_path / "plumbing"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from plumbing import b\n")
    (pkg / "b.py").write_text("def f():\n    from plumbing.a import x\n")
    monkeypatch.setattr(house_stats, "REPO", tmp_path)
    found = house_stats.cycles(house_stats.imports(house_stats.modules()))
    assert found == [["plumbing.a", "plumbing.b"]]


def test_the_checks_can_fail() -> None:
    """The measures above see what they look for (so a passing run means something)."""
    src = "def f(" + ", ".join(f"a{i}" for i in range(9)) + "):\n" + "    x = 1\n" * 120
    f = next(_functions(ast.parse(src)))
    assert f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES
    assert len(f.args.args) > MAX_PARAMETERS


USER_ERRORS = (
    "plumbing.config:ConfigError",
    "acquisition.kinematics:Unreachable",
    "acquisition.protocols:DeviceFault",
    "acquisition.store:RunStoreError",
    "acquisition.operator:OperatorDeclined",
    "calibration.reduce:CalibrationError",
    "calibration.decode:FrameError",
    "calibration.darks:CalibrationFrameError",
    "calibration.planes:PlaneError",
    "calibration.camera_model:BoardSpecError",
    "calibration.camera_model:CalibrationInputError",
    "brdfdata.samples:SamplesError",
    "brdfdata.formats.common:FormatError",
    "fitting.result:FitResultError",
    "fitting.mcmc:ChainFileError",
    "fitting.priors:PriorsError",
    "brdfdata.data_paths:DataNotFound",
)


@pytest.mark.parametrize("where", USER_ERRORS)
def test_every_user_error_derives_from_the_one_base(where: str) -> None:
    module, name = where.split(":")
    assert issubclass(getattr(importlib.import_module(module), name), UserError)


def test_no_error_class_is_left_out() -> None:
    """Every exception class our packages define (but private ones and programming-error
    markers) is a UserError or a subclass of one listed above — none escapes as a traceback."""
    listed = {w.split(":")[1] for w in USER_ERRORS}
    stray = []
    for pkg in ("plumbing", "brdfdata", "fitting", "acquisition", "calibration"):
        mod = importlib.import_module(pkg)
        for info in pkgutil.walk_packages(mod.__path__, pkg + "."):
            m = importlib.import_module(info.name)
            for name, obj in inspect.getmembers(m, inspect.isclass):
                if obj.__module__ != m.__name__ or name.startswith("_"):
                    continue
                if issubclass(obj, BaseException) and not issubclass(obj, UserError):
                    stray.append(f"{m.__name__}.{name}")
    # A model name that is not registered is a KeyError for the registry's callers too; the
    # CLI turns it into one line where it asks for a model.
    assert set(stray) <= {"fitting.models.entries.UnknownModelError"}, (stray, listed)


def test_tests_are_laid_out_like_the_code_and_never_import_each_other() -> None:
    """Every test module sits in the folder of the package it tests (tests/<package>/…, the
    house rules in tests/house/), and shares code only through tests/support/ and fixtures in
    tests/conftest.py — never by importing another test module."""
    tests = REPO / "tests"
    folders = {*PACKAGES, "house", "fitting/models"}
    misplaced, imports_a_test = [], []
    for path in sorted(tests.rglob("test_*.py")):
        rel = path.parent.relative_to(tests).as_posix()
        if rel not in folders:
            misplaced.append(path.relative_to(tests).as_posix())
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            if any(n.split(".")[-1].startswith("test_") for n in names):
                imports_a_test.append(f"{path.relative_to(tests)}: {names}")
    assert misplaced == [] and imports_a_test == [], (misplaced, imports_a_test)
