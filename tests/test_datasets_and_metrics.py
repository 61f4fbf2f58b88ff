"""Tests of the data-set plumbing, the BROAD loader, the BROAD scoring and the peer adapters.

The metrics are checked against scipy's Rotation. Tests that need the BROAD recordings
skip, naming MAVEST_DATA, when the data folder is absent (a fresh clone has none).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from mavest.datasets import DATA_ENV_VAR, data_root, require_data
from mavest.evaluation.metrics import (
    attitude_errors,
    heading_offset,
    quat_multiply,
    remove_heading_offset,
    rmse_deg,
    signed_heading_error,
)

# --------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------


def to_rotation(q: np.ndarray) -> Rotation:
    """scipy Rotation from (w, x, y, z): the only place these tests reorder components."""
    q = np.atleast_2d(q)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])


def from_rotation(r: Rotation) -> np.ndarray:
    """(w, x, y, z) from a scipy Rotation."""
    return np.atleast_2d(r.as_quat())[:, [3, 0, 1, 2]]


def random_quats(n: int, seed: int) -> np.ndarray:
    return from_rotation(Rotation.random(n, random_state=seed))


def about_z(angle: np.ndarray | float) -> np.ndarray:
    angle = np.atleast_1d(np.asarray(angle, dtype=np.float64))
    zeros = np.zeros_like(angle)
    return np.stack([np.cos(angle / 2), zeros, zeros, np.sin(angle / 2)], axis=-1)


quaternion = arrays(
    np.float64, 4, elements=st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)
).filter(lambda q: np.linalg.norm(q) > 0.1)

angle_inside_pi = st.floats(-3.1, 3.1, allow_nan=False)


# --------------------------------------------------------------------------
# Data location
# --------------------------------------------------------------------------


def test_data_root_follows_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    assert data_root() == tmp_path.resolve()
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path / "missing"))
    assert data_root() is None


def test_require_data_names_the_variable(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    with pytest.raises(FileNotFoundError, match=DATA_ENV_VAR):
        require_data("broad")
    (tmp_path / "broad").mkdir()
    assert require_data("broad") == tmp_path.resolve() / "broad"
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match=DATA_ENV_VAR):
        require_data("broad")


# --------------------------------------------------------------------------
# Metrics against scipy
# --------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(quaternion, quaternion)
def test_total_error_is_relative_rotation_angle(q_est: np.ndarray, q_true: np.ndarray) -> None:
    errors = attitude_errors(q_est[None], q_true[None])
    expected = (to_rotation(q_est) * to_rotation(q_true).inv()).magnitude()
    np.testing.assert_allclose(errors.total, expected, atol=1e-6)
    # and it is the same angle whichever side the error is taken on
    body_side = (to_rotation(q_true).inv() * to_rotation(q_est)).magnitude()
    np.testing.assert_allclose(errors.total, body_side, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(quaternion, quaternion)
def test_errors_ignore_quaternion_sign_and_scale(q_est: np.ndarray, q_true: np.ndarray) -> None:
    a = attitude_errors(q_est[None], q_true[None])
    b = attitude_errors(-3.0 * q_est[None], 0.5 * q_true[None])
    for field in ("total", "heading", "inclination"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quaternion, angle_inside_pi)
def test_world_vertical_rotation_is_pure_heading(q_true: np.ndarray, angle: float) -> None:
    q_true = q_true / np.linalg.norm(q_true)
    q_est = quat_multiply(about_z(angle), q_true)
    errors = attitude_errors(q_est, q_true[None])
    np.testing.assert_allclose(errors.inclination, 0.0, atol=1e-6)
    np.testing.assert_allclose(errors.heading, abs(angle), atol=1e-9)
    np.testing.assert_allclose(errors.total, abs(angle), atol=1e-6)
    np.testing.assert_allclose(signed_heading_error(q_est, q_true[None]), angle, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quaternion, st.floats(0.0, 2 * np.pi), angle_inside_pi)
def test_horizontal_axis_rotation_is_pure_inclination(
    q_true: np.ndarray, axis_direction: float, angle: float
) -> None:
    q_true = q_true / np.linalg.norm(q_true)
    axis = np.array([np.cos(axis_direction), np.sin(axis_direction), 0.0])
    tilt = from_rotation(Rotation.from_rotvec(angle * axis))
    q_est = quat_multiply(tilt, q_true)
    errors = attitude_errors(q_est, q_true[None])
    np.testing.assert_allclose(errors.heading, 0.0, atol=1e-9)
    np.testing.assert_allclose(errors.inclination, abs(angle), atol=1e-6)
    np.testing.assert_allclose(errors.total, abs(angle), atol=1e-6)


def test_heading_and_inclination_split_a_composed_error() -> None:
    """q_z(ψ) ⊗ q_tilt(φ): heading ψ and inclination φ, in that (world-side) order."""
    q_true = random_quats(50, seed=1)
    psi, phi = np.deg2rad(25.0), np.deg2rad(7.0)
    tilt = from_rotation(Rotation.from_rotvec([phi / np.sqrt(2), phi / np.sqrt(2), 0.0]))
    q_est = quat_multiply(about_z(psi), quat_multiply(tilt, q_true))
    errors = attitude_errors(q_est, q_true)
    np.testing.assert_allclose(errors.heading, psi, atol=1e-9)
    np.testing.assert_allclose(errors.inclination, phi, atol=1e-9)


def test_rmse_uses_mask_and_skips_nan_truth() -> None:
    q_true = random_quats(6, seed=2)
    angles = np.deg2rad([1.0, 2.0, 3.0, 50.0, 4.0, 60.0])
    q_est = quat_multiply(about_z(angles), q_true)
    q_true[4] = np.nan  # lost tracking: skipped
    mask = np.array([True, True, True, False, True, False])
    result = rmse_deg(q_est, q_true, mask)
    expected = np.sqrt(np.mean(np.array([1.0, 2.0, 3.0]) ** 2))
    assert result["heading"] == pytest.approx(expected, abs=1e-9)
    assert result["total"] == pytest.approx(expected, abs=1e-6)
    assert result["inclination"] == pytest.approx(0.0, abs=1e-5)
    assert set(rmse_deg(q_est, q_true)) == {"total", "heading", "inclination"}
    with pytest.raises(TypeError):
        rmse_deg(q_est, q_true, mask.astype(int))


@settings(max_examples=100, deadline=None)
@given(
    st.floats(-np.pi, np.pi),
    st.floats(0.0, 1.0),
    st.floats(0.0, 0.3),
    st.integers(0, 2**32 - 1),
)
# errors spread over half a turn: a search from their circular mean missed the optimum
@example(offset=0.875, heading_noise=0.9467566887890624, tilt_noise=0.15625, seed=494308968)
def test_remove_heading_offset_never_hurts(
    offset: float, heading_noise: float, tilt_noise: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    n = 64
    q_true = from_rotation(Rotation.random(n, random_state=seed))
    tilt_axis = np.column_stack([rng.normal(size=(n, 2)), np.zeros(n)])
    tilt = from_rotation(Rotation.from_rotvec(tilt_noise * tilt_axis))
    heading = about_z(offset + heading_noise * rng.normal(size=n))
    q_est = quat_multiply(heading, quat_multiply(tilt, q_true))
    mask = rng.random(n) < 0.8
    mask[0] = True

    before = rmse_deg(q_est, q_true, mask)
    fixed = remove_heading_offset(q_est, q_true, mask)
    after = rmse_deg(fixed, q_true, mask)
    assert after["heading"] <= before["heading"] + 1e-9
    np.testing.assert_allclose(
        attitude_errors(fixed, q_true).inclination,
        attitude_errors(q_est, q_true).inclination,
        atol=1e-7,
    )
    # it is the optimum: no other constant turn does better (fine grid search)
    psi = signed_heading_error(q_est, q_true)[mask]
    grid = np.linspace(-np.pi, np.pi, 3601)
    wrapped = (psi[None, :] + grid[:, None] + np.pi) % (2 * np.pi) - np.pi
    best_grid = np.degrees(np.sqrt(np.min(np.mean(wrapped**2, axis=1))))
    assert after["heading"] <= best_grid + 1e-6


def test_heading_offset_recovers_a_constant_turn() -> None:
    q_true = random_quats(200, seed=3)
    for offset in (0.3, -2.0, 3.0, np.pi - 1e-3):
        q_est = quat_multiply(about_z(offset), q_true)
        assert heading_offset(q_est, q_true) == pytest.approx(-offset, abs=1e-7)
        fixed = remove_heading_offset(q_est, q_true)
        assert rmse_deg(fixed, q_true)["total"] == pytest.approx(0.0, abs=1e-4)


# --------------------------------------------------------------------------
# BROAD loader: conversion on a synthetic file (needs h5py only)
# --------------------------------------------------------------------------


def test_broad_conversion_on_a_synthetic_file(tmp_path: Path) -> None:
    """IMU level, x east (opt_quat = identity, IMU → ENU): FRD forward = east, yaw +90°."""
    h5py = pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import load_trial

    n = 5
    path = tmp_path / "99_synthetic.hdf5"
    opt_quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    opt_quat[2] = np.nan
    with h5py.File(path, "w") as f:
        f.attrs["sampling_rate"] = 2000.0 / 7.0
        f["imu_gyr"] = np.tile([0.1, 0.2, 0.3], (n, 1))
        f["imu_acc"] = np.tile([0.0, 0.0, 9.81], (n, 1))
        f["imu_mag"] = np.tile([0.0, 20.0, -40.0], (n, 1))  # north, and down (z up)
        f["opt_quat"] = opt_quat
        f["movement"] = np.array([False, True, True, True, False])

    trial = load_trial(path)
    assert trial.name == "99_synthetic"
    np.testing.assert_allclose(trial.t, np.arange(n) * 7.0 / 2000.0)
    np.testing.assert_allclose(trial.gyro[0], [0.1, -0.2, -0.3])
    np.testing.assert_allclose(trial.accel[0], [0.0, 0.0, -9.81])
    np.testing.assert_allclose(trial.mag[0], [0.0, -20.0, 40.0])
    assert np.all(np.isnan(trial.truth_q[2]))
    expected = from_rotation(Rotation.from_euler("z", 90.0, degrees=True))[0]
    np.testing.assert_allclose(np.abs(trial.truth_q[0] @ expected), 1.0, atol=1e-12)
    # the truth maps the FRD field into NED: north-ish and down (z > 0)
    field_ned = to_rotation(trial.truth_q[0]).apply(trial.mag[0])[0]
    np.testing.assert_allclose(field_ned, [20.0, 0.0, 40.0], atol=1e-9)
    assert trial.movement.dtype == bool and trial.movement.sum() == 3
    assert trial.filled == 0


def write_broad_file(
    path: Path,
    n: int = 400,
    *,
    rate: float = 100.0,
    seed: int = 0,
    drop: tuple[str, ...] = (),
    **arrays: np.ndarray,
) -> Path:
    """A BROAD-format trial: the IMU level and still (with noise, ``seed``), its x east
    (``opt_quat`` identity), moving in its middle half; ``arrays`` replace datasets,
    ``drop`` leaves datasets or the ``sampling_rate`` attribute out."""
    import h5py

    rng = np.random.default_rng(seed)
    movement = np.zeros(n, dtype=bool)
    movement[n // 4 : 3 * n // 4] = True
    data = {
        "imu_gyr": rng.normal(0.0, 0.01, (n, 3)),
        "imu_acc": np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.05, (n, 3)),
        "imu_mag": np.array([0.0, 20.0, -40.0]) + rng.normal(0.0, 0.5, (n, 3)),
        "opt_quat": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        "movement": movement,
    } | arrays
    with h5py.File(path, "w") as f:
        if "sampling_rate" not in drop:
            f.attrs["sampling_rate"] = rate
        for key, value in data.items():
            if key not in drop:
                f[key] = value
    return path


def test_non_finite_imu_samples_are_filled_and_left_out_of_the_scoring(tmp_path: Path) -> None:
    """Every filter gets the same finite samples (VQF carried one NaN into 80° errors
    while mavest skipped it); the filled samples are not scored, and counted."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import C_IMU_FRD, load_trial

    n = 400
    clean = load_trial(write_broad_file(tmp_path / "01_clean.hdf5", n))
    assert clean.filled == 0
    gyr = clean.gyro @ C_IMU_FRD.T  # (back in the IMU frame, as stored)
    acc = clean.accel @ C_IMU_FRD.T
    mag = clean.mag @ C_IMU_FRD.T
    gyr[150, 1] = np.nan  # one axis of one sample, while moving
    gyr[160:163] = np.inf  # a stretch
    mag[0] = np.nan  # the first sample: held from the next
    acc[-2:, 2] = -np.inf  # the last two: held from the one before
    path = write_broad_file(tmp_path / "02_holes.hdf5", n, imu_gyr=gyr, imu_acc=acc, imu_mag=mag)
    trial = load_trial(path)

    assert trial.filled == 1 + 3 + 1 + 2
    for values in (trial.gyro, trial.accel, trial.mag):
        assert np.all(np.isfinite(values))
    np.testing.assert_allclose(trial.gyro[150], (clean.gyro[149] + clean.gyro[151]) / 2)
    for k, i in enumerate(range(160, 163), start=1):  # on the line from 159 to 163
        expected = clean.gyro[159] + k / 4 * (clean.gyro[163] - clean.gyro[159])
        np.testing.assert_allclose(trial.gyro[i], expected)
    np.testing.assert_array_equal(trial.mag[0], clean.mag[1])
    np.testing.assert_array_equal(trial.accel[-2:], clean.accel[[-3, -3]])
    untouched = np.ones(n, dtype=bool)
    untouched[[0, 150, 160, 161, 162, n - 2, n - 1]] = False
    np.testing.assert_array_equal(trial.gyro[untouched], clean.gyro[untouched])
    np.testing.assert_array_equal(trial.movement, clean.movement & untouched)
    assert trial.scored.sum() == clean.scored.sum() - 4  # (0 and the end were at rest)


