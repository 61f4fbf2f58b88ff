"""tools/tune.py: each profile's grid, the rule, and its section of the results."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from tool_module import load_tool

import mavest
from mavest import EstimatorConfig
from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.datasets.broad import BroadTrial
from mavest.evaluation.calibration import score_attitude
from mavest.sim import Motion, simulate

tool = load_tool("tune")
ROOT = Path(__file__).resolve().parents[1]


def test_the_adaptive_profile_keeps_the_vehicle_prior_and_the_gyro_noise() -> None:
    """adaptive is for any vehicle: only the level and the rate noise are chosen; the
    velocity's correlation time (a prior on the vehicle the IMU cannot measure) and the
    white rate noise stay the defaults'."""
    default = EstimatorConfig()
    for values in tool.PROFILES["adaptive"].grid:
        gyro, _, _, velocity_time, alignment = values
        assert gyro == default.gyro_noise_density
        assert velocity_time == default.velocity_time
        assert alignment == default.accel_alignment_sigma == 0.0
    handheld = tool.PROFILES["handheld"].grid
    assert {v[3] for v in handheld} > {default.velocity_time}
    assert {v[4] for v in handheld} == set(tool.ALIGNMENTS)
    for profile in tool.PROFILES.values():
        assert set(profile.quick_grid) <= set(profile.grid)
        assert (ROOT / profile.config_file).is_file()


def test_each_profile_file_holds_the_choice_its_section_reports() -> None:
    """The rule's choice on all 22 trials, as the results say, is what the file sets."""
    results = (ROOT / "docs/results.md").read_text()
    for profile in tool.PROFILES.values():
        config = EstimatorConfig.from_toml(ROOT / profile.config_file)
        section = results.split(f"## {profile.title}\n", 1)[1].split("<!-- END", 1)[0]
        rule = section.split("The rule applied to all 22 trials", 1)[1]
        for key in tool.RULE_KEYS:
            value = rule.split(f"{key} ", 1)[1].split(" ", 1)[0].rstrip(",.s°")
            if key == "accel_alignment_sigma":  # (printed in degrees)
                value = str(math.radians(float(value)))
            assert float(value) == pytest.approx(getattr(config, key), rel=1e-9, abs=0.0), (
                profile.name,
                key,
            )


def test_one_filter_run_scores_every_alignment_as_its_own_run_would() -> None:
    """The alignment only adds to the covariance reported: scoring it on one run's
    covariance gives what running the filter with it gives (a simulated trial, its
    truth known)."""
    flight = simulate(30.0, 100.0, motion=Motion(velocity_sigma=0.5), seed=4)
    trial = BroadTrial(
        "simulated",
        100.0,
        flight.t,
        flight.gyro,
        flight.accel,
        flight.mag,
        flight.q_true,
        np.ones(flight.t.shape[0], dtype=bool),
    )
    values = (0.005, 0.0, 1.0, 1.0, 0.0)
    shared = tool.score_6d(trial, tool.config_6d(values), tool.ALIGNMENTS)
    assert len({s.ratio for s in shared}) == len(tool.ALIGNMENTS)  # each its own σ
    for alignment, score in zip(tool.ALIGNMENTS, shared, strict=True):
        config = tool.config_6d((*values[:4], alignment))
        own = mavest.estimate(trial.t, trial.gyro, trial.accel, None, config)
        tilt, _, _ = score_attitude(trial.t, own.q, own.cov, trial.truth_q, trial.movement)
        assert score.ratio == pytest.approx(tilt.ratio, rel=1e-12)
        assert score.rho == tilt.rank_correlation
    grouped = tool.PROFILES["handheld"].filter_runs(tool.PROFILES["handheld"].grid)
    assert len(grouped) * len(tool.ALIGNMENTS) == len(tool.PROFILES["handheld"].grid)


def test_the_choice_is_accuracy_first_then_calibration() -> None:
    score = tool.TrialScore
    table = {
        # most accurate, never calibrated
        (0.005, 0.0, 0.0, 1.0, 0.0): [score(1.00, 0.2, 0.0), score(1.00, 0.2, 0.0)],
        # 2 % less accurate (within the slack), calibrated on both
        (0.002, 0.0, 3.0, 0.3, 0.0): [score(1.02, 1.0, 0.5), score(1.02, 1.0, 0.5)],
        # calibrated, but 10 % less accurate
        (0.001, 0.0, 3.0, 0.1, 0.0): [score(1.10, 1.0, 0.9), score(1.10, 1.0, 0.9)],
    }
    assert tool.choose_6d(table, [0, 1]) == (0.002, 0.0, 3.0, 0.3, 0.0)


def test_quick_handheld_run_writes_its_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = data_root()
    if root is None or not (root / "broad").is_dir():
        pytest.skip(f"BROAD not found: set {DATA_ENV_VAR} to a folder containing broad/")
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    results = tmp_path / "results.md"
    arguments = ["--quick", "--profile", "handheld", "--results", str(results)]
    assert tool.main(arguments) == 0
    out = capsys.readouterr().out
    assert out.startswith("Profile handheld (configs/handheld.toml).")
    section = results.read_text().split("<!-- BEGIN cross-validation-hand-held-motion -->\n")[1]
    assert section.startswith("## Cross-validation, hand-held motion\n")
    assert f"Regenerate: `.venv/bin/python tools/tune.py {' '.join(arguments)}`" in section
    assert out.strip() in section


