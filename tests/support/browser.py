"""Check an HTML page in a real headless browser (Debian's `chromium --headless`): it loads with
no console error or script exception, every <img> decodes to a non-empty bitmap, and a
screenshot is kept (CI artefact, under `artifacts/` or $GONIO_ARTIFACTS).

How: a copy of the page gets a probe script at the top of <head> that records console.error
calls and uncaught exceptions and, on `load`, counts images whose bitmap did not decode
(`complete && naturalWidth > 0` is how the DOM says an image rendered); the browser's
`--dump-dom` prints the probe's verdict; its stderr log carries any console message the page
itself produced. The page under test is never changed on disk.

Installation policy as for Aravis (tests/support/aravis.py): `make setup` installs chromium as root;
only where it could not (recorded in `<venv>/.chromium-unavailable`) do these tests skip.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.support.paths import REPO

__all__ = ["require_chromium", "PageCheck", "check_page", "screenshot", "artifacts_dir"]

UNAVAILABLE = Path(sys.prefix) / ".chromium-unavailable"
_PROBE = """<script id="gonio-probe">
window.__errors = [];
const _err = console.error.bind(console);
console.error = (...a) => { window.__errors.push(a.join(' ')); _err(...a); };
window.addEventListener('error', e => window.__errors.push('exception: ' + e.message));
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  const p = document.createElement('pre');
  p.id = 'gonio-probe-result';
  p.textContent = `IMAGES=${imgs.length} BROKEN=${broken} ERRORS=${window.__errors.length} `
    + JSON.stringify(window.__errors);
  document.body.appendChild(p);
});
</script>"""
_RESULT = re.compile(r"IMAGES=(\d+) BROKEN=(\d+) ERRORS=(\d+) (.*?)</pre>", re.S)
#: The browser's own stderr lines for a page's console messages, e.g.
#: `[..:INFO:CONSOLE(12)] "message", source: file:///… (12)`.
_CONSOLE = re.compile(r":CONSOLE\(\d+\)\]\s*(.*)")


def require_chromium() -> str:
    """The chromium executable; fail (or, where the Makefile could not install it, skip)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe:
        return exe
    if UNAVAILABLE.exists():
        pytest.skip(f"headless browser check: {UNAVAILABLE.read_text().strip()}")
    pytest.fail("chromium not found: run `make setup` as root (apt-get install chromium)")


def _run(args: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="gonio-chromium-") as profile:
        cmd = [
            require_chromium(),
            "--headless",
            "--no-sandbox",  # CI runs as root, where Chromium's sandbox cannot start
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--enable-logging=stderr",
            "--v=0",
            f"--user-data-dir={profile}",  # parallel runs must not share a profile lock
            *args,
        ]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)


@dataclass(frozen=True)
class PageCheck:
    images: int
    broken: int
    errors: list[str]  # console errors and exceptions the page raised
    dom: str  # the DOM after load, as the browser built it


def check_page(page: Path, timeout_s: float = 120.0) -> PageCheck:
    """Load `page` in headless Chromium (through a probed copy) and report what rendered."""
    html = page.read_text(encoding="utf-8")
    head = html.lower().find("<head>")
    probed = html[: head + 6] + _PROBE + html[head + 6 :] if head >= 0 else _PROBE + html
    with tempfile.TemporaryDirectory(prefix="gonio-page-") as tmp:
        copy = Path(tmp) / page.name
        copy.write_text(probed, encoding="utf-8")
        # virtual time lets the load event (and image decoding) finish before the DOM dump.
        done = _run(["--virtual-time-budget=20000", "--dump-dom", copy.as_uri()], timeout_s)
    match = _RESULT.search(done.stdout)
    if match is None:
        raise AssertionError(f"the page did not finish loading: {done.stderr[-800:]}")
    errors = [m.group(1) for m in _CONSOLE.finditer(done.stderr)]
    import json

    errors += [e for e in json.loads(match.group(4)) if e not in " ".join(errors)]
    return PageCheck(int(match.group(1)), int(match.group(2)), errors, done.stdout)


def artifacts_dir() -> Path:
    """Where screenshots are kept for CI: $GONIO_ARTIFACTS, else `artifacts/` in the checkout."""
    root = os.environ.get("GONIO_ARTIFACTS") or REPO / "artifacts"
    path = Path(root)
    path.mkdir(parents=True, exist_ok=True)
    return path


def screenshot(page: Path, out: Path, width_px: int = 1200, height_px: int = 1600) -> Path:
    """A PNG of the top of `page` as the browser draws it."""
    done = _run(
        [f"--screenshot={out}", f"--window-size={width_px},{height_px}", "--hide-scrollbars",
         page.as_uri()],
        timeout_s=120.0,
    )  # fmt: skip
    if not out.exists() or out.stat().st_size == 0:
        raise AssertionError(f"chromium wrote no screenshot: {done.stderr[-800:]}")
    return out
