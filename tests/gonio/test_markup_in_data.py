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


def test_fit_prints_folder_and_channel_names_as_written(tmp_path: Path) -> None:
    """Issue 47: an output named `teflon[v2]/…` printed as `teflon/…` and a channel named
    `[bold red]R` came out mangled — every console of the CLI is now markup-free. A Lambertian
    table (Mitsuba's diffuse BSDF) whose channels carry markup, in a folder whose name does,
    through `gonio fit` and `gonio report`: every name is printed as written."""
    import numpy as np

    from brdfdata.directions import spherical_to_vector
    from brdfdata.samples import write_samples
    from simulator.scene import DiffuseMaterial
    from simulator.truth import direct_samples

    ti, to = np.meshgrid(np.radians([10.0, 30.0, 50.0]), np.radians([5.0, 25.0, 45.0, 65.0]))
    wi = spherical_to_vector(ti.ravel(), np.zeros(ti.size))
    wo = spherical_to_vector(to.ravel(), np.full(to.size, np.pi))
    table, _ = direct_samples(DiffuseMaterial(reflectance=(0.5, 0.5, 0.5)), wi, wo, rng=1)
    names = {"R": "[bold red]R", "G": "[/G]", "B": "B"}
    table.channel = np.array([names[c] for c in table.channel], dtype=object)
    folder = tmp_path / "teflon[v2]"
    folder.mkdir()
    write_samples(folder / "samples.parquet", table)

    fit = _gonio("fit", str(folder / "samples.parquet"), "--model", "lambert", "--no-mcmc",
                 cwd=tmp_path)  # fmt: skip
    assert fit.returncode == 0, fit.stderr
    assert "kd_[bold red]R" in fit.stdout and "kd_[/G]" in fit.stdout, fit.stdout
    report = _gonio("report", "--samples", str(folder / "samples.parquet"),
                    "--fit", str(folder / "fit-lambert.json"), cwd=tmp_path)  # fmt: skip
    assert report.returncode == 0, report.stderr
    assert report.stdout.strip() == str(folder / "report.html"), report.stdout
