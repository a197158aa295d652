"""Markup and control characters in data (issue 22, item 5): strings from manifests, run paths
and configs are printed as text. A closing-tag-like device path `[/dev/ttyUSB0]` used to crash
`gonio runs show` and `runs list` (for every run under the root); an ESC sequence in an event
message reached the terminal. Real parts: a real SQLite manifest, the CLI in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import tomli_w

from acquisition.store import RunStore
from gonio.plain_text import printable

HOSTILE = "bus [/dev/ttyUSB0] lost; \x1b[2J\x1b]0;owned\x07 [bold]not bold[/bold]"


def _gonio(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "gonio.cli", *args]
    env = {**os.environ, "COLUMNS": "400"}  # wide enough that no cell wraps
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=cwd, env=env)


def test_runs_show_and_list_print_hostile_strings_as_text(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    run = root / "r[/x]"  # a closing tag in the run's own name, too
    doc = {"rig": {"name": "[/rig]", "bus": {"url": "[/dev/ttyUSB0]"}}, "plan": {"name": "[/p]"}}
    with RunStore.create(run, tomli_w.dumps(doc)) as store:
        store.event("stop", HOSTILE)
    (root / "ok").mkdir()
    RunStore.create(root / "ok", tomli_w.dumps({"note": "fine"})).close()

    show = _gonio("runs", "show", str(run), cwd=tmp_path)
    assert show.returncode == 0, show.stderr
    assert "internal error" not in show.stderr and "Traceback" not in show.stderr
    text = show.stdout
    assert "\x1b" not in text and "\x07" not in text  # nothing reaches the terminal raw
    assert printable(HOSTILE) in text
    assert "[/dev/ttyUSB0]" in text and "[/rig]" in text and "[/p]" in text

    listing = _gonio("runs", "list", "--root", str(root), cwd=tmp_path)
    assert listing.returncode == 0, listing.stderr
    assert "r[/x]" in listing.stdout and "ok" in listing.stdout  # nor hides the other runs


def test_printable_escapes_controls_and_keeps_text() -> None:
    assert printable("a\tb") == "a\tb"
    assert printable("\x1b[31mred\x1b[0m\r\n") == "\\x1b[31mred\\x1b[0m\\x0d\\x0a"
    assert printable("\x9b") == "\\x9b" and printable("é [/x]") == "é [/x]"
