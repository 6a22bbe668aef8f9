"""Checkpoint files that are not checkpoints: a clear InputError naming the file, not a KeyError or BadZipFile.

(Resuming a killed chain to the same draws is tested through the command line in tests/cli/test_rough_edges.py.)
"""

import numpy as np
import pytest

from bayescal.bayes.checkpoint import load_checkpoint
from bayescal.errors import InputError


def test_an_npz_of_something_else_is_refused(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, a=np.ones(3))
    with pytest.raises(InputError, match="other.npz: not a bayescal MCMC checkpoint"):
        load_checkpoint(path, {})


def test_a_truncated_checkpoint_is_refused(tmp_path):
    good = tmp_path / "good.npz"
    np.savez(good, a=np.ones(100))
    path = tmp_path / "cut.npz"
    path.write_bytes(good.read_bytes()[:100])
    with pytest.raises(InputError, match="cut.npz: not a bayescal MCMC checkpoint"):
        load_checkpoint(path, {})


def test_a_single_array_file_is_refused(tmp_path):
    path = tmp_path / "one.npz"
    with open(path, "wb") as fh:
        np.save(fh, np.ones(3))
    with pytest.raises(InputError, match="one.npz: not a bayescal MCMC checkpoint"):
        load_checkpoint(path, {})


def test_an_empty_file_is_refused(tmp_path):
    # np.load raises EOFError on an empty file (a `touch`ed path): an InputError (exit 2), not a traceback
    path = tmp_path / "empty.npz"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="empty.npz: not a bayescal MCMC checkpoint"):
        load_checkpoint(path, {})


# ------------------------------------------------------------------ valid archives with bad contents (issue 30)
import emcee  # noqa: E402

from bayescal.bayes.checkpoint import save_checkpoint  # noqa: E402

FP = {"seed": 0, "n_walkers": 4, "names": ["a", "b"], "surrogate": "none", "data_sha256": "x", "proposal": "p"}


def _good(tmp_path):
    backend = emcee.backends.Backend()
    backend.reset(4, 2)
    backend.grow(3, None)
    backend.chain[:] = np.arange(24.0).reshape(3, 4, 2)
    backend.log_prob[:] = -1.0
    backend.accepted[:] = 2
    backend.iteration = 3
    backend.random_state = np.random.RandomState(0).get_state()
    path = tmp_path / "c.npz"
    save_checkpoint(path, backend, FP)
    with np.load(path) as z:
        return path, {k: z[k] for k in z.files}


def test_a_good_checkpoint_loads_back(tmp_path):
    path, _ = _good(tmp_path)
    b = load_checkpoint(path, FP)
    assert b.iteration == 3 and b.chain.shape == (3, 4, 2) and b.random_state[0] == "MT19937"


@pytest.mark.parametrize("change, names", [
    (lambda d: d.update(chain=np.zeros((3, 4, 3))), "chain"),
    (lambda d: d.update(chain=np.full((3, 4, 2), np.nan)), "chain"),
    (lambda d: d.update(iteration=np.array(-1)), "iteration"),
    (lambda d: d.update(iteration=np.array(2.5)), "iteration"),
    (lambda d: d.update(iteration=np.array(7)), "chain"),
    (lambda d: d.update(log_prob=np.zeros((3, 5))), "log_prob"),
    (lambda d: d.update(accepted=np.array(["a", "b", "c", "d"])), "accepted"),
    (lambda d: d.update(rs_keys=np.zeros(5, np.uint32)), "rs_keys"),
    (lambda d: d.update(rs_name=np.array("PCG64")), "rs_name"),
    (lambda d: d.update(rs_meta=np.array([9999, 0])), "rs_meta"),
    (lambda d: d.update(rs_cached=np.array("x")), "rs_cached"),
    (lambda d: d.update(fingerprint=np.array("{not json")), "fingerprint"),
    (lambda d: d.update(fingerprint=np.array("[1, 2]")), "fingerprint"),
    (lambda d: d.update(fingerprint=np.array([1.0, 2.0])), "fingerprint"),
    (lambda d: d.update(blobs=np.zeros(3)), "blobs"),
])
def test_a_damaged_checkpoint_is_refused_naming_what(tmp_path, change, names):
    path, data = _good(tmp_path)
    change(data)
    np.savez(path, **data)
    with pytest.raises(InputError, match=f"c.npz: .*{names}"):
        load_checkpoint(path, FP)


def test_a_checkpoint_that_is_a_pipe_is_refused(tmp_path):
    import os

    os.mkfifo(tmp_path / "p.npz")
    with pytest.raises(InputError, match="p.npz: is a named pipe"):
        load_checkpoint(tmp_path / "p.npz", FP)
