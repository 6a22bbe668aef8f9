"""Klipper's delta printers: ``printer.cfg`` in (with its includes and SAVE_CONFIG block), Klipper's own keys out.

========================  =====================================================
:mod:`.source`            the config's text: includes, line continuations
:mod:`.autosave`          the SAVE_CONFIG block Klipper writes at the end
:mod:`.cfg`               sections and options as Klipper's config reader sees them
:mod:`.printer`           a config's geometry and saved calibration as a machine and a recording
:mod:`.keys`              a calibrated machine back into Klipper's keys and units
:mod:`.baseline`          Klipper's own DELTA_CALIBRATE, re-implemented as a baseline
:mod:`.loo`               leave-one-out comparison of bayescal and that baseline
========================  =====================================================
"""

from .cfg import KlipperConfig, read_klipper_config
from .keys import klipper_keys, klipper_text
from .printer import (
    KLIPPER_TOLERANCE, MAX_LENGTH, SAVED_MARGIN, STEPPERS, KlipperDelta, klipper_machine, klipper_recording,
    read_klipper_delta, saved_counts,
)

__all__ = [
    "KlipperConfig", "read_klipper_config", "klipper_keys", "klipper_text", "KlipperDelta", "read_klipper_delta",
    "klipper_recording", "klipper_machine", "saved_counts", "KLIPPER_TOLERANCE", "STEPPERS", "MAX_LENGTH",
    "SAVED_MARGIN",
]
