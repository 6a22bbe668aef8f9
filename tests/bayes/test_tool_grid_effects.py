"""Both compensation grids apply a machine file's [effect.*] tables, checked against independent physics.

For every effect kind a machine file can carry, a machine is written with
the table by hand (docs/formats.md section 7), the grid is computed in tool space
(and in actuator space at the same actuator positions), and each node is
compared with an independent computation that shares no effect code: the
actuator positions the drives really reach come from the simulators of
tests/physics/ (full statics of compliant drives, growing parts, nut and
screw play) or from the closed form (screw periodic error), or, for the
RASPM's preload, from the restrained module's energy minimum; the machine's
forward kinematics is used as a black box.  Two checks per node:

* the node's error equals ``p_true(q(x)) - x`` (the definition);
* the correction is what a root-find of the true machine asks for: the
  command ``q_c`` that puts the true tool point at ``x`` has the nominal
  tool point ``x + correction`` (to second order in the error).
"""

import numpy as np
import pytest

from bayescal.bayes.grid import compensation_grid
from bayescal.bayes.tool_grid import tool_grid
from bayescal.effects.joint_compliance import GRAVITY
from bayescal.errors import InputError, MachineFileError
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.redundant.physics import solve_restrained
from bayescal.redundant.restrained_recording import true_effect_values
from bayescal.simulate import draw_errors
from tests.conftest import PRS3_FILE, ROOT
from tests.physics.nut_screw import NutScrew
from tests.physics.statics_3prs import GravityLoad, deflected_q
from tests.physics.thermal_growth import PartGrowth

RASPM = ROOT / "examples" / "raspm" / "machine.toml"
DOWN = np.array([0.0, 0.0, -1.0])  # the effect's default gravity direction (docs/formats.md section E2: [0, 0, -1])


def _cov(m):
    """A covariance of the identified errors (the std is not what these tests check)."""
    return np.diag((0.1 * m.tolerance) ** 2)


def _tg(m, theta, **kw):
    return tool_grid(m, theta, covariance=_cov(m), **kw)


def _ag(m, theta, **kw):
    return compensation_grid(m, theta, covariance=_cov(m), **kw)


def _with_table(table: str, text: str | None = None, name: str = "cal.toml"):
    return machine_from_text((PRS3_FILE.read_text() if text is None else text) + "\n" + table, name)


def _table(name: str, values: dict) -> str:
    return f"[effect.{name}]\n" + "".join(f'"{k}" = {float(v)!r}\n' for k, v in values.items())


def _root_find_correction(nominal, true_position, x, ctrl, q0):
    """The command ``q_c`` with ``true_position(q_c) = x`` on the controlled axes, by Newton with a
    finite-difference Jacobian of the black box; returns the nominal tool point's shift ``p_nom(q_c) - x``."""
    q = np.array(q0, float, copy=True)
    h = 1e-4
    for _ in range(8):
        r = true_position(q)[:, ctrl] - x[:, ctrl]
        if np.abs(r).max() < 1e-10:
            break
        J = np.stack([(true_position(q + h * e)[:, ctrl] - true_position(q - h * e)[:, ctrl]) / (2 * h)
                      for e in np.eye(q.shape[1])], axis=-1)
        q = q - np.linalg.solve(J, r[..., None])[..., 0]
    assert np.abs(true_position(q)[:, ctrl] - x[:, ctrl]).max() < 1e-9
    return nominal.forward(q, None).position - x


def _check_against_physics(m, theta, true_position, aux, *, rtol=0.02, n=3):
    """Tool grid and actuator grid of ``m`` (carrying an effect) at ``aux`` against ``true_position(q_cmd)`` (mm)."""
    g = _tg(m, theta, n=n, aux=aux)
    x, q = g.nodes, g.q
    # the definition: actual minus commanded at the nominal inverse kinematics
    actual = true_position(q) - x
    moved = np.abs(actual - (m.forward(q, theta).position - x)).max()  # what the effect alone moves
    assert moved > 2e-3  # the effect moves the tool by microns at least: the check can fail
    err = g.error.reshape(-1, 3)
    np.testing.assert_allclose(err, actual, atol=rtol * moved + 1e-7)
    # the grid without the effect misses it: the difference is the effect's
    plain = _tg(machine_from_text(m.to_toml(None), "plain.toml"), theta, n=n)
    assert np.abs(plain.error.reshape(-1, 3) - err).max() > 0.5 * moved
    # what a controller must command: a direct root-find on the true machine
    ctrl = list(g.controlled)
    shift = _root_find_correction(m, true_position, x, ctrl, q)
    # (first order against exact: the geometric errors' and the effect's second-order terms, ~1 % of the error)
    np.testing.assert_allclose(g.correction.reshape(-1, 3)[:, ctrl], shift[:, ctrl], atol=0.02 * np.abs(err).max())
    # and it is the effect that brings them together: the grid without it misses the root-find by more
    assert np.abs(plain.correction.reshape(-1, 3)[:, ctrl] - shift[:, ctrl]).max() > 0.5 * moved
    # the actuator-space grid at the same actuator positions says the same
    for j in (0, len(q) - 1):
        a1 = _ag(m, theta, axes=tuple(np.array([v]) for v in q[j]), aux=aux)
        np.testing.assert_allclose(-a1.correction.reshape(3), actual[j], atol=rtol * moved + 1e-7)
    return g


