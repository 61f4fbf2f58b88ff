"""The command line: the demo runs and scores itself; mistakes get one line and exit code 2."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mavest import __version__
from mavest.cli import main
from mavest.service.process import MAVEST, mavest_command
from mavest.sim import simulate


def test_demo_flies_through_the_pipeline_and_scores_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["demo", "--seconds", "30", "--rate", "200", "--output-dir", str(tmp_path)]
    assert main(arguments) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if "vs truth (SIMSTATE)" in x)
    tilt = float(line.split("tilt ")[1].split("°")[0])
    assert 0.0 < tilt < 4.0, line
    for name in ("flight.tlog", "mavest.tlog", "mavest.rrd"):
        assert (tmp_path / name).stat().st_size > 0


def test_estimate_reads_csv_and_writes_one_row_per_sample(tmp_path: Path) -> None:
    data = simulate(10.0, 50.0, seed=1)
    source = tmp_path / "imu.csv"
    np.savetxt(source, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    target = tmp_path / "out.csv"
    assert main(["estimate", str(source), "-o", str(target)]) == 0
    rows = np.loadtxt(target, delimiter=",", skiprows=1)
    assert rows.shape == (len(data.t), 15)
    np.testing.assert_allclose(np.linalg.norm(rows[:, 1:5], axis=1), 1.0, atol=1e-8)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["estimate", "{tmp}/missing.csv"], "no such file"),
        (["estimate", "{tmp}"], "is a directory"),
        (["estimate", "{tmp}/words.csv"], "not a CSV of numbers"),
        (["estimate", "{tmp}/narrow.csv"], "expected 7 columns"),
        (["demo", "--config", "{tmp}/bad.toml"], "unknown estimator parameter"),
        (["demo", "--seconds", "-1"], "argument --seconds: -1 is not a number above 0"),
        (["run", "udpin:nowhere"], "needs HOST:PORT"),
        (["sim", "--tlog", "{tmp}/x.tlog"], "--tlog needs --seconds"),
    ],
)
def test_mistakes_get_one_line_and_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    (tmp_path / "words.csv").write_text("t,gx\nnot,numbers\n")
    (tmp_path / "narrow.csv").write_text("0,1,2\n")
    (tmp_path / "bad.toml").write_text("[estimator]\ngyro = 1\n")
    assert main([a.format(tmp=tmp_path) for a in arguments]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


# What the command's process holds in OPENBLAS_NUM_THREADS; numpy, which reads it when
# it loads OpenBLAS, is loaded by the program that launch starts.
_PRINT_BLAS = """
import os, sys
sys.argv = ["mavest", "--version"]
from mavest.launch import main
assert "numpy" not in sys.modules
try:
    main()
except SystemExit:  # argparse's, after --version
    pass
print(os.environ.get("OPENBLAS_NUM_THREADS"))
"""


@pytest.mark.parametrize(("given", "seen"), [(None, "1"), ("3", "3")])
def test_the_command_keeps_openblas_to_one_thread_unless_told(given: str | None, seen: str) -> None:
    environment = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        environment["OPENBLAS_NUM_THREADS"] = given
    done = subprocess.run(
        [sys.executable, "-c", _PRINT_BLAS], env=environment, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["mavest", __version__, seen]


def test_python_dash_m_mavest_is_the_command(tmp_path: Path) -> None:
    done = subprocess.run([*MAVEST, "--version"], capture_output=True, text=True, check=False)
    assert (done.returncode, done.stdout.strip()) == (0, f"mavest {__version__}")
    assert MAVEST[1:] == ["-m", "mavest"]
    # a source tree from before ``python -m mavest`` (a benchmark's baseline) runs its cli
    (tmp_path / "mavest").mkdir()
    assert mavest_command(str(tmp_path))[1:] == ["-m", "mavest.cli"]
    (tmp_path / "mavest" / "__main__.py").touch()
    assert mavest_command(str(tmp_path)) == mavest_command() == MAVEST
