"""The Python API given what it should not be: an output series it cannot write, a
configuration of the wrong types or beyond the filter's health bounds, impossible samples,
a recording nothing can be estimated from, complex numbers; and an estimator pickled,
copied, or fed a sample at a time in a batch-fed service."""

from __future__ import annotations

import copy
import dataclasses
import math
import pickle
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mavest import ConfigError, Estimator, EstimatorConfig, StepFlags, estimate, smooth
from mavest.cli import main
from mavest.estimator import InputError
from mavest.estimator.config import MAX_ANGULAR_RATE, MAX_ITERATIONS
from mavest.estimator.estimator import (
    ITERATIONS_DTYPE,
    SERIES_FIELDS,
    EstimateSeries,
)
from mavest.service import pipeline

G = 9.80665


def quiet(n: int = 600, rate: float = 200.0, seed: int = 0) -> tuple[np.ndarray, ...]:
    """A vehicle at rest turning slowly about the vertical, with sensor noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    gyro = 0.01 * rng.standard_normal((n, 3)) + np.array([0.0, 0.0, 0.3])
    accel = np.array([0.0, 0.3, -G]) + 0.05 * rng.standard_normal((n, 3))
    return t, gyro, accel


# --- update_batch's out ----------------------------------------------------------------


def _broken(array: np.ndarray, how: str) -> np.ndarray:
    if how == "short":
        return array[:-1].copy()
    if how == "wrong trailing shape":
        return np.zeros((array.shape[0], 7), dtype=array.dtype)
    if how == "wrong dtype":
        return np.zeros(array.shape, dtype=np.float32 if array.dtype != np.float32 else np.float64)
    if how == "not contiguous":
        doubled = np.zeros((2 * array.shape[0], *array.shape[1:]), dtype=array.dtype)
        return doubled[::2]
    read_only = array.copy()
    read_only.setflags(write=False)
    return read_only


@pytest.mark.parametrize("how", ["short", "wrong trailing shape", "wrong dtype", "not contiguous",
                                 "read-only"])  # fmt: skip
@pytest.mark.parametrize("name", list(SERIES_FIELDS))
def test_update_batch_refuses_an_out_array_it_cannot_write_naming_it(name: str, how: str) -> None:
    """The compiled loop writes out's arrays unchecked: a short one was written past its
    end (a crash), a (N, 3) q took each row's fourth component into the next row."""
    t, gyro, accel = quiet(20)
    out = EstimateSeries.empty(len(t))
    out = dataclasses.replace(out, **{name: _broken(getattr(out, name), how)})
    with pytest.raises((TypeError, ValueError), match=rf"out\.{name} "):
        Estimator().update_batch(t, gyro, accel, out=out)


def test_update_batch_writes_into_rows_of_a_longer_series_and_refuses_other_outs() -> None:
    t, gyro, accel = quiet(40)
    whole = EstimateSeries.empty(60)
    part = Estimator().update_batch(t, gyro, accel, out=whole.rows(10, 50))
    np.testing.assert_array_equal(whole.q[10:50], estimate(t, gyro, accel).q)
    assert part.q.base is whole.q
    with pytest.raises(TypeError, match="out must be an EstimateSeries"):
        Estimator().update_batch(t, gyro, accel, out=np.empty((40, 4)))  # type: ignore[arg-type]


def test_series_fields_are_those_the_series_has_and_hold_every_iteration_count() -> None:
    assert tuple(SERIES_FIELDS) == tuple(f.name for f in dataclasses.fields(EstimateSeries))
    assert np.iinfo(ITERATIONS_DTYPE).max >= MAX_ITERATIONS


# --- iterations -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [
        {"iteration_tolerance": 0.0},  # with many iterations: an estimate that never returned
        {"max_iterations": MAX_ITERATIONS + 1},
        {"max_iterations": 40000},  # the series' int16 count wrapped negative
        {"max_iterations": 0},
    ],
)
def test_iterations_that_would_hang_or_overflow_are_refused(changes: dict[str, Any]) -> None:
    with pytest.raises(ConfigError, match="iteration"):
        EstimatorConfig(**changes)


