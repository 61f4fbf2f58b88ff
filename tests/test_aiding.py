"""The vehicle's acceleration from GPS velocity: removed in the world frame, with the
heading error's part in it modelled, so that turns reveal heading (as in a GPS-aided
INS); and the service's differencing of GLOBAL_POSITION_INT."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mavest import Estimator
from mavest.estimator.config import EstimatorConfig
from mavest.estimator.layout import StepFlags
from mavest.mavlink.messages import MAVLink
from mavest.service.aiding import (
    AIRSPEED_MAX_AGE,
    GPS_FIX_MAX_AGE,
    GPS_MAX_AGE,
    GpsAcceleration,
    airspeed_fresh,
    gps_acceleration_at,
    gps_fresh,
)
from mavest.service.pipeline import AidingFields, Vehicle

G = 9.80665
RATE = 200.0


def _coordinated_turn(seconds: float, seed: int = 0) -> dict[str, np.ndarray]:
    """5 s straight, a 3 s roll into a 28° bank, then a steady coordinated turn at 50 m/s.

    Built with scipy's Rotation: q body → NED (w, x, y, z), gyro and specific force
    with a little white noise, the true acceleration in NED. Coordinated: the yaw
    rate is g·tan(φ)/V, and the body rates are (φ̇, ψ̇ sin φ, ψ̇ cos φ) at zero pitch.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(round(seconds * RATE) + 1) / RATE
    speed, bank_max, start, roll_in = 50.0, math.radians(28.0), 5.0, 3.0
    ramp = np.clip((t - start) / roll_in, 0.0, 1.0)
    bank = bank_max * 0.5 * (1.0 - np.cos(math.pi * ramp))
    bank_rate = np.where(
        (t > start) & (t < start + roll_in),
        bank_max * 0.5 * math.pi / roll_in * np.sin(math.pi * ramp),
        0.0,
    )
    yaw_rate = G * np.tan(bank) / speed
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1])) / RATE])
    attitude = Rotation.from_euler("ZYX", np.column_stack([yaw, 0 * yaw, bank]))
    accel_ned = speed * yaw_rate[:, None] * np.column_stack([-np.sin(yaw), np.cos(yaw), 0 * yaw])
    specific = attitude.inv().apply(accel_ned - np.array([0.0, 0.0, G]))
    gyro = np.column_stack([bank_rate, yaw_rate * np.sin(bank), yaw_rate * np.cos(bank)])
    q = attitude.as_quat()[:, [3, 0, 1, 2]]
    return {
        "t": t,
        "q": q,
        "gyro": gyro + 1e-3 * math.sqrt(RATE) * rng.standard_normal(gyro.shape),
        "accel": specific + 0.01 * math.sqrt(RATE) * rng.standard_normal(specific.shape),
        "accel_ned": accel_ned,
    }


def _heading_error(q_est: np.ndarray, q_true: np.ndarray) -> float:
    """The estimate's error about the world vertical, rad."""
    est = Rotation.from_quat(q_est[[1, 2, 3, 0]])
    true = Rotation.from_quat(q_true[[1, 2, 3, 0]])
    return float((est * true.inv()).as_rotvec()[2])


def _run(flight: dict[str, np.ndarray], aided: bool, heading_offset: float) -> tuple:
    estimator = Estimator(EstimatorConfig())
    start = Rotation.from_rotvec([0.0, 0.0, heading_offset]) * Rotation.from_quat(
        flight["q"][0, [1, 2, 3, 0]]
    )
    cov = np.diag([math.radians(1.0) ** 2] * 2 + [math.radians(8.0) ** 2] + [1e-8] * 3)
    estimator.initialise(0.0, start.as_quat()[[3, 0, 1, 2]], cov=cov)
    flags = 0
    for i in range(1, len(flight["t"])):
        linear = flight["accel_ned"][i] if aided else None
        estimate = estimator.update(
            flight["t"][i], flight["gyro"][i], flight["accel"][i], None, linear
        )
        flags |= estimate.flags
    error = _heading_error(estimator.q, flight["q"][-1])
    return error, math.sqrt(estimator.cov[2, 2]), flags


def test_turns_reveal_heading_when_the_acceleration_is_known() -> None:
    # No magnetometer: only the modelled coupling of heading into the aided sample
    # (the turn's acceleration seen in the wrong direction) can correct heading.
    flight = _coordinated_turn(60.0)
    offset = math.radians(6.0)
    error, sigma, flags = _run(flight, True, offset)
    assert flags & StepFlags.ACCEL_AIDED
    assert abs(error) < 0.2 * offset  # most of the 6° found
    assert sigma < 0.6 * math.radians(8.0)  # and the filter knows it learnt (σ was 8°)
    assert abs(error) < 3.0 * sigma  # honestly
    # unaided, the accelerometer says nothing about heading: the offset stays
    error_unaided, _, _ = _run(flight, False, offset)
    assert abs(error_unaided) > 0.6 * offset


