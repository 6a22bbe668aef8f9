"""Position-only recordings with an unknown tool point: the frame start registers the frame and the offset together."""

import numpy as np

from bayescal.identify import identify
from bayescal.instrument import prepare_model
from bayescal.instrument.alignment import align_frame, frame_start
from bayescal.machines.files import machine_from_text
from bayescal.simulate import measure
from tests.instrument.frames import random_frame, to_instrument
from tests.machines.test_serial import ARM


def _marker_recording(seed):
    """A 5R1P arm whose tracked marker sits ~100 mm from the nominal tool point, seen from a random frame."""
    arm = machine_from_text(ARM + "\n[tolerance]\ntool_point = 200.0\n")  # the marker's place is unknown
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=arm.n_params) * arm.tolerance * 0.5
    marker = np.array([70.0, -60.0, 40.0])  # ~100 mm from the nominal point
    for k, c in enumerate("xyz"):
        theta[arm.layout.index(f"tool.point.{c}")] = marker[k]
    q = arm.sample_q(40, rng)
    rec = measure(arm, q, theta, 3, rng)
    origin, R = random_frame(rng)
    return arm, theta, to_instrument(rec, origin, R), origin, R


def test_registration_recovers_the_frame_that_plain_alignment_misses():
    for seed in range(5):
        arm, theta, rec, origin, R = _marker_recording(seed)
        nom = arm.forward(rec.q)
        plain = align_frame(rec.position, nom.position)
        start = frame_start(arm, rec, dof=3)
        angle = lambda F: np.linalg.norm(  # noqa: E731
            __import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation.from_matrix(F.rotation @ R.T).as_rotvec())
        # the plain point alignment is turned by degrees; the registration by a fraction of a milliradian
        assert angle(plain) > 0.01
        assert angle(start) < 1e-3 and angle(start) < angle(plain) / 20, (angle(plain), angle(start))
        assert np.linalg.norm(start.origin - origin) < 5.0


def test_frame_fit_from_the_registered_start_reaches_the_noise():
    arm, theta, rec, origin, R = _marker_recording(7)
    machine, model, _ = prepare_model(arm, rec, dof=3, frame="fit")
    res = identify(model, method="ridge", lam=1.0)
    assert res.success, res.message
    # the marker's tolerance declares it unknown: the tool point is kept, the joint-6 origin (its gauge) fixed
    names = [machine.layout.names[j] for j in np.flatnonzero(res.free)]
    assert {"tool.point.x", "tool.point.y", "tool.point.z"} <= set(names)
    assert res.rms_after["position"] < 1.5 * np.sqrt(3) * arm.noise.sigma_position
