"""mavest.smooth: each sample's attitude given the whole recording.

Scored against the simulator's truth; the fusion is checked against a plain
per-sample reference written with scipy (tests/reference.py's charts).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import reference
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation
from tool_module import load_tool

import mavest
from mavest import EstimatorConfig, StepFlags, estimate, smooth
from mavest.estimator import InputError, smoother, zero_phase
from mavest.estimator.estimator import Estimator
from mavest.evaluation.calibration import score_attitude
from mavest.evaluation.consistency import SCENARIOS, chi2_band, monte_carlo, simulate_scenario
from mavest.evaluation.metrics import attitude_errors
from mavest.sim import Motion, simulate
from mavest.so3 import euler_zyx_from_quats

G = 9.80665
ROOT = Path(__file__).resolve().parents[1]


def _yaw(q: np.ndarray) -> np.ndarray:
    return euler_zyx_from_quats(q)[:, 2]


def _rms_deg(x: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(x**2))))


@pytest.fixture(scope="module")
def flight() -> object:
    return simulate(60.0, 100.0, seed=3)


@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_smoothed_error_is_below_the_filtered(flight, with_mag: bool) -> None:
    mag = flight.mag if with_mag else None
    forward = estimate(flight.t, flight.gyro, flight.accel, mag)
    smoothed = smooth(flight.t, flight.gyro, flight.accel, mag)
    f = attitude_errors(forward.q, flight.q_true)
    s = attitude_errors(smoothed.q, flight.q_true)
    assert _rms_deg(s.inclination) < 0.75 * _rms_deg(f.inclination)
    # the first seconds, where the forward pass has seen little
    first = flight.t < 5.0
    assert _rms_deg(s.inclination[first]) < 0.6 * _rms_deg(f.inclination[first])
    # the bias is the forward pass's, corrected through its correlation with attitude
    bias_f = _rms_deg(forward.bias - flight.bias_true)
    bias_s = _rms_deg(smoothed.bias - flight.bias_true)
    assert bias_s < bias_f
    if with_mag:
        assert _rms_deg(s.heading) < _rms_deg(f.heading)
    else:
        # heading keeps the forward pass's frame (the backward pass's, unobserved, drifts
        # away from the forward one's from where it starts) and drifts as the forward's
        def drift(q: np.ndarray) -> np.ndarray:
            yaw = _yaw(q) - _yaw(flight.q_true)
            return np.angle(np.exp(1j * (yaw - yaw[0])))

        assert _rms_deg(drift(smoothed.q)) < 1.2 * _rms_deg(drift(forward.q))


@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_a_recording_that_ends_in_motion_is_smoothed_too(with_mag: bool) -> None:
    """The backward pass starts where the recording ends. Aligned on that sample alone,
    whose linear acceleration the scenario's velocity model makes tens of m/s², it
    was 135° off in tilt on this flight and stayed wrong with a small σ: the smoothed
    tilt was 10.6° RMS against the filter's 3.2°, σ 4.5× too small."""
    scenario = next(s for s in SCENARIOS if s.name == "small_9d")
    data = simulate_scenario(scenario, EstimatorConfig(), seed=0)
    mag = data.mag if with_mag else None
    scored = data.t - data.t[0] >= 5.0  # (the filter aligns itself: after its first seconds)
    forward = estimate(data.t, data.gyro, data.accel, mag)
    smoothed = smooth(data.t, data.gyro, data.accel, mag)
    f_tilt, f_heading, _ = score_attitude(
        data.t, forward.q, forward.cov, data.q_true, scored, heading=with_mag
    )
    s_tilt, s_heading, _ = score_attitude(
        data.t, smoothed.q, smoothed.cov, data.q_true, scored, heading=with_mag
    )
    assert s_tilt.rmse < 0.7 * f_tilt.rmse, (s_tilt, f_tilt)
    assert 0.6 <= s_tilt.ratio <= 1.6, s_tilt
    if with_mag:
        assert f_heading is not None and s_heading is not None
        assert s_heading.rmse < f_heading.rmse, (s_heading, f_heading)
        assert 0.6 <= s_heading.ratio <= 1.6, s_heading


def _forward_pass(t, gyro, accel, mag, config: EstimatorConfig | None = None):
    """The filter as the smoother's forward pass runs it: on the averaged accelerometer."""
    config = config if config is not None else EstimatorConfig()
    return estimate(t, gyro, smoother.forward_accel(t, gyro, accel, config), mag, config)


@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_smoothed_covariance_is_below_the_filtered(flight, with_mag: bool) -> None:
    mag = flight.mag if with_mag else None
    forward = _forward_pass(flight.t, flight.gyro, flight.accel, mag)
    smoothed = smooth(flight.t, flight.gyro, flight.accel, mag)
    assert np.all(np.isfinite(smoothed.cov))
    np.testing.assert_array_equal(smoothed.cov, np.swapaxes(smoothed.cov, 1, 2))
    assert np.linalg.eigvalsh(smoothed.cov).min() > 0.0
    scale = np.trace(forward.cov, axis1=1, axis2=2)
    gap = np.linalg.eigvalsh(forward.cov - smoothed.cov).min(axis=1)
    assert np.all(gap >= -1e-7 * scale)
    # and below the filter's on the accelerometer as measured but for a few tenths of a
    # percent (its gyro-bias variance, after a different history of rest and gates)
    online = estimate(flight.t, flight.gyro, flight.accel, mag)
    gap = np.linalg.eigvalsh(online.cov - smoothed.cov).min(axis=1)
    assert np.all(gap >= -5e-3 * np.trace(online.cov, axis1=1, axis2=2))
    # and much smaller where the forward pass knows little (its first seconds)
    first = flight.t < 5.0
    tilt_f = forward.cov[first, 0, 0] + forward.cov[first, 1, 1]
    tilt_s = smoothed.cov[first, 0, 0] + smoothed.cov[first, 1, 1]
    assert np.all(tilt_s[1:] < 0.7 * tilt_f[1:])


