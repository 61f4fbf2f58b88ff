"""The command line: the demo runs and scores itself; mistakes get one line and exit code 2."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mavest
from mavest import __version__
from mavest.cli import CSV_COLUMNS, EXIT_INTERRUPTED, main
from mavest.mavlink.tlog import TlogError
from mavest.service.process import MAVEST, mavest_command
from mavest.sim import simulate, vehicle


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


def test_estimate_writes_its_numbers_exactly(tmp_path: Path) -> None:
    """A clock of 1e6 s at 1 kHz (a long-running board's, or epoch time at 200 Hz) keeps
    every sample's time, and each number reads back as the filter gave it."""
    data = simulate(2.0, 1000.0, seed=1)
    t = 1e6 + np.arange(len(data.t)) * 1e-3
    source = tmp_path / "imu.csv"
    np.savetxt(source, np.column_stack([t, data.gyro, data.accel]), delimiter=",", fmt="%.17g")
    target = tmp_path / "out.csv"
    assert main(["estimate", str(source), "-o", str(target)]) == 0
    rows = np.loadtxt(target, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(rows[:, 0], np.loadtxt(source, delimiter=",")[:, 0])
    expected = mavest.estimate(np.loadtxt(source, delimiter=",")[:, 0], data.gyro, data.accel)
    np.testing.assert_array_equal(rows[:, 1:5], expected.q)


def test_estimate_writes_its_csv_a_piece_at_a_time(tmp_path: Path) -> None:
    # The text of the whole table at once, and all its numbers as Python floats, came to
    # over three times the file's size on top of the estimates themselves; in pieces,
    # what is left is reading the input and the columns in degrees.
    import tracemalloc

    data = simulate(50.0, 400.0, seed=1)
    source = tmp_path / "imu.csv"
    np.savetxt(source, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    target = tmp_path / "out.csv"
    assert main(["estimate", str(source), "-o", str(target)]) == 0  # (compiled, loaded)
    tracemalloc.start()
    try:
        mavest.estimate(data.t, data.gyro, data.accel)
        estimating = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        assert main(["estimate", str(source), "-o", str(target)]) == 0
        whole = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert whole - estimating < 2 * target.stat().st_size, (whole, estimating)


def test_estimate_writes_parquet_when_asked_the_same_table_as_its_csv(tmp_path: Path) -> None:
    pq = pytest.importorskip("pyarrow.parquet", reason="Parquet needs pyarrow")
    data = simulate(3.0, 200.0, seed=2)
    source = tmp_path / "imu.csv"
    np.savetxt(source, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    as_csv, as_parquet = tmp_path / "out.csv", tmp_path / "out.parquet"
    assert main(["estimate", str(source), "-o", str(as_csv)]) == 0
    assert main(["estimate", str(source), "-o", str(as_parquet)]) == 0
    first = as_parquet.read_bytes()
    assert first.startswith(b"PAR1")  # (a CSV named .parquet before)
    table = pq.read_table(as_parquet)
    header = as_csv.read_text().splitlines()[0].split(",")
    assert table.column_names == header
    rows = np.loadtxt(as_csv, delimiter=",", skiprows=1)
    for at, name in enumerate(header):
        np.testing.assert_array_equal(table.column(name).to_numpy(), rows[:, at])
    assert table.column("flags").type == "int64"
    assert main(["estimate", str(source), "-o", str(as_parquet)]) == 0
    assert as_parquet.read_bytes() == first  # the same bytes every run


def test_estimate_to_parquet_without_pyarrow_is_one_line_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "pyarrow" else real(name, *a)
    )
    target = tmp_path / "out.parquet"
    assert main(["estimate", str(tmp_path / "never-read.csv"), "-o", str(target)]) == 2
    assert "Parquet needs pyarrow" in capsys.readouterr().err
    assert not target.exists()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["estimate", "{tmp}/missing.csv"], "no such file"),
        (["estimate", "{tmp}"], "is a directory"),
        (["estimate", "{tmp}/words.csv"], "not a CSV of numbers"),
        (["estimate", "{tmp}/narrow.csv"], "expected 7 columns"),
        (["estimate", "{tmp}/narrow.csv", "--config", "{tmp}/binary"], "is not a TOML file"),
        (["estimate", "{tmp}/narrow.csv", "--config", "{tmp}/huge.toml"], "gyro_noise_density"),
        (["demo", "--config", "{tmp}/bad.toml"], "unknown estimator parameter"),
        (["demo", "--seconds", "-1"], "argument --seconds: -1 is not a number above 0"),
        (["demo", "--seconds", "1e300"], "1e300 is not a number above 0 to 86400"),
        (["sim", "--tlog", "{tmp}/x.tlog", "--seconds", "1e9"], "--seconds up to 86400"),
        (["run", "udpin:nowhere"], "needs HOST:PORT"),
        (["sim", "--tlog", "{tmp}/x.tlog"], "--tlog needs --seconds"),
    ],
)
def test_mistakes_get_one_line_and_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    (tmp_path / "words.csv").write_text("t,gx,gy,gz,ax,ay,az\nnot,numbers\n")
    (tmp_path / "binary").write_bytes(b"\x00\x00\x00\x01\xfd\xfe" * 100)
    (tmp_path / "huge.toml").write_text("[estimator]\ngyro_noise_density = 1e308\n")
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