@pytest.mark.parametrize("key", ["imu_gyr", "imu_acc", "imu_mag"])
def test_a_sensor_without_a_finite_sample_is_an_error(tmp_path: Path, key: str) -> None:
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import BroadFileError, load_trial

    path = write_broad_file(tmp_path / "01_blank.hdf5", **{key: np.full((400, 3), np.nan)})
    with pytest.raises(BroadFileError, match=f"{key} has no finite sample"):
        load_trial(path)


def _truncated(path: Path) -> None:
    write_broad_file(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


BAD_FILES = {
    "truncated": (_truncated, "cannot be read as HDF5"),
    "empty": (lambda path: path.write_bytes(b""), "cannot be read as HDF5"),
    "text": (lambda path: path.write_text("not hdf5\n"), "cannot be read as HDF5"),
    "broken link": (lambda path: path.symlink_to(path.parent / "absent"), "not a readable file"),
    "no rate": (lambda path: write_broad_file(path, drop=("sampling_rate",)), "sampling_rate"),
    "rate 0": (lambda path: write_broad_file(path, rate=0.0), "not a rate in Hz"),
    "no magnetometer": (lambda path: write_broad_file(path, drop=("imu_mag",)), "'imu_mag'"),
    "short movement": (
        lambda path: write_broad_file(path, movement=np.ones(399, dtype=bool)),
        "movement is bool (399,), not numbers shaped (400,)",
    ),
    "short truth": (
        lambda path: write_broad_file(path, opt_quat=np.ones((300, 4))),
        "opt_quat is float64 (300, 4)",
    ),
    "text gyro": (lambda path: write_broad_file(path, imu_gyr=np.full((400, 3), b"x")), "imu_gyr"),
    "no samples": (
        lambda path: write_broad_file(
            path, imu_gyr=np.zeros((0, 3)), imu_acc=np.zeros((0, 3)), imu_mag=np.zeros((0, 3))
        ),
        "no samples",
    ),
}


@pytest.mark.parametrize("kind", list(BAD_FILES))
def test_a_bad_file_is_one_error_naming_the_file(tmp_path: Path, kind: str) -> None:
    """Truncated, unrelated or misshaped files raised OSError, KeyError or (later)
    IndexError: now one error type, one line naming the file and what is wrong."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import BroadFileError, load_trial

    make, what = BAD_FILES[kind]
    path = tmp_path / "03_bad.hdf5"
    make(path)
    with pytest.raises(BroadFileError) as raised:
        load_trial(path)
    message = str(raised.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and what in message


def test_load_trials_leaves_out_bad_files_and_copies_with_a_line(tmp_path: Path) -> None:
    """One bad file or a second copy of a recording cost the run: now each is left out
    with one line and the others load (a copy would fall in both halves of a split)."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from mavest.datasets.broad import list_trials, load_trials

    write_broad_file(tmp_path / "02_a.hdf5", seed=2)
    (tmp_path / "02_a_copy.hdf5").write_bytes((tmp_path / "02_a.hdf5").read_bytes())
    (tmp_path / "03_b.HDF5").write_bytes(b"")  # (the suffix in any case)
    write_broad_file(tmp_path / "04_still.hdf5", seed=4, movement=np.zeros(400, dtype=bool))
    gyr = np.random.default_rng(5).normal(0.0, 0.01, (400, 3))
    gyr[7] = np.nan
    write_broad_file(tmp_path / "05_hole.hdf5", seed=5, imu_gyr=gyr)
    (tmp_path / "notes.txt").write_text("not a trial")
    paths = list_trials(tmp_path)
    assert [p.name for p in paths] == [
        "02_a.hdf5",  # (a name before its longer variants)
        "02_a_copy.hdf5",
        "03_b.HDF5",
        "04_still.hdf5",
        "05_hole.hdf5",
    ]

    lines: list[str] = []
    names = [t.name for t in load_trials(paths, lines.append)]
    assert names == ["02_a", "04_still", "05_hole"]
    assert lines == [
        "02_a_copy: the same recording as 02_a; left out",
        f"{tmp_path / '03_b.HDF5'}: cannot be read as HDF5 (Unable to synchronously open file "
        "(file signature not found)); left out",
        "05_hole: 1 sample(s) with a non-finite IMU value filled by interpolation and not scored",
    ]
    lines.clear()
    names = [t.name for t in load_trials(paths, lines.append, scored_only=True)]
    assert names == ["02_a", "05_hole"]
    assert "04_still: nothing to score (no movement sample with known truth); left out" in lines


def test_trial_labels_are_numbers_only_when_they_name_the_trials() -> None:
    from mavest.datasets.broad import trial_labels

    assert trial_labels(["02_a", "10_b"]) == ["02", "10"]
    for names in (["lab_recording_A", "02_a"], ["7_single", "02_a"], ["02_a", "02_a_copy"]):
        assert trial_labels(names) == names


# --------------------------------------------------------------------------
# BROAD recordings (skip without data)
# --------------------------------------------------------------------------

SHORT_TRIAL = "02_undisturbed_slow_rotation_B"


def broad_folder() -> Path:
    root = data_root()
    if root is None or not (root / "broad").is_dir():
        pytest.skip(
            f"BROAD data not found: set {DATA_ENV_VAR} to a folder containing broad/ "
            "(default: ../shared/data beside the project)"
        )
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    return root / "broad"


@pytest.fixture(scope="module")
def broad_trials() -> list:
    from mavest.datasets.broad import list_trials, load_trial

    paths = list_trials(broad_folder())
    if not paths:
        pytest.skip(f"no BROAD .hdf5 files in {broad_folder()} ({DATA_ENV_VAR})")
    return [load_trial(p) for p in paths]


@pytest.fixture(scope="module")
def short_trial(broad_trials: list):
    by_name = {trial.name: trial for trial in broad_trials}
    return by_name.get(SHORT_TRIAL, broad_trials[0])


def rest_window(trial) -> np.ndarray:
    """Indices of a rest phase with valid truth: 12 s to 2 s before the first movement."""
    first = int(np.argmax(trial.movement))
    idx = np.arange(max(0, first - int(12 * trial.rate)), first - int(2 * trial.rate))
    idx = idx[np.all(np.isfinite(trial.truth_q[idx]), axis=1)]
    assert idx.size > trial.rate, f"{trial.name}: no rest phase with truth before movement"
    return idx


def test_broad_trials_are_listed_and_shaped(broad_trials: list) -> None:
    names = [trial.name for trial in broad_trials]
    assert names == sorted(names)
    for trial in broad_trials:
        n = len(trial)
        assert trial.rate == pytest.approx(2000.0 / 7.0, rel=1e-9)
        for array, width in ((trial.gyro, 3), (trial.accel, 3), (trial.mag, 3), (trial.truth_q, 4)):
            assert array.shape == (n, width) and array.dtype == np.float64
        assert trial.movement.shape == (n,) and trial.movement.dtype == bool
        assert trial.movement.any()
        valid = np.all(np.isfinite(trial.truth_q), axis=1)
        np.testing.assert_allclose(np.linalg.norm(trial.truth_q[valid], axis=1), 1.0, atol=1e-9)


def test_broad_accelerometer_reads_minus_g_at_rest(broad_trials: list) -> None:
    for trial in broad_trials:
        mean = trial.accel[rest_window(trial)].mean(axis=0)
        assert np.linalg.norm(mean - [0.0, 0.0, -9.81]) < 0.5, (trial.name, mean)


def test_broad_truth_maps_measured_gravity_to_world_down(broad_trials: list) -> None:
    for trial in broad_trials:
        idx = rest_window(trial)
        down_body = -trial.accel[idx] / np.linalg.norm(trial.accel[idx], axis=1, keepdims=True)
        down_world = to_rotation(trial.truth_q[idx]).apply(down_body).mean(axis=0)
        angle = np.degrees(np.arccos(np.clip(down_world[2] / np.linalg.norm(down_world), -1, 1)))
        assert angle < 2.0, (trial.name, angle)


def test_vqf_adapter_inclination_on_broad(short_trial) -> None:
    pytest.importorskip("vqf", reason="vqf (dev extra) is not installed")
    from mavest.evaluation.peers import run_vqf

    q = run_vqf(short_trial.t, short_trial.gyro, short_trial.accel, rate=short_trial.rate)
    assert q.shape == (len(short_trial), 4)
    scores = rmse_deg(q, short_trial.truth_q, short_trial.movement)
    assert scores["inclination"] < 2.0, scores

    # a 6-D heading is arbitrary; removing the best constant offset only helps
    fixed = remove_heading_offset(q, short_trial.truth_q, short_trial.movement)
    after = rmse_deg(fixed, short_trial.truth_q, short_trial.movement)
    assert after["heading"] <= scores["heading"] + 1e-9
    assert after["inclination"] == pytest.approx(scores["inclination"], abs=1e-6)


@pytest.mark.parametrize(
    ("peer", "module"),
    [("VQF", "vqf"), ("Fusion", "imufusion"), ("Madgwick", "ahrs"), ("Mahony", "ahrs")],
)
def test_peer_frames_on_broad(broad_trials: list, peer: str, module: str) -> None:
    """Every adapter lands in FRD → NED: a wrong frame shows up as tens of degrees.

    The first 35 s of trial 07 (fast rotation; movement from 26.5 s) keep the pure-Python
    peers quick. 9-D also checks the heading (magnetic north along NED x).
    """
    pytest.importorskip(module, reason=f"{module} (dev extra) is not installed")
    from mavest.evaluation.peers import PEERS

    by_name = {trial.name: trial for trial in broad_trials}
    trial = by_name.get("07_undisturbed_fast_rotation_B")
    if trial is None:
        pytest.skip("trial 07_undisturbed_fast_rotation_B is not in the BROAD folder")
    n = int(35 * trial.rate)
    window = trial.movement[:n]
    for mag in (None, trial.mag[:n]):
        q = PEERS[peer](trial.t[:n], trial.gyro[:n], trial.accel[:n], mag, trial.rate)
        scores = rmse_deg(q, trial.truth_q[:n], window)
        assert scores["inclination"] < 5.0, (peer, mag is not None, scores)
        if mag is not None:
            assert scores["heading"] < 10.0, (peer, scores)


def test_mavest_inclination_on_broad_is_within_1_2_of_vqf(broad_trials: list) -> None:
    """Within 1.2× VQF, on all trials and on each half (even / odd trial numbers)."""
    pytest.importorskip("vqf", reason="vqf (dev extra) is not installed")
    from mavest.evaluation.accuracy import mavest_filter, peer_filter, score_inclination

    result = score_inclination(broad_trials, {"mavest": mavest_filter(), "VQF": peer_filter("VQF")})
    numbers = [int(name[:2]) for name in result.trials]
    halves = {
        "all": None,
        "even": [i for i, k in enumerate(numbers) if k % 2 == 0],
        "odd": [i for i, k in enumerate(numbers) if k % 2 == 1],
    }
    for half, subset in halves.items():
        ours, theirs = result.mean("mavest", subset), result.mean("VQF", subset)
        assert ours <= 1.2 * theirs, (half, ours, theirs)
    assert np.all(np.isfinite(result.scores["mavest"]))


def test_an_estimate_that_gives_up_where_it_is_worst_scores_nan() -> None:
    """A filter that outputs NaN on its worst rows must not score better than one that
    keeps estimating: rows with truth and no estimate make the figure NaN."""
    from mavest.evaluation.metrics import missing_rows, scored_rows

    q_true = random_quats(8, seed=5)
    angles = np.deg2rad([1.0, 1.0, 1.0, 1.0, 9.0, 9.0, 9.0, 9.0])
    q_est = quat_multiply(about_z(angles), q_true)
    mask = np.ones(8, dtype=bool)
    whole = rmse_deg(q_est, q_true, mask)["heading"]
    assert whole == pytest.approx(np.sqrt(41.0), abs=1e-9)
    q_est[4:] = np.nan  # the worse half left without an estimate
    assert missing_rows(q_est, q_true, mask) == 4
    assert all(np.isnan(v) for v in rmse_deg(q_est, q_true, mask).values())
    q_est[:4] = 0.0  # a zero quaternion is no estimate either
    assert missing_rows(q_est, q_true) == 8
    # where the truth is lost or the row is not scored, a missing estimate costs nothing
    q_true[4:6] = np.nan
    mask[6:] = False
    q_est[:4] = quat_multiply(about_z(angles[:4]), q_true[:4])
    assert scored_rows(q_true, mask).tolist() == [True] * 4 + [False] * 4
    assert missing_rows(q_est, q_true, mask) == 0
    assert rmse_deg(q_est, q_true, mask)["heading"] == pytest.approx(1.0, abs=1e-9)
    # nothing to score: no row in the mask with truth
    assert not scored_rows(q_true, np.zeros(8, dtype=bool)).any()
    assert np.isnan(rmse_deg(q_est, q_true, np.zeros(8, dtype=bool))["total"])


def test_trial_parity_reads_the_leading_number_or_none() -> None:
    from mavest.evaluation.metrics import trial_parity

    assert trial_parity("07_undisturbed_fast_rotation_B") == 1
    assert trial_parity("10_undisturbed_slow_translation_A") == 0
    assert trial_parity("7_single_digit") == 1
    assert trial_parity("lab_recording_A") is None
    assert trial_parity("") is None
