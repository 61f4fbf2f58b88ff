"""What the vehicle's other messages say about its acceleration.

The accelerometer measures gravity only when the vehicle does not accelerate;
in a coordinated turn it does, by V·ψ̇, for as long as the turn lasts, and no
low-pass averages that away. Two sources the autopilots send remove it:

- GPS velocity (GLOBAL_POSITION_INT's vx, vy, vz, while GPS_RAW_INT reports a
  3-D fix): its difference over each report interval is the vehicle's
  acceleration relative to the Earth in NED, all of it, which the estimator
  takes as ``linear_accel`` (removed in the world frame, with the heading
  error's part in it modelled).
- Airspeed (VFR_HUD), on fixed wings: the centripetal term ω × v with v ≈
  (V, 0, 0) in the body, removed from the sample itself (as ArduPilot's DCM
  does). It misses sideslip and speed changes: the fallback when there is no
  GPS, or no heading to turn a world-frame acceleration into the body.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

GPS_MAX_AGE = 0.5  # s: a GPS acceleration older than this (vehicle time) is not used
GPS_FIX_MAX_AGE = 2.0  # s: the last 3-D fix report must be this recent
AIRSPEED_MAX_AGE = 2.0  # s: an older VFR_HUD airspeed is not used
_MIN_GPS_INTERVAL = 0.02  # s: reports closer than this are not differenced (jitter)
_MAX_GPS_INTERVAL = 1.0  # s: nor farther apart (a gap: the acceleration is unknown)
_MAX_SPEED = 300.0  # m/s: a faster velocity report is corrupt
_MAX_ACCELERATION = 50.0  # m/s² (5 g): a larger difference is a glitch, not motion
_FIX_3D = 3  # GPS_FIX_TYPE_3D_FIX; higher values (DGPS, RTK) are better fixes


@dataclass
class GpsAcceleration:
    """The acceleration from consecutive GLOBAL_POSITION_INT velocities, per vehicle."""

    velocity: tuple[float, float, float] | None = None  # m/s NED, the last report
    report_time: float = math.nan  # s, its time_boot_ms
    accel: tuple[float, float, float] | None = None  # m/s² NED, the last difference
    accel_t: float = -math.inf  # vehicle (IMU) time it was formed at
    fix_t: float = -math.inf  # vehicle time of the last 3-D fix report
    glitches: int = 0  # reports not differenced: absurd values or an absurd difference

    def on_fix(self, fix_type: int, t: float) -> None:
        """A GPS_RAW_INT at vehicle time t."""
        if fix_type >= _FIX_3D:
            self.fix_t = t

    def on_velocity_report(self, vx: int, vy: int, vz: int, time_boot_ms: int, t: float) -> None:
        """A GLOBAL_POSITION_INT's fields (cm/s, ms: as on the wire) at vehicle time t."""
        velocity = (vx * 0.01, vy * 0.01, vz * 0.01)  # cm/s → m/s
        report_time = time_boot_ms * 1e-3
        if not all(abs(v) < _MAX_SPEED for v in velocity):
            self.glitches += 1
            self.velocity = None
            return
        previous, previous_time = self.velocity, self.report_time
        self.velocity, self.report_time = velocity, report_time
        interval = report_time - previous_time  # NaN the first time
        if previous is None or not _MIN_GPS_INTERVAL <= interval <= _MAX_GPS_INTERVAL:
            return
        accel = tuple((v - p) / interval for v, p in zip(velocity, previous, strict=True))
        if not all(abs(a) < _MAX_ACCELERATION for a in accel):
            self.glitches += 1
            return
        self.accel = accel  # type: ignore[assignment]
        self.accel_t = t

    def at(self, t: float) -> tuple[float, float, float] | None:
        """The acceleration to use for an IMU sample at t, or None (unknown)."""
        if self.accel is None or not gps_fresh(t, self.accel_t, self.fix_t):
            return None
        return self.accel


# The freshness rules, written once for one sample's time (a number) and for a block's
# (arrays): the element-wise operators give a bool on numbers and a mask on arrays.


def gps_fresh(t: Any, accel_t: Any, fix_t: Any) -> Any:
    """Whether a GPS acceleration formed at ``accel_t``, the last 3-D fix reported at
    ``fix_t``, is used for an IMU sample at ``t`` (all vehicle time)."""
    since_fix = t - fix_t
    since_accel = t - accel_t
    return (
        (since_fix >= 0.0)
        & (since_fix <= GPS_FIX_MAX_AGE)
        & (since_accel >= 0.0)
        & (since_accel <= GPS_MAX_AGE)
    )


def airspeed_fresh(t: Any, airspeed_t: Any) -> Any:
    """Whether an airspeed reported at ``airspeed_t`` is used for an IMU sample at ``t``."""
    since = t - airspeed_t
    return (since >= 0.0) & (since <= AIRSPEED_MAX_AGE)


def gps_acceleration_at(
    accel: np.ndarray, accel_t: np.ndarray, fix_t: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """:meth:`GpsAcceleration.at` for many samples, each with the state it meets
    (the replay's fast path): ``accel`` (n, 3), NaN rows where there is none yet,
    ``accel_t`` and ``fix_t`` per sample; (n, 3), NaN rows where it is unknown.
    The same rule (:func:`gps_fresh`)."""
    return np.where(gps_fresh(t, accel_t, fix_t)[:, None], accel, math.nan)


def without_centripetal(
    accel: tuple[float, float, float],
    gyro: tuple[float, float, float],
    bias: Any,
    airspeed: float,
) -> tuple[float, float, float]:
    """The specific force less the centripetal acceleration of flight along body x.

    A fixed wing in a steady coordinated turn feels its load factor straight
    down the body z axis: the accelerometer alone says "level" at any bank
    (22° RMS tilt error on the JSBSim flight, for VQF as for mavest). With
    v ≈ (V, 0, 0) in the body frame, a = v̇ + ω × v and ω × v = (0, ω_z V, −ω_y V);
    removing it leaves gravity and v̇ (ArduPilot's DCM does the same with its
    airspeed). v̇ (speed changes, sideslip, gusts) stays: GPS velocity removes it.
    """
    wy = gyro[1] - bias[1]
    wz = gyro[2] - bias[2]
    return (accel[0], accel[1] - wz * airspeed, accel[2] + wy * airspeed)
