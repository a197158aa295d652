"""Every compiled kernel releases the GIL while it runs (numba ``nogil=True``).

Why: the calibration decodes the next pose's frames in a thread beside the kernels of the
current one (calibration.reduce, plumbing.prefetch). A kernel that holds the GIL stops that
thread at its first Python step: measured on a 24 MP DNG, its decode took 24× its time beside
a GIL-holding kernel and 0.7× beside the same kernel with ``nogil``. The check is on the
kernels' compile options, not a timing, so it cannot flake on a loaded machine; it fails for
any kernel added without the flag. (numba's disk cache is keyed by source, not options: a build
cached before a flag changed loads with the new flag reported; see plumbing.numba_policy.njit.)
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import numba.core.registry
import pytest

PACKAGES = ("calibration", "fitting", "simulator", "plumbing", "brdfdata", "acquisition")


def _kernels() -> list[tuple[str, object]]:
    found = []
    for name in PACKAGES:
        pkg = importlib.import_module(name)
        mods = [pkg] + [
            importlib.import_module(m.name) for m in pkgutil.walk_packages(pkg.__path__, name + ".")
        ]
        for mod in mods:
            for attr, obj in vars(mod).items():
                if isinstance(obj, numba.core.registry.CPUDispatcher) and (
                    obj.py_func.__module__ == mod.__name__
                ):
                    found.append((f"{mod.__name__}.{attr}", obj))
    return found


KERNELS = _kernels()


def test_the_kernels_are_found() -> None:
    names = {n for n, _ in KERNELS}
    # the calibration's merge and geometry and the models' kernels, at least
    assert {"calibration.hdr._merge_par", "calibration.geometry._rays_par"} <= names
    kernel_modules = ("fitting.models.microfacet_kernels.", "fitting.models.lobe_kernels.")
    assert any(n.startswith(kernel_modules) for n in names) and len(names) > 30


@pytest.mark.parametrize("name,kernel", KERNELS, ids=[n for n, _ in KERNELS])
def test_kernel_releases_the_gil(name: str, kernel) -> None:
    assert kernel.targetoptions.get("nogil") is True, f"{name} holds the GIL while it runs"


def _kernel_modules() -> list[str]:
    return sorted({name.rsplit(".", 1)[0] for name, _ in KERNELS})


@pytest.mark.parametrize("module", _kernel_modules())
def test_kernel_module_imports_the_compile_policy_itself(module: str) -> None:
    """Every module that holds a kernel imports plumbing.numba_policy itself, not through a
    sibling: the policy picks the vector width (numba's CPU features) when it is imported, and
    numba fixes them at its first compile in a process. A process whose first kernel came from a
    module without it (the darks' master, say, in a `gonio calibrate`) compiled every kernel with
    the host's features instead — another key in numba's cache, so each kernel of the suite was
    compiled twice over (measured: a suite run left 280 builds in the cache, 178 under one key and
    102 under the other) and ran with the narrower vectors in those processes."""
    mod = importlib.import_module(module)
    tree = ast.parse(Path(mod.__file__).read_text(encoding="utf-8"))
    imported = {
        node.module if isinstance(node, ast.ImportFrom) else alias.name
        for node in ast.walk(tree)
        if isinstance(node, (ast.Import, ast.ImportFrom))
        for alias in node.names
    }
    assert "plumbing.numba_policy" in imported, (
        f"{module} defines numba kernels but does not import plumbing.numba_policy"
    )