@pytest.fixture(scope="module")
def prs3_theta():
    m = load_machine(PRS3_FILE)
    return np.random.default_rng(5).normal(size=m.n_params) * m.tolerance


def test_joint_compliance_under_a_payload_against_full_statics(prs3_theta):
    c, mp, com = np.array([0.4, 0.7, 0.55]), 40.0, np.array([20.0, -15.0, -60.0])  # um/N, kg, mm
    values = {"com.x": com[0], "com.y": com[1], "com.z": com[2], "gravity.tilt_1": 0.0, "gravity.tilt_2": 0.0,
              "compliance.q1": c[0], "compliance.q2": c[1], "compliance.q3": c[2], "platform_mass": mp}
    m = _with_table(_table("joint_compliance", values))
    load = GravityLoad(mp, com, DOWN)
    for payload in (0.0, 25.0):
        # the statics at the machine file's geometry (the stored table's loads are evaluated there)
        def true_position(q, payload=payload):
            return m.forward(deflected_q(m, None, q, c, load, np.full(len(q), payload)), prs3_theta).position

        _check_against_physics(m, prs3_theta, true_position, {"payload_kg": payload}, n=2)  # statics: slow
    # a table parametrised with a payload (compliance per N, platform mass) needs the payload stated
    with pytest.raises(MachineFileError, match=r"cal.toml: key 'effect.joint_compliance': parametrised for a recording "
                                               r"with channel\(s\) payload_kg.*--aux payload_kg=VALUE; payload_kg=0 is no payload"):
        _tg(m, prs3_theta, n=3)
    # one parametrised without a payload (the deflection under the platform's own weight) needs none
    wd = {k: v for k, v in values.items() if not k.startswith("compliance") and k != "platform_mass"}
    wd.update({f"weight_deflection.q{i + 1}": c[i] * mp * GRAVITY for i in range(3)})  # um: c (um/N) x m g (N)
    m2 = _with_table(_table("joint_compliance", wd))

    def own_weight(q):
        return m.forward(deflected_q(m, None, q, c, load, np.zeros(len(q))), prs3_theta).position

    _check_against_physics(m2, prs3_theta, own_weight, {}, n=2)


def test_thermal_expansion_at_a_temperature_against_growing_parts(prs3_theta):
    m0 = load_machine(PRS3_FILE)
    a_s, a_l = np.array([11.0, 18.0, 23.0]), np.array([12.0, 20.0, 15.0])  # um/m/K
    bearing = np.array([0.0, m0.q_limits[1, 1] + 50.0, 0.0])  # screws fixed at either end
    q0 = m0.home_q()
    lam = 1e-3 * a_l * m0.geometry_arrays(None)["link_length"]  # um/K
    # the table's drift: the screw's growth about q0 plus the links' at the home pose (K there, by the
    # closed form of the 3-PRS: 1 / (L_hat . u), from the geometry, not from the effect's code)
    g = m0.geometry_arrays(None)
    home = m0.forward(q0[None], None)
    A = home.state.p[0][None, :] + g["sphere_center"] @ home.state.R[0].T  # sphere centres, one row per chain
    L = A - (g["rail_origin"] + q0[:, None] * g["rail_direction"])
    K0 = 1.0 / np.einsum("ki,ki->k", L / np.linalg.norm(L, axis=1, keepdims=True), g["rail_direction"])
    drift = 1e-3 * a_s * (q0 - bearing) + K0 * lam
    values = {**{f"drift.q{i + 1}": drift[i] for i in range(3)}, **{f"alpha.q{i + 1}": a_s[i] for i in range(3)},
              **{f"link.q{i + 1}": lam[i] for i in range(3)}}
    m = _with_table(_table("thermal_expansion", values))
    for temp in (28.0, 12.0):
        growth = PartGrowth(m, [temp], alpha_screw=a_s, bearing_mm=bearing, alpha_link=a_l)

        def true_position(q, growth=growth):
            # grown screws move the sliders, grown links change the geometry: the true machine's tool point
            qg, th = growth.transform(q, np.broadcast_to(prs3_theta, (len(q), m.n_params)), {}, None)
            return m.forward(qg, th).position

        _check_against_physics(m, prs3_theta, true_position, {"temp_C": temp}, rtol=0.03)
    # the temperature is a needed input with no default: a clear error naming the table
    with pytest.raises(InputError, match=r"cal.toml: \[effect.thermal_expansion\] cannot be applied for a recording "
                                         r"without auxiliary channels: needs a temp_C or time_s channel.*"
                                         r"--aux NAME=VALUE, e.g. --aux temp_C=25"):
        _tg(m, prs3_theta, n=3)


