"""The import DAG of DESIGN §2 is enforced by import-linter — and the contract can fail."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("fitting", "acquisition", "calibration", "simulator", "gonio")
LINT = Path(sys.executable).with_name("lint-imports")


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
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, dst / pkg, ignore=shutil.ignore_patterns("__pycache__"))


def test_contracts_hold_on_the_repository(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    res = _lint(tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr


def test_contract_catches_acquisition_importing_simulator(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "acquisition" / "sneaky.py").write_text("import simulator.scene  # noqa\n")
    res = _lint(tmp_path)
    assert res.returncode != 0
    assert "BROKEN" in res.stdout


def test_contract_catches_fitting_importing_acquisition(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "fitting" / "sneaky.py").write_text("import acquisition.store  # noqa\n")
    assert _lint(tmp_path).returncode != 0


def test_contract_catches_calibration_importing_simulator(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "calibration" / "sneaky.py").write_text("import simulator.scene  # noqa\n")
    assert _lint(tmp_path).returncode != 0
