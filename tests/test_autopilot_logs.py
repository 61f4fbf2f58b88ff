"""Autopilot onboard logs: loaders, units and frames, scoring, mavest against the autopilot.

The table over all logs is tools/evidence.py's (tests/test_evidence_tool.py).

The logs are third-party files in the shared data folder; the tests that need them skip,
naming MAVEST_DATA, when it is absent (a fresh clone has none). The bounds below were
measured on the local copies (numbers in each test) and carry a margin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mavest import estimate
from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.datasets.autopilot_logs import (
    DATAFLASH_LOG171,
    ULOG_REAL,
    ULOG_SIMULATOR,
    AutopilotLog,
    load_dataflash,
    load_ulog,
    log_path,
)
from mavest.evaluation.logs import Segment, gravity_at_rest, score, score_segments, slerp_onto

G0 = 9.80665


def shared_log(relative: str) -> Path:
    """The shared log file, or a skip naming MAVEST_DATA."""
    root = data_root()
    if root is None or not (root / relative).is_file():
        pytest.skip(
            f"autopilot log {relative} not found: set {DATA_ENV_VAR} to a folder containing "
            "dataflash/ and ulog/ (default: ../shared/data beside the project)"
        )
    return log_path(relative)


@pytest.fixture(scope="module")
def log171() -> AutopilotLog:
    return load_dataflash(shared_log(DATAFLASH_LOG171))


@pytest.fixture(scope="module")
def px4_real() -> AutopilotLog:
    pytest.importorskip("pyulog", reason="pyulog (dev extra) is needed to read ULog files")
    return load_ulog(shared_log(ULOG_REAL))


@pytest.fixture(scope="module")
def px4_simulator() -> AutopilotLog:
    pytest.importorskip("pyulog", reason="pyulog (dev extra) is needed to read ULog files")
    return load_ulog(shared_log(ULOG_SIMULATOR))


def window(log: AutopilotLog, start: float, end: float) -> np.ndarray:
    return (log.t >= start) & (log.t < end)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b))))


def inclination_rmse(log: AutopilotLog, q: np.ndarray, start: float, end: float) -> float:
    """Inclination RMSE (°) of q (at log.t) slerped onto the reference times in [start, end)."""
    inside, q_at_ref = slerp_onto(log.t, q, log.reference_t)
    times = log.reference_t[inside]
    chosen = (times >= start) & (times < end)
    return score(q_at_ref[chosen], log.reference_q[inside][chosen]).inclination


# --------------------------------------------------------------------------
# Without data: errors, the scoring helpers, the tool's exit code
# --------------------------------------------------------------------------


def test_missing_files_raise_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_dataflash(tmp_path / "absent.bin")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_ulog(tmp_path / "absent.ulg")


def test_wrong_files_raise_value_error(tmp_path: Path) -> None:
    not_dataflash = tmp_path / "noise.bin"
    not_dataflash.write_bytes(b"\x00\x01 not a log " * 100)
    with pytest.raises(ValueError, match="not an ArduPilot dataflash log"):
        load_dataflash(not_dataflash)
    wrong_suffix = tmp_path / "log.ulg"
    wrong_suffix.write_bytes(b"ULog")
    with pytest.raises(ValueError, match=r"expected an ArduPilot dataflash log \(\.bin\)"):
        load_dataflash(wrong_suffix)
    with pytest.raises(ValueError, match="imu_instance"):
        load_dataflash(not_dataflash, imu_instance=3)
    pytest.importorskip("pyulog", reason="pyulog (dev extra) is needed to read ULog files")
    not_ulog = tmp_path / "noise.ulg"
    not_ulog.write_bytes(b"\x00\x01 not a log " * 100)
    with pytest.raises(ValueError, match="not a readable ULog file"):
        load_ulog(not_ulog)


def test_slerp_and_score_on_known_rotations() -> None:
    # Roll 0° at t = 0 and 10° at t = 1: slerp gives 5° at t = 0.5; t = 2 is outside.
    q = Rotation.from_euler("x", [[0.0], [10.0]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    inside, q_mid = slerp_onto(np.array([0.0, 1.0]), q, np.array([0.5, 2.0]))
    assert inside.tolist() == [True, False]
    reference = Rotation.from_euler("x", [[5.0]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    s = score(q_mid, reference)
    assert s.n == 1 and s.roll == pytest.approx(0.0, abs=1e-9)
    # A 2° pitch error with any heading: pitch and inclination 2°, roll 0°.
    est = Rotation.from_euler("ZYX", [[30.0, 2.0, 0.0]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    ref = Rotation.from_euler("ZYX", [[30.0, 0.0, 0.0]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    s = score(est, ref)
    assert (s.roll, s.pitch, s.inclination) == pytest.approx((0.0, 2.0, 2.0), abs=1e-9)


def test_segments_share_the_reference_times_all_candidates_cover() -> None:
    # A constant 1° roll error; one candidate starts at 1 s, so both are scored from 1 s.
    reference_t = np.arange(0.0, 4.0, 0.5)
    level = np.tile([1.0, 0.0, 0.0, 0.0], (len(reference_t), 1))
    rolled = Rotation.from_euler("x", 1.0, degrees=True).as_quat()[[3, 0, 1, 2]]
    candidates = {
        "whole": (np.arange(0.0, 4.0, 0.1), np.tile(rolled, (40, 1))),
        "late": (np.arange(1.0, 4.0, 0.1), np.tile(rolled, (30, 1))),
    }
    scores = score_segments(
        candidates, reference_t, level, [Segment("early", 0.0, 2.0), Segment("all", 0, np.inf)]
    )
    assert scores["early"]["whole"].n == scores["early"]["late"].n == 2  # 1.0 and 1.5 s
    assert scores["all"]["late"].n == 6  # 1.0 … 3.5 s
    assert scores["all"]["whole"].inclination == pytest.approx(1.0, abs=1e-9)
    assert Segment("crash", 200.0, np.inf).describe(242.6) == "crash 200–243 s"


def test_gravity_at_rest_is_the_still_accelerometers_tilt_and_only_there() -> None:
    """A vehicle that rests at one attitude (2 s), turns (1 s), rests at another (2 s),
    is shaken in place (1 s) and accelerates level (2 s), sampled at 100 Hz with noise:
    the reference has one window per still second, with scipy's roll and pitch of the
    resting attitude (any heading) within 0.1° (the mean noise: 0.03° σ)."""
    rng = np.random.default_rng(7)
    rate, g = 100.0, 9.80665
    first = Rotation.from_euler("ZYX", [40.0, -8.0, 175.0], degrees=True)  # upside down
    second = Rotation.from_euler("ZYX", [-120.0, 12.0, 5.0], degrees=True)
    t = np.arange(0.0, 8.0, 1.0 / rate)
    gyro = rng.normal(0.0, np.radians(0.3), (t.size, 3))
    accel = rng.normal(0.0, 0.05, (t.size, 3))
    # the specific force at rest: −g along the world vertical, in the body
    accel[t < 2.0] += first.inv().apply([0.0, 0.0, -g])
    turning = (t >= 2.0) & (t < 3.0)
    gyro[turning] += np.radians([0.0, 0.0, 90.0])
    accel[turning] += first.inv().apply([0.0, 0.0, -g])
    accel[t >= 3.0] += second.inv().apply([0.0, 0.0, -g])
    shaken = (t >= 5.0) & (t < 6.0)
    gyro[shaken] += np.radians(20.0) * np.sin(2 * np.pi * 30.0 * t[shaken])[:, None]
    accelerating = t >= 6.0
    accel[accelerating] += second.inv().apply([5.0, 0.0, 0.0])  # 5 m/s² north

    times, q = gravity_at_rest(t, gyro, accel, [Segment("all", 0.0, np.inf)])
    assert np.allclose(times, [0.495, 1.495, 3.495, 4.495], atol=0.01)
    expected = [first, first, second, second]
    for quaternion, truth in zip(q, expected, strict=True):
        pitch, roll = np.degrees(Rotation.from_quat(quaternion[[1, 2, 3, 0]]).as_euler("ZYX")[1:])
        truth_pitch, truth_roll = truth.as_euler("ZYX", degrees=True)[1:]
        assert (roll - truth_roll + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.1)
        assert pitch == pytest.approx(truth_pitch, abs=0.1)
    # only inside the spans given
    times, _ = gravity_at_rest(t, gyro, accel, [Segment("second rest", 3.0, 5.0)])
    assert times.size == 2 and np.all((times > 3.0) & (times < 5.0))


# --------------------------------------------------------------------------
# Loaders on the shared logs: counts, rates, units, frames, raw equality
# --------------------------------------------------------------------------


def test_log171_counts_rates_and_time_base(log171: AutopilotLog) -> None:
    assert len(log171) == 11916 and log171.gyro.shape == log171.accel.shape == (11916, 3)
    assert log171.rate == pytest.approx(50.0, abs=0.01)
    assert log171.t[0] == 0.0 and np.all(np.diff(log171.t) > 0.0)
    assert log171.duration == pytest.approx(242.6, abs=0.1)
    assert log171.boot_time == pytest.approx(11.46)  # TimeMS (ms) of the first IMU sample
    assert len(log171.reference_t) == 2383  # ATT at 10 Hz
    assert np.median(np.diff(log171.reference_t)) == pytest.approx(0.1, abs=0.002)
    assert log171.truth_t is None and log171.reference_source == "ATT + AHRS_TRIM"
    assert any("IMU instance 0" in note for note in log171.notes)


def test_log171_units_and_frame_at_rest(log171: AutopilotLog) -> None:
    # 20–55 s (log time) the vehicle stands still (gyro RMS 0.0012 rad/s measured).
    rest = window(log171, 20.0, 55.0)
    norm = np.linalg.norm(log171.accel[rest], axis=1)
    # Measured: mean 9.587 m/s², 2.2 % below g (the stored calibration; IMU2 and IMU3
    # read 9.41 and 9.13), spread 0.011. FRD: gravity reads as −z.
    assert np.mean(norm) == pytest.approx(G0, abs=0.35)
    assert np.std(norm) < 0.05
    assert np.mean(log171.accel[rest, 2]) < -9.0
    assert np.sqrt(np.mean(np.sum(log171.gyro[rest] ** 2, axis=1))) < 0.01  # rad/s, not °/s


def gravity_direction_error_deg(log: AutopilotLog, start: float, end: float) -> float:
    """Angle between the mean accelerometer and the reference's predicted −g direction."""
    at_rest = window(log, start, end)
    chosen = (log.reference_t >= start) & (log.reference_t < end)
    body_to_ned = Rotation.from_quat(log.reference_q[chosen][:, [1, 2, 3, 0]])
    predicted = body_to_ned.inv().apply([0.0, 0.0, -1.0]).mean(axis=0)
    return angle_deg(log.accel[at_rest].mean(axis=0), predicted)


