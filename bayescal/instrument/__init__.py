"""Recordings as instruments deliver them (docs/formats.md section 4).

* :mod:`~bayescal.instrument.alignment`: closed-form rigid alignment (the start
  of ``--frame fit``) and the check that suggests it;
* :mod:`~bayescal.instrument.units`: positions that look like metres, angles
  that look like degrees;
* :mod:`~bayescal.instrument.prepare`: the measurement model of a recording
  in the base frame, a known frame or a fitted one;
* :mod:`~bayescal.instrument.plausibility`: results that refuse to be
  implausible.

The frame itself is a machine wrapper, :class:`bayescal.machines.framed.InstrumentFrame`.
"""

from .alignment import FrameCheck, align_frame, check_frame, frame_start
from .plausibility import Plausibility, assess_plausibility, frame_answer
from .prepare import FRAMES, prepare_model
from .units import check_recording_units

__all__ = [
    "FrameCheck", "align_frame", "check_frame", "frame_start", "Plausibility", "assess_plausibility",
    "frame_answer", "FRAMES", "prepare_model", "check_recording_units",
]
