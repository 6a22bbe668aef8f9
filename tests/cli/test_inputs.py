"""Argument parsing shared by the commands."""

import argparse

import pytest

from bayescal.cli.inputs import free_arg, name_list, recording_model
from bayescal.errors import BayescalError
from tests.conftest import ROOT


def test_name_lists_and_free():
    assert name_list(" a, b,,c ,") == ["a", "b", "c"]
    assert name_list(" , ") == []
    assert free_arg("auto") == "auto" and free_arg("all") == "all"
    assert free_arg("chain1.link_length, tool.point.z") == ["chain1.link_length", "tool.point.z"]


def test_recording_model_reads_the_example_and_names_a_bad_file(tmp_path):
    ex = ROOT / "examples" / "prs3"
    args = argparse.Namespace(machine=str(ex / "machine.toml"), recording=str(ex / "recording.csv"), dof=5)
    machine, rec, model = recording_model(args)
    assert model.dof == 5 and model.n_poses == rec.q.shape[0] and machine.n_actuators == 3
    bad = tmp_path / "rec.csv"
    bad.write_text("q1,q2,q3,x,y,z\n1,2\n")
    with pytest.raises(BayescalError, match="rec.csv"):
        recording_model(argparse.Namespace(machine=str(ex / "machine.toml"), recording=str(bad)))
