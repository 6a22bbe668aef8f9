"""Per-parameter tolerances in a machine file's ``[tolerance]`` table (issue 31: ``"chain2.link_length" = 0.5``).

The override is read for every kind (the bundled machines), survives writing and reading back, is refused with
the file and key named when it names no parameter, and reaches the answer: the MAP covariance under it equals the
dense closed-form Gaussian posterior built here with the override put in by hand.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from bayescal.effects.stored import machine_file_text
from bayescal.errors import MachineFileError
from bayescal.identify import identify
from bayescal.io import read_recording
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.tolerance import tolerance_vector
from bayescal.measurement import MeasurementModel
from bayescal.params import ParamSpec

EX = Path(__file__).resolve().parents[2] / "examples"
SINGLE = ["prs3", "delta", "arm6", "raspm", "rupus_prs", "positioner", "tiago", "telescope"]


def _with_tolerance(text: str, lines: str) -> str:
    """``text`` with ``lines`` put into its [tolerance] table (made if it has none)."""
    if "\n[tolerance]" in text:
        head, tail = text.split("\n[tolerance]", 1)
        first, rest = tail.split("\n", 1)
        return f"{head}\n[tolerance]{first}\n{lines}\n{rest}"
    return f"{text}\n[tolerance]\n{lines}\n"


@pytest.mark.parametrize("name", SINGLE)
def test_one_parameter_overrides_its_group_and_round_trips(name):
    path = EX / name / "machine.toml"
    plain = load_machine(path)
    target = plain.inside.layout.names[len(plain.inside.layout) // 2]
    i = plain.layout.index(target)
    value = float(7.25 * plain.tolerance[i])
    m = machine_from_text(_with_tolerance(path.read_text(), f'"{target}" = {value!r}'), str(path))
    expected = plain.tolerance.copy()
    expected[i] = value
    np.testing.assert_array_equal(m.tolerance, expected)
    again = machine_from_text(machine_file_text(m), str(path))
    np.testing.assert_array_equal(again.tolerance, expected)


def test_a_bare_dotted_key_is_the_same_as_a_quoted_one():
    path = EX / "prs3" / "machine.toml"
    quoted = machine_from_text(_with_tolerance(path.read_text(), '"chain2.link_length" = 0.5'), str(path))
    bare = machine_from_text(_with_tolerance(path.read_text(), "chain2.link_length = 0.5\nlink_length = 0.01"), str(path))
    i, j = quoted.layout.index("chain2.link_length"), quoted.layout.index("chain1.link_length")
    assert quoted.tolerance[i] == bare.tolerance[i] == 0.5
    # the group's own value holds for the others, whichever order the keys come in
    assert quoted.tolerance[j] == 0.05 and bare.tolerance[j] == 0.01


@pytest.mark.parametrize("lines, key, words", [
    ('"chain2.link_lenght" = 0.5', 'tolerance."chain2.link_lenght"', "did you mean 'chain2.link_length'"),
    ('"chain9.link_length" = 0.5', 'tolerance."chain9.link_length"', "unknown parameter"),
    ("linklength = 0.5", "tolerance.linklength", "or a parameter's name"),
    ('"chain2.link_length" = -0.5', "tolerance.chain2.link_length", "expected a positive number"),
    ('"chain2.link_length" = "wide"', "tolerance.chain2.link_length", "expected a finite number"),
])
def test_bad_keys_and_values_are_refused_naming_the_key(lines, key, words):
    path = EX / "prs3" / "machine.toml"
    with pytest.raises(MachineFileError) as err:
        machine_from_text(_with_tolerance(path.read_text(), lines), "m.toml")
    assert err.value.key == key and words in str(err.value) and str(err.value).startswith("m.toml: ")


def test_a_hybrid_module_file_names_its_own_parameters(tmp_path):
    shutil.copytree(EX / "hybrid_wrist", tmp_path / "h")
    head = tmp_path / "h" / "head.toml"
    plain = load_machine(tmp_path / "h" / "machine.toml")
    head.write_text(_with_tolerance(head.read_text(), '"chain1.link_length" = 0.321'))
    m = load_machine(tmp_path / "h" / "machine.toml")
    changed = np.flatnonzero(m.tolerance != plain.tolerance)
    assert [m.layout.names[k] for k in changed] == ["m1.chain1.link_length"] and m.tolerance[changed[0]] == 0.321
    head.write_text(_with_tolerance(head.read_text(), '"m1.chain1.link_length" = 0.5'))
    with pytest.raises(MachineFileError) as err:
        load_machine(tmp_path / "h" / "machine.toml")
    assert err.value.path.endswith("head.toml") and "chain1.link_length" in str(err.value)


def test_tolerance_vector_resolves_names_before_groups():
    specs = [ParamSpec("a.x", "mm", "g"), ParamSpec("a.y", "mm", "g"), ParamSpec("b", "rad", "h")]
    np.testing.assert_array_equal(tolerance_vector(specs, {"g": 1.0, "h": 2.0, "a.y": 3.0}), [1.0, 3.0, 2.0])


def test_the_map_posterior_uses_the_parameters_own_tolerance():
    path = EX / "prs3" / "machine.toml"
    rec = read_recording(EX / "prs3" / "recording.csv")
    tight = machine_from_text(_with_tolerance(path.read_text(), '"chain2.link_length" = 1.0e-4'), str(path))
    i = tight.layout.index("chain2.link_length")
    model = MeasurementModel.from_recording(tight, rec).subset([0, 7, 21])
    res = identify(model, method="map", free="all")
    assert res.success
    # the dense closed-form posterior with the override put in by hand (not through the machine's tolerance)
    tol = load_machine(path).tolerance.copy()
    tol[i] = 1.0e-4
    pred = model.predict(res.theta)
    J = (model.jacobian(res.theta, pred) / model.row_sigma[:, :, None]).reshape(-1, model.n_params)
    dense = np.linalg.inv(J.T @ J + np.diag(1.0 / tol**2))
    np.testing.assert_allclose(res.std, np.sqrt(np.diag(dense)), rtol=1e-6)
    loose = identify(MeasurementModel.from_recording(load_machine(path), rec).subset([0, 7, 21]), method="map",
                     free="all")
    # three poses alone leave the link length near its group's 0.05 mm; the override holds it to 0.1 um
    assert res.std[i] <= 1.0e-4 < 0.1 * loose.std[i]
