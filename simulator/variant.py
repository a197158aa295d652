"""Choose the Mitsuba 3 variant once per process: ``llvm_ad_rgb`` if it works, else ``scalar_rgb``.

Why a subprocess probe: drjit's LLVM backend *aborts the whole process* (no Python exception) in the
path integrator when it binds LLVM 15/16 (docs/design.md §7). So we render a tiny path-traced scene
in a child interpreter first; only if it exits cleanly do we select the llvm variant here. libLLVM ≥
17 is needed; if the default lookup fails we retry with ``DRJIT_LIBLLVM_PATH`` pointed at a known
libLLVM 19 and, on success, export that variable in this process before the variant is set.

Override with the environment variable ``GONIO_MITSUBA_VARIANT`` (e.g. ``scalar_rgb``).

The probe's answer is exported (``GONIO_MITSUBA_PROBED``, with the interpreter it holds for) so
that the processes this one starts — `gonio` commands a study or the tests run, spawned workers
— use it instead of probing again: the probe is a second interpreter importing Mitsuba and
rendering, ~0.5 CPU-s each time (47 times in one `make test`, measured).
"""

from __future__ import annotations

import functools
import logging
import os
import subprocess
import sys
from pathlib import Path

__all__ = ["choose_variant", "ensure_variant", "use_variant", "probe_variant", "LLVM_CANDIDATES"]

log = logging.getLogger(__name__)

FALLBACK = "scalar_rgb"
ENV_OVERRIDE = "GONIO_MITSUBA_VARIANT"
#: "PREFER=CHOSEN@PYTHON": what the probe chose for PREFER in this interpreter's parent.
PROBED_ENV = "GONIO_MITSUBA_PROBED"
# libLLVM ≥ 17 locations tried when drjit's own lookup does not work (Debian/Ubuntu package paths).
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-18.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-17.so",
)

# A path-integrator render (the integrator that aborts with LLVM 15/16) plus a version check.
_PROBE = """
import sys
import drjit as dr
import mitsuba as mi
mi.set_variant(sys.argv[1])
if sys.argv[1].startswith("llvm"):
    v = dr.detail.llvm_version()
    if tuple(v) < (17,):
        print(f"libLLVM {'.'.join(map(str, v))} < 17"); sys.exit(3)
s = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4},
               "to_world": mi.ScalarTransform4f().look_at([0, 0, 2], [0, 0, 0], [0, 1, 0])},
    "light": {"type": "point", "position": [0, 0, 1]},
    "rect": {"type": "rectangle"}})
img = mi.render(s, spp=2)
import numpy as np
assert np.isfinite(np.asarray(img)).all()
print("ok")
"""


def probe_variant(variant: str, env: dict[str, str] | None = None, timeout_s: float = 120.0):
    """Render a tiny scene with ``variant`` in a child interpreter. Returns (ok, reason)."""
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE, variant],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )
    except subprocess.TimeoutExpired:
        return False, f"probe timed out after {timeout_s:.0f} s"
    if proc.returncode == 0 and proc.stdout.strip().endswith("ok"):
        return True, "ok"
    # Our own diagnosis goes to stdout; a crash leaves only stderr.
    tail = (proc.stdout.strip() or proc.stderr.strip()).splitlines()
    msg = tail[-1] if tail else "no output"
    return False, f"probe exit code {proc.returncode}: {msg}"[:200]


@functools.cache
def choose_variant(prefer: str = "llvm_ad_rgb") -> str:
    """Return a usable Mitsuba variant name (cached per process).

    Order: ``$GONIO_MITSUBA_VARIANT`` if set; else what a parent process's probe chose
    (``$GONIO_MITSUBA_PROBED``, module docstring); else ``prefer`` if the subprocess probe passes
    (retrying with ``DRJIT_LIBLLVM_PATH`` = a libLLVM ≥ 17 for llvm variants); else ``scalar_rgb``,
    with a single logged note giving the reason.
    """
    forced = os.environ.get(ENV_OVERRIDE)
    if forced:
        return forced
    if not prefer.startswith("llvm"):
        return prefer
    key, _, inherited = os.environ.get(PROBED_ENV, "").partition("=")
    chosen, _, python = inherited.partition("@")
    if key == prefer and python == sys.executable and chosen in (prefer, FALLBACK):
        return chosen
    chosen = _probed_choice(prefer)
    os.environ[PROBED_ENV] = f"{prefer}={chosen}@{sys.executable}"
    return chosen


def _probed_choice(prefer: str) -> str:
    """``prefer`` if its probe passes (with a libLLVM ≥ 17 found for it if need be), else
    the fallback with one logged note."""
    ok, reason = probe_variant(prefer)
    if ok:
        return prefer
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for cand in LLVM_CANDIDATES:
            if Path(cand).exists():
                env = dict(os.environ, DRJIT_LIBLLVM_PATH=cand)
                ok2, reason2 = probe_variant(prefer, env=env)
                if ok2:
                    # Must be in place before drjit initialises its LLVM backend in this process.
                    os.environ["DRJIT_LIBLLVM_PATH"] = cand
                    return prefer
                reason = f"{reason}; with {cand}: {reason2}"
    log.warning("note: Mitsuba llvm variant unavailable (%s); using %s", reason, FALLBACK)
    return FALLBACK


def ensure_variant(prefer: str = "llvm_ad_rgb") -> str:
    """Set the chosen variant in this process if it is not already active; return its name."""
    import mitsuba as mi

    name = choose_variant(prefer)
    if mi.variant() != name:
        mi.set_variant(name)
    return name


def use_variant(variant: str | None) -> str:
    """Make ``variant`` Mitsuba's active one (None: the chosen one, :func:`ensure_variant`);
    returns its name."""
    import mitsuba as mi

    if variant is None:
        return ensure_variant()
    if mi.variant() != variant:
        mi.set_variant(variant)
    return variant