def test_log171_ahrs_trim_puts_att_in_the_imu_frame(log171: AutopilotLog) -> None:
    # Measured at rest: 0.06° with AHRS_TRIM added back to ATT, 1.27° without.
    assert gravity_direction_error_deg(log171, 20.0, 55.0) < 0.2
    untrimmed = load_dataflash(shared_log(DATAFLASH_LOG171), apply_ahrs_trim=False)
    assert gravity_direction_error_deg(untrimmed, 20.0, 55.0) > 1.0


def test_log171_other_references(log171: AutopilotLog) -> None:
    sources = [reference.source for reference in log171.other_references]
    assert sources == ["EKF1 + AHRS_TRIM", "AHR2 + AHRS_TRIM"]
    ekf1, ahr2 = log171.other_references
    # EKF1's first 24 rows (before 2.44 s) hold no attitude yet and are dropped.
    assert len(ekf1.t) == 2383 - 24 and ekf1.t[0] == pytest.approx(2.442)
    # From 10 s on ArduCopter 3.3's ATT is the EKF's output: EKF1 equals it (logged 0.01°).
    later = log171.reference_t >= 10.0
    _, ekf1_at_att = slerp_onto(ekf1.t, ekf1.q, log171.reference_t[later])
    assert score(ekf1_at_att, log171.reference_q[later]).inclination < 0.01
    # AHR2 (DCM) is independent but in the same frame: at rest the accelerometer's gravity
    # is 0.20° off its prediction (1.15° without the trim).
    as_main = AutopilotLog(**{**log171.__dict__, "reference_t": ahr2.t, "reference_q": ahr2.q})
    assert gravity_direction_error_deg(as_main, 20.0, 55.0) < 0.3


