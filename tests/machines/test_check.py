"""check_machine: passes the shipped 3-PRS and catches deliberately broken machines."""

from dataclasses import dataclass, fields, replace

import numpy as np
import pytest

from bayescal.machines import Prs3
from bayescal.machines.check import MachineCheckError, check_machine
from bayescal.machines.files import load_machine
from tests.conftest import ROOT
from bayescal.params import ParamLayout, ParamSpec


def _as(cls, machine):
    return cls(**{f.name: getattr(machine, f.name) for f in fields(Prs3) if f.init})


@dataclass(frozen=True, eq=False)
class _WrongJacobianColumn(Prs3):
    """chain2.link_length's column 1 % too large: the kind of slip a hand-derived Jacobian has."""

    def tool_jacobian(self, q, theta, poses):
        J = super().tool_jacobian(q, theta, poses)
        J[:, :, self.layout.index("chain2.link_length")] *= 1.01
        return J


@dataclass(frozen=True, eq=False)
class _WrongRotationRows(Prs3):
    """Rotation rows with the wrong sign for one tilt: positions alone would not show it."""

    def tool_jacobian(self, q, theta, poses):
        J = super().tool_jacobian(q, theta, poses)
        J[:, 3:, self.layout.index("chain1.rail_direction.tilt_x")] *= -1.0
        return J


@dataclass(frozen=True, eq=False)
class _ForgetsToolPoint(Prs3):
    """A writer that drops the identified tool-point error."""

    def to_toml(self, theta=None):
        theta = None if theta is None else np.array(theta, dtype=float)
        if theta is not None:
            theta[-3:] = 0.0
        return super().to_toml(theta)


@dataclass(frozen=True, eq=False)
class _IgnoresPerPoseTheta(Prs3):
    """Uses only the first row of a per-pose theta."""

    def forward(self, q, theta=None, *, guess=None):
        theta = None if theta is None else np.asarray(theta, dtype=float)
        if theta is not None and theta.ndim == 2:
            theta = theta[0]
        return super().forward(q, theta, guess=guess)


def test_prs3_conforms(prs3):
    assert check_machine(prs3) == []
    assert check_machine(prs3, seed=3, n_poses=4, strict=True) == []


def test_wrong_jacobian_column_is_caught_and_named(prs3):
    problems = check_machine(_as(_WrongJacobianColumn, prs3))
    assert problems and all("chain2.link_length" in p for p in problems)
    with pytest.raises(MachineCheckError, match="chain2.link_length"):
        check_machine(_as(_WrongJacobianColumn, prs3), strict=True)


def test_wrong_rotation_rows_are_caught(prs3):
    problems = check_machine(_as(_WrongRotationRows, prs3))
    assert len(problems) == 1
    assert "chain1.rail_direction.tilt_x" in problems[0] and "rotation rows" in problems[0]


def test_lossy_machine_file_is_caught(prs3):
    problems = check_machine(_as(_ForgetsToolPoint, prs3))
    assert len(problems) == 1 and problems[0].startswith("to_toml:")


def test_per_pose_theta_ignored_is_caught(prs3):
    problems = check_machine(_as(_IgnoresPerPoseTheta, prs3))
    assert problems and any("theta of shape (n, P)" in p for p in problems)


def test_bad_names_units_and_missing_limits_are_reported(prs3):
    m = replace(prs3, q_limits=None)
    specs = list(m.layout.specs)
    specs[0] = ParamSpec("sphere1_x", "mm", "sphere_center")
    specs[1] = ParamSpec(specs[1].name, "inch", "sphere_center")
    object.__setattr__(m, "layout", ParamLayout(tuple(specs)))
    problems = check_machine(m)
    assert any("'sphere1_x' is not chain<i>" in p for p in problems)
    assert any("unit 'inch'" in p for p in problems)
    assert any(p.startswith("q_limits:") for p in problems)


@pytest.mark.parametrize("path", sorted((ROOT / "examples").glob("*/machine.toml")), ids=lambda p: p.parent.name)
def test_every_shipped_machine_passes_the_conformance_check(path):
    assert check_machine(load_machine(path)) == []
