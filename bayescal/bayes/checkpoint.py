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
import io
import json
import os
import zipfile
from pathlib import Path

import emcee
import numpy as np

from ..errors import InputError

__all__ = ["save_checkpoint", "load_checkpoint", "run_fingerprint"]

#: What every checkpoint holds (blobs only when the chain has them).
_KEYS = frozenset({"chain", "log_prob", "accepted", "iteration", "rs_keys", "rs_meta", "rs_cached", "rs_name", "fingerprint"})


def run_fingerprint(model, names, *, seed: int, n_walkers: int, surrogate: str, held=None, bounds=()) -> dict:
    """What must match between a checkpoint and the run resuming it."""
    h = hashlib.sha256()
    for a in (model.y_measured, np.asarray(model.q), np.asarray(model.row_sigma)):
        h.update(np.ascontiguousarray(np.asarray(a, dtype=float)).tobytes())
    # the parameters not sampled are held where the MAP started (a machine file's effect values): part of the target
    if held is not None:
        h.update(np.ascontiguousarray(np.asarray(held, dtype=float)).tobytes())
    if bounds:  # the posterior truncated elsewhere is another target
        h.update(repr(tuple((n, float(a), float(b)) for n, a, b in bounds)).encode())
    # the sampler's proposal changed (bent Laplace map, then the bend kept only where importance weights say it
    # helps, 24 November 2026; its Gaussian mixed in where the tails allow it, 28 November 2026): a chain of an
    # older one must not continue
    return {"seed": int(seed), "n_walkers": int(n_walkers), "names": list(names), "surrogate": str(surrogate),
            "data_sha256": h.hexdigest(), "proposal": "bent-laplace-t-checked-gaussian-mixed"}


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
    from ..io.answers import write_with_atomic

    write_with_atomic(path, stream=lambda fh: np.savez(fh, **arrays))
    return path


def load_checkpoint(path: str | os.PathLike, fingerprint: dict) -> emcee.backends.Backend:
    """The emcee backend saved in ``path``; InputError if missing, unreadable, damaged or of another run.

    The file must be a regular file (of at most
    :data:`~bayescal.io.safe_paths.MAX_CHECKPOINT_BYTES`), an ``.npz``
    archive with every array a checkpoint holds, each of the type and shape
    the fingerprint's walkers and parameters imply, the chain finite, the
    random state a whole MT19937 state (:func:`_check_arrays`).
    """
    from ..io.safe_paths import MAX_CHECKPOINT_BYTES, read_input_bytes

    path = Path(path)
    if not path.exists():
        raise InputError(f"--resume: {path}: no checkpoint there (run once with --checkpoint {path})")
    # protect=False: the run rewrites its own checkpoint
    raw = read_input_bytes(path, "an MCMC checkpoint (.npz)", limit=MAX_CHECKPOINT_BYTES, protect=False)
    try:
        z = np.load(io.BytesIO(raw), allow_pickle=False)
        if not hasattr(z, "files"):  # a single .npy array, not an .npz archive
            raise ValueError("a single array, not an .npz archive")
        with z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, RuntimeError, KeyError) as exc:
        # truncated: a bad zip file; empty: EOFError; a damaged member: zlib's error (an OSError) or BadZipFile
        raise InputError(f"{path}: not a bayescal MCMC checkpoint ({exc})") from None
    missing = sorted(_KEYS - set(data))
    if missing:
        raise InputError(f"{path}: not a bayescal MCMC checkpoint (no {', '.join(missing)})")
    saved = _saved_fingerprint(path, data["fingerprint"])
    mine = json.loads(json.dumps(fingerprint, sort_keys=True))
    diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
    if diff:
        raise InputError(f"{path}: this checkpoint belongs to another run ({', '.join(diff)} differ)")
    it = _check_arrays(path, data, saved)
    chain = data["chain"]
    backend = emcee.backends.Backend()
    backend.reset(chain.shape[1], chain.shape[2])
    backend.chain = chain.astype(float)
    backend.log_prob = data["log_prob"].astype(float)
    backend.blobs = data.get("blobs")
    backend.accepted = data["accepted"]
    backend.iteration = it
    pos, has_gauss = (int(v) for v in data["rs_meta"])
    backend.random_state = (str(data["rs_name"]), data["rs_keys"], pos, has_gauss, float(data["rs_cached"]))
    return backend


def _saved_fingerprint(path: Path, arr: np.ndarray) -> dict:
    """The fingerprint stored in a checkpoint: a JSON object in a 0-d string array."""
    try:
        if arr.ndim != 0 or arr.dtype.kind != "U":
            raise ValueError("not a text value")
        saved = json.loads(str(arr))
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: damaged MCMC checkpoint (its run fingerprint is not readable: {exc})") from None
    if not isinstance(saved, dict):
        raise InputError(f"{path}: damaged MCMC checkpoint (its run fingerprint is not a JSON object)")
    return saved


def _check_arrays(path: Path, data: dict, saved: dict) -> int:
    """The number of saved steps, after checking every array of a checkpoint; InputError naming the first bad one."""
    def bad(name: str, expected: str):
        got = data[name]
        return InputError(f"{path}: damaged MCMC checkpoint: '{name}' is {got.dtype} of shape {got.shape}; expected {expected}")

    walkers, names = saved.get("n_walkers"), saved.get("names")
    if not isinstance(walkers, int) or not isinstance(names, list):
        raise InputError(f"{path}: damaged MCMC checkpoint (its fingerprint has no walkers or parameter names)")
    it_arr = data["iteration"]
    if it_arr.ndim != 0 or it_arr.dtype.kind not in "iu" or int(it_arr) < 0:
        raise bad("iteration", "a non-negative integer")
    it = int(it_arr)
    expect = {
        "chain": ((it, walkers, len(names)), "f", "finite numbers"),
        "log_prob": ((it, walkers), "f", "numbers"),
        "accepted": ((walkers,), "fiu", "counts"),
        "rs_keys": ((624,), "iu", "the 624 words of an MT19937 state"),
        "rs_meta": ((2,), "iu", "two integers"),
        "rs_cached": ((), "f", "a number"),
        "rs_name": ((), "U", "the text 'MT19937'"),
    }
    for name, (shape, kinds, what) in expect.items():
        a = data[name]
        if a.shape != shape or a.dtype.kind not in kinds:
            raise bad(name, f"{what}, shape {shape}")
    if not np.all(np.isfinite(data["chain"])):
        raise bad("chain", "finite numbers")
    if np.any(np.isnan(data["log_prob"])) or np.any(data["accepted"] < 0):
        raise bad("log_prob" if np.any(np.isnan(data["log_prob"])) else "accepted", "numbers (no NaN) and counts >= 0")
    if str(data["rs_name"]) != "MT19937":
        raise bad("rs_name", "the text 'MT19937'")
    if not 0 <= int(data["rs_meta"][0]) <= 624 or int(data["rs_meta"][1]) not in (0, 1):
        raise bad("rs_meta", "a position 0..624 and a flag 0 or 1")
    if "blobs" in data and (data["blobs"].ndim < 2 or data["blobs"].shape[:2] != (it, walkers)):
        raise bad("blobs", f"shape ({it}, {walkers}, ...)")
    return it
