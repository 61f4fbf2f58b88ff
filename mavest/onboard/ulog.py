"""PX4 ULog files (``.ulg``) through pyulog, which reads each topic into NumPy arrays.

Topics and units (a ULog field's name carries its unit, its type the storage):

* IMU: ``sensor_combined`` — ``gyro_rad`` (rad/s) at ``timestamp`` (µs since boot) and
  ``accelerometer_m_s2`` (m/s²) ``accelerometer_timestamp_relative`` µs from it; body
  FRD, board rotation applied. The accelerometer is paired with the gyro's time, and a
  message whose accelerometer part is marked invalid is dropped.
* magnetometer: ``vehicle_magnetometer.magnetometer_ga`` (Gauss, calibrated, FRD), else
  ``sensor_combined.magnetometer_ga`` (older PX4), else ``sensor_mag`` (uncalibrated);
  in µT (× 100).
* GPS: ``vehicle_gps_position`` (else ``sensor_gps``): ``fix_type`` (as MAVLink's
  GPS_FIX_TYPE) and ``vel_n_m_s``, ``vel_e_m_s``, ``vel_d_m_s`` where the fix is 3-D.
* airspeed: ``true_airspeed_m_s`` of ``airspeed_validated`` or ``airspeed``, whichever
  holds more samples.
* attitude: ``vehicle_attitude.q`` (w, x, y, z), as ZYX Euler angles; the simulator's
  ``vehicle_attitude_groundtruth`` is the truth. ``timestamp_sample`` (the IMU sample the
  estimate belongs to) where PX4 fills it in, else ``timestamp``.
* vehicle type: the ``MAV_TYPE`` parameter.

pyulog reads past damage by looking for the next sync marker and stops at a cut-off end;
it says only *that* it found corrupt data, so a damaged file counts one bad record.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any

import numpy as np

from mavest.mavlink.bulk import euler_rows
from mavest.mavlink.messages import mavlink2
from mavest.onboard.errors import FieldError, OnboardLogError
from mavest.onboard.model import ImuStream, LogDamage, OnboardLog, Series
from mavest.onboard.series import Collector, boot_times

__all__ = ["load_ulog"]

_TOPICS = [
    "sensor_combined",
    "vehicle_magnetometer",
    "sensor_mag",
    "vehicle_gps_position",
    "sensor_gps",
    "airspeed",
    "airspeed_validated",
    "vehicle_attitude",
    "vehicle_attitude_groundtruth",
]

# PX4 marks a sensor_combined part that is missing with this relative timestamp
# (RELATIVE_TIMESTAMP_INVALID, INT32_MAX).
_RELATIVE_TIMESTAMP_INVALID = 2**31 - 1
_GAUSS_TO_MICROTESLA = 100.0


def _numbers(data: dict[str, np.ndarray], topic: str, field: str) -> np.ndarray:
    """One field as stored; FieldError if the topic's format lacks it or it is not a number."""
    values = data.get(field)
    if values is None:
        raise FieldError(f"{topic} has no field {field}")
    if values.dtype.kind not in "biuf":
        raise FieldError(f"{topic}.{field} is not a number")
    return values


def _scalar(data: dict[str, np.ndarray], topic: str, field: str) -> np.ndarray:
    """(N,) float64 of one field (see :func:`_numbers`)."""
    return _numbers(data, topic, field).astype(np.float64)


def _vector(data: dict[str, np.ndarray], topic: str, field: str, count: int = 3) -> np.ndarray:
    """(N, count) float64 from an array field stored as ``field[0]``, ``field[1]``…"""
    return np.column_stack([_scalar(data, topic, f"{field}[{i}]") for i in range(count)])


def _time(data: dict[str, np.ndarray]) -> np.ndarray:
    """µs since boot of each message (``timestamp``: every topic read has one)."""
    return boot_times(data["timestamp"])


def _sample_time(data: dict[str, np.ndarray]) -> np.ndarray:
    """µs since boot of each message's sample: ``timestamp_sample`` where all are set."""
    sample = data.get("timestamp_sample")
    if sample is not None and len(sample) and sample.dtype.kind in "iu" and np.all(sample > 0):
        return boot_times(sample)
    return _time(data)


class _Builder(Collector):
    """Collects the series of one log and what it says about them."""


def _read(path: Path) -> tuple[Any, str]:
    """pyulog's ULog of the wanted topics, and what pyulog printed while reading."""
    from pyulog import ULog

    printed = io.StringIO()
    try:
        # pyulog reports corruption by printing; that becomes a note instead.
        with contextlib.redirect_stdout(printed):
            ulog = ULog(str(path), _TOPICS)
    except Exception as error:  # pyulog raises bare and assorted errors on a bad file
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise OnboardLogError(f"{path.name}: not a readable ULog ({message})") from error
    return ulog, printed.getvalue().strip()