def test_smooth_is_exported_and_keeps_the_forward_flags(flight) -> None:
    assert mavest.smooth is smooth
    forward = _forward_pass(flight.t, flight.gyro, flight.accel, None)
    smoothed = smooth(flight.t, flight.gyro, flight.accel)
    np.testing.assert_array_equal(smoothed.flags, forward.flags)
    np.testing.assert_array_equal(smoothed.nis, forward.nis)
    # without the average, the filter's own
    plain = EstimatorConfig(smooth_accel_time=0.0)
    forward = estimate(flight.t, flight.gyro, flight.accel, None, plain)
    smoothed = smooth(flight.t, flight.gyro, flight.accel, None, plain)
    np.testing.assert_array_equal(smoothed.flags, forward.flags)
    np.testing.assert_allclose(np.linalg.norm(smoothed.q, axis=1), 1.0, atol=1e-12)
    assert np.all(smoothed.q[:, 0] >= 0.0)
    assert smoothed.euler.shape == (len(flight.t), 3)


# --- a plain reference of the whole method ------------------------------------------


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(phi)
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1 - math.cos(theta)) / theta**2 * K
        + (theta - math.sin(theta)) / theta**3 * K @ K
    )


def _rotation(q: np.ndarray) -> Rotation:
    return Rotation.from_quat([q[1], q[2], q[3], q[0]])


