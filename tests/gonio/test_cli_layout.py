"""`gonio --help` reads in the order a lab works, and tables printed to a pipe or a narrow
terminal stay readable (issue 42, item 7). The real command line in a process of its own, with
stdin closed: rich would otherwise take the width of whatever terminal stdin is on."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from tests.support.paths import REPO

SIM_RIG = REPO / "configs" / "rigs" / "sim.toml"
ROLES = ("light_theta", "light_phi", "camera_theta", "camera_phi")
PANELS = {
    "Lab": ["rig", "acquire", "capture", "calibrate-rig", "calibrate-camera", "calibrate", "runs"],
    "Analysis": ["fit", "report", "plan", "models"],
    "Data": ["import", "export", "data"],
    "Scale-out": ["fit-texels", "fit-batch"],
    "Simulation and studies": ["demo", "simulate", "study"],
}


def gonio(*args: str, columns: int | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    if columns is not None:
        env["COLUMNS"] = str(columns)
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        cwd=REPO,
    )


def test_help_lists_the_panels_and_their_commands_in_lab_order() -> None:
    res = gonio("--help")
    assert res.returncode == 0, res.stderr
    panels: dict[str, list[str]] = {}
    current: list[str] = []
    for line in res.stdout.splitlines():
        if title := re.match(r"╭─ (.+?) ─", line):
            current = panels.setdefault(title[1], [])
        elif command := re.match(r"│ (\S+)\s", line):  # a row's first word (wraps are indented)
            current.append(command[1])
    assert list(panels) == ["Options", *PANELS], list(panels)
    assert {title: panels[title] for title in PANELS} == PANELS


def test_tables_printed_to_a_pipe_keep_each_row_on_one_line() -> None:
    res = gonio("rig", "check", "--rig", str(SIM_RIG))
    assert res.returncode == 0, res.stdout + res.stderr
    lines = res.stdout.splitlines()
    for role in ROLES:  # role, servo model and status word whole, on the row's one line
        assert any(re.search(rf"│ {role} +│.*XM430-W350.*│ OK +│$", ln) for ln in lines), role
    for device in ("light", "camera"):
        assert any(re.match(rf"│ {device} +│.*│ OK +│$", ln) for ln in lines), device
    assert any("clipped: 0 of 12288 values ≥ white level" in ln for ln in lines)
    res = gonio("models")
    assert res.returncode == 0, res.stderr
    # the options table: a model's name whole, its first option and its reference on one line
    rows = (
        r"│ torrance-sparrow-anisotropic +│ distribution: beckmann\* \| ggx +│.*│ Walter et al\.",
        r"│ abc +│ exponent: 2\* \| 3 +│.*│ Löw, Kronander, Ynnerman, Unger, ACM TOG",
    )
    for row in rows:
        assert any(re.search(row, ln) for ln in res.stdout.splitlines()), row


def test_a_narrow_terminal_gets_records_not_folded_columns() -> None:
    res = gonio("rig", "check", "--rig", str(SIM_RIG), columns=60)
    assert res.returncode == 0, res.stdout + res.stderr
    lines = res.stdout.splitlines()
    assert max(len(ln) for ln in lines) <= 60, res.stdout
    for role in ROLES:
        assert f"- role: {role}" in lines, res.stdout
    assert lines.count("  status: OK") == len(ROLES), res.stdout
    # the device table, whose one long column may wrap, stays a table: its status words whole
    assert sum(bool(re.search(r"│ OK +│$", ln)) for ln in lines) == 2, res.stdout
    res = gonio("models", columns=60)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert max(len(ln) for ln in lines) <= 60, res.stdout
    assert "- model: torrance-sparrow-anisotropic" in lines  # no name folded over two lines