def _topics(ulog: Any) -> dict[str, dict[int, dict[str, np.ndarray]]]:
    """Topic name → multi-instance id → fields, the topics that hold messages."""
    topics: dict[str, dict[int, dict[str, np.ndarray]]] = {}
    for dataset in ulog.data_list:
        if len(dataset.data.get("timestamp", ())):
            topics.setdefault(dataset.name, {})[int(dataset.multi_id)] = dataset.data
    return topics


def _imu(build: _Builder, sensors: dict[str, np.ndarray]) -> ImuStream | None:
    """FieldError if sensor_combined lacks the gyro or the accelerometer."""
    t_us = _time(sensors)
    relative = sensors.get("accelerometer_timestamp_relative", np.zeros_like(t_us))
    valid = relative.astype(np.int64) != _RELATIVE_TIMESTAMP_INVALID
    if not np.any(valid):
        return None
    both = np.hstack(
        (
            _vector(sensors, "sensor_combined", "gyro_rad"),
            _vector(sensors, "sensor_combined", "accelerometer_m_s2"),
        )
    )
    imu = build.series(t_us[valid], both[valid])
    build.notes.append(
        f"IMU instance 0 (sensor_combined): {len(imu.t_us)} samples, accelerometer paired "
        f"with the gyro's time (up to {int(np.max(np.abs(relative[valid])))} µs apart)"
    )
    if not np.all(valid):
        build.notes.append(f"{int(np.sum(~valid))} sensor_combined messages without accelerometer")
    return ImuStream(0, imu.t_us, imu.values[:, :3], imu.values[:, 3:], imu.restarts)


def _magnetometers(build: _Builder, topics: dict[str, Any]) -> dict[int, Series]:
    """The first source of vehicle_magnetometer, sensor_combined, sensor_mag that gives
    a field (one whose format lacks it is left out, with a note, for the next)."""
    for read in (_vehicle_magnetometer, _combined_magnetometer, _sensor_mag):
        found = build.attempt(read, build, topics)
        if found:  # (None: left out, with a note; empty: no such topic)
            return found
    return {}


def _vehicle_magnetometer(build: _Builder, topics: dict[str, Any]) -> dict[int, Series]:
    if "vehicle_magnetometer" not in topics:
        return {}
    field = {
        instance: (_sample_time(data), _vector(data, "vehicle_magnetometer", "magnetometer_ga"))
        for instance, data in sorted(topics["vehicle_magnetometer"].items())
    }
    build.notes.append("magnetometer: vehicle_magnetometer (calibrated)")
    return {k: build.series(t, gauss * _GAUSS_TO_MICROTESLA) for k, (t, gauss) in field.items()}


def _combined_magnetometer(build: _Builder, topics: dict[str, Any]) -> dict[int, Series]:
    sensors = topics.get("sensor_combined", {}).get(0, {})
    if "magnetometer_ga[0]" not in sensors:
        return {}
    name = "sensor_combined"
    relative = _numbers(sensors, name, "magnetometer_timestamp_relative").astype(np.int64)
    valid = relative != _RELATIVE_TIMESTAMP_INVALID
    t_us = _time(sensors)[valid] + relative[valid]
    field = _vector(sensors, name, "magnetometer_ga")[valid] * _GAUSS_TO_MICROTESLA
    # sensor_combined repeats the last magnetometer sample in every message
    new = np.concatenate(([True], np.diff(t_us) != 0))
    build.notes.append("magnetometer: sensor_combined.magnetometer_ga")
    return {0: build.series(t_us[new], field[new])} if len(t_us) else {}


def _sensor_mag(build: _Builder, topics: dict[str, Any]) -> dict[int, Series]:
    if "sensor_mag" not in topics:
        return {}
    field = {
        instance: (
            _sample_time(data),
            np.column_stack([_scalar(data, "sensor_mag", a) for a in "xyz"]),
        )
        for instance, data in sorted(topics["sensor_mag"].items())
    }
    build.notes.append("magnetometer: sensor_mag (uncalibrated: no vehicle_magnetometer)")
    return {k: build.series(t, gauss * _GAUSS_TO_MICROTESLA) for k, (t, gauss) in field.items()}


def _gps(build: _Builder, topics: dict[str, Any]) -> tuple[Series | None, Series | None]:
    name = next((n for n in ("vehicle_gps_position", "sensor_gps") if n in topics), None)
    if name is None:
        return None, None
    data = topics[name][min(topics[name])]
    t_us = _time(data)
    fix_type = build.attempt(_scalar, data, name, "fix_type")
    if fix_type is None:
        return None, None
    three_d = fix_type >= 3
    valid = (
        build.attempt(_numbers, data, name, "vel_ned_valid") if "vel_ned_valid" in data else None
    )
    if valid is not None:
        three_d &= valid.astype(bool)
    velocity = None
    if np.any(three_d):
        ned = build.attempt(_ned, data, name, part="GPS velocity")
        if ned is not None:
            velocity = build.series(t_us[three_d], ned[three_d])
    build.notes.append(f"GPS: {name}")
    return build.series(t_us, fix_type[:, None]), velocity


