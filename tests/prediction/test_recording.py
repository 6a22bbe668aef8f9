"""``predict_recording`` (bayescal/prediction/recording.py): what it refuses."""

from __future__ import annotations

from dataclasses import replace

import pytest

from bayescal.errors import RecordingError
from bayescal.prediction.recording import predict_recording
from bayescal.simulate import simulate_recording


def test_frame_fit_with_no_station_to_fit_names_the_stations(prs3):
    # every station had one fit row: the frame fit was asked for no parameter ("free: expected at least one parameter")
    rec = simulate_recording(prs3, 4, seed=2, dof=6).recording
    rec = replace(rec, station=("a", "b", "c", "d"))
    with pytest.raises(RecordingError, match=r"--frame fit: no station has the 2 fit rows needed to fit its instrument "
                       r"frame \(fit rows per station: 'a' 1, 'b' 1, 'c' 1, 'd' 1\)") as err:
        predict_recording(prs3, rec, frame="fit")
    assert err.value.column == "station"


def test_frame_fit_with_one_fit_row_and_no_station_column(prs3):
    rec = simulate_recording(prs3, 3, seed=2, dof=6).recording
    rec = replace(rec, role=("fit", "check", "check"))
    with pytest.raises(RecordingError, match=r"--frame fit: 1 fit row\(s\); at least 2 are needed"):
        predict_recording(prs3, rec, frame="fit")


def test_held_out_rows_are_predicted_with_the_effects_fitted_with_the_geometry(prs3):
    """score_held_out_result(effects=...): the check rows' predictions carry the effect (its dq on the actuators)."""
    import numpy as np

    import bayescal
    from bayescal.effects.stored import StoredEffect
    from bayescal.identify import identify
    from bayescal.measurement import MeasurementModel
    from bayescal.prediction.recording import score_held_out_result

    rec = simulate_recording(prs3, 16, seed=4, dof=6).recording
    rec = replace(rec, role=tuple("check" if i % 4 == 3 else "fit" for i in range(rec.n_poses)))
    session = bayescal.load(prs3, rec)
    res = identify(session.model.subset(np.flatnonzero(~rec.is_check)), method="ridge", lam=1.0)
    backlash = StoredEffect("backlash", (("backlash.q1", 20.0), ("backlash.q2", 30.0), ("backlash.q3", 25.0)))
    plain = score_held_out_result(res, session)["check"]["rows"]
    moved = score_held_out_result(res, session, effects=(backlash,))["check"]["rows"]
    check = np.flatnonzero(rec.is_check)
    expected = MeasurementModel.from_recording(prs3.with_effects((backlash,)), rec).subset(check).predict(res.theta).y
    assert len(moved) == check.size and all("error" not in r for r in moved)
    got = np.array([r["predicted"][:3] for r in moved])
    np.testing.assert_allclose(got, expected[:, :3], rtol=0, atol=1e-9)
    shift = np.abs(got - np.array([r["predicted"][:3] for r in plain])).max()
    assert shift > 1e-4  # the backlash moved the predicted tool points (mm)