def test_screw_periodic_error_against_its_closed_form(prs3_theta):
    m0 = load_machine(PRS3_FILE)
    pitch, a, b = 5.0, np.array([8.0, -5.0, 3.0]), np.array([2.0, 6.0, -7.0])  # mm, um, um
    values = {"pitch": pitch, **{f"sin.q{i + 1}": a[i] for i in range(3)}, **{f"cos.q{i + 1}": b[i] for i in range(3)}}
    m = _with_table(_table("screw_periodic_error", values))
    q0 = m0.home_q()

    def true_position(q):
        ph = 2 * np.pi * (q - q0) / pitch
        return m.forward(q + 1e-3 * (a * np.sin(ph) + b * np.cos(ph)), prs3_theta).position

    _check_against_physics(m, prs3_theta, true_position, {}, rtol=0.01)


def test_backlash_at_a_node_reached_without_a_last_move_is_the_centre_of_the_band(prs3_theta):
    """A grid node has no approach direction: the nut is taken at the centre of its play (no dq).

    The nut-and-screw simulator started with the gap at the centre and not
    moved puts the nut where the screw is; the grid must equal the grid
    without the table (and a table is still read and checked).
    """
    dead = np.array([20.0, 35.0, 50.0])  # um
    m = _with_table(_table("backlash", {f"backlash.q{i + 1}": dead[i] for i in range(3)}))
    g = _tg(m, prs3_theta, n=3)
    nut = np.array([NutScrew(dead).run(qi[None], np.array([True]))[0] for qi in g.q])
    np.testing.assert_allclose(nut, g.q, atol=1e-12)
    plain = _tg(load_machine(PRS3_FILE), prs3_theta, n=3)
    np.testing.assert_allclose(g.error, plain.error, atol=1e-12)


def test_redundancy_preload_on_the_raspm_against_the_restrained_energy_minimum():
    m0 = load_machine(RASPM)
    rng = np.random.default_rng(3)
    theta_true = 0.2 * draw_errors(m0, rng)  # errors of a machine built to a fifth of its tolerances
    k = rng.uniform(150, 500, 4) * 1e3  # N/mm
    from bayescal.effects import get_effect

    eff = get_effect("redundancy_preload")
    f = eff.features(m0, m0.sample_q(3, rng), np.zeros(m0.n_params), {}, None, None)
    cols = list(f.const["columns"])
    params = eff.params(m0, f)

    class Sim:
        theta, stiffness = theta_true, k

    vals = true_effect_values(m0, Sim, params)
    # the machine file's geometry is the true one except the redundant chain, whose errors the table carries
    theta = theta_true.copy()
    theta[cols] = 0.0
    m = machine_from_text(m0.to_toml(theta) + "\n" + _table("redundancy_preload", vals), "raspm_cal.toml")
    ranges = {"x": (-150.0, 150.0), "z": (-480.0, -300.0)}
    g = _tg(m, np.zeros(m.n_params), n=3, ranges=ranges)
    true = m0.tool_from_planar(solve_restrained(m0, g.q, theta_true, k).x, theta_true)[0]
    moved = np.abs(true - m0.forward(g.q, theta).position).max()
    assert moved > 0.01  # the preload moves the tool by more than 10 um
    np.testing.assert_allclose(g.error.reshape(-1, 3), true - g.nodes, atol=0.05 * moved)
    plain = _tg(machine_from_text(m0.to_toml(theta), "plain.toml"), np.zeros(m.n_params), n=3, ranges=ranges)
    assert np.abs(plain.error - g.error).max() > 0.5 * moved