def test_log171_matches_pymavlink_raw_reading(log171: AutopilotLog) -> None:
    from pymavlink import mavutil

    reader = mavutil.mavlink_connection(str(shared_log(DATAFLASH_LOG171)))
    imu = [reader.recv_match(type="IMU") for _ in range(5)]
    for i, message in enumerate(imu):
        assert log171.t[i] == pytest.approx(message.TimeMS * 1e-3 - log171.boot_time, abs=1e-9)
        np.testing.assert_array_equal(log171.gyro[i], [message.GyrX, message.GyrY, message.GyrZ])
        np.testing.assert_array_equal(log171.accel[i], [message.AccX, message.AccY, message.AccZ])
    # DFReader returns None when recv_match's type changes mid-file (pymavlink 2.4.50):
    # start again from the beginning for ATT.
    reader.rewind()
    att = [reader.recv_match(type="ATT") for _ in range(3)]
    untrimmed = load_dataflash(shared_log(DATAFLASH_LOG171), apply_ahrs_trim=False)
    for i, message in enumerate(att):
        expected = Rotation.from_euler(
            "ZYX", [message.Yaw, message.Pitch, message.Roll], degrees=True
        )
        got = Rotation.from_quat(untrimmed.reference_q[i, [1, 2, 3, 0]])
        assert (expected.inv() * got).magnitude() < 1e-9
        assert untrimmed.reference_t[i] == pytest.approx(
            message.TimeMS * 1e-3 - untrimmed.boot_time, abs=1e-9
        )