# --- the configuration's health -----------------------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [
        {"initial_bias_sigma": 0.6},
        {"initial_bias": (0.6, 0.0, 0.0)},
        {"initial_bias": (0.0, 0.0, -1e308)},
        {"initial_tilt_sigma": 7.0},
        {"velocity_sigma": 1e4},
        {"aided_velocity_sigma": 1e4},
        {"velocity_sigma_min": 1e4},
        {"gyro_noise_density": 1e3},
    ],
)
def test_a_start_the_health_check_rejects_on_every_sample_is_refused(
    changes: dict[str, Any],
) -> None:
    """Each of these was accepted, then the filter re-initialised at every sample
    (UNHEALTHY_RESET on 1000 of 1000)."""
    with pytest.raises(ConfigError, match=next(iter(changes))):
        EstimatorConfig(**changes)


def test_a_start_within_the_health_bounds_is_estimated_without_resets() -> None:
    t, gyro, accel = quiet(2000)
    config = EstimatorConfig(initial_tilt_sigma=6.0, initial_bias=(0.2, 0.0, -0.2))
    out = estimate(t, gyro, accel, config=config)
    assert not np.any(out.flags & StepFlags.UNHEALTHY_RESET)


def test_toml_initial_bias_beyond_the_bounds_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "huge.toml"
    path.write_text("[estimator]\ninitial_bias = [1e308, 0.0, 0.0]\n")
    with pytest.raises(ConfigError, match="initial_bias"):
        EstimatorConfig.from_toml(path)


# --- the configuration's types ------------------------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [
        {"gravity": True},
        {"gyro_bias_random_walk": True},
        {"rest_detection": math.nan},
        {"rest_detection": "no"},
        {"max_iterations": math.inf},
        {"max_iterations": 6.0},
        {"timeline_confirm": 1e100},
        {"timeline_confirm": 10**100},
        {"sigma_beta": 1 + 0j},
        {"gyro_noise_density": "0.005"},
        {"max_jump": None},
        {"compass_ofs": 0.0},
        {"compass_ofs": {"x": 0.0}},
        {"compass_ofs": (0.0, 0.0)},
        {"update": 1},
        {"accel_norm_tolerance": 0.0},  # never documented as "off": no sample would be gravity
    ],
)
def test_the_constructor_refuses_what_the_toml_path_refuses(changes: dict[str, Any]) -> None:
    """Before, these passed (a bool as 1.0) or failed inside layout.py on the first estimate."""
    with pytest.raises(ConfigError, match=next(iter(changes))):
        EstimatorConfig(**changes)


def test_the_constructor_takes_numpy_numbers_and_sequences_as_python_ones() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        config = EstimatorConfig(
            gravity=np.float32(9.8),
            max_iterations=np.int64(4),
            rest_detection=np.bool_(False),
            compass_ofs=np.array([1.0, 2.0, 3.0]),
            initial_bias=[0.01, 0, 0],
        )
    assert type(config.gravity) is float and config.gravity == pytest.approx(9.8)
    assert type(config.max_iterations) is int and config.max_iterations == 4
    assert config.rest_detection is False
    assert config.compass_ofs == (1.0, 2.0, 3.0) and type(config.compass_ofs[0]) is float
    assert config.initial_bias == (0.01, 0.0, 0.0)
    assert config == EstimatorConfig.from_mapping(dataclasses.asdict(config))


def test_a_table_that_is_not_a_table_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"\[estimator\] must be a table"):
        EstimatorConfig.from_mapping(5)  # type: ignore[arg-type]
    path = tmp_path / "five.toml"
    path.write_text("estimator = 5\n")
    with pytest.raises(ConfigError, match=r"\[estimator\] must be a table"):
        EstimatorConfig.from_toml(path)


@pytest.mark.parametrize("config", [{"update_rate": 10.0}, "configs/default.toml"])
def test_a_config_that_is_not_an_estimator_config_is_a_type_error(config: Any) -> None:
    t, gyro, accel = quiet(10)
    with pytest.raises(TypeError, match="config must be an EstimatorConfig"):
        estimate(t, gyro, accel, config=config)
    with pytest.raises(TypeError, match="config must be an EstimatorConfig"):
        Estimator(config)
    with pytest.raises(TypeError, match="config must be an EstimatorConfig"):
        smooth(t, gyro, accel, config=config)


# --- impossible samples -------------------------------------------------------------------