def test_the_closing_line_compares_the_runs_choice_with_the_file() -> None:
    """The closing line printed this run's choice as what the file sets, on any data."""
    profile = tool.PROFILES["adaptive"]
    config = EstimatorConfig.from_toml(ROOT / profile.config_file)
    values = (
        config.gyro_noise_density,
        config.gyro_scale_noise_density,
        config.velocity_adapt_time,
        config.velocity_time,
        config.accel_alignment_sigma,
    )
    same = tool.against_file(profile, (values, config.mag_heading_noise_density))
    assert same == "configs/adaptive.toml sets the same."
    other = tool.against_file(profile, ((*values[:2], 0.0, *values[3:]), 0.02))
    assert other == (
        "configs/adaptive.toml sets otherwise: velocity_adapt_time "
        f"{config.velocity_adapt_time:g} s (this run 0 s), mag_heading_noise_density "
        f"{config.mag_heading_noise_density:g} (this run 0.02)."
    )


def _root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, **trials: dict) -> Path:
    """A data root whose broad/ holds these synthetic trials (name: write_broad_file's
    keywords), MAVEST_DATA pointing at it."""
    from test_datasets_and_metrics import write_broad_file

    (tmp_path / "broad").mkdir()
    for seed, (name, keywords) in enumerate(trials.items()):
        write_broad_file(tmp_path / "broad" / f"{name}.hdf5", seed=seed, **keywords)
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    return tmp_path


STILL = {"movement": np.zeros(400, dtype=bool)}


@pytest.mark.parametrize("name", ["tune", "tune_smooth", "imu_delay"])
@pytest.mark.parametrize(
    ("trials", "lines"),
    [
        (None, ["data set folder"]),
        ({}, ["found 0"]),
        ({"02_a": {}}, ["found 1"]),
        ({"02_a": {}, "03_still": STILL}, ["03_still: nothing to score", "found 1"]),
    ],
)
def test_too_few_trials_to_split_is_one_line_and_exit_2(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    name: str,
    trials: dict | None,
    lines: list[str],
) -> None:
    """No BROAD folder, an empty one, one trial, or one with something to score ended
    in a traceback (max() of an empty sequence) or a NaN choice."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    if trials is None:
        monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))  # (no broad/ in it)
    else:
        _root(tmp_path, monkeypatch, **trials)
    assert load_tool(name).main(["--quick"]) == 2
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert captured.out == "" and len(err) == len(lines)
    for line, expected in zip(err, lines, strict=True):
        assert line.startswith(f"{name}: ") and expected in line


def test_quick_runs_on_other_trials_say_what_they_are(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """On trials other than the shared ones: the defaults' figures are marked in-sample
    only where they are, the halves are named when the names are not numbers, and a
    trial with a non-finite sample, a copy or a trial with nothing to score says so."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    n = 3000
    gyr = np.random.default_rng(9).normal(0.0, 0.01, (n, 3))
    gyr[1000, 0] = np.nan
    movement = np.ones(n, dtype=bool)
    root = _root(
        tmp_path,
        monkeypatch,
        **{
            "02_undisturbed_slow_rotation_B": {"n": n, "movement": movement},
            "lab_recording_A": {"n": n, "movement": movement, "imu_gyr": gyr},
            "lab_recording_still": {"n": n, "movement": ~movement},
        },
    )
    copy = root / "broad" / "lab_recording_B.hdf5"
    copy.write_bytes((root / "broad" / "lab_recording_A.hdf5").read_bytes())

    assert tool.main(["--quick"]) == 0
    captured = capsys.readouterr()
    notes = [line for line in captured.err.splitlines() if line.startswith("tune: ")]
    assert notes == [
        "tune: lab_recording_A: 1 sample(s) with a non-finite IMU value filled by "
        "interpolation and not scored",
        "tune: lab_recording_B: the same recording as lab_recording_A; left out",
        "tune: lab_recording_still: nothing to score (no movement sample with known "
        "truth); left out",
    ]
    out = captured.out
    assert "Halves of the 2 BROAD trials (1 of them among the 22 mavest's defaults" in out
    assert "A = 02_undisturbed_slow_rotation_B; B = lab_recording_A." in out
    assert "shared" not in out
    assert "| lab_recording_A | B |" in out and out.count("| no |\n") == 1
    assert "| 02_undisturbed_slow_rotation_B | A |" in out and out.count("| yes |\n") == 1
    assert " | 0 of 1 |\n" in out and " | 1 of 1 |\n" in out  # (per direction)
    assert "The rule applied to all 2 trials, this run's choice" in out
    assert "configs/adaptive.toml sets" in out

    smooth = load_tool("tune_smooth")
    assert smooth.main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "Halves of the 2 BROAD trials (1 of them among the 22 mavest's defaults" in out
    assert "A = 02_undisturbed_slow_rotation_B; B = lab_recording_A." in out
    assert out.count("| no |\n") == 1 and out.count("| yes |\n") == 1
    assert "this run's choice" in out and "nan" not in out
