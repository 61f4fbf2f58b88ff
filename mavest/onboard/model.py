"""What an onboard autopilot log holds once decoded: the types every reader returns.

The readers (DataFlash, ULog) turn a log into an :class:`OnboardLog` in SI units and body
FRD / NED frames, so a consumer never needs to know which autopilot wrote the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _none() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class Series:
    """Samples of one quantity: t_us (N,) int64 µs since the autopilot's boot, strictly
    increasing after loading within each timeline (duplicates/backsteps dropped and
    counted); values (N, k) float64; restarts: the indices where a new timeline starts
    (a clock that went back and stayed), in order, none for most logs."""

    t_us: np.ndarray
    values: np.ndarray
    restarts: np.ndarray = field(default_factory=_none)


@dataclass(frozen=True)
class ImuStream:
    """One inertial sensor's samples."""

    instance: int  # 0, 1, 2 … (ArduPilot IMU/IMU2/IMU3 or IMU.I; PX4 0)
    t_us: np.ndarray  # (N,) int64 µs since boot
    gyro: np.ndarray  # (N, 3) rad/s, body FRD (as logged: board rotation applied)
    accel: np.ndarray  # (N, 3) m/s², specific force, body FRD (≈ (0,0,-g) level at rest)
    restarts: np.ndarray = field(default_factory=_none)  # as Series.restarts


@dataclass(frozen=True)
class LogDamage:
    """What a reader had to pass over; all zero for an intact log."""

    bad_records: int = 0  # records that failed their checks (unknown type, bad length)
    skipped_bytes: int = 0  # bytes passed over while resynchronising
    truncated_bytes: int = 0  # a last record cut off at the end of the file
    dropped_samples: int = 0  # samples dropped for time going back or repeating
    # the reader passed over damage without saying how much (pyulog): skipped_bytes is 0
    # for want of a count, not for want of damage
    extent_unknown: bool = False


@dataclass(frozen=True)
class OnboardLog:
    """An autopilot's onboard log, decoded."""

    format: str  # "dataflash" | "ulog"
    autopilot: str  # "ArduPilot" | "PX4"
    vehicle_type: int  # MAV_TYPE_* (ArduPilot: from the firmware string/"VER"/MSG
    # "ArduPlane"/"ArduCopter"/…; PX4: from the MAV_TYPE parameter);
    # MAV_TYPE_GENERIC if unknown
    imus: tuple[ImuStream, ...]
    mag: dict[int, Series]  # instance → field in µT, body FRD (values (N,3)); may be empty
    attitude: Series | None  # the autopilot's attitude: values (N,3) roll, pitch, yaw rad,
    # ZYX Euler, NED (ArduPilot ATT with AHRS_TRIM_X/Y added back,
    # as mavest/datasets/autopilot_logs.py does; PX4 vehicle_attitude q)
    truth: Series | None  # a simulator's true attitude (values (N,3) rad), if logged
    gps_velocity: Series | None  # values (N,3) m/s NED, only samples with a 3-D fix
    gps_fix: Series | None  # values (N,1): fix type as MAVLink GPS_FIX_TYPE (3 = 3-D)
    airspeed: Series | None  # values (N,1) m/s
    declination: float | None  # rad (ArduPilot COMPASS_DEC parameter; PX4 none unless logged)
    damage: LogDamage
    notes: tuple[str, ...]  # what the loader chose or found, one line each