def test_aided_tilt_holds_in_a_turn() -> None:
    flight = _coordinated_turn(60.0, seed=1)
    for aided, bound in ((True, 0.5), (False, 10.0)):
        estimator = Estimator(EstimatorConfig())
        cov = np.diag([math.radians(1.0) ** 2] * 2 + [math.radians(2.0) ** 2] + [1e-8] * 3)
        estimator.initialise(0.0, flight["q"][0], cov=cov)
        worst = 0.0
        for i in range(1, len(flight["t"])):
            linear = flight["accel_ned"][i] if aided else None
            estimate = estimator.update(
                flight["t"][i], flight["gyro"][i], flight["accel"][i], None, linear
            )
            if flight["t"][i] > 20.0:
                est = Rotation.from_quat(estimate.q[[1, 2, 3, 0]])
                true = Rotation.from_quat(flight["q"][i, [1, 2, 3, 0]])
                tilt = np.linalg.norm((est * true.inv()).as_rotvec()[:2])
                worst = max(worst, math.degrees(tilt))
        if aided:
            assert worst < bound
        else:  # the bank the accelerometer cannot see without it
            assert worst > bound


def test_unknown_heading_leaves_the_sample_unaided() -> None:
    # heading σ beyond aided_max_heading_sigma: the world-frame acceleration is not used
    flight = _coordinated_turn(6.0)
    estimator = Estimator(EstimatorConfig())
    cov = np.diag([1e-4, 1e-4, math.radians(30.0) ** 2, 1e-8, 1e-8, 1e-8])
    estimator.initialise(0.0, flight["q"][0], cov=cov)
    estimate = estimator.update(
        flight["t"][1], flight["gyro"][1], flight["accel"][1], None, [1.0, 0.0, 0.0]
    )
    assert not estimate.flags & StepFlags.ACCEL_AIDED


def test_online_and_batch_agree_with_aiding() -> None:
    import mavest

    flight = _coordinated_turn(20.0, seed=2)
    linear = flight["accel_ned"].copy()
    linear[::7] = np.nan  # some samples without
    batch = mavest.estimate(flight["t"], flight["gyro"], flight["accel"], linear_accel=linear)
    estimator = Estimator()
    for i in range(len(flight["t"])):
        online = estimator.update(
            flight["t"][i], flight["gyro"][i], flight["accel"][i], None, linear[i]
        )
    assert np.array_equal(online.q, batch.q[-1])
    assert np.array_equal(online.cov, batch.cov[-1])


def _position(t: float, v: tuple[float, float, float]) -> tuple[int, int, int, int]:
    """A GLOBAL_POSITION_INT's vx, vy, vz (cm/s) and time_boot_ms."""
    return round(v[0] * 100), round(v[1] * 100), round(v[2] * 100), round(t * 1000)


def test_gps_acceleration_differences_velocity_reports() -> None:
    gps = GpsAcceleration()
    gps.on_fix(3, 0.0)
    gps.on_velocity_report(*_position(0.0, (10.0, 0.0, 0.0)), 0.0)
    assert gps.at(0.05) is None  # one report: no difference yet
    gps.on_velocity_report(*_position(0.1, (10.5, -0.2, 0.1)), 0.1)
    assert gps.at(0.15) == pytest.approx((5.0, -2.0, 1.0))
    assert gps.at(0.1 + 0.6) is None  # stale
    assert gps.at(2.5) is None  # and the fix too


def test_gps_acceleration_needs_a_fix_and_sane_reports() -> None:
    gps = GpsAcceleration()
    gps.on_fix(1, 0.0)  # no fix
    gps.on_velocity_report(*_position(0.0, (10.0, 0.0, 0.0)), 0.0)
    gps.on_velocity_report(*_position(0.1, (10.5, 0.0, 0.0)), 0.1)
    assert gps.at(0.1) is None
    gps.on_fix(3, 0.1)
    assert gps.at(0.1) == pytest.approx((5.0, 0.0, 0.0))
    gps.on_velocity_report(*_position(0.2, (60.0, 0.0, 0.0)), 0.2)  # 495 m/s²: a glitch
    assert gps.glitches == 1
    assert gps.at(0.2) == pytest.approx((5.0, 0.0, 0.0))  # the last good one
    gps.on_velocity_report(*_position(2.0, (60.0, 0.0, 0.0)), 2.0)  # 1.8 s apart: not differenced
    gps.on_fix(3, 2.0)
    assert gps.at(2.0) is None


