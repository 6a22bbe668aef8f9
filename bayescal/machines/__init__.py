"""Kinematic families, each registered by its ``kind`` (:data:`KINDS`).

Reading a machine file (its geometry, effect tables, instrument frame and
calibration) is :func:`bayescal.machines.files.load_machine`: the tables
above the geometry belong to layers above this package.  The conformance
check every kind passes is :func:`bayescal.machines.check.check_machine`.
"""

from __future__ import annotations

from .base import KINDS, Machine, MeasurementNoise, ToolPoses
from .framed import Frame, InstrumentFrame

# the kinds, in the order KINDS lists them (each registers itself: Machine.__init_subclass__)
from .prs3 import Prs3  # noqa: I001
from .rupus_prs import RupusPrs
from .raspm import Raspm
from .serial import Serial
from .hybrid import Hybrid, write_machine_files
from .linear_delta import LinearDelta

__all__ = [
    "Machine", "ToolPoses", "MeasurementNoise", "Prs3", "RupusPrs", "Raspm", "Serial", "Hybrid", "LinearDelta", "KINDS",
    "write_machine_files", "InstrumentFrame",
    "Frame",
]