def test_the_service_drops_the_gyro_rates_the_filter_skips() -> None:
    assert pipeline.MAX_GYRO == MAX_ANGULAR_RATE


@pytest.mark.parametrize("value", [1.01 * MAX_ANGULAR_RATE, 1e10, 1e300, -1e300])
def test_an_impossible_gyro_rate_is_skipped_as_a_nan_one(value: float) -> None:
    """Integrated, one such sample turned heading by an arbitrary angle (82° for 1e10)."""
    t, gyro, accel = quiet(800)
    absurd, missing = gyro.copy(), gyro.copy()
    absurd[[0, 500], 2] = value  # before initialisation and after
    missing[[0, 500], 2] = math.nan
    out = estimate(t, absurd, accel)
    assert out.flags[500] == StepFlags.GYRO_INVALID
    assert out.flags[0] & StepFlags.GYRO_INVALID and out.flags[0] & StepFlags.NOT_INITIALISED
    expected = estimate(t, missing, accel)
    np.testing.assert_array_equal(out.q, expected.q)
    np.testing.assert_array_equal(out.flags, expected.flags)


def test_a_gyro_rate_within_the_range_is_taken() -> None:
    t, gyro, accel = quiet(800)
    gyro[500, 2] = 0.99 * MAX_ANGULAR_RATE  # beyond gyro_clip: clipped, not skipped
    out = estimate(t, gyro, accel)
    assert not out.flags[500] & StepFlags.GYRO_INVALID
    assert out.flags[500] & StepFlags.GYRO_CLIPPED


@pytest.mark.parametrize("value", [1e300, -1e10, 60.0 * G])
def test_an_impossible_known_acceleration_is_taken_as_unknown(value: float) -> None:
    """1e300 at one sample re-initialised the filter (UNHEALTHY_RESET)."""
    t, gyro, accel = quiet(800)
    known = np.zeros((len(t), 3))
    absurd, unknown = known.copy(), known.copy()
    absurd[500, 0] = value
    unknown[500] = math.nan
    out = estimate(t, gyro, accel, linear_accel=absurd)
    assert not np.any(out.flags & StepFlags.UNHEALTHY_RESET)
    np.testing.assert_array_equal(out.q, estimate(t, gyro, accel, linear_accel=unknown).q)


def test_an_all_zero_accelerometer_is_invalid_after_initialisation_too() -> None:
    """It was taken into the low-pass and reported used (4 of 20)."""
    t, gyro, accel = quiet(800)
    accel[300:320] = 0.0
    out = estimate(t, gyro, accel)
    assert np.all(out.flags[300:320] & StepFlags.ACCEL_INVALID)
    assert not np.any(out.accel_used[300:320])
    assert not np.any(out.flags & StepFlags.UNHEALTHY_RESET)


@pytest.mark.parametrize("value", [1e20, -1e4, 51.0 * G])
def test_an_accelerometer_beyond_any_range_is_invalid_and_leaves_the_low_pass_alone(
    value: float,
) -> None:
    """One such sample went into the low-pass: 1e20 held every update after it rejected
    (ACCEL_REJECTED_NORM for the rest of a minute) and grew tilt σ to 5.8°; -1e4 cost
    seconds of updates. It is now what a NaN sample is."""
    t, gyro, accel = quiet(1500)
    absurd, nan = accel.copy(), accel.copy()
    absurd[600, 2] = value
    nan[600] = math.nan
    out, reference = estimate(t, gyro, absurd), estimate(t, gyro, nan)
    assert out.flags[600] & StepFlags.ACCEL_INVALID
    assert not np.any(out.flags & StepFlags.ACCEL_REJECTED_NORM)
    np.testing.assert_array_equal(out.q, reference.q)
    np.testing.assert_array_equal(out.cov, reference.cov)


def test_rest_detection_takes_an_all_zero_accelerometer_as_none() -> None:
    """As a NaN one: not into the rest criteria's low-pass (it was, and held rest off
    for a while after)."""
    t, gyro, accel = quiet(1200)
    gyro[:, 2] -= 0.3  # at rest
    zero, nan = accel.copy(), accel.copy()
    zero[300:320] = 0.0
    nan[300:320] = np.nan
    with_zero, with_nan = estimate(t, gyro, zero), estimate(t, gyro, nan)
    assert with_nan.at_rest[320:].any()
    np.testing.assert_array_equal(with_zero.at_rest, with_nan.at_rest)
    np.testing.assert_array_equal(with_zero.q, with_nan.q)