def test_px4_counts_rates_units_and_frame(
    px4_real: AutopilotLog, px4_simulator: AutopilotLog
) -> None:
    assert len(px4_real) == 17070 and px4_real.rate == pytest.approx(250.0, abs=0.5)
    assert len(px4_real.reference_t) == 6461  # vehicle_attitude, 94 Hz on average
    assert len(px4_real.reference_t) / px4_real.duration == pytest.approx(93.8, abs=0.5)
    assert px4_real.truth_t is None
    assert any("no vehicle_attitude_groundtruth" in note for note in px4_real.notes)
    assert len(px4_simulator) == 2028 and px4_simulator.truth_q is not None
    assert px4_simulator.truth_t is not None and len(px4_simulator.truth_t) == 1078
    # At rest: measured norm 9.704 (real board, 10 s to end) and 9.883 (simulator);
    # gravity along −z (FRD), and along the direction vehicle_attitude predicts
    # (measured 0.044° and 0.009°).
    for log, start, end in ((px4_real, 10.0, 69.0), (px4_simulator, 0.0, 11.0)):
        rest = window(log, start, end)
        assert np.mean(np.linalg.norm(log.accel[rest], axis=1)) == pytest.approx(G0, abs=0.2)
        assert np.mean(log.accel[rest, 2]) < -9.5
        assert gravity_direction_error_deg(log, start, end) < 0.15


def test_px4_matches_pyulog_raw_reading(px4_real: AutopilotLog) -> None:
    from pyulog import ULog

    raw = ULog(str(shared_log(ULOG_REAL)), ["sensor_combined", "vehicle_attitude"])
    sensors = raw.get_dataset("sensor_combined").data
    attitude = raw.get_dataset("vehicle_attitude").data
    t0 = int(sensors["timestamp"][0])
    for i in range(5):
        assert px4_real.t[i] == pytest.approx((int(sensors["timestamp"][i]) - t0) * 1e-6)
        for axis in range(3):
            assert px4_real.gyro[i, axis] == sensors[f"gyro_rad[{axis}]"][i]
            assert px4_real.accel[i, axis] == sensors[f"accelerometer_m_s2[{axis}]"][i]
        q = np.array([attitude[f"q[{k}]"][i] for k in range(4)], dtype=np.float64)
        np.testing.assert_allclose(px4_real.reference_q[i], q / np.linalg.norm(q), atol=1e-12)


# --------------------------------------------------------------------------
# mavest against the autopilot
# --------------------------------------------------------------------------


def test_mavest_on_log171_against_att(log171: AutopilotLog) -> None:
    q = estimate(log171.t, log171.gyro, log171.accel).q
    # Measured inclination RMSE: 0.10° over the quiet 20–60 s; 0.64° over the rest
    # segment 0–60 s (it includes the vehicle being handled at ~14–19 s and the start);
    # 4.99° in flight 60–200 s, where VQF gives 5.37° and Fusion 6.05°.
    assert inclination_rmse(log171, q, 20.0, 60.0) < 0.2
    assert inclination_rmse(log171, q, 0.0, 60.0) < 0.8
    assert inclination_rmse(log171, q, 60.0, 200.0) < 6.0


def test_mavest_on_log171_upside_down_against_the_resting_accelerometer(
    log171: AutopilotLog,
) -> None:
    """After the crash the copter lies upside down, still; the gyro clipped in the flip.
    Against the accelerometer's own gravity direction there (a reference no filter
    wrote) mavest is within 0.51° (it re-aligns once calm), where the autopilot's ATT
    is 8.9° off and VQF 11.8° (tools/evidence.py, same windows)."""
    violent = np.flatnonzero(np.linalg.norm(log171.gyro, axis=1) > np.radians(100.0))
    after_flip = Segment("upside down", float(log171.t[violent[-1]]), np.inf)
    still_t, still_q = gravity_at_rest(log171.t, log171.gyro, log171.accel, [after_flip])
    assert still_t.size >= 10  # 229.5 s to the end of the log
    q = estimate(log171.t, log171.gyro, log171.accel).q
    ours = score_segments({"mavest": (log171.t, q)}, still_t, still_q, [after_flip])
    autopilot = score_segments(
        {"ATT": (log171.reference_t, log171.reference_q)}, still_t, still_q, [after_flip]
    )
    assert ours["upside down"]["mavest"].inclination < 1.0
    assert autopilot["upside down"]["ATT"].inclination > 5.0
