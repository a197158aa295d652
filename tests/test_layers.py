"""The import DAG of DESIGN §2 is enforced by import-linter — and the contract can fail."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("plumbing", "fitting", "acquisition", "calibration", "simulator", "gonio")
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


def _broken(res: subprocess.CompletedProcess, contract: str) -> bool:
    """The named contract is reported BROKEN (the others may hold)."""
    return res.returncode != 0 and f"{contract} BROKEN" in res.stdout


def test_contract_catches_plumbing_importing_anything_of_ours(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "plumbing" / "sneaky.py").write_text("import fitting.models  # noqa\n")
    assert _broken(_lint(tmp_path), "Layered pipeline (DESIGN section 2)")


def test_contract_catches_a_front_door_layer_running_back_up(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "gonio" / "report.py").write_text(
        (REPO / "gonio" / "report.py").read_text() + "\nimport gonio.pipeline  # noqa\n"
    )
    assert _broken(_lint(tmp_path), "The front door's own layers (docs/architecture.md)")


def test_contract_catches_the_studies_importing_the_simulator(tmp_path: Path) -> None:
    _copy_tree(tmp_path)
    (tmp_path / "gonio" / "studies" / "sneaky.py").write_text("import simulator.render  # noqa\n")
    res = _lint(tmp_path)
    assert _broken(res, "Only the simulator and gonio.backends import the simulator")
    # The same import from the one allowed door is fine (this contract holds without it).
    (tmp_path / "gonio" / "studies" / "sneaky.py").unlink()
    (tmp_path / "gonio" / "backends.py").write_text(
        (REPO / "gonio" / "backends.py").read_text() + "\nimport simulator.render  # noqa\n"
    )
    assert _lint(tmp_path).returncode == 0