# --- a recording nothing is estimated from ------------------------------------------------


@pytest.mark.parametrize(
    ("mistake", "flag", "said"),
    [
        ("ft/s²", StepFlags.ACCEL_REJECTED_NORM, "accelerometer norm not within"),
        ("zero accel", StepFlags.ACCEL_INVALID, "accelerometer zero, not finite or beyond"),
        ("NaN gyro", StepFlags.GYRO_INVALID, "gyro not finite"),
    ],
)
def test_samples_before_initialisation_say_why_and_a_recording_of_none_is_refused(
    mistake: str, flag: int, said: str
) -> None:
    t, gyro, accel = quiet(400)
    if mistake == "ft/s²":
        accel = accel * 3.28084
    elif mistake == "zero accel":
        accel = 0.0 * accel
    else:
        gyro = gyro + math.nan
    flags = Estimator().update_batch(t, gyro, accel).flags
    assert np.all(flags == StepFlags.NOT_INITIALISED | flag)
    for run in (estimate, smooth):
        with pytest.raises(InputError, match=said) as raised:
            run(t, gyro, accel)
        assert "\n" not in str(raised.value) and "400 of 400" in str(raised.value)


def test_a_recording_that_starts_late_is_estimated_and_says_why_it_did_not_earlier() -> None:
    t, gyro, accel = quiet(400)
    accel[:50] = 0.0
    out = estimate(t, gyro, accel)
    assert np.all(out.flags[:50] == StepFlags.NOT_INITIALISED | StepFlags.ACCEL_INVALID)
    assert out.flags[50] & StepFlags.INITIALISED