def _quat(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def slow_zero_phase(
    t,
    gyro,
    accel,
    time_constant: float,
    max_dt: float,
    taper: float = 0.0,
    limits: tuple[float, float] = (math.inf, math.inf),
) -> np.ndarray:
    """The forward pass's accelerometer, one sample at a time with scipy's rotations:
    per segment (split at intervals outside (0, max_dt] and at non-finite samples, which
    stay as they are), the gyro integrated from the identity, the specific force turned
    into that frame, averaged backward then forward (each step's weight
    1 − exp(−Δt/τ), starting from the segment's end sample) and turned back; within
    ``taper`` s of the segment's ends, blended linearly into the sample as measured."""
    out = np.array(accel, dtype=float)
    valid = (
        np.isfinite(t)
        & np.all(np.abs(gyro) <= limits[0], axis=1)
        & np.all(np.abs(accel) <= limits[1], axis=1)
    )
    segments: list[list[int]] = []
    for k in np.flatnonzero(valid).tolist():
        if segments and segments[-1][-1] == k - 1 and 0.0 < t[k] - t[k - 1] <= max_dt:
            segments[-1].append(k)
        else:
            segments.append([k])
    for segment in segments:
        k = np.array(segment)
        turns = [Rotation.identity()]
        for j in k[1:]:
            turns.append(turns[-1] * Rotation.from_rotvec(gyro[j] * (t[j] - t[j - 1])))
        frame = Rotation.concatenate(turns)
        world = frame.apply(accel[k])
        weights = 1.0 - np.exp(-np.diff(t[k]) / time_constant)
        for i in range(len(k) - 2, -1, -1):
            world[i] = world[i + 1] + weights[i] * (world[i] - world[i + 1])
        for i in range(1, len(k)):
            world[i] = world[i - 1] + weights[i - 1] * (world[i] - world[i - 1])
        out[k] = frame.inv().apply(world)
        if taper > 0.0:
            inside = np.minimum(t[k] - t[k[0]], t[k[-1]] - t[k])
            share = np.minimum(inside / taper, 1.0)[:, None]
            out[k] = share * out[k] + (1.0 - share) * accel[k]
    return out


def test_zero_phase_average_agrees_with_references_and_ignores_blocks() -> None:
    """The forward pass's accelerometer against a sample-by-sample statement with scipy's
    rotations, on a recording with a gap, a NaN gyro sample, a repeated time and a NaN
    time; on an even recording, against scipy's lfilter run backward and forward; the
    same bytes whatever the block size."""
    data = simulate(12.0, 100.0, seed=5)
    blocks = zero_phase.zero_phase_blocks(data.t, data.gyro, data.accel, 0.7, 2.0, 64)
    even = np.concatenate(list(blocks))
    np.testing.assert_allclose(
        even, slow_zero_phase(data.t, data.gyro, data.accel, 0.7, 2.0), rtol=0, atol=1e-12
    )
    frame = Rotation.identity()
    turns = [frame]
    for k in range(1, len(data.t)):
        turns.append(turns[-1] * Rotation.from_rotvec(data.gyro[k] * (data.t[k] - data.t[k - 1])))
    frame = Rotation.concatenate(turns)
    alpha = 1.0 - math.exp(-0.01 / 0.7)
    world = frame.apply(data.accel)[::-1]
    world, _ = lfilter([alpha], [1.0, alpha - 1.0], world, axis=0, zi=(1 - alpha) * world[:1])
    world = world[::-1]
    world, _ = lfilter([alpha], [1.0, alpha - 1.0], world, axis=0, zi=(1 - alpha) * world[:1])
    np.testing.assert_allclose(even, frame.inv().apply(world), rtol=0, atol=1e-9)

    t, gyro, accel = data.t.copy(), data.gyro.copy(), data.accel.copy()
    t[700:] += 5.0  # a gap beyond max_dt
    gyro[300] = np.nan
    t[500] = t[499]  # the same time again: a new segment
    t[900] = np.nan
    gyro[1000, 2] = 40.0  # beyond the clip below
    accel[1050, 0] = -600.0  # beyond the limit below
    expected = slow_zero_phase(t, gyro, accel, 0.7, 2.0)
    limited = zero_phase.zero_phase_blocks(t, gyro, accel, 0.7, 2.0, 64, 0.0, 30.0, 500.0)
    np.testing.assert_allclose(
        np.concatenate(list(limited)),
        slow_zero_phase(t, gyro, accel, 0.7, 2.0, 0.0, (30.0, 500.0)),
        rtol=0,
        atol=1e-12,
    )
    tapered = np.concatenate(list(zero_phase.zero_phase_blocks(t, gyro, accel, 0.7, 2.0, 50, 1.5)))
    np.testing.assert_allclose(
        tapered, slow_zero_phase(t, gyro, accel, 0.7, 2.0, 1.5), rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(tapered[[0, 299, 699, len(t) - 1]], accel[[0, 299, 699, -1]])
    blocks = {
        block: np.concatenate(list(zero_phase.zero_phase_blocks(t, gyro, accel, 0.7, 2.0, block)))
        for block in (8192, 100, 37, 1)
    }
    np.testing.assert_allclose(blocks[8192], expected, rtol=0, atol=1e-12)
    for block, averaged in blocks.items():
        assert averaged.tobytes() == blocks[8192].tobytes(), block
    np.testing.assert_array_equal(blocks[1][[300, 900]], accel[[300, 900]])
    # it did average: the linear acceleration and the noise are gone
    assert np.std(blocks[1][:290] - accel[:290]) > 0.05


def slow_smooth(t, gyro, accel, mag, config: EstimatorConfig):
    """The smoother, one sample at a time, with scipy rotations and matrix inverses."""
    n = len(t)
    # (the average is checked against slow_zero_phase on its own: here a difference in
    # its last bits could flip one of the filter's decisions, a gate or rest)
    forward = estimate(t, gyro, smoother.forward_accel(t, gyro, accel, config), mag, config)
    done = (forward.flags & (StepFlags.NOT_INITIALISED | StepFlags.SKIPPED)) == 0
    last = np.flatnonzero(done)[-1]
    t_last = t[last]
    back_config = config.replace(initial_bias=tuple(-np.asarray(config.initial_bias)))
    # the backward pass starts at the forward pass's last attitude, with the configured
    # initial uncertainty (diagonal: the bias's change of sign leaves it as it is); its
    # own magnetometer sets its heading
    initial = np.diag(
        [config.initial_tilt_sigma**2] * 2
        + [config.initial_heading_sigma**2]
        + [config.initial_bias_sigma**2] * 3
    )
    backward = Estimator(back_config)
    backward.initialise(
        0.0, forward.q[last], -np.asarray(config.initial_bias), initial, heading_known=False
    )
    rev = np.arange(n - 1, -1, -1)
    back = backward.update_batch(
        t_last - t[rev],
        -gyro[np.minimum(rev + 1, n - 1)],
        accel[rev],
        None if mag is None else mag[rev],
    )
    bflags, bq, bb, bP = back.flags[::-1], back.q[::-1], back.bias[::-1], back.cov[::-1]
    bmag = back.mag_used[::-1]
    restarts = (
        StepFlags.INITIALISED
        | StepFlags.GAP_REALIGNED
        | StepFlags.UNHEALTHY_RESET
        | StepFlags.DIVERGED
        | StepFlags.CLIP_REALIGNED
        | StepFlags.TIME_RESTARTED
    )
    none = StepFlags.NOT_INITIALISED | StepFlags.SKIPPED
    q_out, b_out, P_out = forward.q.copy(), forward.bias.copy(), forward.cov.copy()
    sg2, sb2 = config.gyro_noise_density**2, config.gyro_bias_random_walk**2
    ss2 = config.gyro_scale_noise_density**2  # × |ω|²: the rate noise's part ∝ the rate
    # a pass's heading is referenced from its magnetometer (or a heading set) on, until it
    # starts afresh (INITIALISED: heading free again, unless referenced at that sample)
    f_heading = b_heading = False
    b_heading_at = np.zeros(n, dtype=bool)
    for k in range(n - 1, -1, -1):
        b_heading = b_heading and not bflags[k] & StepFlags.INITIALISED
        b_heading = b_heading or bool(bflags[k] & StepFlags.HEADING_ALIGNED) or bmag[k]
        b_heading_at[k] = b_heading
    for k in range(n):
        f_heading = f_heading and not forward.flags[k] & StepFlags.INITIALISED
        f_heading = f_heading or bool(forward.flags[k] & StepFlags.HEADING_ALIGNED)
        f_heading = f_heading or bool(forward.mag_used[k])
        if forward.flags[k] & none or bflags[k] & (none | restarts):
            continue
        measured = not (bflags[k] & StepFlags.BETWEEN_UPDATES) or bmag[k]
        R_b, P_b = _rotation(bq[k]), bP[k]
        if measured:  # the backward prior: its estimate at k + 1 predicted back to k
            if k + 1 >= n or bflags[k + 1] & none:
                continue
            dt = t[k + 1] - t[k]
            R0 = _rotation(bq[k + 1])
            phi = (-gyro[k + 1] - bb[k + 1]) * dt
            R_b = R0 * Rotation.from_rotvec(phi)
            Phi = np.eye(6)
            Phi[:3, 3:] = -R0.as_matrix() @ _left_jacobian(phi) * dt
            Q = np.zeros((6, 6))
            rate_sq = float(np.sum(phi * phi)) / dt**2
            Q[:3, :3] = ((sg2 + ss2 * rate_sq) * dt + sb2 * dt**3 / 3) * np.eye(3)
            Q[:3, 3:] = -0.5 * sb2 * dt**2 * R0.as_matrix()
            Q[3:, :3] = Q[:3, 3:].T
            Q[3:, 3:] = sb2 * dt * np.eye(3)
            P_b = Phi @ bP[k + 1] @ Phi.T + Q
        R_f = _rotation(forward.q[k])
        d = reference.chart_inverse(R_b * R_f.inv(), "heading_tilt")
        # the backward attitude's information, turned onto the forward heading where the
        # backward heading is free; where only the forward one is, that one is taken as
        # free (uniform: its variance raised by π²)
        both = b_heading_at[k]
        A = np.eye(3) if both else reference.rz(-d[2]).as_matrix()
        dims = [0, 1, 2] if both else [0, 1]
        R = (A @ P_b[:3, :3] @ A.T)[np.ix_(dims, dims)]
        H = np.eye(6)[dims]
        information = H.T @ np.linalg.inv(R) @ H
        P_f = forward.cov[k].copy()
        if both and not f_heading:
            P_f[2, 2] += np.pi**2
        P = np.linalg.inv(np.linalg.inv(P_f) + information)
        x = P @ H.T @ np.linalg.inv(R) @ d[dims]
        q_out[k] = _quat(reference.chart(x[:3], "heading_tilt") * R_f)
        b_out[k] = forward.bias[k] + x[3:]
        P_out[k] = 0.5 * (P + P.T)
    return q_out, b_out, P_out


@pytest.mark.parametrize("scale_noise", [0.0, 0.003], ids=["white", "rate_noise"])
@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_smooth_agrees_with_a_slow_reference(with_mag: bool, scale_noise: float) -> None:
    data = simulate(8.0, 100.0, seed=11)
    mag = data.mag if with_mag else None
    config = EstimatorConfig(
        initial_bias=(0.001, -0.002, 0.003), gyro_scale_noise_density=scale_noise
    )
    q, b, P = slow_smooth(data.t, data.gyro, data.accel, mag, config)
    out = smooth(data.t, data.gyro, data.accel, mag, config)
    np.testing.assert_allclose(out.q, q, atol=1e-9)
    np.testing.assert_allclose(out.bias, b, atol=1e-9)
    np.testing.assert_allclose(out.cov, P, atol=1e-9 * np.abs(P).max())
    # and it did fuse: most samples moved off the forward estimate
    forward = estimate(data.t, data.gyro, data.accel, mag, config)
    assert np.mean(np.any(out.q != forward.q, axis=1)) > 0.95


def _restarted_flight(seeds: tuple[int, int], silent: float) -> tuple[np.ndarray, ...]:
    """Two simulated flights (100 Hz, the magnetometer at 10 Hz), the second's clock
    started again at 0 (a reboot) and its magnetometer silent for its first ``silent`` s;
    t, gyro, accel, mag, the true attitude, and where the second begins."""
    flights = [simulate(30.0, 100.0, seed=seed) for seed in seeds]
    mags = []
    for i, data in enumerate(flights):
        mag = np.full_like(data.mag, np.nan)
        mag[::10] = data.mag[::10]
        if i:
            mag[data.t < silent] = np.nan
        mags.append(mag)
    joined = (
        np.concatenate([getattr(d, name) for d in flights])
        for name in ("t", "gyro", "accel", "q_true")
    )
    t, gyro, accel, q_true = joined
    return t, gyro, accel, np.concatenate(mags), q_true, flights[0].t.shape[0]


def test_smooth_agrees_with_a_slow_reference_across_a_restart() -> None:
    """After a reboot the forward pass's heading is free until its magnetometer speaks
    again, and the backward pass's after its own restart: which pass's heading is fused
    follows each one's since it last started (INITIALISED)."""
    t, gyro, accel, mag, _, _ = _restarted_flight((1, 2), 3.0)
    keep = slice(2500, 3600)  # the first flight's end, the restart, 8 s of the second
    t, gyro, accel, mag = t[keep], gyro[keep], accel[keep], mag[keep]
    config = EstimatorConfig()
    q, b, P = slow_smooth(t, gyro, accel, mag, config)
    out = smooth(t, gyro, accel, mag, config)
    np.testing.assert_allclose(out.q, q, atol=1e-9)
    np.testing.assert_allclose(out.bias, b, atol=1e-9)
    np.testing.assert_allclose(out.cov, P, atol=1e-9 * np.abs(P).max())


@pytest.mark.parametrize("seeds", [(1, 2), (5, 6)])
def test_after_a_restart_the_heading_is_the_pass_that_references_it(
    seeds: tuple[int, int],
) -> None:
    """The 3 s after a reboot, before the magnetometer's next reading: the filter's heading
    is free (tens of degrees off, with its initial σ); the smoothed one is the backward
    pass's, which its magnetometer referenced, with that pass's σ."""
    t, gyro, accel, mag, q_true, restart = _restarted_flight(seeds, 3.0)
    window = slice(restart + 5, restart + 300)
    filtered = estimate(t, gyro, accel, mag)
    smoothed = smooth(t, gyro, accel, mag)
    errors = {}
    for name, out in (("filter", filtered), ("smooth", smoothed)):
        heading = np.degrees(attitude_errors(out.q[window], q_true[window]).heading)
        sigma = np.degrees(np.sqrt(out.cov[window, 2, 2]))
        errors[name] = (np.median(np.abs(heading)), np.mean(np.abs(heading) > 3.0 * sigma))
    assert errors["filter"][0] > 10.0, errors  # (what there is to mend)
    assert errors["smooth"][0] < 4.0, errors
    assert errors["smooth"][1] < 0.1, errors


def test_blocks_do_not_change_the_result(monkeypatch: pytest.MonkeyPatch) -> None:
    data = simulate(10.0, 100.0, seed=12)
    whole = smooth(data.t, data.gyro, data.accel, data.mag)
    monkeypatch.setattr(smoother, "BLOCK", 37)
    blocks = smooth(data.t, data.gyro, data.accel, data.mag)
    for name in ("q", "bias", "cov"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))


def _from_blocks(*args: object, **kwargs: object) -> dict[str, np.ndarray]:
    """smooth_blocks' blocks put together: every field of the series, in row order."""
    parts: dict[int, mavest.EstimateSeries] = dict(smoother.smooth_blocks(*args, **kwargs))
    assert list(parts) == sorted(parts, reverse=True)  # (from the end)
    firsts = sorted(parts)
    assert [lo + len(parts[lo]) for lo in firsts[:-1]] == firsts[1:]
    return {
        name: np.concatenate([getattr(parts[lo], name) for lo in firsts])
        for name in mavest.EstimateSeries.__dataclass_fields__
    }


@pytest.mark.parametrize(
    "case",
    [
        "6d",
        "9d",
        "right_error_aligned",
        "measured_accel",
        "known_acceleration",
        "restart",
        "nan",
        "delayed_nan",
    ],
)
def test_smoothing_a_block_at_a_time_gives_smooth_bit_for_bit(
    case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """smooth_blocks runs the forward pass again a block at a time instead of holding it:
    the same estimates, every field, every bit, blocks from the end to the start."""
    monkeypatch.setattr(smoother, "BLOCK", 257)  # (many blocks, one of them short)
    damage = {"restart": "restart", "nan": "nan", "delayed_nan": "nan"}.get(case, "none")
    data, t, gyro, accel, mag = _damaged(damage)
    config, linear = None, None
    if case == "6d":
        mag = None
    elif case == "right_error_aligned":
        config = EstimatorConfig(error="right", chart="exp", accel_alignment_sigma=0.004)
    elif case == "measured_accel":
        config = EstimatorConfig(smooth_accel_time=0.0)
    elif case == "delayed_nan":  # (the start of the backward pass taken back by the delay)
        config = EstimatorConfig(imu_delay=0.0025)
    elif case == "known_acceleration":
        linear = np.full_like(accel, np.nan)
        linear[::10] = data.linear_accel[::10]
    whole = smooth(t, gyro, accel, mag, config, linear)
    blocks = _from_blocks(t, gyro, accel, mag, config, linear)
    for name, values in blocks.items():
        np.testing.assert_array_equal(values, getattr(whole, name), err_msg=name)


def test_smoothing_a_block_at_a_time_refuses_as_smooth_and_starts_where_it_does() -> None:
    data = simulate(5.0, 100.0, seed=14)
    with pytest.raises(InputError, match="g"):
        next(smoother.smooth_blocks(data.t, data.gyro, data.accel / G))
    # the averaged accelerometer never near g: the forward pass takes it as measured
    n = 3000
    t = np.arange(n) * 0.01
    gyro = np.zeros((n, 3))
    gyro[:, 2] = 0.3
    accel = np.tile([0.0, 0.0, -1.6 * G], (n, 1))
    accel[1500:1520] = [0.0, 0.0, -G]
    blocks = _from_blocks(t, gyro, accel)
    np.testing.assert_array_equal(blocks["q"], smooth(t, gyro, accel).q)
    assert list(smoother.smooth_blocks(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))) == []


@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_memory_beyond_the_result_is_small(with_mag: bool) -> None:
    """An hour at 1 kHz must smooth in 1.5 GB: the result (401 B a sample) and little
    more. What else grows with the samples (the slope between two lengths, past the
    smoother's fixed blocks) is bounded here at 16 B a sample."""
    import tracemalloc

    data = simulate(80.0, 500.0, seed=4)
    mag = data.mag if with_mag else None
    n = len(data.t)
    for run in (estimate, smooth):
        run(data.t[:500], data.gyro[:500], data.accel[:500], None if mag is None else mag[:500])
        beyond = []
        for m in (n // 2, n):
            tracemalloc.start()
            try:
                out = run(
                    data.t[:m], data.gyro[:m], data.accel[:m], None if mag is None else mag[:m]
                )
                _, peak = tracemalloc.get_traced_memory()
            finally:
                tracemalloc.stop()
            held = sum(getattr(out, name).nbytes for name in type(out).__dataclass_fields__)
            assert held / m <= 401, (run.__name__, held / m)
            beyond.append(peak - held)
        slope = (beyond[1] - beyond[0]) / (n - n // 2)
        assert slope < 16, (run.__name__, slope)


def test_smooth_is_deterministic(flight) -> None:
    a = smooth(flight.t, flight.gyro, flight.accel, flight.mag)
    b = smooth(flight.t, flight.gyro, flight.accel, flight.mag)
    for name in ("q", "bias", "cov"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes()


def test_right_error_smooths_as_well(flight) -> None:
    config = EstimatorConfig(error="right", chart="exp")
    forward = _forward_pass(flight.t, flight.gyro, flight.accel, None, config)
    smoothed = smooth(flight.t, flight.gyro, flight.accel, None, config)
    f = attitude_errors(forward.q, flight.q_true).inclination
    s = attitude_errors(smoothed.q, flight.q_true).inclination
    assert _rms_deg(s) < 0.75 * _rms_deg(f)

    # body-frame errors about different attitudes: compared in the world frame
    def world(out) -> np.ndarray:
        A = np.zeros((len(out), 6, 6))
        A[:, :3, :3] = Rotation.from_quat(out.q[:, [1, 2, 3, 0]]).as_matrix()
        A[:, 3:, 3:] = np.eye(3)
        return A @ out.cov @ np.swapaxes(A, 1, 2)

    gap = np.linalg.eigvalsh(world(forward) - world(smoothed)).min(axis=1)
    assert np.all(gap >= -1e-7 * np.trace(forward.cov, axis1=1, axis2=2))


# --- bad input: flagged as estimate() flags it, never fatal -------------------------


def _damaged(kind: str):
    data = simulate(20.0, 100.0, seed=13)
    t, gyro, accel, mag = data.t.copy(), data.gyro.copy(), data.accel.copy(), data.mag.copy()
    if kind == "nan":
        gyro[300:305] = np.nan
        accel[700:720] = np.nan
        mag[900:950] = np.nan
        t[1200] = np.nan
    elif kind == "time_back":
        t[800:805] = t[800:805] - 0.5
    elif kind == "absurd_timestamp":
        t[1000] = 1e12
    elif kind == "absurd_last_timestamp":
        t[-1] = 1e12
    elif kind == "infinite_last_timestamp":
        t[-1] = np.inf
    elif kind == "gap":
        t[1000:] += 30.0
    elif kind == "restart":
        t[1500:] -= 100.0
    elif kind == "absurd_values":  # finite, but no sensor's: a corrupt sample
        accel[600] = [1e30, 0.0, 0.0]
        gyro[1100] = [0.0, -1e30, 0.0]
    return data, t, gyro, accel, mag


@pytest.mark.parametrize(
    "kind",
    [
        "nan",
        "time_back",
        "absurd_timestamp",
        "absurd_last_timestamp",
        "infinite_last_timestamp",
        "gap",
        "restart",
        "absurd_values",
    ],
)
@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_bad_input_is_flagged_never_fatal(kind: str, with_mag: bool) -> None:
    data, t, gyro, accel, mag = _damaged(kind)
    mag = mag if with_mag else None
    forward = _forward_pass(t, gyro, accel, mag)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (nor a NumPy warning: the flags say it)
        out = smooth(t, gyro, accel, mag)
    np.testing.assert_array_equal(out.flags, forward.flags)
    for name in ("q", "bias", "cov"):
        assert np.all(np.isfinite(getattr(out, name))), name
    np.testing.assert_allclose(np.linalg.norm(out.q, axis=1), 1.0, atol=1e-12)
    # where the forward pass has no estimate the smoother has none either
    held = (forward.flags & (StepFlags.NOT_INITIALISED | StepFlags.SKIPPED)) != 0
    np.testing.assert_array_equal(out.q[held], forward.q[held])
    if kind in ("nan", "time_back", "absurd_timestamp", "gap", "absurd_values"):
        good = ~held & np.isfinite(t)
        f = attitude_errors(forward.q[good], data.q_true[good]).inclination
        s = attitude_errors(out.q[good], data.q_true[good]).inclination
        assert _rms_deg(s) < _rms_deg(f)


def test_what_the_filter_can_start_on_is_smoothed() -> None:
    """A sustained 1.6 g turn with a moment level (0.2 s): the filter starts there, the
    averaged accelerometer never comes near g; the smoother starts where the filter does
    (its forward pass then takes the accelerometer as measured) rather than refuse."""
    n = 3000
    t = np.arange(n) * 0.01
    gyro = np.zeros((n, 3))
    gyro[:, 2] = 0.3
    accel = np.tile([0.0, 0.0, -1.6 * 9.80665], (n, 1))
    accel[1500:1520] = [0.0, 0.0, -9.80665]
    started = StepFlags.NOT_INITIALISED
    filtered = estimate(t, gyro, accel)
    smoothed = smooth(t, gyro, accel)
    np.testing.assert_array_equal(smoothed.flags & started, filtered.flags & started)
    assert np.count_nonzero((smoothed.flags & started) == 0) == 1500


def test_accelerometer_in_g_is_refused_as_by_estimate() -> None:
    data = simulate(5.0, 100.0, seed=14)
    with pytest.raises(InputError):
        smooth(data.t, data.gyro, data.accel / G)


@pytest.mark.parametrize("with_mag", [False, True], ids=["6d", "9d"])
def test_a_recording_with_no_accelerometer_is_refused_as_by_estimate(with_mag: bool) -> None:
    """Nothing to estimate from: not N placeholder estimates, but the reason in one line."""
    _, t, gyro, accel, mag = _damaged("nan")
    accel[:] = np.nan
    with pytest.raises(InputError, match="accelerometer zero, not finite or beyond"):
        smooth(t, gyro, accel, mag if with_mag else None)


def test_empty_and_single_sample_inputs() -> None:
    empty = smooth(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0
    one = smooth([0.0], [[0.0, 0.0, 0.0]], [[0.0, 0.0, -G]])
    np.testing.assert_allclose(one.q, [[1.0, 0.0, 0.0, 0.0]])


def test_the_smoothers_parts_name_a_wrong_argument() -> None:
    """forward_accel and smooth_forward, for a forward pass run otherwise, check what
    they are given as smooth does: a ValueError naming it, not NumPy's own."""
    data = simulate(2.0, 100.0, seed=3)
    t, gyro, accel = data.t, data.gyro, data.accel
    config = EstimatorConfig()
    assert smoother.forward_accel(t[:0], gyro[:0], accel[:0], config).shape == (0, 3)
    forward = estimate(t, gyro, accel)
    with pytest.raises(ValueError, match="forward pass has 201 samples, t has 196"):
        smoother.smooth_forward(forward, t[:-5], gyro[:-5], accel[:-5])
    with pytest.raises(ValueError, match="gyro must have shape"):
        smoother.smooth_forward(forward, t, gyro[:, :2], accel)
    with pytest.raises(ValueError, match="cov must be"):
        start = ([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], np.eye(3))
        smoother.smooth_forward(forward, t, gyro, accel, backward_start=start)


@pytest.mark.parametrize("name", ["small", "bursts", "small_9d"])
def test_smoothed_covariance_is_consistent(name: str) -> None:
    """A small Monte Carlo of the smoother (tools/consistency.py --smooth runs the full one)."""
    scenario = next(s for s in SCENARIOS if s.name == name)
    runs = 6
    summary = monte_carlo([EstimatorConfig()], scenario, runs, seed=50, smoothed=True)[0]
    lo, hi = chi2_band(6, runs, level=0.99)
    assert lo <= summary.anees <= hi, summary


def test_the_handheld_smoother_takes_the_accelerometer_as_measured() -> None:
    """With the hand-held prior (velocity decorrelating in 0.1 s) the forward pass's
    averaged accelerometer would count the next seconds' samples twice, once through the
    average and once in the backward pass: its smoothed σ was half the error's. As
    configs/handheld.toml sets it (no average), the smoother is consistent."""
    handheld = EstimatorConfig.from_toml(ROOT / "configs" / "handheld.toml")
    assert handheld.smooth_accel_time == 0.0
    scenario = next(s for s in SCENARIOS if s.name == "small")
    runs = 8  # flights of the profile's own motion
    low, high = chi2_band(6, runs * 4)  # ~4 independent stretches per run: a looser band
    (plain,) = monte_carlo([handheld], scenario, runs, smoothed=True)
    assert low < plain.anees < high, plain  # (measured 5.27)
    averaged = handheld.replace(smooth_accel_time=0.5)
    (twice,) = monte_carlo([averaged], scenario, runs, smoothed=True)
    assert twice.anees > 1.5 * high, twice  # (measured 11.9)


# --- the tools ------------------------------------------------------------------------


def test_cost_tool_prints_the_ratio_and_the_hour(capsys: pytest.CaptureFixture[str]) -> None:
    tool = load_tool("smooth_cost")
    assert tool.main(["--seconds", "12", "--rate", "100"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("| 6-D", "| 9-D"))]
    assert len(rows) == 2
    assert all(float(row.split("|")[4]) > 1.0 for row in rows)  # smoothing costs more
    assert "| estimate |" in out and "| smooth |" in out and "an hour" in out


def test_evidence_shows_the_offline_estimates_apart() -> None:
    evidence = load_tool("evidence")
    online = evidence.Filters.chosen(quick=True)
    offline = evidence.Filters.chosen(quick=True, offline=True)
    assert offline.names == [*online.names, "mavest smoothed", "offline VQF"]
    # an estimate that saw the future is shown, never the best of the online filters
    assert offline.online == set(online.names)


def test_offline_vqf_peer_lands_in_ned() -> None:
    """The offline VQF adapter's frames: a wrong one shows up as tens of degrees."""
    pytest.importorskip("vqf", reason="vqf (dev extra) is not installed")
    from mavest.evaluation.peers import PEERS

    data = simulate(30.0, 100.0, seed=15)
    settled = data.t > 5.0
    for mag in (None, data.mag):
        q = PEERS["offline VQF"](data.t, data.gyro, data.accel, mag, 100.0)
        errors = attitude_errors(q[settled], data.q_true[settled])
        assert _rms_deg(errors.inclination) < 1.0  # measured 0.37°
        if mag is not None:  # measured 6.8° (magnetic north is 1.9° off true north here)
            assert _rms_deg(errors.heading) < 10.0


def test_consistency_tool_smooth_mode(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    results = tmp_path / "results.md"
    arguments = ["--smooth", "--runs", "2", "--scenario", "small", "--jobs", "1"]
    assert load_tool("consistency").main([*arguments, "--results", str(results)]) == 0
    out = capsys.readouterr().out
    rows = [line.split("|")[1].strip() for line in out.splitlines() if line.startswith("| ")]
    assert rows == ["estimate", "filter", "smoother"]
    section = results.read_text().split("<!-- BEGIN smoothing-consistency -->\n", 1)[1]
    assert section.startswith("## Smoothing consistency\n")
    assert out.strip() in section


def test_consistency_tool_smooths_with_the_configuration_given(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    mine = tmp_path / "mine.toml"
    mine.write_text("[estimator]\nvelocity_sigma = 0.3\n")  # the flights carry it too
    tool = load_tool("consistency")
    arguments = ["--smooth", "--runs", "2", "--scenario", "small", "--jobs", "1"]
    assert tool.main([*arguments, "--config", str(mine)]) == 0
    with_file = capsys.readouterr().out
    assert "consistency of the smoother with mine.toml" in with_file
    assert tool.main(arguments) == 0
    default = capsys.readouterr().out
    assert "consistency of the smoother," in default
    # other flights (their velocity's σ is the file's), other rows
    assert _rows(with_file) != _rows(default)
    with pytest.raises(SystemExit) as exit_:
        tool.main([*arguments, "--config", str(mine), "--config", str(mine)])
    assert exit_.value.code == 2 and "one --config" in capsys.readouterr().err


def _rows(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("| filter")]


def test_evidence_never_bolds_an_offline_column() -> None:
    evidence = load_tool("evidence")
    rows = [
        evidence.Row("error", {"mavest": 0.5, "mavest smoothed": 0.4}),
        evidence.Row("count", {"mavest": 3.0, "mavest smoothed": 5.0}, 0, bold_lowest=False),
    ]
    table = evidence.format_table("t", ["mavest", "mavest smoothed"], rows, True, {"mavest"})
    assert table.splitlines()[2:] == ["| error | **0.50** | 0.40 |", "| count | 3 | 5 |"]


def test_known_acceleration_reaches_both_passes() -> None:
    """With the vehicle's acceleration known (GPS), both passes remove it: the smoothed
    estimate gains on the filter's, and on the unaided smoother."""
    data = simulate(40.0, 100.0, motion=Motion(velocity_sigma=1.0), seed=16)
    aided = smooth(data.t, data.gyro, data.accel, linear_accel=data.linear_accel)
    forward = estimate(data.t, data.gyro, data.accel, linear_accel=data.linear_accel)
    plain = smooth(data.t, data.gyro, data.accel)
    error = {
        name: _rms_deg(attitude_errors(out.q, data.q_true).inclination)
        for name, out in (("aided", aided), ("forward", forward), ("plain", plain))
    }
    assert error["aided"] < error["forward"] and error["aided"] < error["plain"], error
    np.testing.assert_array_equal(aided.flags, forward.flags)


def test_averaging_time_is_chosen_on_one_half_and_reported_on_the_other() -> None:
    """tools/tune_smooth.py: the choice is the tuning half's best mean, and the row
    reports the other half only, with the paired per-trial differences, against the
    peer as it is and carried forward by the same delay."""
    from mavest.datasets.broad import halves, lowest_mean
    from mavest.evaluation.report import paired

    tool = load_tool("tune_smooth")
    table = {
        (0.0, 0.0): [1.0, 2.0, 3.0, 4.0],
        (0.25, 0.002): [0.9, 2.5, 2.9, 4.5],
        (0.5, 0.0): [1.1, 1.5, 3.1, 3.5],
    }
    a, b = halves(["02", "03", "05", "07"])
    assert (a, b) == ([0, 2], [1, 3])
    assert lowest_mean(table, a) == (0.25, 0.002) and lowest_mean(table, b) == (0.5, 0.0)
    offline = {0.0: [3.0, 3.0, 3.0, 3.0], 0.002: [2.0, 4.0, 2.0, 3.0]}
    (row,) = tool.held_out_rows(table, offline, [("A", "B", b, (0.25, 0.002))])
    assert "| A → B | 0.25 s, 2 ms | 3.500° / 3.000° / 3.000° (1.17×) |" in row
    assert "| better on 1 of 2, median difference +0.500° |" in row
    assert "| 3.500° (1.00×), better on 1 of 2, median difference +0.000° |" in row
    assert row.endswith("| better on 0 of 2, median difference +0.500° |")
    assert paired([1.0, 2.0, 3.0], [2.0, 2.0, 2.0]) == "better on 1 of 3, median difference +0.000°"
