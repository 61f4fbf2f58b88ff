"""The filter's mathematics against independent references (tests/reference.py).

Each test here fails when a piece of the math is wrong: the update against a
textbook EKF with finite-difference Jacobians and against a general solver of
the MAP problem, the reset against Monte Carlo, the left/right equivalence.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import reference as ref
from numba import njit
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from mavest import EstimatorConfig, estimate, so3
from mavest.estimator import magnetic
from mavest.estimator.charts import reset_jacobian_into
from mavest.estimator.estimator import Estimator
from mavest.estimator.frames import world_move_into
from mavest.estimator.gravity_update import accel_update
from mavest.estimator.layout import (
    CHARTS,
    ERROR_SIDES,
    N_STATE_MAX,
    RESET_POLICIES,
    make_coefficients,
    new_state,
)
from mavest.estimator.lowpass import absorb_sample
from mavest.estimator.propagation import flush_pending, predict
from mavest.sim import ImuNoise, Motion, simulate

G = 9.80665
DT = 0.01


@njit
def _accel_update_kernel(state, coefficients, t, accel, dt):
    accel_update(state[0], coefficients[0], t, accel, dt)


def single_update(
    config: EstimatorConfig, R: Rotation, b: np.ndarray, P: np.ndarray, accel: np.ndarray
) -> tuple[Rotation, np.ndarray, np.ndarray, dict]:
    """Run mavest's accelerometer update once on a given prior."""
    est = Estimator(config)
    s = est._state
    s["q"][0] = np.roll(R.as_quat(), 1)
    s["b"][0] = b
    s["P"][0][:6, :6] = P  # the low-pass is off: the considered states are not in play
    s["initialised"] = 1
    s["t"] = 1.0
    s["t_accel"] = 1.0
    _accel_update_kernel(s, est._coefficients, 1.0, accel.astype(float), DT)
    out = s[0]
    info = {
        "nis": float(out["nis"]),
        "used": bool(out["accel_used"]),
        "iterations": int(out["iterations"]),
    }
    P_post = out["P"][:6, :6].copy()
    return Rotation.from_quat(np.roll(out["q"], -1)), out["b"].copy(), P_post, info


def update_config(side: str, chart: str, **kw: object) -> EstimatorConfig:
    base = dict(
        error=side,
        chart=chart,
        reset="full",
        accel_gate=0.0,
        accel_max_disturbance_time=0.0,
        accel_norm_tolerance=100.0,
        # one bare update: no low-pass (its considered states), no rest logic
        accel_lowpass_time=0.0,
        rest_detection=False,
    )
    base.update(kw)
    return EstimatorConfig(**base)


def measurement_variance(config: EstimatorConfig) -> float:
    return config.accel_noise_density**2 / DT / G**2