def test_the_estimate_command_says_in_one_line_that_nothing_was_estimated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t, gyro, accel = quiet(400)
    source = tmp_path / "zero.csv"
    np.savetxt(source, np.column_stack([t, gyro, 0.0 * accel]), delimiter=",")
    assert main(["estimate", str(source), "-o", str(tmp_path / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert "nothing estimated" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out.csv").exists()


# --- complex numbers ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["t", "gyro", "accel", "mag", "linear_accel"])
def test_complex_inputs_are_refused_not_cut_to_their_real_part(name: str) -> None:
    t, gyro, accel = quiet(50)
    inputs = {"t": t, "gyro": gyro, "accel": accel, "mag": np.full((50, 3), 30.0)}
    inputs["linear_accel"] = np.zeros((50, 3))
    inputs[name] = inputs[name] + 1j
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (not numpy's ComplexWarning)
        for run in (estimate, smooth, Estimator().update_batch):
            with pytest.raises(TypeError, match=f"{name} must be real numbers"):
                run(**inputs)


@pytest.mark.parametrize("vector", ["gyro", "accel", "mag"])
def test_a_list_of_complex_numbers_is_refused_by_every_update(vector: str) -> None:
    """Given one sample at a time, as a list: numpy would take its real part, with only a
    ComplexWarning (the compiled update reads a list of Python floats itself and hands
    anything else to the same conversion as the Python one)."""
    sample = {"gyro": [0.0, 0.0, 0.0], "accel": [0.0, 0.0, -G], "mag": [20.0, 0.0, 40.0]}
    sample[vector] = [0.1 + 2j, 0.0, 0.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for estimator in (Estimator(), Estimator(batch_fed=True)):
            for k in range(300):  # (the first are batches of one; then the online step)
                estimator.update(0.01 * (k + 1), [0.0, 0.0, 0.0], [0.0, 0.0, -G])
            with pytest.raises(TypeError, match=f"{vector} must be real numbers"):
                estimator.update(5.0, **sample)


# --- a batch-fed estimator's lone samples ---------------------------------------------------


@pytest.mark.parametrize(
    "sample",
    [
        (None, [0.0, 0.0, 0.0], [0.0, 0.0, -G]),
        (np.array([1.0, 2.0]), [0.0, 0.0, 0.0], [0.0, 0.0, -G]),
        (0.03, np.array([0.1 + 5j, 0.0, 0.0]), [0.0, 0.0, -G]),
        (0.03, (0.0, 0.0), [0.0, 0.0, -G]),
        (0.03, [0.0, 0.0, 0.0], "up"),
    ],
)
def test_a_batch_fed_update_refuses_what_the_online_one_refuses(sample: tuple[Any, ...]) -> None:
    """Its first 256 calls ran as batches of one: t=None was a skipped sample, a complex
    gyro lost its imaginary part."""
    said = []
    for batch_fed in (False, True):
        estimator = Estimator(batch_fed=batch_fed)
        for i in range(3):
            estimator.update(i * 0.005, [0.0, 0.0, 0.0], [0.0, 0.0, -G])
        with pytest.raises((TypeError, ValueError)) as raised:
            estimator.update(*sample)
        said.append((type(raised.value), str(raised.value)))
    assert said[0] == said[1]


# --- pickle and copy ------------------------------------------------------------------------


@pytest.mark.parametrize("online", [False, True])
def test_a_pickled_estimator_continues_as_the_original(online: bool) -> None:
    t, gyro, accel = quiet(600)
    config = EstimatorConfig(update_rate=50.0)
    original = Estimator(config)
    if online:
        for i in range(300):
            original.update(t[i], gyro[i], accel[i])
    else:
        original.update_batch(t[:300], gyro[:300], accel[:300])
    original.declination = 0.1
    restored = pickle.loads(pickle.dumps(original))
    assert restored.config == config and restored.declination == 0.1
    for estimator in (original, restored):
        if online:
            q = np.array([estimator.update(t[i], gyro[i], accel[i]).q for i in range(300, 600)])
        else:
            q = estimator.update_batch(t[300:], gyro[300:], accel[300:]).q
        if estimator is original:
            expected = q
    np.testing.assert_array_equal(q, expected)
    assert restored.samples == original.samples == 600


def test_a_copy_of_an_estimator_is_independent() -> None:
    t, gyro, accel = quiet(100)
    original = Estimator()
    original.update_batch(t[:50], gyro[:50], accel[:50])
    for duplicate in (copy.copy(original), copy.deepcopy(original)):
        duplicate.update_batch(t[50:], gyro[50:], accel[50:])
        assert original.samples == 50 and duplicate.samples == 100


# --- slices ---------------------------------------------------------------------------------


def test_a_series_slice_is_a_series_of_views() -> None:
    t, gyro, accel = quiet(10)
    series = estimate(t, gyro, accel)
    part = series[1:3]
    assert isinstance(part, EstimateSeries) and len(part) == 2
    np.testing.assert_array_equal(part.q, series.q[1:3])
    assert part.q.base is series.q.base or part.q.base is series.q
    np.testing.assert_array_equal(series[::2].flags, series.flags[::2])
    assert series[np.int64(-1)].t == t[-1]
    with pytest.raises(TypeError, match="indexed by a sample number or a slice"):
        series[[1, 2]]  # type: ignore[call-overload]


# --- what a caller hands over besides the samples ------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [
        {"compass_dia": (-1.0, -1.0, -1.0)},  # the field turned: heading 170° off
        {"compass_dia": (1.0, 1.0, -1.0)},  # a reflection
        {"compass_dia": (1e200, 1e200, 1e200)},  # numpy overflowed, then every reading invalid
        {"compass_dec": 12.5},  # degrees
    ],
)
def test_a_magnetometer_calibration_no_sensor_has_is_refused(changes: dict[str, Any]) -> None:
    """Each was taken: a heading turned or mirrored, or a declination in degrees."""
    name = next(iter(changes))
    with pytest.raises(ConfigError, match=name.replace("compass_dia", "compass_dia/compass_odi")):
        EstimatorConfig(**changes)
    with pytest.raises(ValueError, match="declination must be within"):
        Estimator().declination = 12.5


@pytest.mark.parametrize(
    ("arguments", "said"),
    [
        ({"t": math.nan, "q": [1.0, 0.0, 0.0, 0.0]}, "t must be a finite time"),
        ({"t": 0.0, "q": [1e300, 1e300, 0.0, 0.0]}, None),  # a finite quaternion: normalised
        ({"t": 0.0, "q": [1e-320, 0.0, 0.0, 0.0]}, None),
        ({"t": 0.0, "q": [1.0, 0.0, 0.0, 0.0], "bias": [math.nan, 0.0, 0.0]}, "bias must be"),
        ({"t": 0.0, "q": [1.0, 0.0, 0.0, 0.0], "bias": [0.6, 0.0, 0.0]}, "bias must be"),
        ({"t": 0.0, "q": [1.0, 0.0, 0.0, 0.0], "cov": 100.0 * np.eye(6)}, "variances"),
    ],
)
def test_initialise_refuses_a_state_the_health_check_would_throw_away(
    arguments: dict[str, Any], said: str | None
) -> None:
    """A NaN time made every later sample TIME_NOT_INCREASING, a huge quaternion was
    stored as [0, 0, 0, 0], and a bias or covariance beyond the health bounds was
    thrown away at the next sample (UNHEALTHY_RESET)."""
    estimator = Estimator()
    if said is not None:
        with pytest.raises(ValueError, match=said):
            estimator.initialise(**arguments)
        return
    estimator.initialise(**arguments)
    q = estimator.q
    assert np.isclose(np.linalg.norm(q), 1.0) and np.all(np.isfinite(q))
    t, gyro, accel = quiet(200)
    out = estimator.update_batch(t + 1.0, gyro, accel)
    assert not np.any(out.flags & StepFlags.UNHEALTHY_RESET)


def test_restore_takes_only_a_snapshot() -> None:
    """restore(0) zeroed the state; a wrong shape failed with numpy's broadcast error."""
    estimator = Estimator()
    for wrong in (0, np.zeros(3), estimator.snapshot()[["t"]]):
        with pytest.raises(TypeError, match="snapshot"):
            estimator.restore(wrong)


def test_a_masked_array_is_taken_with_its_mask_and_dates_are_refused() -> None:
    """The values under a mask were estimated from as if measured (80° off there)."""
    t, gyro, accel = quiet(1200)
    masked = np.ma.masked_array(gyro.copy(), mask=False)
    masked.data[500:600] = 3.0
    masked[500:600] = np.ma.masked
    nan = gyro.copy()
    nan[500:600] = math.nan
    np.testing.assert_array_equal(estimate(t, masked, accel).q, estimate(t, nan, accel).q)
    with pytest.raises(TypeError, match="seconds as float64"):
        estimate((t * 1e3).astype("datetime64[ms]"), gyro, accel)


def test_a_clock_that_jumps_by_years_and_stays_keeps_the_bias() -> None:
    """Boot time turned Unix time: the bias's variance grew past the health bound over
    the gap and the filter re-initialised, the bias learned lost (kept at 1e8 s)."""
    t, gyro, accel = quiet(4000)
    gyro[:, 0] += 0.01  # a bias to learn
    t[2000:] += 1.7e9
    out = estimate(t, gyro, accel)
    # (the first samples after the jump wait for the new timeline to be confirmed)
    (gap,) = np.flatnonzero(out.flags & StepFlags.GAP_REALIGNED)
    assert 2000 <= gap < 2010
    assert not np.any(out.flags & StepFlags.UNHEALTHY_RESET)
    np.testing.assert_allclose(out.bias[gap], out.bias[1999], atol=1e-12)
    assert out.bias[gap, 0] > 0.003  # (learning it: the prior is 0)


def test_subnormal_time_steps_are_no_crash() -> None:
    """The gyro unit's window of a 1e-310 s step was infinite: OverflowError."""
    n = 100
    accel = np.tile([0.0, 0.0, -G], (n, 1))
    out = estimate(np.arange(n) * 1e-310, np.zeros((n, 3)), accel)
    assert np.all(np.isfinite(out.q))


def test_a_magnetometer_reading_not_finite_in_part_is_invalid_and_all_nan_is_none() -> None:
    """An inf or part-NaN reading was skipped as "no reading", without a flag, while
    1e300 said MAG_INVALID."""
    t, gyro, accel = quiet(1200)
    mag = np.tile([20.0, 0.0, 45.0], (len(t), 1))
    mag[600] = [math.inf, 0.0, 45.0]
    mag[700] = [20.0, math.nan, 45.0]
    mag[800] = math.nan
    flags = estimate(t, gyro, accel, mag).flags
    assert flags[600] & StepFlags.MAG_INVALID and flags[700] & StepFlags.MAG_INVALID
    assert not flags[800] & StepFlags.MAG_INVALID