def _ned(data: dict[str, np.ndarray], name: str) -> np.ndarray:
    return np.column_stack([_scalar(data, name, f"vel_{a}_m_s") for a in "ned"])


def _airspeed(build: _Builder, topics: dict[str, Any]) -> Series | None:
    candidates = [
        (len(topics[n][0]["timestamp"]), n)
        for n in ("airspeed_validated", "airspeed")
        if 0 in topics.get(n, {}) and "true_airspeed_m_s" in topics[n][0]
    ]
    if not candidates:
        return None
    _, name = max(candidates)
    data = topics[name][0]
    speed = build.attempt(_scalar, data, name, "true_airspeed_m_s")
    if speed is None:
        return None
    build.notes.append(f"airspeed: {name}.true_airspeed_m_s")
    return build.series(_time(data), speed[:, None])


def _attitude(build: _Builder, topics: dict[str, Any], name: str) -> Series | None:
    if 0 not in topics.get(name, {}):
        return None
    data = topics[name][0]
    q = build.attempt(_vector, data, name, "q", 4)
    if q is None:
        return None
    norm = np.linalg.norm(q, axis=1)
    usable = norm > 0.5  # (an all-zero quaternion: no estimate yet)
    q = q[usable] / norm[usable, None]  # logged as float32
    return build.series(_sample_time(data)[usable], euler_rows(q))


def load_ulog(path: Path | str) -> OnboardLog:
    """A PX4 ULog as an :class:`~mavest.onboard.model.OnboardLog` (see the module docstring).

    OnboardLogError if the file cannot be read or holds no sensor_combined samples.
    """
    path = Path(path)
    ulog, printed = _read(path)
    topics = _topics(ulog)
    build = _Builder()
    corrupt = bool(getattr(ulog, "file_corruption", False))
    if corrupt:
        build.notes.append(
            "pyulog found corrupt data" + (f": {printed.splitlines()[0]}" if printed else "")
        )
    sensors = topics.get("sensor_combined", {}).get(0)
    try:
        imu = _imu(build, sensors) if sensors is not None else None
    except FieldError as error:
        raise OnboardLogError(f"{path.name}: no IMU samples in this ULog ({error})") from error
    if imu is None:
        raise OnboardLogError(f"{path.name}: no sensor_combined (IMU) samples in this ULog")
    if not len(imu.t_us):  # every sample unusable (NaN, a time off the log's timeline)
        raise OnboardLogError(
            f"{path.name}: no IMU samples in this ULog (sensor_combined: no usable sample)"
        )

    mag = _magnetometers(build, topics)
    gps_fix, gps_velocity = _gps(build, topics)
    airspeed = _airspeed(build, topics)
    attitude = _attitude(build, topics, "vehicle_attitude")
    truth = _attitude(build, topics, "vehicle_attitude_groundtruth")
    if truth is None:
        build.notes.append("no vehicle_attitude_groundtruth (not a simulator log)")

    parameter = ulog.initial_parameters.get("MAV_TYPE")
    build.notes.append(_vehicle_note(parameter))
    vehicle = int(parameter) if _is_mav_type(parameter) else mavlink2.MAV_TYPE_GENERIC
    return OnboardLog(
        format="ulog",
        autopilot="PX4",
        vehicle_type=vehicle,
        imus=(imu,),
        mag=mag,
        attitude=attitude,
        truth=truth,
        gps_velocity=gps_velocity,
        gps_fix=gps_fix,
        airspeed=airspeed,
        declination=None,
        damage=LogDamage(
            bad_records=int(corrupt) + build.timeline.unreadable,
            dropped_samples=build.timeline.dropped + build.timeline.off_timeline,
            extent_unknown=corrupt,
        ),
        notes=build.final_notes(),
    )


_LAST_MAV_TYPE = 255  # (HEARTBEAT's type, a uint8)


def _is_mav_type(parameter: Any) -> bool:
    """Whether a MAV_TYPE parameter's value is one HEARTBEAT can carry: a whole number
    0…255 (a damaged one may be anything, NaN included)."""
    try:
        return float(parameter).is_integer() and 0 <= float(parameter) <= _LAST_MAV_TYPE
    except (TypeError, ValueError):
        return False


def _vehicle_note(parameter: Any) -> str:
    if parameter is None:
        return "vehicle type unknown (no MAV_TYPE parameter)"
    if not _is_mav_type(parameter):
        return f"MAV_TYPE {parameter} is no vehicle type: taken as generic"
    return f"vehicle type {int(parameter)} from MAV_TYPE"