def prior_and_measurement(
    seed: int, offset_deg: float
) -> tuple[Rotation, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("ZYX", rng.uniform([-3, -0.6, -0.6], [3, 0.6, 0.6]))
    b = rng.normal(0, 0.01, 3)
    P = ref.random_covariance(rng, np.radians(25.0), np.radians(2.0))
    # the measured down direction, offset_deg away from the predicted one
    h = R.inv().apply(ref.E3)
    axis = np.cross(h, rng.normal(size=3))
    z = Rotation.from_rotvec(np.radians(offset_deg) * axis / np.linalg.norm(axis)).apply(h)
    return R, b, P, -G * z


def rotation_angle(a: Rotation, b: Rotation) -> float:
    return float(np.linalg.norm((a.inv() * b).as_rotvec()))


# ---------------------------------------------------------------- EKF = one Gauss–Newton step


@pytest.mark.parametrize(("side", "chart"), ref.CHARTS)
@pytest.mark.parametrize("update", ["ekf", "iterated"])
def test_one_iteration_is_the_textbook_ekf(side: str, chart: str, update: str) -> None:
    config = update_config(side, chart, update=update, max_iterations=1, accel_noise_density=0.5)
    R, b, P, accel = prior_and_measurement(1, offset_deg=20.0)
    R_ours, b_ours, P_ours, info = single_update(config, R, b, P, accel)
    R_ref, b_ref, P_ref = ref.ekf_update(R, b, P, accel, measurement_variance(config), side, chart)
    assert info["iterations"] == 1 and info["used"]
    assert rotation_angle(R_ours, R_ref) < 1e-8
    np.testing.assert_allclose(b_ours, b_ref, atol=1e-9)
    np.testing.assert_allclose(P_ours, P_ref, rtol=1e-6, atol=1e-12)


# ------------------------------------------------------- IEKF = Gauss–Newton on the MAP cost


@pytest.mark.parametrize(("side", "chart"), ref.CHARTS)
@pytest.mark.parametrize("seed", [2, 3])
def test_converged_iterate_is_the_map_minimiser(side: str, chart: str, seed: int) -> None:
    config = update_config(
        side,
        chart,
        update="iterated",
        max_iterations=100,
        iteration_tolerance=1e-14,
        accel_noise_density=0.05,
    )
    R, b, P, accel = prior_and_measurement(seed, offset_deg=50.0)
    var = measurement_variance(config)
    basis = ref.measurement_basis(accel)
    L_inv = np.linalg.inv(np.linalg.cholesky(P))

    def cost_residuals(dx: np.ndarray) -> np.ndarray:
        r = ref.gravity_residual(ref.retract(R, dx[:3], side, chart), accel, basis)
        return np.concatenate([r / np.sqrt(var), L_inv @ dx])

    # least_squares stops on a flat cost about 1e-9 from the minimiser; a restart
    # from its own answer (a fresh trust region) tightens that.
    options = dict(method="trf", jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    solution = least_squares(cost_residuals, np.zeros(6), **options)
    solution = least_squares(cost_residuals, solution.x, **options)
    R_map = ref.retract(R, solution.x[:3], side, chart)

    R_ours, b_ours, P_ours, info = single_update(config, R, b, P, accel)
    assert 1 < info["iterations"] < 100
    assert rotation_angle(R_ours, R_map) < 1e-8
    np.testing.assert_allclose(b_ours, b + solution.x[3:], atol=1e-8)
    # the posterior covariance is the Gauss–Newton inverse Hessian, moved onto the optimum
    T = np.eye(6)
    T[:3, :3] = ref.reset_jacobian(solution.x[:3], side, chart)
    J = solution.jac
    np.testing.assert_allclose(P_ours, T @ np.linalg.inv(J.T @ J) @ T.T, rtol=1e-5, atol=1e-12)


# ------------------------------------------------------- gravity says nothing about heading


def heading_information(config: EstimatorConfig) -> float:
    R, b, P, accel = prior_and_measurement(4, offset_deg=15.0)
    _, _, P_post, _ = single_update(config, R, b, P, accel)
    e3 = np.zeros(6)
    e3[2] = 1.0
    return float(
        e3 @ (np.linalg.inv(P_post) - np.linalg.inv(P)) @ e3 / (e3 @ np.linalg.inv(P) @ e3)
    )


@pytest.mark.parametrize("update", ["ekf", "iterated", "sigma_point"])
def test_gravity_update_adds_no_heading_information_with_the_left_error(update: str) -> None:
    # the MEKF (no reset) and the heading-tilt chart (whose reset keeps heading apart)
    for chart, reset in [
        ("exp", "none"),
        ("heading_tilt", "full"),
        ("heading_tilt", "first_order"),
    ]:
        config = update_config("left", chart, reset=reset, update=update, accel_noise_density=0.5)
        assert abs(heading_information(config)) < 1e-6, (chart, reset)


def test_the_exponential_reset_leaks_tilt_information_into_heading() -> None:
    # the trap of docs/design.md#recursion-and-reset: J_l(δ̂) with a horizontal δ̂
    # couples heading into tilt
    config = update_config("left", "exp", reset="full", update="ekf", accel_noise_density=0.5)
    assert abs(heading_information(config)) > 1e-3


# ---------------------------------------------------------------- the reset against Monte Carlo


def reset_covariance_errors(
    side: str, chart: str, correction_deg: float, spread_deg: float, elongated: bool
) -> dict[str, float]:
    """Relative Frobenius error of T Σ Tᵀ against sampled errors pushed through the exact reset.

    ``elongated``: Σ has the spread along one axis ⊥ the correction and a
    tenth of the variance on the others (the shape where the rotation part
    of the reset shows). Otherwise
    Σ is isotropic, where only the reset's scaling matters.
    """
    rng = np.random.default_rng(5)
    direction = np.array([0.6, -0.48, 0.64])
    direction /= np.linalg.norm(direction)
    delta_hat = np.radians(correction_deg) * direction
    long_axis = np.cross(direction, [0.0, 0.0, 1.0])
    long_axis /= np.linalg.norm(long_axis)
    U = np.column_stack([long_axis, np.cross(direction, long_axis), direction])
    shape = [1.0, 0.1, 0.1] if elongated else [1.0, 1.0, 1.0]
    sigma = U @ np.diag(np.radians(spread_deg) ** 2 * np.array(shape)) @ U.T
    samples = rng.multivariate_normal(delta_hat, sigma, size=20_000)
    identity = Rotation.identity()
    new_ref = ref.retract(identity, delta_hat, side, chart)
    moved = np.array(
        [ref.local(ref.retract(identity, d, side, chart), new_ref, side, chart) for d in samples]
    )
    empirical = np.cov(moved.T)
    errors = {}
    for policy in RESET_POLICIES:
        T = np.empty((3, 3))
        reset_jacobian_into(
            delta_hat, ERROR_SIDES.index(side), CHARTS.index(chart), RESET_POLICIES.index(policy), T
        )
        errors[policy] = float(
            np.linalg.norm(T @ sigma @ T.T - empirical) / np.linalg.norm(empirical)
        )
    return errors


@pytest.mark.parametrize(("side", "chart"), ref.CHARTS)
def test_full_reset_matches_monte_carlo_at_a_large_correction(side: str, chart: str) -> None:
    elongated = reset_covariance_errors(side, chart, 60.0, 20.0, elongated=True)
    isotropic = reset_covariance_errors(side, chart, 60.0, 20.0, elongated=False)
    # The heading-tilt chart Rz(ψ)·Exp(τ) bends more than Exp over a 60° step, so
    # the second-order terms the linear reset ignores are larger: 3.7 % here.
    tolerance = 0.03 if chart == "exp" else 0.05
    assert elongated["full"] < tolerance and isotropic["full"] < tolerance, (elongated, isotropic)
    assert elongated["full"] < 0.1 * elongated["none"], elongated
    assert elongated["first_order"] < elongated["none"], elongated
    if chart == "exp":  # the reset's rotation by ~δ̂/2 is what "none" misses
        assert elongated["none"] > 0.3, elongated


@pytest.mark.parametrize(("side", "chart"), ref.CHARTS)
def test_reset_jacobian_is_the_derivative_of_the_reset_map(side: str, chart: str) -> None:
    delta_hat = np.array([0.4, -0.7, 0.9])
    T = np.empty((3, 3))
    reset_jacobian_into(
        delta_hat, ERROR_SIDES.index(side), CHARTS.index(chart), RESET_POLICIES.index("full"), T
    )
    np.testing.assert_allclose(T, ref.reset_jacobian(delta_hat, side, chart), atol=1e-8)


# ---------------------------------------------------------------- left and right agree


def flight(seed: int = 7, duration: float = 30.0, rate: float = 100.0) -> object:
    return simulate(
        duration, rate, noise=ImuNoise(accel_noise_density=0.05), motion=Motion(), seed=seed
    )


@pytest.mark.parametrize("update", ["ekf", "iterated"])
def test_left_and_right_error_with_full_reset_give_the_same_estimate(update: str) -> None:
    data = flight()
    results = {}
    for side in ("left", "right"):
        # Without the low-pass: its filter steps amplify rounding differences
        # (two runs 1e-12 apart end up ~0.02° apart, see docs/limits.md), which would
        # hide a real difference among rounding noise.
        config = EstimatorConfig(
            update=update, error=side, chart="exp", reset="full", accel_lowpass_time=0.0
        )
        results[side] = estimate(data.t, data.gyro, data.accel, config=config)
    left, right = results["left"], results["right"]
    angle = [
        np.linalg.norm(so3.quat_log(so3.quat_multiply(so3.quat_conjugate(a), b)))
        for a, b in zip(left.q, right.q, strict=True)
    ]
    assert max(angle) < 1e-9
    np.testing.assert_allclose(left.bias, right.bias, atol=1e-11)
    # covariances are the same distribution in different frames: P_left = Ad P_right Adᵀ
    for k in (100, 1000, len(data.t) - 1):
        Ad = np.eye(6)
        Ad[:3, :3] = so3.matrix_from_quat(left.q[k])
        np.testing.assert_allclose(left.cov[k], Ad @ right.cov[k] @ Ad.T, rtol=1e-7, atol=1e-16)


# ---------------------------------------------------------------- long runs and convergence


def extreme_inputs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random motion mixed with absurd values, NaN/inf, saturation, zero and time faults."""
    rng = np.random.default_rng(seed)
    dt = rng.choice(
        [1e-4, 5e-4, 1e-3, 0.01, 0.1, 1.0, 3.0], size=n, p=[0.1, 0.2, 0.3, 0.3, 0.06, 0.03, 0.01]
    )
    t = np.cumsum(dt)
    t[rng.random(n) < 0.002] -= 0.5  # time going back
    gyro = rng.normal(0.0, 1.0, (n, 3)) * rng.choice([0.01, 1.0, 30.0], size=(n, 1))
    accel = np.array([0.0, 0.0, -G]) + rng.normal(0.0, 1.0, (n, 3)) * rng.choice(
        [0.01, 2.0, 50.0], size=(n, 1)
    )
    faults = rng.random(n)
    gyro[faults < 0.001] = np.nan
    accel[(faults > 0.001) & (faults < 0.002)] = np.inf
    accel[(faults > 0.002) & (faults < 0.003)] = 0.0
    accel[(faults > 0.003) & (faults < 0.004)] = 32767 * 0.0098  # saturated int16 in mG
    gyro[(faults > 0.004) & (faults < 0.005)] = 32.767  # saturated int16 in mrad/s
    return t, gyro, accel


@pytest.mark.parametrize(
    "config",
    [
        EstimatorConfig(),
        EstimatorConfig(update="ekf", error="right", chart="exp", reset="first_order"),
        EstimatorConfig(update="sigma_point", error="left", chart="exp", reset="none"),
    ],
    ids=lambda c: c.variant,
)
def test_covariance_stays_symmetric_positive_definite_through_a_million_extreme_steps(
    config: EstimatorConfig,
) -> None:
    est = Estimator(config)
    for chunk in range(10):
        t, gyro, accel = extreme_inputs(100_000, seed=chunk)
        out = est.update_batch(t + chunk * 1e5, gyro, accel)
        assert (
            np.all(np.isfinite(out.q))
            and np.all(np.isfinite(out.bias))
            and np.all(np.isfinite(out.cov))
        )
        np.testing.assert_array_equal(out.cov, np.swapaxes(out.cov, 1, 2))
        assert np.linalg.eigvalsh(out.cov).min() > 0.0
        np.testing.assert_allclose(np.linalg.norm(out.q, axis=1), 1.0, atol=1e-12)


def test_gyro_bias_converges_to_the_truth_on_a_simulated_flight() -> None:
    data = simulate(
        120.0, 100.0, noise=ImuNoise(gyro_bias_sigma=np.radians(1.0)), motion=Motion(), seed=11
    )
    out = estimate(data.t, data.gyro, data.accel)
    error = out.bias[-1] - data.bias_true[-1]
    sigma = np.sqrt(np.diag(out.cov[-1])[3:])
    initial = np.abs(data.bias_true[0])
    assert np.all(np.abs(error) < 4 * sigma), (np.degrees(error), np.degrees(sigma))
    assert np.all(np.abs(error) < 0.2 * np.maximum(initial, np.radians(0.1)))


@pytest.mark.parametrize("error", [0, 1])  # ERROR_LEFT, ERROR_RIGHT
@pytest.mark.parametrize("declination", [0.0, 0.3, -2.9])
@pytest.mark.parametrize("dip", [0.0, 1.1, -0.4])
def test_heading_jacobians_are_the_two_single_jacobians(
    error: int, declination: float, dip: float
) -> None:
    """mag_update's pair is, to the bit, the full Jacobian at the reference's dip and
    at zero dip (the heading term alone), which test_magnetometer holds to finite
    differences."""
    q = Rotation.from_rotvec([0.3, -0.5, 2.0]).as_quat(scalar_first=True)
    expected_full, expected_heading = np.empty(3), np.empty(3)
    magnetic.heading_jacobian_into(q, dip, declination, error, np.empty((3, 3)), expected_full)
    magnetic.heading_jacobian_into(q, 0.0, declination, error, np.empty((3, 3)), expected_heading)
    full, heading = np.empty(3), np.empty(3)
    magnetic.heading_jacobians_into(q, dip, declination, error, np.empty((3, 3)), full, heading)
    assert full.tobytes() == expected_full.tobytes()
    assert heading.tobytes() == expected_heading.tobytes()


@njit
def _predict_and_absorb(state, coefficients, gyro, accel, dt):
    s = state[0]
    c = coefficients[0]
    for k in range(gyro.shape[0]):
        predict(s, c, gyro[k], dt)
        absorb_sample(s, c, accel[k], dt, False)
    flush_pending(s, c)


# the process noise as near zero as the config allows
_NO_NOISE = dict(
    gyro_noise_density=1e-12,
    gyro_scale_noise_density=0.0,
    velocity_adapt_time=0.0,
    gyro_bias_random_walk=0.0,
    accel_noise_density=1e-12,
    velocity_sigma=1e-9,
    aided_velocity_sigma=1e-9,
)


@pytest.mark.parametrize("side, chart", [("left", "heading_tilt"), ("right", "exp")])
@pytest.mark.parametrize("settled", [False, True], ids=["averaging", "second_order"])
@pytest.mark.parametrize("aided", [False, True], ids=["unaided", "aided"])
def test_the_pending_transition_is_the_per_sample_propagation(
    side: str, chart: str, settled: bool, aided: bool
) -> None:
    """Between updates the considered rows' transition is accumulated and applied at
    once (propagation.flush_pending), P's 6×6 propagated every sample. Against the same
    samples propagated one by one through the whole P: without process noise the same to
    rounding; with it, the estimate's 6×6 still is, and the rest differs by what the
    accumulation leaves out (the gyro noise's share in ε counted as if it came at the
    flush: ~ωΔT of that share, ~1e-5 of P here; an aided sample's share of that noise
    is left out too: ~1e-4)."""
    rng = np.random.default_rng(int(settled) + 2 * int(aided) + 4 * (side == "right"))
    samples = 5
    gyro = rng.normal(0.0, 0.5, (samples, 3))
    accel = rng.normal(0.0, 1.0, (samples, 3)) + np.array([0.0, 0.0, -G])
    for noise, tolerance in ((_NO_NOISE, 1e-12), ({}, 2e-4 if aided else 3e-5)):
        config = EstimatorConfig(error=side, chart=chart, **noise)
        coefficients = make_coefficients(config)
        assert coefficients["accumulate"][0] == 1
        state = new_state(coefficients)
        A = rng.normal(size=(N_STATE_MAX, N_STATE_MAX))
        state["P"][0] = A @ A.T * 1e-3 + 1e-4 * np.eye(N_STATE_MAX)  # everything correlated
        state["q"][0] = Rotation.from_rotvec(rng.normal(0.0, 1.0, 3)).as_quat(scalar_first=True)
        state["b"][0] = rng.normal(0.0, 0.01, 3)
        state["initialised"] = 1
        state["filters_primed"] = 1
        state["lowpass_time"] = 10.0 if settled else 0.5  # past or within its averaging
        state["linear_accel"][0] = rng.normal(0.0, 2.0, 3) if aided else np.nan
        accumulated, one_by_one = state.copy(), state.copy()
        per_sample = coefficients.copy()
        per_sample["accumulate"] = 0
        _predict_and_absorb(accumulated, coefficients, gyro, accel, 0.005)
        _predict_and_absorb(one_by_one, per_sample, gyro, accel, 0.005)
        np.testing.assert_array_equal(accumulated["q"], one_by_one["q"])
        P, expected = accumulated["P"][0], one_by_one["P"][0]
        scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
        assert np.max(np.abs(P - expected) / scale) < tolerance
        assert np.max(np.abs(P - expected)[:6, :6] / scale[:6, :6]) < 1e-12


def test_a_reset_turns_the_considered_states_by_its_turn_about_the_vertical() -> None:
    """world_move_into's W is the twist of the world frame's move: what is left of the
    move without it (scipy composes them) turns nothing about the vertical, a swing about
    a horizontal axis. W is a rotation, so the horizontal errors keep their variance
    through a tilt, as the vertical components (not carried) would give it back."""
    rng = np.random.default_rng(11)
    W, work = np.empty((2, 2)), np.empty(4)
    for _ in range(50):
        q_old, move = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
        q_new = move * q_old
        world_move_into(q_new.as_quat(scalar_first=True), q_old.as_quat(scalar_first=True), W, work)
        np.testing.assert_allclose(W @ W.T, np.eye(2), atol=1e-14)
        twist = math.atan2(W[1, 0], W[0, 0])
        swing = Rotation.from_euler("z", -twist) * move
        assert abs(swing.as_quat(scalar_first=True)[3]) < 1e-12
    tilt = Rotation.from_rotvec([0.3, -0.2, 0.0])
    world_move_into(
        (tilt * q_old).as_quat(scalar_first=True), q_old.as_quat(scalar_first=True), W, work
    )
    np.testing.assert_allclose(W, np.eye(2), atol=1e-15)