# How the collector fared while the command loaded: the collections it made, whether it
# is on afterwards, how many objects loading left frozen out of its reach.
_PRINT_COLLECTOR = """
import gc, sys
sys.argv = ["mavest", "--version"]
collections = []
gc.callbacks.append(lambda phase, info: phase == "start" and collections.append(info))
from mavest.launch import main
before = len(collections)
try:
    main()
except SystemExit:  # argparse's, after --version
    pass
print(len(collections) - before, gc.isenabled(), gc.get_freeze_count())
"""


def test_the_command_loads_without_the_collector_and_runs_with_it() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _PRINT_COLLECTOR], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    collections, enabled, frozen = done.stdout.split()[-3:]
    # (with it on, loading made over a hundred collections)
    assert (collections, enabled) == ("0", "True")
    assert int(frozen) > 100_000


# The command run as its entry point does, with an exit handler of the kind Rerun and
# logging register (here: one line on standard error, after standard output's line)
# and, if asked, a thread of the program's own still at work when the command is done.
_COMMAND_WITH_A_HANDLER = """
import atexit, sys, threading, time
from pathlib import Path
atexit.register(lambda: print("handler ran", file=sys.stderr))
if len(sys.argv) > 2:
    mark = Path(sys.argv[2])
    def late() -> None:
        time.sleep(0.3)
        mark.write_text("the thread finished")
    threading.Thread(target=late).start()
sys.argv = ["mavest", *sys.argv[1].split()]
from mavest.launch import command
command()
"""


