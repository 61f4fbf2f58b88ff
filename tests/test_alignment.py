"""The accelerometer's alignment (``accel_alignment_sigma``): a tilt error no update
removes, added to the covariance every estimate reports and to nothing else."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mavest
from mavest import Estimator, EstimatorConfig, smooth
from mavest.estimator.config import ConfigError
from mavest.estimator.frames import add_alignment
from mavest.estimator.reference import reference_estimate
from mavest.evaluation.calibration import tilt_heading_errors, world_attitude_covariance
from mavest.sim import ImuNoise, Motion, simulate

SIGMA = math.radians(0.2)
WORLD_FLOOR = np.diag([SIGMA**2, SIGMA**2, 0.0])


@pytest.fixture(scope="module")
def flight():
    return simulate(20.0, 100.0, motion=Motion(velocity_sigma=0.5), seed=3)


def test_it_adds_to_the_world_tilt_in_either_error_frame() -> None:
    """diag(v, v, 0) in the world, whatever the attitude: the body-frame form (right
    error) turned into the world with scipy's rotation matrix gives the same."""
    rng = np.random.default_rng(1)
    q = Rotation.random(50, random_state=2).as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    q = np.ascontiguousarray(q)
    base = np.tile(np.eye(6) * 1e-4, (50, 1, 1)) + 1e-6 * rng.standard_normal((50, 6, 6))
    for right in (False, True):
        cov = base.copy()
        add_alignment(q, SIGMA**2, right, cov)
        added = cov - base
        R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # body → world
        world = R @ added[:, :3, :3] @ R.transpose(0, 2, 1) if right else added[:, :3, :3]
        np.testing.assert_allclose(world, np.broadcast_to(WORLD_FLOOR, world.shape), atol=1e-18)
        assert not added[:, 3:, :].any() and not added[:, :3, 3:].any()


@pytest.mark.parametrize("error", ["left", "right"])
def test_the_estimate_is_unchanged_and_its_covariance_gains_the_floor(flight, error) -> None:
    chart = {} if error == "left" else {"chart": "exp"}
    plain = EstimatorConfig(error=error, **chart)
    aligned = plain.replace(accel_alignment_sigma=SIGMA)
    a = mavest.estimate(flight.t, flight.gyro, flight.accel, config=plain)
    b = mavest.estimate(flight.t, flight.gyro, flight.accel, config=aligned)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.bias, b.bias)
    gained = world_attitude_covariance(b.q, b.cov[:, :3, :3], error) - world_attitude_covariance(
        a.q, a.cov[:, :3, :3], error
    )
    # (the right error's P turned into the world: rounding of its entries, ~1e-2 rad²)
    np.testing.assert_allclose(gained, np.broadcast_to(WORLD_FLOOR, gained.shape), atol=1e-16)
    # online, one sample at a time: the same
    online = Estimator(aligned)
    for i in range(flight.t.shape[0]):
        last = online.update(flight.t[i], flight.gyro[i], flight.accel[i])
    np.testing.assert_array_equal(last.cov, b.cov[-1])
    # the filter's own P, what initialise() takes, has none of it
    np.testing.assert_allclose(online.cov, a.cov[-1], rtol=0, atol=0)


def test_the_smoother_fuses_without_it_and_reports_it_once(flight) -> None:
    """The alignment is common to both passes: fused as two independent errors it would
    shrink; the smoothed covariance holds it once and the smoothed attitude does not
    depend on it."""
    plain = smooth(flight.t, flight.gyro, flight.accel)
    aligned = smooth(
        flight.t, flight.gyro, flight.accel, config=EstimatorConfig(accel_alignment_sigma=SIGMA)
    )
    np.testing.assert_allclose(aligned.q, plain.q, rtol=0, atol=1e-15)
    gained = aligned.cov[:, :3, :3] - plain.cov[:, :3, :3]
    np.testing.assert_allclose(gained, np.broadcast_to(WORLD_FLOOR, gained.shape), atol=1e-15)


def test_the_reference_filter_reports_it_alike(flight) -> None:
    """Over the low-pass's first time constant, where the two filters agree to rounding
    (tests/test_reference.py; later the flight's chaos amplifies the rounding)."""
    config = EstimatorConfig(update_rate=0.0, accel_alignment_sigma=SIGMA)
    compiled = mavest.estimate(flight.t, flight.gyro, flight.accel, config=config)
    reference = reference_estimate(flight.t, flight.gyro, flight.accel, None, config)
    k = slice(0, int(np.searchsorted(flight.t, flight.t[0] + config.accel_lowpass_time)))
    scale = np.abs(compiled.cov[k]).max(axis=(1, 2))
    assert (np.abs(reference.cov[k] - compiled.cov[k]).max(axis=(1, 2)) / scale).max() < 1e-12
    assert reference.cov[5, 0, 0] > SIGMA**2


def test_a_misaligned_accelerometer_is_consistent_only_with_its_alignment() -> None:
    """Monte Carlo: 24 flights at rest whose accelerometer is turned off the body by a
    tilt drawn with σ 1°. After a minute the tilt's NEES (2 dof) averages about 2 when
    the filter is told that σ and far above it when it is not (the motion level measured,
    so that at rest the filter's own σ is small)."""
    sigma = math.radians(1.0)
    told = EstimatorConfig(velocity_adapt_time=3.0, accel_alignment_sigma=sigma)
    nees = {"told": [], "not told": []}
    for seed in range(24):
        flight = simulate(
            60.0, 50.0, noise=ImuNoise.matching(told), motion=Motion.static(), seed=seed
        )
        for name, config in (("told", told), ("not told", told.replace(accel_alignment_sigma=0))):
            series = mavest.estimate(flight.t, flight.gyro, flight.accel, config=config)
            error = tilt_heading_errors(series.q[-1:], flight.q_true[-1:]).tilt[0]
            cov = world_attitude_covariance(series.q[-1:], series.cov[-1:, :3, :3], "left")[0]
            nees[name].append(float(error @ np.linalg.solve(cov[:2, :2], error)))
    assert 1.0 < np.mean(nees["told"]) < 3.3  # χ²(2·24)/24, 99.9 %: [1.0, 3.3]
    assert np.mean(nees["not told"]) > 10.0  # (its own σ at rest: about 0.3°)


@pytest.mark.parametrize("value", [-0.001, math.radians(10.5), math.inf, math.nan])
def test_an_impossible_alignment_is_refused(value: float) -> None:
    with pytest.raises(ConfigError, match="accel_alignment_sigma"):
        EstimatorConfig(accel_alignment_sigma=value)


def test_it_is_read_from_a_config_file(tmp_path) -> None:
    path = tmp_path / "aligned.toml"
    path.write_text("[estimator]\naccel_alignment_sigma = 0.0035\n")
    assert EstimatorConfig.from_toml(path).accel_alignment_sigma == 0.0035
