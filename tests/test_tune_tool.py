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
        for key in (
            "gyro_noise_density",
            "gyro_scale_noise_density",
            "velocity_adapt_time",
            "velocity_time",
            "accel_alignment_sigma",
            "mag_heading_noise_density",
        ):
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
