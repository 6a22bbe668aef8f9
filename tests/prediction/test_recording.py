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
