"""A gyroscope not in rad/s, told by the turn of gravity its own accelerometer sees
(mavest.estimator.gyro_unit): refused in one line by the batch calls, never on a
recording in rad/s, simulated or real."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import mavest
from mavest.estimator import InputError
from mavest.estimator.gyro_unit import MIN_WINDOWS, gyro_unit_problem, turn_ratios
from mavest.estimator.smoother import smooth_blocks
from mavest.sim import Motion, simulate

G = 9.80665


@pytest.fixture(scope="module")
def flight():
    return simulate(60.0, 200.0, seed=3, motion=Motion(min_period=2.0, max_period=6.0))


def test_in_rad_s_the_two_turns_agree(flight) -> None:
    """The accelerometer's turn over a window is the gyro's, to its noise: the median
    ratio is near 1 (linear acceleration only adds to the accelerometer's)."""
    ratios = turn_ratios(flight.t, flight.gyro, flight.accel, G, 0.1)
    assert ratios.shape[0] >= MIN_WINDOWS
    assert 0.7 < float(np.median(ratios)) < 1.2
    assert gyro_unit_problem(flight.t, flight.gyro, flight.accel, G, 0.1) is None


@pytest.mark.parametrize(("factor", "unit"), [(180.0 / math.pi, "°/s"), (1000.0, "mrad/s")])
def test_another_unit_is_named_and_refused_by_every_batch_call(flight, factor, unit) -> None:
    gyro = flight.gyro * factor
    problem = gyro_unit_problem(flight.t, gyro, flight.accel, G, 0.1)
    assert problem is not None and f"in {unit}?" in problem and "rad/s" in problem
    assert "\n" not in problem
    for call in (mavest.estimate, mavest.smooth, lambda *a: next(smooth_blocks(*a))):
        with pytest.raises(InputError, match="the gyro turns gravity"):
            call(flight.t, gyro, flight.accel)


def test_a_vehicle_that_tilts_slowly_is_judged_over_longer_windows() -> None:
    """The simulator's own flight, banking ±30° over seconds, had 1–13 windows of
    0.25 s that tilt by 5°: in °/s it was estimated 129° off without a word."""
    from mavest.sim.kinematic import simulate as fly

    slow = fly(duration=60.0, rate=200.0, seed=1)
    assert turn_ratios(slow.t, slow.gyro, slow.accel, G, 0.1).shape[0] < MIN_WINDOWS
    assert gyro_unit_problem(slow.t, slow.gyro, slow.accel, G, 0.1) is None
    problem = gyro_unit_problem(slow.t, np.degrees(slow.gyro), slow.accel, G, 0.1)
    assert problem is not None and "in °/s?" in problem


def test_without_tilting_there_is_no_verdict() -> None:
    """At rest, or turning about the vertical alone, the accelerometer shows no turn to
    compare: nothing is said, whatever the unit."""
    t = np.arange(0.0, 60.0, 0.005)
    accel = np.tile([0.0, 0.0, -G], (t.shape[0], 1))
    gyro = np.zeros_like(accel)
    gyro[:, 2] = 57.3 * 0.5  # (°/s of a steady yaw)
    assert turn_ratios(t, gyro, accel, G, 0.1).shape[0] == 0
    assert gyro_unit_problem(t, gyro, accel, G, 0.1) is None


def test_gaps_and_bad_samples_are_left_out(flight) -> None:
    """A window with a gap, a clock going back or a sample not finite is not compared;
    the rest still tell the unit; windows that each hold a gap tell nothing."""
    t, gyro, accel = flight.t.copy(), np.degrees(flight.gyro), flight.accel.copy()
    t[3000:] += 5.0
    t[6000] = t[5990]
    gyro[100:400] = np.nan
    accel[8000:8100] = np.inf
    ratios = turn_ratios(t, gyro, accel, G, 0.1)
    clean = turn_ratios(flight.t, np.degrees(flight.gyro), flight.accel, G, 0.1)
    assert np.all(np.isfinite(ratios)) and ratios.shape[0] <= clean.shape[0]
    assert gyro_unit_problem(t, gyro, accel, G, 0.1) is not None
    gappy = flight.t + np.floor(np.arange(flight.t.shape[0]) / 20.0)  # 1 s every 20 steps
    assert turn_ratios(gappy, gyro, flight.accel, G, 0.1).shape[0] == 0


def test_absurd_values_are_left_out_without_numpys_warnings(flight) -> None:
    """Values near the float's limit overflowed in the norms, and numpy's warning text
    reached the command line's stderr above mavest's own line."""
    gyro, accel = flight.gyro.copy(), flight.accel.copy()
    gyro[500] = [-1e308, 1e308, 0.0]
    accel[2000:2100, 2] = -1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ratios = turn_ratios(flight.t, gyro, accel, G, 0.1)
    clean = turn_ratios(flight.t, flight.gyro, flight.accel, G, 0.1)
    assert np.all(np.isfinite(ratios)) and 0 < clean.shape[0] - ratios.shape[0] <= 3


def test_real_recordings_in_rad_s_are_never_refused() -> None:
    """BROAD's trials, hand-held with fast turns, taps, vibration and translations: the
    median ratio in rad/s is under 1.2 on every trial; the same samples in °/s are
    refused wherever there are windows enough to tell."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import list_trials, load_trials

    try:
        paths = list_trials()
    except FileNotFoundError as error:
        pytest.skip(f"BROAD is not here: {error}")
    told = 0
    for trial in load_trials(paths, say=lambda line: None):
        ratios = turn_ratios(trial.t, trial.gyro, trial.accel, G, 0.1)
        if ratios.shape[0]:
            assert float(np.median(ratios)) < 1.2, trial.name
        assert gyro_unit_problem(trial.t, trial.gyro, trial.accel, G, 0.1) is None
        if ratios.shape[0] >= MIN_WINDOWS:
            problem = gyro_unit_problem(trial.t, np.degrees(trial.gyro), trial.accel, G, 0.1)
            assert problem is not None, trial.name
            told += 1
    assert told >= 15
