"""The MCMC chain file (``fit-<model>.h5``): emcee's HDF5 layout, written only whole and
atomically.

emcee's ``HDFBackend`` writes every step into the file in place. On a full disk HDF5 then fails
inside its own buffers: the write error is swallowed in a destructor and the process later dies
(a segmentation fault, measured on a 64 KiB tmpfs), leaving a half-written file that every later
fit into the folder refuses. So the sampler runs on emcee's in-memory ``Backend`` and the chain
is saved at checkpoints: the HDF5 file is built in memory (h5py on a ``BytesIO``) and written
with :func:`plumbing.atomic.atomic_write_bytes` (temp file, fsync, rename). A failed write leaves
the previous checkpoint as it was and removes its temp file; the file on disk is always either
absent or a complete chain, which the next fit of the same problem continues.

The layout is emcee 3.1's (group ``name`` with attrs version, nwalkers, ndim, has_blobs,
iteration, random_state_0…4; datasets accepted, chain, log_prob), so
``emcee.backends.HDFBackend(path, name, read_only=True)`` reads the file as before; gonio adds
the attribute ``gonio_fingerprint`` (the problem the chain samples)."""

from __future__ import annotations

import io
from pathlib import Path

import emcee
import numpy as np

from plumbing.atomic import atomic_write_bytes

__all__ = ["load_chain", "save_chain"]


def load_chain(path: Path, name: str) -> tuple[emcee.backends.Backend, str | None] | None:
    """The stored chain of group ``name`` as an in-memory backend and its fingerprint, or
    None when the file or the group does not exist (the caller has checked it is HDF5)."""
    import h5py

    if not path.exists():
        return None
    with h5py.File(path, "r") as fh:
        if name not in fh:
            return None
        g = fh[name]
        walkers, ndim = int(g.attrs["nwalkers"]), int(g.attrs["ndim"])
        n = int(g.attrs["iteration"])
        backend = emcee.backends.Backend()
        backend.reset(walkers, ndim)
        backend.chain = np.array(g["chain"][:n], dtype=np.float64).reshape(n, walkers, ndim)
        backend.log_prob = np.array(g["log_prob"][:n], dtype=np.float64).reshape(n, walkers)
        backend.accepted = np.array(g["accepted"][...], dtype=np.float64)
        state = [v for k, v in sorted(g.attrs.items()) if k.startswith("random_state_")]
        backend.random_state = tuple(state) if state else None
        backend.iteration = n
        fingerprint = g.attrs.get("gonio_fingerprint")
    return backend, None if fingerprint is None else str(fingerprint)


def save_chain(
    path: Path, name: str, backend: emcee.backends.Backend, fingerprint: str | None
) -> None:
    """Replace group ``name`` of the chain file with ``backend``'s chain, keeping the file's other
    groups (the other ensembles), in one atomic write."""
    import h5py

    buffer = io.BytesIO(path.read_bytes() if path.exists() else b"")
    n = int(backend.iteration)
    walkers, ndim = int(backend.nwalkers), int(backend.ndim)
    with h5py.File(buffer, "a") as fh:
        if name in fh:
            del fh[name]
        g = fh.create_group(name)
        g.attrs["version"] = emcee.__version__
        g.attrs["nwalkers"] = walkers
        g.attrs["ndim"] = ndim
        g.attrs["has_blobs"] = False
        g.attrs["iteration"] = n
        if fingerprint is not None:
            g.attrs["gonio_fingerprint"] = fingerprint
        g.create_dataset("accepted", data=np.asarray(backend.accepted, dtype=np.float64))
        chain = np.asarray(backend.chain[:n], dtype=np.float64).reshape(n, walkers, ndim)
        log_prob = np.asarray(backend.log_prob[:n], dtype=np.float64).reshape(n, walkers)
        g.create_dataset("chain", data=chain, maxshape=(None, walkers, ndim))
        g.create_dataset("log_prob", data=log_prob, maxshape=(None, walkers))
        for i, value in enumerate(backend.random_state or ()):
            g.attrs[f"random_state_{i}"] = value
    atomic_write_bytes(path, buffer.getvalue(), overwrite=True)
