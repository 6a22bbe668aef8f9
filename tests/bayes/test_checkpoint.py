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
