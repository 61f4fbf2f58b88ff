"""tools/motion_prior.py: its spectral predictions against a simulated Gauss–Markov
velocity, and its table on BROAD."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import signal
from tool_module import load_tool

from mavest.datasets import DATA_ENV_VAR, data_root

tool = load_tool("motion_prior")
TAU = 3.0


def _gauss_markov(time: float, n: int, dt: float, seed: int) -> np.ndarray:
    """A unit-variance Gauss–Markov velocity, two independent axes."""
    gamma = math.exp(-dt / time)
    noise = np.random.default_rng(seed).normal(0.0, math.sqrt(1.0 - gamma**2), (n, 2))
    return signal.lfilter([1.0], [1.0, -gamma], noise, axis=0)


@pytest.mark.parametrize("time", [0.1, 1.0])
def test_the_spectra_agree_with_a_simulated_velocity(time: float) -> None:
    dt, n = 0.002, 3_000_000  # 6000 s (the spectra are continuous: a fine step)
    velocity = _gauss_markov(time, n, dt, seed=int(10 * time))
    accel = np.diff(velocity, axis=0, prepend=0.0) / dt
    b, a = signal.bilinear([2.0 / TAU**2], [1.0, 2.0 / TAU, 2.0 / TAU**2], fs=1.0 / dt)
    lowpassed = signal.lfilter(b, a, accel, axis=0)[n // 10 :]
    # the low-passed acceleration: what the filter's gravity direction is wrong by
    assert np.sqrt(np.mean(lowpassed**2)) == pytest.approx(
        tool.predicted_error(1.0, time, TAU), rel=0.05
    )
    departure = accel - signal.lfilter(b, a, accel, axis=0)
    kept = []
    for leak in (tool.LONG, tool.SHORT):
        fast = signal.lfilter([dt], [1.0, -math.exp(-dt / leak)], departure, axis=0)
        kept.append(float(np.mean(fast[n // 10 :] ** 2)))
        assert kept[-1] == pytest.approx(tool.fast_share(time, leak, TAU), rel=0.05)
    # and the correlation time read back from the two
    assert float(tool.ratio_to_time(kept[1] / kept[0], TAU)) == pytest.approx(time, rel=0.15)


def test_the_share_kept_at_one_second_is_the_designs() -> None:
    # docs/design.md: the model's own velocity keeps 1/1.71 of its variance through the
    # measure, so a gain of 2 errs safe (computed there by simulation, here by spectrum)
    assert 1.0 / tool.fast_share(1.0, 1.0, TAU) == pytest.approx(1.71, abs=0.05)


def test_one_broad_trial(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = data_root()
    if root is None or not (root / "broad").is_dir():
        pytest.skip(f"BROAD not found: set {DATA_ENV_VAR} to a folder containing broad/")
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    results = tmp_path / "results.md"
    assert tool.main(["--trials", "10", "--results", str(results)]) == 0
    out = capsys.readouterr().out
    (row,) = [line for line in out.splitlines() if line.startswith("| 10_")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    actual, predicted = float(cells[4]), float(cells[5])
    # measured: 0.176° of low-pass error against 0.595° predicted at 1 s
    assert actual < 0.5 * predicted
    assert "## Motion prior" in results.read_text()


def test_exits_2_with_one_line_without_broad(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path / "absent"))
    assert tool.main([]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("motion_prior: ")


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_a_trial_with_nothing_to_score_or_a_bad_file_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A trial without movement printed a row of NaN and RuntimeWarnings; a bad file
    ended the run in a traceback."""
    pytest.importorskip("h5py", reason="h5py (dev extra) is needed to read BROAD")
    from test_datasets_and_metrics import write_broad_file

    broad = tmp_path / "broad"
    broad.mkdir()
    write_broad_file(broad / "01_moving.hdf5", 2000, seed=1)
    write_broad_file(broad / "02_still.hdf5", 2000, seed=2, movement=np.zeros(2000, dtype=bool))
    (broad / "03_broken.hdf5").write_bytes(b"")
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    assert tool.main([]) == 0
    captured = capsys.readouterr()
    rows = [line for line in captured.out.splitlines() if line.startswith("| 0")]
    assert len(rows) == 1 and rows[0].startswith("| 01_moving |") and "nan" not in rows[0]
    err = captured.err.splitlines()
    assert len(err) == 2 and all(line.startswith("motion_prior: ") for line in err)
    assert "02_still: nothing to score" in err[0] and "03_broken.hdf5: cannot be read" in err[1]

    (broad / "01_moving.hdf5").unlink()
    assert tool.main([]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "motion_prior: no BROAD trial with something to score is left"
