"""Checkpoints of an emcee chain: save every N steps, resume after a kill with the same result.

emcee's own HDF5 backend (:class:`emcee.backends.HDFBackend`) needs h5py,
which is not a dependency; its in-memory :class:`emcee.backends.Backend`
holds everything a continuation needs (chain, log-probabilities, blobs,
acceptance counts, the iteration and the legacy numpy RandomState), so a
checkpoint is that backend in one ``.npz`` file, written atomically
(temporary file in the same folder, fsync, rename): a run killed while
writing leaves the previous checkpoint intact.

Resuming rebuilds the backend; :class:`emcee.EnsembleSampler` then
continues from its last state and random state, so N steps, a kill and a
resume to 2N give the draws of an uninterrupted 2N-step run bit for bit
(tests/cli/test_rough_edges.py).  A fingerprint of the run (seed,
walkers, parameters, data) is stored with the chain; resuming with
another run's checkpoint is an error, never a silent mix.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import zipfile
from pathlib import Path

import emcee
import numpy as np

from ..errors import InputError

__all__ = ["save_checkpoint", "load_checkpoint", "run_fingerprint"]

#: What every checkpoint holds (blobs only when the chain has them).
_KEYS = frozenset({"chain", "log_prob", "accepted", "iteration", "rs_keys", "rs_meta", "rs_cached", "rs_name", "fingerprint"})


def run_fingerprint(model, names, *, seed: int, n_walkers: int, surrogate: str, held=None) -> dict:
    """What must match between a checkpoint and the run resuming it."""
    h = hashlib.sha256()
    for a in (model.y_measured, np.asarray(model.q), np.asarray(model.row_sigma)):
        h.update(np.ascontiguousarray(np.asarray(a, dtype=float)).tobytes())
    # the parameters not sampled are held where the MAP started (a machine file's effect values): part of the target
    if held is not None:
        h.update(np.ascontiguousarray(np.asarray(held, dtype=float)).tobytes())
    # the sampler's proposal changed (bent Laplace map, then the bend kept only where importance weights say it
    # helps, 24 November 2026): a chain of an older one must not continue
    return {"seed": int(seed), "n_walkers": int(n_walkers), "names": list(names), "surrogate": str(surrogate),
            "data_sha256": h.hexdigest(), "proposal": "bent-laplace-t-checked"}


def save_checkpoint(path: str | os.PathLike, backend: emcee.backends.Backend, fingerprint: dict) -> Path:
    """Write the backend's state to ``path`` (.npz) atomically."""
    path = Path(path)
    it = int(backend.iteration)
    name, keys, pos, has_gauss, cached = backend.random_state
    arrays = {
        "chain": backend.chain[:it],
        "log_prob": backend.log_prob[:it],
        "accepted": backend.accepted,
        "iteration": np.array(it),
        "rs_keys": np.asarray(keys),
        "rs_meta": np.array([pos, has_gauss], dtype=np.int64),
        "rs_cached": np.array(cached, dtype=float),
        "rs_name": np.array(name),
        "fingerprint": np.array(json.dumps(fingerprint, sort_keys=True)),
    }
    if backend.blobs is not None:
        arrays["blobs"] = backend.blobs[:it]
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.npz", dir=path.parent if str(path.parent) else ".")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def load_checkpoint(path: str | os.PathLike, fingerprint: dict) -> emcee.backends.Backend:
    """The emcee backend saved in ``path``; InputError if missing, unreadable or of another run."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--resume: {path}: no checkpoint there (run once with --checkpoint {path})")
    try:
        # our own handle: np.load leaks its file when the zip is truncated (a ResourceWarning)
        with open(path, "rb") as fh:
            z = np.load(fh, allow_pickle=False)
            if not hasattr(z, "files"):  # a single .npy array, not an .npz archive
                raise ValueError("a single array, not an .npz archive")
            with z:
                data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # truncated: a bad zip file; empty: EOFError
        raise InputError(f"{path}: not a bayescal MCMC checkpoint ({exc})") from None
    missing = sorted(_KEYS - set(data))
    if missing:
        raise InputError(f"{path}: not a bayescal MCMC checkpoint (no {', '.join(missing)})")
    saved = json.loads(str(data["fingerprint"]))
    mine = json.loads(json.dumps(fingerprint, sort_keys=True))
    diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
    if diff:
        raise InputError(f"{path}: this checkpoint belongs to another run ({', '.join(diff)} differ)")
    chain = data["chain"]
    backend = emcee.backends.Backend()
    backend.reset(chain.shape[1], chain.shape[2])
    backend.chain = chain
    backend.log_prob = data["log_prob"]
    backend.blobs = data.get("blobs")
    backend.accepted = data["accepted"]
    backend.iteration = int(data["iteration"])
    pos, has_gauss = (int(v) for v in data["rs_meta"])
    backend.random_state = (str(data["rs_name"]), data["rs_keys"], pos, has_gauss, float(data["rs_cached"]))
    return backend