@pytest.mark.parametrize(
    ("arguments", "code"), [("--version", 0), ("replay /nonexistent/flight.tlog", 2)]
)
def test_the_command_leaves_with_its_status_after_the_exit_handlers(
    arguments: str, code: int
) -> None:
    done = subprocess.run(
        [sys.executable, "-c", _COMMAND_WITH_A_HANDLER, arguments],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == code, done.stderr
    assert done.stderr.splitlines()[-1] == "handler ran"
    if code == 0:  # (standard output, a pipe here, written out before leaving)
        assert done.stdout == f"mavest {__version__}\n"


def test_the_command_waits_for_a_thread_still_at_work(tmp_path: Path) -> None:
    """With a thread of the program still running, the interpreter's own exit, which
    waits for it, rather than the quick one."""
    mark = tmp_path / "thread.txt"
    done = subprocess.run(
        [sys.executable, "-c", _COMMAND_WITH_A_HANDLER, "--version", str(mark)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert (done.returncode, done.stderr.splitlines()[-1]) == (0, "handler ran")
    assert mark.read_text() == "the thread finished"


def test_python_dash_m_mavest_is_the_command(tmp_path: Path) -> None:
    done = subprocess.run([*MAVEST, "--version"], capture_output=True, text=True, check=False)
    assert (done.returncode, done.stdout.strip()) == (0, f"mavest {__version__}")
    assert MAVEST[1:] == ["-m", "mavest"]
    # a source tree from before ``python -m mavest`` (a benchmark's baseline) runs its cli
    (tmp_path / "mavest").mkdir()
    assert mavest_command(str(tmp_path))[1:] == ["-m", "mavest.cli"]
    (tmp_path / "mavest" / "__main__.py").touch()
    assert mavest_command(str(tmp_path)) == mavest_command() == MAVEST


# ------------------------------------------------------------------ estimate: its input


def _imu_csv(path: Path, t_scale: float = 1.0, **changes: tuple[int, float]) -> np.ndarray:
    """Four seconds of simulated samples at 50 Hz as the CSV estimate reads; ``changes``
    sets row → t (``t``) or the gyro's x (``gx``) in some rows."""
    data = simulate(4.0, 50.0, seed=1)
    table = np.column_stack([data.t * t_scale, data.gyro, data.accel])
    for column, (row, value) in changes.items():
        table[row, CSV_COLUMNS.index(column)] = value
    np.savetxt(path, table, delimiter=",")
    return table


@pytest.mark.parametrize(
    ("header", "said"),
    [
        (
            "time,acc_x,acc_y,acc_z,gyro_x,gyro_y,gyro_z",
            "not understood: 'time', 'acc_x', 'acc_y', 'acc_z', 'gyro_x', 'gyro_y', 'gyro_z'; "
            "missing: t, gx, gy, gz, ax, ay, az; understood: none",
        ),
        (
            "t,gx,gy,gz,ax,ay,accel_z",
            "not understood: 'accel_z'; missing: az; understood: t, gx, gy, gz, ax, ay",
        ),
        ("t,gx,gy,gz,ax,ay,ay", "named twice: ay; missing: az; understood: t, gx"),
    ],
)
def test_a_header_of_other_names_is_refused_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], header: str, said: str
) -> None:
    """Read in the default order, such a file would take the accelerometer for the gyro."""
    table = _imu_csv(tmp_path / "plain.csv")
    path = tmp_path / "named.csv"
    np.savetxt(path, table, delimiter=",", header=header, comments="")
    assert main(["estimate", str(path), "-o", str(tmp_path / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1, err
    assert not (tmp_path / "out.csv").exists()


def test_a_header_with_a_byte_order_mark_crlf_and_spaces_is_read(tmp_path: Path) -> None:
    table = _imu_csv(tmp_path / "plain.csv")
    rows = "".join(
        ",".join(repr(float(v)) for v in row[[4, 5, 6, 0, 1, 2, 3]]) + "\r\n" for row in table
    )
    (tmp_path / "named.csv").write_bytes(
        ("\ufeff ax, ay ,az,T,gx,gy,gz\r\n" + rows).encode("utf-8")
    )
    for name in ("plain", "named"):
        assert main(["estimate", str(tmp_path / f"{name}.csv"), "-o", str(tmp_path / name)]) == 0
    assert (tmp_path / "plain").read_bytes() == (tmp_path / "named").read_bytes()


@pytest.mark.parametrize(
    ("changes", "t_scale", "said"),
    [
        ({}, 1.0, []),
        (
            {"gx": (20, math.nan), "t": (30, math.nan)},
            1.0,
            ["2 samples skipped: gyro invalid (1), time not increasing (1)"],
        ),
        ({"t": (40, 0.76)}, 1.0, ["1 sample skipped: time not increasing (1)"]),
        (
            {"t": (100, 1e9)},
            1.0,
            ["1 sample skipped: time off timeline (1)"],
        ),
        (
            {},
            1000.0,
            [
                "gap realigned: 200 samples (the median step of t is 20: milliseconds? t must "
                "be in seconds)"
            ],
        ),
        (
            {},
            1e6,
            [
                "200 samples skipped: time off timeline (200); the median step of t is 20000: "
                "microseconds? t must be in seconds"
            ],
        ),
        (
            {},
            1e9,
            [
                "200 samples skipped: time off timeline (200); the median step of t is 2e+07: "
                "nanoseconds? t must be in seconds"
            ],
        ),
        (
            {"gx": (50, 40.0)},  # (beyond MAX_ANGULAR_RATE a sample is skipped, not clipped)
            1.0,
            ["gyro clipped: 1 sample (beyond gyro_clip = 33.86: °/s? the gyro must be in rad/s)"],
        ),
        (
            {"gx": (50, 100.0)},
            1.0,
            ["1 sample skipped: gyro invalid (1); beyond 50 rad/s: °/s? the gyro must be in rad/s"],
        ),
    ],
    ids=["clean", "nan", "back", "jump", "ms", "us", "ns", "clipped", "beyond"],
)
def test_estimate_says_what_the_flags_tell_of_its_samples(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    changes: dict[str, tuple[int, float]],
    t_scale: float,
    said: list[str],
) -> None:
    path = tmp_path / "imu.csv"
    _imu_csv(path, t_scale, **changes)
    assert main(["estimate", str(path), "-o", str(tmp_path / "out.csv")]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"mavest: {path}: {line}" for line in said]


# ------------------------------------------------------------------ outputs that fail


def _small_tlog(path: Path) -> None:
    """Two seconds of RAW_IMU at 200 Hz at rest, a HEARTBEAT a second."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    records = []
    for i in range(400):
        stamp = (1_700_000_000_000_000 + i * 5000).to_bytes(8, "big")
        if i % 200 == 0:
            records.append(stamp + mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3).pack(mav))
        imu = mavlink2.MAVLink_raw_imu_message(i * 5000, 0, 0, -1000, 0, 0, 0, 200, 0, 400)
        records.append(stamp + imu.pack(mav))
    path.write_bytes(b"".join(records))


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
@pytest.mark.parametrize("command", ["estimate", "replay"])
def test_a_full_standard_output_is_one_line_and_exit_code_2(tmp_path: Path, command: str) -> None:
    if command == "estimate":
        source = tmp_path / "imu.csv"
        _imu_csv(source)
    else:
        source = tmp_path / "in.tlog"
        _small_tlog(source)
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [*MAVEST, command, str(source), "-q"], stdout=full, stderr=subprocess.PIPE, text=True
        )
    assert done.returncode == 2, done.stderr
    assert done.stderr == "mavest: cannot write to standard output: No space left on device\n"


def test_a_file_name_that_is_not_text_in_the_locale_is_printed_escaped(tmp_path: Path) -> None:
    """A Linux file name is bytes: ``r\xe9.csv`` is no UTF-8. Standard output in a UTF-8
    locale is strict (unlike the C locale's): the summary's last line ended the run in
    a traceback, the file written. It is escaped now, as standard error does."""
    source = tmp_path / "in.tlog"
    _small_tlog(source)
    out = os.fsdecode(bytes(tmp_path) + b"/r\xe9.csv")
    env = {**os.environ, "PYTHONIOENCODING": "utf-8:strict"}  # (a UTF-8 locale's stdout)
    done = subprocess.run(
        [*MAVEST, "replay", str(source), "--estimates", out],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert "r\\udce9.csv (estimates table)" in done.stdout
    assert Path(out).stat().st_size > 0


@pytest.mark.parametrize("command", [["sim", "--seconds", "1", "--tlog"], ["demo", "--output-dir"]])
def test_a_tlog_that_cannot_be_written_is_one_line(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
) -> None:
    """Beyond what the outputs' check can see (a folder made read-only meanwhile, a
    quota): the writer's own error."""

    def refused(path: Path, *args: object) -> str:
        raise TlogError(f"cannot write {path}: Read-only file system")

    monkeypatch.setattr(vehicle, "write_flight_tlog", refused)
    target = tmp_path / "x.tlog" if command[0] == "sim" else tmp_path
    assert main([*command, str(target)]) == 2
    err = capsys.readouterr().err
    assert "Read-only file system" in err and err.count("\n") == 1, err


def test_a_simulated_flight_onto_a_full_disk_is_not_said_written(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The writer stops at its last whole record when the disk is full; the command
    ends on it (exit 2) instead of saying it wrote the flight."""
    pytest.importorskip("jsbsim", reason="jsbsim (sim extra) flies the simulated vehicle")
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    assert main(["sim", "--tlog", "/dev/full", "--seconds", "2", "--rate", "100"]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "not all written" in err, err
    assert "Traceback" not in err and "wrote /dev/full" not in err


# SIGTERM while the output is being written: the signal arrives as the partial file,
# already holding the table, is synced to disk.
_TERMINATED_WHILE_WRITING = """
import os, signal, sys
from mavest.cli import main
fsync = os.fsync
def fsync_after_sigterm(fd):
    if os.fstat(fd).st_size > 0:
        os.kill(os.getpid(), signal.SIGTERM)
    fsync(fd)
os.fsync = fsync_after_sigterm
sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_while_estimate_writes_is_ctrl_c(tmp_path: Path) -> None:
    source = tmp_path / "imu.csv"
    _imu_csv(source)
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            _TERMINATED_WHILE_WRITING,
            "estimate",
            str(source),
            "-o",
            str(tmp_path / "out.csv"),
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == EXIT_INTERRUPTED, done.stderr
    assert done.stderr.splitlines()[-1:] == ["mavest: interrupted"], done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imu.csv"]  # no partial, no output