def test_gps_acceleration_for_many_samples_is_at_sample_by_sample() -> None:
    """The replay's array form against GpsAcceleration.at, each sample with its own state
    (some before any difference, some stale, some before their fix or acceleration)."""
    rng = np.random.default_rng(7)
    n = 2000
    t = rng.uniform(0.0, 10.0, n)
    accel_t = t - rng.choice([-0.1, 0.0, 0.2, 0.5, 0.6, 3.0], n)  # some at the limit
    fix_t = t - rng.choice([-0.5, 0.0, 1.0, 2.0, 2.5], n)
    accel = rng.normal(0.0, 3.0, (n, 3))
    accel[rng.random(n) < 0.2] = math.nan  # no difference yet
    expected = np.full((n, 3), math.nan)
    for i in range(n):
        gps = GpsAcceleration(
            accel=None if math.isnan(accel[i, 0]) else tuple(accel[i].tolist()),  # type: ignore[arg-type]
            accel_t=float(accel_t[i]),
            fix_t=float(fix_t[i]),
        )
        known = gps.at(float(t[i]))
        if known is not None:
            expected[i] = known
    ours = gps_acceleration_at(accel, accel_t, fix_t, t)
    np.testing.assert_array_equal(ours, expected)
    assert 0.2 * n < np.count_nonzero(~np.isnan(expected[:, 0])) < 0.8 * n


def test_freshness_decides_alike_on_one_sample_and_on_arrays() -> None:
    """The live path asks for one sample's time, the replay for a block's: the same
    verdicts, a bool for one, at and around each limit (and with nothing known yet)."""
    ages = [-1e-9, 0.0, 0.3, GPS_MAX_AGE, GPS_MAX_AGE + 1e-9, 1.0, 2.0, 2.0 + 1e-9, math.inf]
    t = 10.0
    cases = [(t, t - a, t - f) for a in ages for f in ages]
    for now, accel_t, fix_t in cases:
        one = gps_fresh(now, accel_t, fix_t)
        expected = 0.0 <= now - accel_t <= GPS_MAX_AGE and 0.0 <= now - fix_t <= GPS_FIX_MAX_AGE
        assert type(one) is bool and one == expected
        one = airspeed_fresh(now, fix_t)
        assert type(one) is bool and one == (0.0 <= now - fix_t <= AIRSPEED_MAX_AGE)
    now, accel_t, fix_t = (np.array(column) for column in zip(*cases, strict=True))
    assert gps_fresh(now, accel_t, fix_t).tolist() == [gps_fresh(*case) for case in cases]
    assert airspeed_fresh(now, fix_t).tolist() == [airspeed_fresh(c[0], c[2]) for c in cases]


def test_a_vehicle_follows_its_gps_and_airspeed_messages_by_their_fields() -> None:
    """Pipeline and replay hand a vehicle the same fields (AidingFields, from a message
    or from the replay's decoded columns): each message goes where it belongs, at the
    vehicle's time, and none before it has one."""
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    messages = [
        mav.gps_raw_int_encode(0, 3, 0, 0, 0, 0, 0, 0, 0, 10),
        mav.global_position_int_encode(1000, 0, 0, 0, 0, 1000, 0, 0, 0),
        mav.global_position_int_encode(1100, 0, 0, 0, 0, 1050, -20, 10, 0),
        mav.vfr_hud_encode(21.5, 20.0, 90, 50, 100.0, 0.0),
    ]
    vehicle = Vehicle(1, 1)
    untimed = Vehicle(1, 1)
    expected = GpsAcceleration()
    for k, message in enumerate(messages):
        fields = AidingFields.of(MAVLink(None).decode(bytearray(message.pack(mav))))
        vehicle.follow(fields, 0.1 * k)
        untimed.follow(fields, None)
    expected.on_fix(3, 0.0)
    expected.on_velocity_report(1000, 0, 0, 1000, 0.1)
    expected.on_velocity_report(1050, -20, 10, 1100, 0.2)
    assert vehicle.gps == expected and vehicle.gps.at(0.25) == pytest.approx((5.0, -2.0, 1.0))
    assert (vehicle.airspeed, vehicle.airspeed_t) == (21.5, pytest.approx(0.3))
    assert untimed == Vehicle(1, 1)
