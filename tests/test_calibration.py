"""The covariance scored against truth (mavest.evaluation.calibration, tools/covariance.py).

The metrics are checked on cases whose answer is known: errors drawn from N(0, P) are
calibrated (ratio 1, 95 % inside), σ that follows the error ranks with it (ρ = 1), the
error split is the default chart's and the frame change scipy's. The tool runs on a
short simulated flight, and on one BROAD trial when the shared data is there.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tool_module import load_tool

import mavest
import mavest.datasets.broad as broad
from mavest import EstimatorConfig, estimate
from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.estimator.charts import local_into
from mavest.estimator.layout import CHART_HEADING_TILT, ERROR_LEFT
from mavest.evaluation.calibration import (
    calibration,
    rank_correlation,
    rotate_about_vertical,
    tilt_heading_errors,
    window_rms,
    world_attitude_covariance,
)
from mavest.evaluation.consistency import SCENARIOS, simulate_scenario
from mavest.evaluation.metrics import attitude_errors

tool = load_tool("covariance")

RATE = 100.0


def wxyz(rotation: Rotation) -> np.ndarray:
    return rotation.as_quat()[..., [3, 0, 1, 2]]


def random_spd(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """(n, d, d) covariances of varied size and shape (σ from ~0.1° to ~10°)."""
    a = rng.normal(size=(n, d, d))
    scale = np.radians(10.0 ** rng.uniform(-1.0, 1.0, n))
    return scale[:, None, None] ** 2 * (a @ np.swapaxes(a, 1, 2) / d + 0.1 * np.eye(d))


def draw(rng: np.random.Generator, cov: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=cov.shape[:2]))


@pytest.mark.parametrize(("dof", "threshold"), [(2, 5.991), (1, 3.841)])
def test_errors_drawn_from_the_covariance_are_calibrated(dof: int, threshold: float) -> None:
    rng = np.random.default_rng(1)
    n = 40_000
    cov = random_spd(rng, n, dof)
    errors = draw(rng, cov)
    t = np.arange(n) / RATE
    c = calibration(t, errors if dof == 2 else errors[:, 0], cov if dof == 2 else cov[:, 0, 0])
    assert c.samples == n and c.dof == dof
    assert c.threshold == pytest.approx(threshold, abs=1e-3)
    # Monte Carlo: the ratio's relative spread ~ the spread of tr P, a few % here
    assert c.ratio == pytest.approx(1.0, abs=0.05)
    assert c.inside == pytest.approx(0.95, abs=0.005)  # binomial σ 0.0011
    # the σ per axis the table prints: sqrt(tr P / dof)
    sigma = np.sqrt(np.trace(cov, axis1=1, axis2=2) / dof)
    assert c.sigma_mean == pytest.approx(sigma.mean())
    assert c.sigma_p1 == pytest.approx(np.percentile(sigma, 1.0))
    assert c.sigma_p95 == pytest.approx(np.percentile(sigma, 95.0))
    # a σ twice too large: the ratio halves, nearly every sample is inside
    doubled = calibration(t, errors, 4.0 * cov)
    assert doubled.ratio == pytest.approx(0.5 * c.ratio)
    assert doubled.inside > 0.999


def test_sigma_that_follows_the_error_ranks_with_it() -> None:
    rng = np.random.default_rng(2)
    windows = 30
    level = np.radians(rng.uniform(0.1, 5.0, windows))  # one error level per 1 s window
    per = int(RATE)
    t = np.arange(windows * per) / RATE
    magnitude = np.repeat(level, per)
    direction = rng.normal(size=(len(t), 2))
    errors = magnitude[:, None] * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    proportional = 0.7 * magnitude[:, None, None] ** 2 * np.eye(2)
    c = calibration(t, errors, proportional)
    assert c.windows == windows
    assert c.rank_correlation == pytest.approx(1.0)
    np.testing.assert_allclose(c.window_error, level)
    inverse = (1.0 / magnitude)[:, None, None] ** 2 * np.eye(2)
    assert calibration(t, errors, inverse).rank_correlation == pytest.approx(-1.0)
    # a σ that does not move carries no ranking
    constant = np.broadcast_to(np.eye(2), (len(t), 2, 2))
    assert math.isnan(calibration(t, errors, constant).rank_correlation)
    assert math.isnan(rank_correlation(np.ones(2), np.arange(2.0)))


def test_windows_follow_the_clock_and_skip_sparse_ones() -> None:
    # 2.5 s at 100 Hz, then a gap, then 0.2 s: windows [0, 1), [1, 2) full; [2, 3) half
    # full (kept); [5, 6) a fifth (left out)
    t = np.concatenate([np.arange(250) / RATE, 5.0 + np.arange(20) / RATE])
    values = np.concatenate([np.full(100, 1.0), np.full(100, 2.0), np.full(50, 3.0)])
    values = np.concatenate([values, np.full(20, 9.0)])
    np.testing.assert_allclose(window_rms(t, values)[:, 0], [1.0, 2.0, 3.0])


def test_lost_truth_is_left_out() -> None:
    t = np.arange(400) / RATE
    errors = np.full((400, 2), 0.01)
    errors[:100] = np.nan
    cov = np.broadcast_to(np.eye(2) * 0.01**2, (400, 2, 2))
    c = calibration(t, errors, cov)
    assert c.samples == 300
    assert c.ratio == pytest.approx(1.0)
    assert calibration(t[:0], errors[:0], cov[:0]).samples == 0


def test_the_error_split_is_the_default_chart() -> None:
    rng = np.random.default_rng(3)
    n = 500
    q_est = wxyz(Rotation.random(n, random_state=4))
    # errors from tiny to large, heading anywhere: a 6-D estimate's heading is arbitrary
    tilt = rng.normal(size=(n, 2)) * np.radians(10.0 ** rng.uniform(-4.0, 1.5, n))[:, None]
    psi = rng.uniform(-np.pi, np.pi, n)
    error = Rotation.from_rotvec(psi[:, None] * [0.0, 0.0, 1.0]) * Rotation.from_rotvec(
        np.column_stack([tilt, np.zeros(n)])
    )
    q_true = wxyz(error * Rotation.from_quat(q_est[:, [1, 2, 3, 0]]))
    split = tilt_heading_errors(q_est, q_true)
    np.testing.assert_allclose(split.tilt, tilt, atol=1e-12)
    np.testing.assert_allclose(split.heading, psi, atol=1e-12)
    # the filter's own chart (left, heading-tilt) names the same coordinates
    chart = np.empty(3)
    work = np.empty(4)
    for i in range(0, n, 50):
        local_into(q_true[i], q_est[i], ERROR_LEFT, CHART_HEADING_TILT, chart, work)
        np.testing.assert_allclose(chart, [*split.tilt[i], split.heading[i]], atol=1e-12)
    # |τ| is BROAD's inclination error, |ψ| its heading error
    broad = attitude_errors(q_est, q_true)
    np.testing.assert_allclose(np.linalg.norm(split.tilt, axis=1), broad.inclination, atol=1e-12)
    np.testing.assert_allclose(np.abs(split.heading), broad.heading, atol=1e-12)


def test_small_errors_are_the_components_of_log() -> None:
    rng = np.random.default_rng(5)
    q_est = Rotation.random(200, random_state=6)
    delta = rng.normal(size=(200, 3)) * np.radians(0.5)
    q_true = Rotation.from_rotvec(delta) * q_est
    split = tilt_heading_errors(wxyz(q_est), wxyz(q_true))
    log = (q_true * q_est.inv()).as_rotvec()  # Log(R_true R̂ᵀ), world frame
    # they differ in second order (Baker–Campbell–Hausdorff: ½ ψ ẑ × τ), within ½ |δ|²
    bound = 0.5 * np.sum(delta**2, axis=1)
    assert np.all(np.linalg.norm(split.tilt - log[:, :2], axis=1) <= bound)
    assert np.all(np.abs(split.heading - log[:, 2]) <= bound)
    assert np.max(bound) < 1e-3  # rad: far below the errors themselves


def test_a_body_frame_covariance_is_turned_into_the_world() -> None:
    rng = np.random.default_rng(7)
    n = 100
    r_est = Rotation.random(n, random_state=8)
    p_body = random_spd(rng, n, 3)
    cov = np.zeros((n, 6, 6))
    cov[:, :3, :3] = p_body
    cov[:, 3:, 3:] = np.eye(3)
    p_world = world_attitude_covariance(wxyz(r_est), cov, "right")
    matrices = r_est.as_matrix()
    np.testing.assert_allclose(p_world, matrices @ p_body @ np.transpose(matrices, (0, 2, 1)))
    # a right error δ_b (R = R̂ Exp(δ_b)) is the world error R̂ δ_b: Exp(R̂ δ_b) R̂ = R̂ Exp(δ_b)
    delta_body = draw(rng, p_body)
    r_true = r_est * Rotation.from_rotvec(delta_body)
    delta_world = (r_true * r_est.inv()).as_rotvec()
    np.testing.assert_allclose(delta_world, r_est.apply(delta_body), atol=1e-12)
    nees_body = np.einsum(
        "ni,ni->n", delta_body, np.linalg.solve(p_body, delta_body[..., None])[..., 0]
    )
    nees_world = np.einsum(
        "ni,ni->n", delta_world, np.linalg.solve(p_world, delta_world[..., None])[..., 0]
    )
    np.testing.assert_allclose(nees_world, nees_body, rtol=1e-9)
    np.testing.assert_array_equal(world_attitude_covariance(wxyz(r_est), cov), p_body)
    with pytest.raises(ValueError, match="left"):
        world_attitude_covariance(wxyz(r_est), cov, "up")  # type: ignore[arg-type]


def test_turning_about_the_vertical_moves_error_and_covariance_together() -> None:
    rng = np.random.default_rng(9)
    n = 300
    q_est = wxyz(Rotation.random(n, random_state=10))
    p = random_spd(rng, n, 3)
    q_true = wxyz(Rotation.from_rotvec(draw(rng, p)) * Rotation.from_quat(q_est[:, [1, 2, 3, 0]]))
    before = tilt_heading_errors(q_est, q_true)
    turned_q, turned_p = rotate_about_vertical(q_est, p, math.radians(40.0))
    after = tilt_heading_errors(turned_q, q_true)
    t = np.arange(n) / RATE
    # the tilt vector turns with the world axes, and its covariance with it: same NEES,
    # same share inside; heading moves by the offset
    a = calibration(t, before.tilt, p[:, :2, :2])
    b = calibration(t, after.tilt, turned_p[:, :2, :2])
    assert b.inside == a.inside and b.ratio == pytest.approx(a.ratio, rel=1e-3)
    np.testing.assert_allclose(after.heading, before.heading - math.radians(40.0), atol=1e-9)


# --------------------------------------------------------------------------
# The tool
# --------------------------------------------------------------------------


def test_left_and_right_errors_score_the_same_flight_alike() -> None:
    scenario = next(s for s in SCENARIOS if s.name == "small_9d")
    flight = simulate_scenario(scenario, EstimatorConfig(), seed=3)
    n = 2000
    recording = tool.Recording(
        "simulated",
        "small_9d",
        flight.t[:n],
        flight.gyro[:n],
        flight.accel[:n],
        flight.mag[:n],
        flight.q_true[:n],
        flight.t[:n] >= tool.SETTLE,
    )
    ratios = {}
    for config in (
        EstimatorConfig(error="left", chart="exp"),
        EstimatorConfig(error="right", chart="exp"),
    ):
        series = estimate(recording.t, recording.gyro, recording.accel, recording.mag, config)
        tilt, heading, offset = tool.score(recording, series.q, series.cov, config.error)
        assert offset == 0.0  # the simulated field's north is the truth's
        assert heading is not None
        ratios[config.error] = (tilt.ratio, heading.ratio)
    # The two filters differ in second order only; once the right one's body-frame
    # covariance is turned into the world they score alike (measured: tilt 1.09 and
    # 1.15, heading 1.03 and 0.87), near the honest 1 on the model's own motion.
    for left, right in zip(ratios["left"], ratios["right"], strict=True):
        assert right == pytest.approx(left, rel=0.25)
        assert 0.7 < left < 1.4 and 0.7 < right < 1.4


def test_a_smoother_in_the_package_becomes_an_entry(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    names = [entry.name for entry in tool.estimators()]
    assert names[:3] == ["mavest", "mavest adaptive", "mavest handheld"]
    assert ("mavest.smooth" in names) == hasattr(mavest, "smooth")
    monkeypatch.setattr(mavest, "smooth", lambda *args: None, raising=False)
    names = [entry.name for entry in tool.estimators()]
    assert names[3:] == ["mavest.smooth", "mavest.smooth adaptive", "mavest.smooth handheld"]


def test_a_configuration_file_adds_the_filter_and_the_smoother_with_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "mine.toml"
    config.write_text("[estimator]\nerror = 'right'\nchart = 'exp'\nvelocity_sigma = 0.5\n")
    entries = tool.estimators([config])
    assert [e.name for e in entries[-2:]] == ["mavest (mine.toml)", "mavest.smooth (mine.toml)"]
    assert [e.error for e in entries[-2:]] == ["right", "right"]
    arguments = ["--quick", "--parts", "sim", "--scenario", "small", "--config", str(config)]
    assert tool.main([*arguments, "--estimator", "mavest (mine.toml)"]) == 0
    out = capsys.readouterr().out
    assert "### mavest (mine.toml): simulated 6-D tilt" in out and "### mavest:" not in out
    # σ follows the file's velocity model: smaller than the default's on the same flight
    ours = _sigma_cell(out, "mavest (mine.toml)")
    assert tool.main([*arguments, "--estimator", "mavest"]) == 0
    assert ours < _sigma_cell(capsys.readouterr().out, "mavest")
    config.write_text("[estimator]\nvelocity_sigma = 'fast'\n")
    with pytest.raises(SystemExit) as exit_:
        tool.main(["--config", str(config)])
    assert exit_.value.code == 2
    assert "--config: " in capsys.readouterr().err


def _sigma_cell(out: str, estimator: str) -> float:
    """σ per axis (mean) of an estimator's first simulated tilt row."""
    table = out.split(f"### {estimator}: simulated 6-D tilt", 1)[1]
    row = next(line for line in table.splitlines() if line.startswith("| small seed 0 |"))
    return float(row.strip("|").split("|")[3])


