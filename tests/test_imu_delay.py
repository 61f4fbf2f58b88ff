"""The IMU's delay (``imu_delay``): the filter runs on the samples as they are, and the
attitude each estimate reports is its own carried forward by the sample's rate over the
delay, the attitude at the sample's time stamp (docs/design.md#the-imus-delay)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mavest
from mavest import Estimator, EstimatorConfig, smooth
from mavest.estimator import smoother
from mavest.estimator.config import ConfigError
from mavest.estimator.frames import lead
from mavest.estimator.reference import reference_estimate
from mavest.evaluation.metrics import attitude_errors
from mavest.sim import ImuNoise, Motion, simulate

RATE = 200.0
LAG = 4  # samples: 20 ms
DELAY = LAG / RATE


@pytest.fixture(scope="module")
def delayed():
    """A flight of quick oscillations (periods 1–3 s, rates up to about 2 rad/s) whose IMU
    samples each measure the motion ``LAG`` samples before their time stamp."""
    motion = Motion(min_period=1.0, max_period=3.0, velocity_sigma=0.2)
    flight = simulate(40.0, RATE, motion=motion, seed=5)
    gyro = np.concatenate([np.repeat(flight.gyro[:1], LAG, axis=0), flight.gyro[:-LAG]])
    accel = np.concatenate([np.repeat(flight.accel[:1], LAG, axis=0), flight.accel[:-LAG]])
    return flight, gyro, accel


def _rms_deg(q: np.ndarray, truth: np.ndarray) -> float:
    errors = attitude_errors(q[200:], truth[200:])  # (after the first second)
    return math.degrees(float(np.sqrt(np.mean(errors.inclination**2))))


def test_it_is_scipys_rotation_carried_forward() -> None:
    """q ⊗ Exp((ω − b) τ), against scipy's composition of rotations; no delay, or a rate
    that is not a measurement (not finite, beyond any gyro's range), reports q itself."""
    rng = np.random.default_rng(7)
    q = np.ascontiguousarray(Rotation.random(100, random_state=3).as_quat()[:, [3, 0, 1, 2]])
    gyro = rng.normal(0.0, 3.0, (100, 3))
    bias = rng.normal(0.0, 0.05, (100, 3))
    led = lead(q, gyro, bias, 0.02)
    turned = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_rotvec((gyro - bias) * 0.02)
    expected = turned.as_quat()[:, [3, 0, 1, 2]]
    expected *= np.sign(np.sum(expected * led, axis=1))[:, None]
    np.testing.assert_allclose(led, expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(lead(q, gyro, bias, 0.0), q)
    gyro[3] = np.nan
    gyro[4, 1] = 1e6
    carried = lead(q, gyro, bias, 0.02)
    np.testing.assert_array_equal(carried[3:5], q[3:5])


def test_a_turn_beyond_half_a_turn_stays_on_the_side_of_q() -> None:
    """40 rad/s over 0.1 s turns by 4 rad, beyond π: the carried quaternion is scipy's
    rotation on q's side of the double cover, the side the filter and its reference keep."""
    q = np.array([[0.9, 0.1, -0.2, 0.3]])
    q /= np.linalg.norm(q)
    gyro = np.array([[0.0, 0.0, 40.0]])
    led = lead(q, gyro, np.zeros((1, 3)), 0.1)
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_rotvec([0, 0, 4.0])
    expected_q = expected.as_quat()[:, [3, 0, 1, 2]]
    assert float(led[0] @ q[0]) > 0.0
    np.testing.assert_allclose(np.abs(led[0] @ expected_q[0]), 1.0, rtol=0, atol=1e-14)


def test_a_skipped_sample_reports_the_estimate_before_it(delayed) -> None:
    """A sample the step skips (a corrupt gyro beyond any gyro's range, a time stamp
    going back) reports the estimate before it as it was reported: not turned by a
    million rad/s over the delay, nor jumping back to the filter's own attitude, nor
    carried by the skipped sample's rate. The placeholder before the filter starts is
    the identity, as without a delay."""
    flight, gyro, accel = delayed
    t, gyro, accel = flight.t[:400].copy(), gyro[:400].copy(), accel[:400].copy()
    gyro[300] = (1e6, -1e6, 0.0)
    t[350] = t[340]  # back in time
    gyro[350] = (3.0, -2.0, 1.0)
    accel[:5] = 0.0  # nothing to align on yet
    gyro[:5] = (1.0, 2.0, 3.0)
    config = EstimatorConfig(imu_delay=DELAY)
    out = mavest.estimate(t, gyro, accel, config=config)
    assert out.flags[300] & mavest.StepFlags.GYRO_INVALID
    assert out.flags[350] & mavest.StepFlags.TIME_NOT_INCREASING
    np.testing.assert_array_equal(out.q[300], out.q[299])
    np.testing.assert_array_equal(out.q[350], out.q[349])
    assert np.all(out.flags[:5] & mavest.StepFlags.NOT_INITIALISED)
    np.testing.assert_array_equal(out.q[:5], np.tile([1.0, 0.0, 0.0, 0.0], (5, 1)))
    # the estimates of steps taken are the filter's own carried by their own rate
    state = lead(out.q[301:302], gyro[301:302], out.bias[301:302], -DELAY)
    unled = mavest.estimate(t, gyro, accel, config=config.replace(imu_delay=0.0))
    np.testing.assert_allclose(state[0], unled.q[301], rtol=0, atol=1e-15)


def test_a_delayed_imu_is_reported_at_its_time_stamps(delayed) -> None:
    """Told the delay, the estimate is as near the truth at the time stamps as it is with
    an IMU without one (1.05° against 1.03°; 1.61° not told); its bias and covariance are
    the filter's, unchanged."""
    flight, gyro, accel = delayed
    undelayed = _rms_deg(mavest.estimate(flight.t, flight.gyro, flight.accel).q, flight.q_true)
    plain = mavest.estimate(flight.t, gyro, accel)
    told = mavest.estimate(flight.t, gyro, accel, config=EstimatorConfig(imu_delay=DELAY))
    before, after = _rms_deg(plain.q, flight.q_true), _rms_deg(told.q, flight.q_true)
    assert after < 1.05 * undelayed < 0.75 * before, (undelayed, before, after)
    np.testing.assert_array_equal(told.bias, plain.bias)
    np.testing.assert_array_equal(told.cov, plain.cov)
    np.testing.assert_allclose(told.q, lead(plain.q, gyro, plain.bias, DELAY), rtol=0, atol=0)


def test_online_and_batch_report_the_same(delayed) -> None:
    flight, gyro, accel = delayed
    config = EstimatorConfig(imu_delay=DELAY)
    batch = mavest.estimate(flight.t[:600], gyro[:600], accel[:600], config=config)
    online = Estimator(config)
    q = np.array([online.update(flight.t[i], gyro[i], accel[i]).q for i in range(600)])
    np.testing.assert_array_equal(q, batch.q)
    # the filter's own attitude, what initialise() and snapshots hold, is not carried
    plain = mavest.estimate(flight.t[:600], gyro[:600], accel[:600])
    np.testing.assert_array_equal(online.q, plain.q[-1])


def test_the_reference_filter_reports_it_alike(delayed) -> None:
    """The slow twin carries its attitude forward with scipy's rotations: the same to
    rounding over the low-pass's first time constant (tests/test_reference.py)."""
    flight, gyro, accel = delayed
    config = EstimatorConfig(update_rate=0.0, imu_delay=DELAY)
    k = slice(0, int(RATE * config.accel_lowpass_time))
    compiled = mavest.estimate(flight.t[k], gyro[k], accel[k], config=config)
    reference = reference_estimate(flight.t[k], gyro[k], accel[k], None, config)
    np.testing.assert_allclose(reference.q, compiled.q, rtol=0, atol=1e-11)
    unled = reference_estimate(flight.t[k], gyro[k], accel[k], None, config.replace(imu_delay=0))
    assert np.abs(unled.q - compiled.q).max() > 1e-3  # (the delay moves it: 20 ms at 2 rad/s)


def test_the_smoother_fuses_the_filters_attitudes_and_reports_them_carried(delayed) -> None:
    """Both passes' states lag the time stamps alike: the smoother fuses them there and
    carries the smoothed attitude forward once, with the smoothed bias: what carrying the
    plain smoother's forward gives (to the rounding of taking the forward pass's attitude
    back, which the passes' gates may amplify: median 2e-5), as near the truth as with an
    IMU without a delay (0.51° against 0.48°; 1.33° not told) and nearer than the filter."""
    flight, gyro, accel = delayed
    config = EstimatorConfig(imu_delay=DELAY)
    plain = smooth(flight.t, gyro, accel)
    told = smooth(flight.t, gyro, accel, config=config)
    carried = lead(plain.q, gyro, plain.bias, DELAY)
    assert np.median(np.abs(told.q - carried)) < 1e-4
    after = _rms_deg(told.q, flight.q_true)
    assert after == pytest.approx(_rms_deg(carried, flight.q_true), rel=0.01)
    undelayed = _rms_deg(smooth(flight.t, flight.gyro, flight.accel).q, flight.q_true)
    assert after < 1.1 * undelayed < 0.5 * _rms_deg(plain.q, flight.q_true)
    filtered = mavest.estimate(flight.t, gyro, accel, config=config)
    assert after < 0.6 * _rms_deg(filtered.q, flight.q_true)


def test_the_smoother_gives_back_what_it_does_not_fuse_bit_for_bit() -> None:
    """Rows without an estimate (the placeholder before the filter starts), which the
    smoother does not fuse, are the filter's as reported, every bit: not taken back by
    the delay and carried forward again."""
    t = np.arange(400) / 200.0
    gyro = np.tile([0.3, -0.2, 2.0], (400, 1))
    accel = np.tile([0.0, 0.0, -9.80665], (400, 1))
    accel[:100] = 0.0  # nothing to start on
    config = EstimatorConfig(imu_delay=DELAY, smooth_accel_time=0.0)
    filtered = mavest.estimate(t, gyro, accel, config=config)
    smoothed = smooth(t, gyro, accel, config=config)
    assert np.all(filtered.flags[:100] & mavest.StepFlags.NOT_INITIALISED)
    np.testing.assert_array_equal(smoothed.q[:100], filtered.q[:100])
    assert np.abs(smoothed.q[100:] - filtered.q[100:]).max() > 0.0  # (the rest is fused)


def test_rows_next_to_skipped_samples_are_given_back_as_reported() -> None:
    """The samples beside a skipped one (a NaN gyro, a time stamp going back) have an
    estimate the smoother does not fuse: theirs as the filter reported it, every bit,
    not taken back by the delay and carried forward again (which moves it by rounding);
    every other row moves by far more than that."""
    data = simulate(20.0, 100.0, seed=13)
    t, gyro = data.t.copy(), data.gyro.copy()
    gyro[300:305] = np.nan
    t[1200] = t[1100]
    config = EstimatorConfig(imu_delay=DELAY, smooth_accel_time=0.0)
    filtered = mavest.estimate(t, gyro, data.accel, data.mag, config)
    smoothed = smooth(t, gyro, data.accel, data.mag, config)
    moved = np.abs(smoothed.q - filtered.q).max(axis=1)
    assert np.all((moved == 0.0) | (moved > 1e-9))
    held = np.flatnonzero((filtered.flags & smoother.NO_ESTIMATE) != 0)
    given_back = np.flatnonzero(moved == 0.0)
    assert set(held) < set(given_back)  # (and some with an estimate: 298, 299, …)


def test_the_reference_filter_refuses_a_clipped_first_sample() -> None:
    """A clipped gyro is outside the slow twin's scope on its first sample too, where it
    would otherwise carry its first attitude forward by a corrupt rate."""
    with pytest.raises(ValueError, match="clipped"):
        reference_estimate(
            np.array([0.0, 0.01]),
            np.array([[1e6, 0.0, 0.0], [0.0, 0.0, 0.0]]),
            np.tile([0.0, 0.0, -9.80665], (2, 1)),
            None,
            EstimatorConfig(imu_delay=DELAY),
        )


@pytest.mark.parametrize("value", [-0.01, math.nan, math.inf])
def test_the_simulator_refuses_an_impossible_delay(value: float) -> None:
    with pytest.raises(ValueError, match="imu_delay"):
        ImuNoise(imu_delay=value)


@pytest.mark.parametrize("value", [-0.001, 0.06, math.inf, math.nan])
def test_an_impossible_delay_is_refused(value: float) -> None:
    with pytest.raises(ConfigError, match="imu_delay"):
        EstimatorConfig(imu_delay=value)


def test_it_is_read_from_a_config_file(tmp_path) -> None:
    path = tmp_path / "delayed.toml"
    path.write_text("[estimator]\nimu_delay = 0.0025\n")
    assert EstimatorConfig.from_toml(path).imu_delay == 0.0025


def test_the_simulator_flies_a_delayed_imu() -> None:
    """``ImuNoise.imu_delay``: the same samples, the truth τ later (scipy's rotation of
    the midpoint rate), so that a Monte Carlo of a configuration that sets the delay
    flies what it claims: told, the filter is as near that truth as without a delay."""
    motion = Motion(min_period=1.0, max_period=3.0)
    noise = ImuNoise.matching(EstimatorConfig(imu_delay=DELAY))
    assert noise.imu_delay == DELAY
    plain = simulate(20.0, RATE, motion=motion, seed=2)
    delayed = simulate(20.0, RATE, noise=noise, motion=motion, seed=2)
    np.testing.assert_array_equal(delayed.gyro, plain.gyro)
    np.testing.assert_array_equal(delayed.accel, plain.accel)
    moved = attitude_errors(delayed.q_true, plain.q_true)
    turned = np.degrees(np.sqrt(moved.inclination**2 + moved.heading**2))
    assert 0.3 < turned.max() < 5.0  # (20 ms at up to 2 rad/s)
    told = mavest.estimate(
        delayed.t, delayed.gyro, delayed.accel, config=EstimatorConfig(imu_delay=DELAY)
    )
    undelayed = _rms_deg(mavest.estimate(plain.t, plain.gyro, plain.accel).q, plain.q_true)
    assert _rms_deg(told.q, delayed.q_true) < 1.05 * undelayed
    not_told = mavest.estimate(delayed.t, delayed.gyro, delayed.accel)
    assert _rms_deg(not_told.q, delayed.q_true) > 1.3 * undelayed


def test_the_tool_finds_a_simulated_delay(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """tools/imu_delay.py on two simulated trials in BROAD's format whose IMU lags the
    truth by 2 ms: every filter's error is least carried forward by 2 ms."""
    h5py = pytest.importorskip("h5py", reason="h5py (dev extra) is needed to write BROAD")
    pytest.importorskip("vqf", reason="vqf (dev extra) is the peer the tool reports")
    from tool_module import load_tool

    from mavest.datasets import DATA_ENV_VAR
    from mavest.datasets.broad import C_IMU_FRD, C_NED_ENU

    (tmp_path / "broad").mkdir()
    noise = ImuNoise.matching(EstimatorConfig(imu_delay=0.002))
    for seed, name in enumerate(("01_simulated_a", "02_simulated_b")):
        flight = simulate(
            60.0, RATE, noise=noise, motion=Motion(min_period=1.0, max_period=3.0), seed=seed
        )
        truth = Rotation.from_quat(flight.q_true[:, [1, 2, 3, 0]]).as_matrix()
        optical = Rotation.from_matrix(C_NED_ENU.T @ truth @ C_IMU_FRD.T).as_quat()
        with h5py.File(tmp_path / "broad" / f"{name}.hdf5", "w") as f:
            f.attrs["sampling_rate"] = RATE
            f["imu_gyr"] = flight.gyro @ C_IMU_FRD.T
            f["imu_acc"] = flight.accel @ C_IMU_FRD.T
            f["imu_mag"] = flight.mag @ C_IMU_FRD.T
            f["opt_quat"] = optical[:, [3, 0, 1, 2]]
            f["movement"] = flight.t > 5.0
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    assert load_tool("imu_delay").main(["--quick"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| 2.0 ms |"))
    assert row.count("**") == 8, out  # (each of the four filters' least)
