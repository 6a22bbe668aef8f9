"""Tilt sensors and accelerometers on the machine's bodies as measurements (docs/formats.md section 8).

:func:`attach_sensors` reads a recording's ``accel.<body>.x/y/z`` columns,
fixes each sensor's nominal mounting from the data and extends the
machine's parameters by the mountings (:class:`~bayescal.sensors.mounts.SensorMounts`);
:class:`~bayescal.measurement.MeasurementModel` then appends two tilt rows
per sensor to every pose (:mod:`bayescal.sensors.rows`), so every consumer
of the model fits the geometry from the tool and the sensors together.
"""

from __future__ import annotations


import numpy as np
from numpy.typing import NDArray

from .columns import SENSOR_COLUMN, sensor_readings
from .mounts import SensorMounts, sensor_base
from .rows import SensorSet

__all__ = ["SENSOR_COLUMN", "SensorMounts", "SensorSet", "attach_sensors", "sensor_readings", "sensor_rows",
           "sensor_jacobian", "sensor_actuator_jacobian", "predicted_readings", "sensor_rotation_rows", "sensor_base"]


def attach_sensors(machine, rec, q: NDArray):
    """The machine with its body sensors' parameters, and the sensors, for recording ``rec`` at actuator positions ``q``.

    Parameters
    ----------
    machine : Machine
        As the model would use it (an :class:`InstrumentFrame` is kept outermost).
    rec : Recording
        Its ``accel.<body>.x/y/z`` columns are read (:func:`sensor_readings`).
    q : ndarray, shape (n, N)
        The actuator positions the mountings' start values are computed at
        (the commanded ones: the same start whatever effects are applied).

    Returns
    -------
    (Machine, SensorSet or None)
        Unchanged and None when the recording has no sensor on a body other
        than the base (a base sensor alone gives no rows: it only gives the
        gravity-driven effects their per-pose gravity).

    Raises
    ------
    RecordingError
        A body the machine does not expose (naming the column and the bodies
        it has), an incomplete x/y/z set, a zero-length reading.
    """
    inner = sensor_base(machine.inside)  # a model's machine again: its sensors are replaced, not added twice
    machine = machine.rewrapped(inner)
    readings = sensor_readings(dict(rec.aux), rec.path, rec.lines, tuple(inner.sensor_bodies))
    bodies = tuple(b for b in readings if b != "base")
    if not bodies:
        return machine, None
    frames = tuple(inner.body_frame(b) for b in bodies)
    R_nom, _ = inner.body_rotations(q, None, list(frames))
    u = np.stack([readings[b] for b in bodies], axis=1)
    # the nominal mountings from the fit rows only: a held-out check reading must not shape its own prediction
    fit = np.flatnonzero(~np.asarray(rec.is_check, dtype=bool))
    sensors = SensorSet.start(bodies, frames, u, readings.get("base"), R_nom, rows=fit)
    nz = inner.noise
    tol = ()
    for t in sensors.turn:  # two tilts and (where fitted) the turn of each sensor, then the level
        tol += (nz.sensor_mount, nz.sensor_mount) + ((nz.sensor_turn,) if t else ())
    level = nz.sensor_mount if sensors.base_sensor else nz.base_level
    tol += (level, level)
    view = SensorMounts(inner, sensors.names, tol)
    return machine.rewrapped(view), sensors


def _split(machine, theta: NDArray):
    """The chain, its part of ``theta``, the sensors' part, and where the chain's columns start."""
    view = machine.inside
    off = machine.n_frame
    th = np.asarray(theta, dtype=float)
    return view.base, th[..., off : off + view.n_base], th[..., off + view.n_base :], off


def sensor_rows(machine, sensors: SensorSet, q: NDArray, theta: NDArray) -> NDArray:
    """Predicted tilt rows (N, 2 S), rad, for the model's machine (a :class:`SensorMounts` view, maybe framed)."""
    chain, th_m, th_s, _ = _split(machine, theta)
    R, Jb = chain.body_rotations(q, th_m, list(sensors.frames))
    return sensors.rows(sensors.bent(R, Jb)[0], th_s)


def predicted_readings(machine, sensors: SensorSet, q: NDArray, theta: NDArray) -> NDArray:
    """Predicted unit readings (N, S, 3) of the sensors, each in its own frame, sign as recorded."""
    chain, th_m, th_s, _ = _split(machine, theta)
    R, Jb = chain.body_rotations(q, th_m, list(sensors.frames))
    return sensors.readings(sensors.bent(R, Jb)[0], th_s)


def sensor_jacobian(machine, sensors: SensorSet, q: NDArray, theta: NDArray) -> NDArray:
    """``d rows / d theta`` (N, 2 S, P) over the model machine's whole parameter vector."""
    chain, th_m, th_s, off = _split(machine, theta)
    R, Jb = sensors.bent(*chain.body_rotations(q, th_m, list(sensors.frames)))
    Jm, Js = sensors.jacobian(R, Jb, th_s)
    J = np.zeros(Jm.shape[:2] + (machine.n_params,))
    J[:, :, off : off + Jm.shape[2]] = Jm
    J[:, :, machine.n_params - Js.shape[2] :] = Js
    return J


def sensor_actuator_jacobian(machine, sensors: SensorSet, q: NDArray, theta: NDArray) -> NDArray:
    """``d rows / d q`` (N, 2 S, n_actuators): how the tilt rows move with the actuators (an effect's ``dq``)."""
    chain, th_m, th_s, _ = _split(machine, theta)
    frames = list(sensors.frames)
    R, Jq = sensors.bent(chain.body_rotations(q, th_m, frames)[0], chain.body_actuator_jacobian(q, th_m, frames))
    return sensors.jacobian(R, Jq, th_s)[0]


def sensor_rotation_rows(machine, sensors: SensorSet, q: NDArray, theta: NDArray, rotation: NDArray) -> NDArray:
    """``d rows / d w`` times ``rotation``: the tilt rows' change when the bodies turn by small base-frame rotations.

    Parameters
    ----------
    rotation : ndarray, shape (N, S, 3, k)
        Per pose and sensor, ``k`` small rotations of the sensor's body (rad per unit of what they are columns of).

    Returns
    -------
    ndarray, shape (N, 2 S, k)
    """
    chain, th_m, th_s, _ = _split(machine, theta)
    R, _ = sensors.bent(*chain.body_rotations(q, th_m, list(sensors.frames)))
    return sensors.jacobian(R, rotation, th_s)[0]