def test_quick_simulated_flight_table_and_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results.md"
    arguments = ["--quick", "--parts", "sim", "--scenario", "small", "--results", str(results)]
    assert tool.main(arguments) == 0
    out = capsys.readouterr().out
    section = results.read_text().split("<!-- BEGIN covariance-on-real-data -->\n", 1)[1]
    assert section.startswith("## Covariance on real data\n")
    assert f"Regenerate: `.venv/bin/python tools/covariance.py {' '.join(arguments)}`" in section
    assert f"\n\n{out.strip()}\n\n<!-- END covariance-on-real-data -->\n" in section
    rows = [line for line in out.splitlines() if line.startswith("| small seed 0 |")]
    assert len(rows) == len(tool.estimators())  # a table per estimator, mavest's first
    cells = [cell.strip() for cell in rows[0].strip("|").split("|")]
    # 30 s at 100 Hz scored after 5 s; the flight carries the motion the filter assumes:
    # measured ratio 0.73, σ per axis 2.4°
    assert cells[1] == "2501"
    assert 0.5 < float(cells[5]) < 1.5
    assert "defaults tuned" not in out  # no BROAD trial in it


def test_estimators_and_trials_are_chosen(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(mavest, "smooth", mavest.estimate, raising=False)
    arguments = ["--quick", "--parts", "sim", "--scenario", "small"]
    assert tool.main([*arguments, "--estimator", "mavest.smooth"]) == 0
    out = capsys.readouterr().out
    assert "estimators: mavest.smooth." in out
    assert "### mavest.smooth: simulated 6-D tilt" in out and "### mavest:" not in out


def test_split_keeps_the_trials_of_one_parity(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    folder = tmp_path / "broad"
    folder.mkdir()
    names = ["02_a", "03_b", "07_c", "10_d", "11_e"]
    for name in names:
        (folder / f"{name}.hdf5").touch()
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    loaded: list[str] = []
    monkeypatch.setattr(broad, "load_trial", lambda path: loaded.append(path.stem) or _stub(path))
    tool.broad_recordings(None, "odd", quick=False)
    assert loaded == ["03_b", "07_c", "11_e"]
    loaded.clear()
    tool.broad_recordings(None, "even", quick=False)
    assert loaded == ["02_a", "10_d"]
    loaded.clear()
    tool.broad_recordings(None, "all", quick=True)  # three, spread over the selection
    assert loaded == ["02_a", "07_c", "11_e"]


def _stub(path: Path) -> object:
    """A one-sample trial: what the recordings are built from (its field its own, so that
    no two are taken for copies of one recording)."""
    one = np.zeros((1, 3))
    mag = np.full((1, 3), float(zlib.crc32(path.stem.encode())))
    return broad.BroadTrial(
        path.stem, RATE, np.zeros(1), one, one, mag, np.ones((1, 4)), np.ones(1, bool)
    )


def test_exits_2_with_one_line_when_broad_is_missing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path / "absent"))
    assert tool.main(["--parts", "broad"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and captured.err.startswith("covariance: ")


def test_one_broad_trial(capsys: pytest.CaptureFixture[str]) -> None:
    root = data_root()
    if root is None or not (root / "broad").is_dir():
        pytest.skip(f"BROAD not found: set {DATA_ENV_VAR} to a folder containing broad/")
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    assert tool.main(["--parts", "broad", "--trials", "07"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 07_undisturbed_fast")]
    # 6-D tilt, 9-D tilt, 9-D heading per estimator, mavest's first
    assert len(rows) == 3 * len(tool.estimators())
    tilt = [cell.strip() for cell in rows[0].strip("|").split("|")]
    # measured: RMSE 1.02°, σ per axis 1.80° (set by velocity_sigma), ratio 0.40
    assert 0.5 < float(tilt[2]) < 1.5
    assert 1.5 < float(tilt[3]) < 2.1
    assert 0.2 < float(tilt[5]) < 0.7
    heading = [cell.strip() for cell in rows[2].strip("|").split("|")]
    assert abs(float(heading[-1])) < 5.0  # north offset, measured −0.09°
    assert "(defaults tuned on these)" in out and "(held out" not in out
    assert "chosen on this trial, so none of its BROAD figures here is held out" in out


def _still_trial(name: str, movement: bool = True, seconds: float = 20.0) -> object:
    """A level trial at rest, truth level and north, scored throughout (or nowhere)."""
    from mavest.datasets.broad import BroadTrial

    n = int(seconds * RATE)
    t = np.arange(n) / RATE
    gyro = np.zeros((n, 3))
    accel = np.tile([0.0, 0.0, -9.81], (n, 1))
    mag = np.tile([20.0, 0.0, 45.0], (n, 1))
    mag[0, 1] = 1e-9 * zlib.crc32(name.encode())  # (its own: no two are taken for copies)
    truth = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return BroadTrial(name, RATE, t, gyro, accel, mag, truth, np.full(n, movement))


def _broad_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, names: list[str]) -> None:
    """A BROAD folder of these (empty) files, each loaded as :func:`_still_trial`; a name
    with "nomove" in it has no movement phase."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    folder = tmp_path / "broad"
    folder.mkdir()
    for name in names:
        (folder / f"{name}.hdf5").touch()
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    monkeypatch.setattr(
        broad, "load_trial", lambda path: _still_trial(path.stem, "nomove" not in path.stem)
    )


def test_split_by_a_number_that_is_not_two_digits_or_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _broad_folder(tmp_path, monkeypatch, ["02_b", "7_single_digit", "lab_recording_A"])
    odd = tool.broad_recordings(None, "odd", quick=False)
    assert [r.name for r in odd] == ["7_single_digit"] * 2  # 6-D and 9-D
    assert capsys.readouterr().err == (
        "covariance: --split odd: lab_recording_A has no trial number: left out\n"
    )
    assert {r.name for r in tool.broad_recordings(None, "even", quick=False)} == {"02_b"}


def test_a_trial_with_nothing_to_score_is_left_out(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _broad_folder(tmp_path, monkeypatch, ["01_nomove", "07_undisturbed_fast_rotation_B"])
    assert tool.main(["--parts", "broad", "--estimator", "mavest"]) == 0
    captured = capsys.readouterr()
    assert (
        "covariance: 01_nomove: nothing to score (no movement sample with known truth); left out\n"
        in (captured.err)
    )
    assert "01_nomove" not in captured.out
    assert "| mavest | BROAD 6-D tilt (defaults tuned on these) | 1 |" in captured.out
    assert "in [0.6, 1.6] | median" in captured.out and "of 2" not in captured.out


def test_trials_tuned_on_and_held_out_are_scored_apart(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    tuned, unseen = "07_undisturbed_fast_rotation_B", "01_undisturbed_slow_rotation_A"
    _broad_folder(tmp_path, monkeypatch, [tuned, unseen])
    assert tool.main(["--parts", "broad", "--estimator", "mavest"]) == 0
    out = capsys.readouterr().out
    summary = [line for line in out.splitlines() if line.startswith("| mavest | BROAD")]
    assert [line.split(" | ")[1:3] for line in summary] == [
        [f"BROAD {quantity} ({kind})", "1"]
        for quantity in ("6-D tilt", "9-D tilt", "9-D heading")
        for kind in ("defaults tuned on these", "held out: defaults not tuned on these")
    ]
    assert "chosen on 1 of these 2 trials" in out and "the other 1 is held out" in out
    assert "reported on" not in out  # no figure measured elsewhere beside this run's
    titles = [line for line in out.splitlines() if line.startswith("### ")]
    for title in titles:
        rows = out.split(title, 1)[1].split("###", 1)[0]
        assert (tuned in rows) != (unseen in rows), title
        assert (tuned in rows) == ("(defaults tuned on these)" in title), title


def test_no_trial_of_a_selection_tuned_on_says_every_figure_is_held_out(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _broad_folder(tmp_path, monkeypatch, ["01_undisturbed_slow_rotation_A", "lab_recording"])
    assert tool.main(["--parts", "broad", "--estimator", "mavest"]) == 0
    out = capsys.readouterr().out
    assert "(defaults tuned on these)" not in out and "none of its BROAD figures" not in out
    assert "not chosen on any of these 2 trials: every BROAD figure here is held out" in out


def test_an_estimator_that_leaves_samples_without_an_estimate_is_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _broad_folder(tmp_path, monkeypatch, ["07_undisturbed_fast_rotation_B"])
    (recording, _) = tool.broad_recordings(None, "all", quick=False)

    def gives_up(recording: object) -> tuple[np.ndarray, np.ndarray]:
        n = len(recording.t)  # type: ignore[attr-defined]
        q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        q[n // 2 :] = np.nan
        return q, np.tile(np.eye(6) * 1e-4, (n, 1, 1))

    (scored,) = tool.run_all([recording], [tool.NamedEstimator("gives up", gives_up, "left")])
    assert scored.tilt.samples == 1000  # of 2000: what the calibration is computed on
    assert (
        "covariance: gives up left 1000 of the 2000 scored samples of "
        "07_undisturbed_fast_rotation_B 6-D without an estimate and covariance: scored on the "
        "rest\n"
    ) in capsys.readouterr().err
