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
from mavest.onboard.errors import OnboardLogError
from mavest.onboard.model import ImuStream, LogDamage, OnboardLog, Series
from mavest.onboard.series import Timeline

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


def _vector(data: dict[str, np.ndarray], field: str, count: int = 3) -> np.ndarray:
    """(N, count) float64 from an array field stored as ``field[0]``, ``field[1]``…"""
    return np.column_stack([data[f"{field}[{i}]"] for i in range(count)]).astype(np.float64)


def _sample_time(data: dict[str, np.ndarray]) -> np.ndarray:
    """µs since boot of each message's sample: ``timestamp_sample`` where all are set."""
    sample = data.get("timestamp_sample")
    if sample is not None and len(sample) and np.all(sample > 0):
        return sample.astype(np.int64)
    return data["timestamp"].astype(np.int64)


class _Builder:
    """Collects the series of one log and what it says about them."""

    def __init__(self) -> None:
        self.timeline = Timeline()
        self.notes: list[str] = []

    def series(self, t_us: np.ndarray, values: np.ndarray) -> Series:
        return self.timeline.series(t_us, values)


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
    t_us = sensors["timestamp"].astype(np.int64)
    relative = sensors.get("accelerometer_timestamp_relative", np.zeros_like(t_us))
    valid = relative.astype(np.int64) != _RELATIVE_TIMESTAMP_INVALID
    if not np.any(valid):
        return None
    both = np.hstack((_vector(sensors, "gyro_rad"), _vector(sensors, "accelerometer_m_s2")))
    imu = build.series(t_us[valid], both[valid])
    build.notes.append(
        f"IMU instance 0 (sensor_combined): {len(imu.t_us)} samples, accelerometer paired "
        f"with the gyro's time (up to {int(np.max(np.abs(relative[valid])))} µs apart)"
    )
    if not np.all(valid):
        build.notes.append(f"{int(np.sum(~valid))} sensor_combined messages without accelerometer")
    return ImuStream(0, imu.t_us, imu.values[:, :3], imu.values[:, 3:])


def _magnetometers(build: _Builder, topics: dict[str, Any]) -> dict[int, Series]:
    if "vehicle_magnetometer" in topics:
        build.notes.append("magnetometer: vehicle_magnetometer (calibrated)")
        return {
            instance: build.series(
                _sample_time(data), _vector(data, "magnetometer_ga") * _GAUSS_TO_MICROTESLA
            )
            for instance, data in sorted(topics["vehicle_magnetometer"].items())
        }
    sensors = topics.get("sensor_combined", {}).get(0, {})
    if "magnetometer_ga[0]" in sensors:
        relative = sensors["magnetometer_timestamp_relative"].astype(np.int64)
        valid = relative != _RELATIVE_TIMESTAMP_INVALID
        t_us = sensors["timestamp"].astype(np.int64)[valid] + relative[valid]
        field = _vector(sensors, "magnetometer_ga")[valid] * _GAUSS_TO_MICROTESLA
        # sensor_combined repeats the last magnetometer sample in every message
        new = np.concatenate(([True], np.diff(t_us) != 0))
        build.notes.append("magnetometer: sensor_combined.magnetometer_ga")
        return {0: build.series(t_us[new], field[new])} if len(t_us) else {}
    if "sensor_mag" in topics:
        build.notes.append("magnetometer: sensor_mag (uncalibrated: no vehicle_magnetometer)")
        return {
            instance: build.series(
                _sample_time(data),
                np.column_stack([data[a] for a in "xyz"]).astype(np.float64) * _GAUSS_TO_MICROTESLA,
            )
            for instance, data in sorted(topics["sensor_mag"].items())
        }
    return {}


def _gps(build: _Builder, topics: dict[str, Any]) -> tuple[Series | None, Series | None]:
    name = next((n for n in ("vehicle_gps_position", "sensor_gps") if n in topics), None)
    if name is None:
        return None, None
    data = topics[name][min(topics[name])]
    t_us = data["timestamp"].astype(np.int64)
    fix_type = data["fix_type"].astype(np.float64)
    three_d = fix_type >= 3
    if "vel_ned_valid" in data:
        three_d &= data["vel_ned_valid"].astype(bool)
    velocity = None
    if np.any(three_d):
        ned = np.column_stack([data[f"vel_{a}_m_s"] for a in "ned"]).astype(np.float64)
        velocity = build.series(t_us[three_d], ned[three_d])
    build.notes.append(f"GPS: {name}")
    return build.series(t_us, fix_type[:, None]), velocity


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
    build.notes.append(f"airspeed: {name}.true_airspeed_m_s")
    speed = data["true_airspeed_m_s"].astype(np.float64)[:, None]
    return build.series(data["timestamp"].astype(np.int64), speed)


def _attitude(build: _Builder, topics: dict[str, Any], name: str) -> Series | None:
    if 0 not in topics.get(name, {}):
        return None
    data = topics[name][0]
    q = _vector(data, "q", 4)
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
    imu = _imu(build, sensors) if sensors is not None else None
    if imu is None:
        raise OnboardLogError(f"{path.name}: no sensor_combined (IMU) samples in this ULog")

    mag = _magnetometers(build, topics)
    gps_fix, gps_velocity = _gps(build, topics)
    airspeed = _airspeed(build, topics)
    attitude = _attitude(build, topics, "vehicle_attitude")
    truth = _attitude(build, topics, "vehicle_attitude_groundtruth")
    if truth is None:
        build.notes.append("no vehicle_attitude_groundtruth (not a simulator log)")

    parameter = ulog.initial_parameters.get("MAV_TYPE")
    vehicle = int(parameter) if parameter is not None else mavlink2.MAV_TYPE_GENERIC
    build.notes.append(
        f"vehicle type {vehicle} from MAV_TYPE"
        if parameter is not None
        else "vehicle type unknown (no MAV_TYPE parameter)"
    )
    build.notes += build.timeline.notes()
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
            dropped_samples=build.timeline.dropped,
        ),
        notes=tuple(build.notes),
    )
