"""``mavest fleet``: logs → one table on Dask, on a LocalCluster and on a scheduler and
workers started apart (``dask scheduler``, ``dask worker``), as an operator would.

The good logs are short simulated flights (a few seconds, scored after 1 s); the
broken ones are what a folder of real logs holds: an empty file, random bytes, a
tlog cut off mid-packet, a text file.
"""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import io
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("distributed", reason="mavest fleet needs mavest[fleet]")
pytest.importorskip("jsbsim", reason="jsbsim is needed for the simulated flights")

import dask
import fsspec
import pyarrow.parquet as pq
from distributed import Client
from test_estimates_table import file_size_limit
from test_output_files import read_only_folder  # noqa: F401 (a fixture)
from tool_module import load_tool

import mavest._jit as jit
import mavest.fleet.cluster as cluster
from mavest.cli import main
from mavest.datasets import data_root
from mavest.fleet.cluster import Progress, local_cluster, run_fleet
from mavest.fleet.inputs import FleetInputError, expand, output_names
from mavest.fleet.rows import COLUMN_NAMES, LogTask, log_rows, warm_up
from mavest.fleet.table import csv_bytes, parquet_bytes
from mavest.service.config import ServiceConfig
from mavest.service.process import free_port
from mavest.service.runners import replay
from mavest.sim.vehicle import write_flight_tlog

DASK = Path(sys.executable).with_name("dask")
CONFIG = ServiceConfig().replace(input={"settle_time": 1.0})
SETTLE = ["--settle", "1"]


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder as a fleet leaves it: good logs (one in a sub-folder), broken ones, a
    hidden partial file and a text file (not a log by its name)."""
    folder = tmp_path_factory.mktemp("flights")
    (folder / "day2").mkdir()
    for path, seed in ((folder / "a.tlog", 1), (folder / "b.tlog", 2), (folder / "day2/c.tlog", 3)):
        write_flight_tlog(path, 4.0, 100.0, seed=seed)
    (folder / "empty.tlog").write_bytes(b"")
    (folder / "random.bin").write_bytes(os.urandom(5000))
    (folder / "cut.tlog").write_bytes((folder / "a.tlog").read_bytes()[:2001])
    (folder / ".b.tlog.123.partial").write_bytes(b"half")
    (folder / "notes.txt").write_text("landed hard, check the IMU\n")
    return folder


GOOD = ["a.tlog", "b.tlog", "cut.tlog", "day2/c.tlog"]
BROKEN = ["empty.tlog", "random.bin", "notes.txt"]


def _table(path: Path) -> list[dict[str, Any]]:
    return pq.read_table(path).to_pylist()


def _same(a: Any, b: Any) -> bool:
    return a == b or (
        isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
    )


# ------------------------------------------------------------------------ inputs


def test_folders_globs_and_names_expand_to_a_fixed_list(flights: Path) -> None:
    logs, empty = expand([str(flights), str(flights / "notes.txt"), str(flights / "*.tlog")])
    names = [str(Path(p).relative_to(flights)) for p in logs]
    # the folder's logs, sorted, sub-folders too, hidden files not; a text file only when
    # named; a log named twice (the glob) once
    assert names == ["a.tlog", "b.tlog", "cut.tlog", "day2/c.tlog", "empty.tlog", "random.bin",
                     "notes.txt"]  # fmt: skip
    assert empty == []
    logs, empty = expand([str(flights / "*.ulg")])
    assert logs == [] and empty == [f"{flights / '*.ulg'}: no .tlog, .bin or .ulg log there"]


def test_a_url_without_its_backend_is_one_line() -> None:
    with pytest.raises(FleetInputError, match=r"^nosuch://bucket/x.tlog: Protocol not known"):
        expand(["nosuch://bucket/x.tlog"])
    try:
        import s3fs  # noqa: F401
    except ImportError:
        with pytest.raises(FleetInputError, match=r"^s3://bucket/logs/: Install s3fs"):
            expand(["s3://bucket/logs/"])


def test_output_names_are_the_logs_told_apart_in_order() -> None:
    logs = ["x/flight.tlog", "y/flight.tlog", "flight.BIN", "Flight-2.ulg", "memory://b/z.tlog"]
    assert output_names(logs) == ["flight", "flight-2", "flight-3", "Flight-2-2", "z"]


# ---------------------------------------------------------- one log = mavest replay


def test_output_names_of_long_log_names_are_file_names() -> None:
    """A log's name may take the 255 bytes a file name has; its outputs add a suffix."""
    long = "l" * 250
    names = output_names([f"{long}.tlog", f"a/{long}.bin", "é" * 126 + ".ulg"])
    assert names[0] == "l" * 233 and names[1] == "l" * 233 + "-2"
    assert names[2] == "é" * 116  # (whole characters: 232 bytes)
    assert all(len(os.fsencode(f"{n}.estimates.parquet")) <= 255 for n in names)


def test_a_log_s_rows_are_its_replay(flights: Path, tmp_path: Path) -> None:
    log = flights / "a.tlog"
    ours = tmp_path / "fleet.csv"
    (row,) = log_rows(LogTask(str(log), CONFIG, estimates=str(ours)))
    report = asyncio.run(replay(log, CONFIG, progress=False))
    (stream,) = report.streams
    truth = stream.vs_truth.result()
    assert row["status"] == "ok" and row["error"] is None
    assert row["samples"] == stream.stats.estimated > 0
    assert row["duration_s"] == stream.stats.span and row["rate_hz"] == stream.rate
    assert row["tilt_rms_vs_truth_deg"] == truth.inclination_rms
    assert row["heading_rms_vs_truth_deg"] == truth.yaw_rms
    assert row["compared_vs_truth"] == truth.count > 0
    assert math.isnan(row["tilt_rms_vs_autopilot_deg"])  # the simulator sends no ATTITUDE
    assert row["autopilot"] == "ARDUPILOTMEGA" and row["system"] == 1
    assert 0.0 < row["mean_sigma_tilt_deg"] < 10.0
    assert row["records"] == report.records
    # the estimates table is `mavest replay --estimates`'s, byte for byte
    theirs = tmp_path / "replay.csv"
    assert main(["replay", str(log), "--estimates", str(theirs), "-q", *SETTLE]) == 0
    assert ours.read_bytes() == theirs.read_bytes()
    # the mean σ are the table's sigma columns' means from settle_time after the first
    with ours.open(newline="") as file:
        table = list(csv.DictReader(file))
    t = np.array([float(r["time_s"]) for r in table])
    names = [f"sigma_{angle}_deg" for angle in ("roll", "pitch", "yaw")]
    sigma = np.array([[float(r[name]) for name in names] for r in table])
    settled = t >= t[0] + CONFIG.input.settle_time
    assert 0 < np.count_nonzero(settled) < t.shape[0]
    tilt = np.hypot(sigma[settled, 0], sigma[settled, 1])
    assert row["mean_sigma_tilt_deg"] == pytest.approx(tilt.mean(), rel=1e-12)
    assert row["mean_sigma_heading_deg"] == pytest.approx(sigma[settled, 2].mean(), rel=1e-12)


@pytest.mark.parametrize("name", BROKEN)
def test_a_broken_log_is_a_row_with_replay_s_message(
    name: str, flights: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = str(flights / name)
    (row,) = log_rows(LogTask(log, CONFIG))
    assert main(["replay", log, "-q"]) == 2
    said = capsys.readouterr().err.strip()
    assert row["status"] == "error" and f"mavest: {row['error']}" == said
    assert row["samples"] is None


def test_real_logs_rows_are_their_replays() -> None:
    root = data_root()
    if root is None:
        pytest.skip("no shared data (MAVEST_DATA)")
    logs = [root / "tlogs/EAICS_flight.tlog", root / "dataflash/erlerobot_copter_112.BIN"]
    logs = [log for log in logs if log.exists()]
    if not logs:
        pytest.skip("the shared logs are not there")
    for log in logs:
        rows = log_rows(LogTask(str(log), ServiceConfig()))
        report = asyncio.run(replay(log, ServiceConfig(), progress=False))
        assert len(rows) == len(report.streams)
        for row, stream in zip(rows, report.streams, strict=True):
            ours = stream.vs_autopilot.result()
            assert row["samples"] == stream.stats.estimated
            assert _same(
                row["tilt_rms_vs_autopilot_deg"], ours.inclination_rms if ours.count else math.nan
            )
            assert _same(
                row["heading_rms_vs_autopilot_deg"], ours.yaw_rms if ours.count else math.nan
            )
        assert any(row["compared_vs_autopilot"] for row in rows), log
    gappy = root / "tlogs/Phoenix_mission2_2018-09-25_15-36-53.tlog"
    if gappy.exists():  # a gap every few seconds: the first ten warnings, and a count
        (row,) = log_rows(LogTask.of(str(gappy), ServiceConfig()))
        warnings = row["warnings"].split("; ")
        assert len(warnings) == 11 and re.fullmatch(r"\d+ more warnings", warnings[-1])
        assert warnings[0].startswith("RAW_IMU[0] from 1/1: no samples for")


def test_a_remote_log_is_copied_and_replayed(flights: Path) -> None:
    memory = fsspec.filesystem("memory")
    memory.pipe("/fleet/logs/a.tlog", (flights / "a.tlog").read_bytes())
    memory.pipe("/fleet/logs/empty.tlog", b"")
    memory.pipe("/fleet/logs/readme.md", b"not a log")
    logs, _ = expand(["memory://fleet/logs/"])
    assert logs == ["memory:///fleet/logs/a.tlog", "memory:///fleet/logs/empty.tlog"]
    assert expand(["memory://fleet/logs/*.tlog"])[0] == logs
    # memory:// is the process's own: workers in this process (a notebook's Client)
    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as c:
        result = run_fleet([LogTask(log, CONFIG) for log in logs], c)
    remote, empty = result.rows
    (local,) = log_rows(LogTask(str(flights / "a.tlog"), CONFIG))
    assert remote["path"] == logs[0]
    assert all(_same(remote[k], local[k]) for k in COLUMN_NAMES if k != "path")
    assert empty["error"] == "memory:///fleet/logs/empty.tlog is empty"


def test_a_recording_cut_short_is_named_as_it_is_left(flights: Path, tmp_path: Path) -> None:
    """A recording is written under a hidden partial name and renamed when done; a full
    disk's warning named that partial file, gone by the time the row is read."""
    rrd = tmp_path / "a.rrd"
    task = dataclasses.replace(LogTask(str(flights / "a.tlog"), CONFIG), rrd=str(rrd))
    with file_size_limit(20_000):
        (row,) = log_rows(task)
    assert row["status"] == "ok" and row["warnings"], row
    assert ".partial" not in row["warnings"] and str(rrd) in row["warnings"]
    assert rrd.exists() and not list(tmp_path.glob(".*"))


def test_a_file_url_is_the_path_it_names(flights: Path) -> None:
    url = (flights / "a.tlog").as_uri()  # file:///…/a.tlog
    assert url in expand([flights.as_uri() + "/*.tlog"])[0]
    (by_url,) = log_rows(LogTask(url, CONFIG))
    (by_path,) = log_rows(LogTask(str(flights / "a.tlog"), CONFIG))
    assert by_url["path"] == url and by_url["status"] == "ok"
    assert all(_same(by_url[k], by_path[k]) for k in COLUMN_NAMES if k != "path")


# ------------------------------------------------------------------ LocalCluster


def test_a_folder_of_good_and_broken_logs_on_a_local_cluster(
    flights: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    table, out_dir = tmp_path / "fleet.parquet", tmp_path / "each"
    arguments = [str(flights), str(flights / "notes.txt"), "--out", str(table)]
    assert main(["fleet", *arguments, "--out-dir", str(out_dir), "--workers", "2", *SETTLE]) == 0
    printed = capsys.readouterr()
    assert printed.out.strip() == (
        f"7 logs replayed: 4 ok, 3 with an error (the table's error column); wrote {table}"
    )
    assert "Traceback" not in printed.err
    assert len(printed.err.strip().splitlines()) == 3  # a line per broken log
    rows = _table(table)
    assert [str(Path(r["path"]).relative_to(flights)) for r in rows] == [
        "a.tlog", "b.tlog", "cut.tlog", "day2/c.tlog", "empty.tlog", "random.bin", "notes.txt"
    ]  # fmt: skip
    assert [r["status"] for r in rows] == ["ok"] * 4 + ["error"] * 3
    assert all(r["error"] for r in rows[4:]) and all(r["samples"] > 0 for r in rows[:4])
    assert rows[5]["error"].startswith("random.bin: neither")  # replay's words
    # each good log's own outputs, named after it, the table's format
    for name in ("a", "b", "cut", "c"):
        assert (out_dir / f"{name}.rrd").stat().st_size > 0
        assert pq.read_table(out_dir / f"{name}.estimates.parquet").num_rows > 0
    assert not list(out_dir.glob(".*"))  # no partial file left
    (a_row,) = log_rows(LogTask(str(flights / "a.tlog"), CONFIG))
    assert all(_same(rows[0][k], a_row[k]) for k in COLUMN_NAMES)


def test_every_failed_log_is_named_up_to_twenty(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The failures are distinct (a log each): the repeat limiter, which keeps a stream's
    repeated event to three lines, named three of them and counted the rest as "more
    lines like this". Twenty are named, and how many more there are."""
    for i in range(23):
        (tmp_path / f"log{i:02d}.tlog").write_bytes(b"")
    table = tmp_path / "t.csv"
    assert main(["fleet", str(tmp_path), "--out", str(table), "--workers", "1"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[:20] == [f"mavest: {tmp_path}/log{i:02d}.tlog is empty" for i in range(20)]
    assert err[20:] == ["mavest: and 3 more with an error: the table's error column says why"]


def test_an_output_over_an_input_is_refused(
    flights: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    named = tmp_path / "list.csv"
    named.write_text("keep me\n")
    assert main(["fleet", str(flights / "a.tlog"), str(named), "--out", str(named)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"mavest: --out {named} is the log {named}: refusing to write over it"
    )
    # a log's own output in --out-dir that would be a log given
    own = tmp_path / "a.estimates.csv"
    own.write_text("keep me too\n")
    arguments = [str(flights / "a.tlog"), str(own), "--out", str(tmp_path / "t.csv")]
    assert main(["fleet", *arguments, "--out-dir", str(tmp_path)]) == 2
    assert "refusing to write over it" in capsys.readouterr().err
    assert named.read_text() == "keep me\n" and own.read_text() == "keep me too\n"
    # a log named by its file:// URL is as much an input as by its path
    assert main(["fleet", named.as_uri(), "--out", str(named)]) == 2
    assert "refusing to write over it" in capsys.readouterr().err
    # an --out-dir file that is a link to a log (in another folder) given
    logs, out_dir = tmp_path / "logs", tmp_path / "each"
    logs.mkdir()
    out_dir.mkdir()
    keep = logs / "keep.tlog"
    keep.write_bytes((flights / "a.tlog").read_bytes())
    (out_dir / "b.rrd").symlink_to(keep)
    arguments = [str(flights / "b.tlog"), str(keep), "--out", str(tmp_path / "t.csv")]
    assert main(["fleet", *arguments, "--out-dir", str(out_dir)]) == 2
    assert f"is the log {keep}: refusing" in capsys.readouterr().err
    assert keep.read_bytes() == (flights / "a.tlog").read_bytes()
    # a refused run leaves no --out-dir it made
    new = tmp_path / "new" / "each"
    arguments = [str(flights / "a.tlog"), "--out", str(new / "a.estimates.csv")]
    assert main(["fleet", *arguments, "--out-dir", str(new)]) == 2
    assert "is the --out table" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_a_recursive_glob_goes_through_no_link_to_a_folder(flights: Path, tmp_path: Path) -> None:
    """Links back up (``x -> .``) made a ``**`` glob endless (two of them) or name a log
    through 40 links (one); it now finds what a folder argument's walk finds."""
    folder = tmp_path / "loops"
    (folder / "day").mkdir(parents=True)
    for name in ("z.tlog", "day/y.tlog"):
        (folder / name).write_bytes(b"")
    (folder / "x").symlink_to(".")
    (folder / "day" / "up").symlink_to("..")
    (folder / ".hidden").mkdir()
    (folder / ".hidden" / "w.tlog").write_bytes(b"")
    logs, _ = expand([str(folder / "**" / "*.tlog")])
    assert logs == [str(folder / "day" / "y.tlog"), str(folder / "z.tlog")]
    assert expand([str(folder)])[0] == logs


# ------------------------------------------- a scheduler and workers started apart


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """``dask scheduler`` and two ``dask worker`` (one thread each) on 127.0.0.1."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    started = [
        subprocess.Popen(
            [DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            **quiet,
        )
    ]
    try:
        for name in ("w1", "w2"):
            started.append(_worker(address, name))
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for process in reversed(started):
            process.terminate()
        for process in started:
            try:
                process.wait(3)
            except subprocess.TimeoutExpired:  # a worker still saying goodbye
                process.kill()
                process.wait()


def _worker(address: str, name: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [DASK, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
         "--name", name],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip


def test_a_separate_scheduler_gives_the_same_table(
    flights: Path, scheduler: str, tmp_path: Path
) -> None:
    tables = []
    for how in (["--scheduler", scheduler], ["--workers", "1"]):
        table = tmp_path / f"fleet{len(tables)}.csv"
        arguments = [str(flights), str(flights / "notes.txt"), "--out", str(table), "-q"]
        assert main(["fleet", *arguments, *how, *SETTLE]) == 0
        tables.append(table.read_bytes())
    assert tables[0] == tables[1]  # the same bytes, whichever cluster and order
    assert tables[0].count(b"\n") == 1 + len(GOOD) + len(BROKEN)


def test_a_worker_killed_mid_run_loses_no_log(flights: Path, scheduler: str) -> None:
    logs = [str(flights / name) for name in GOOD] * 3
    tasks = [LogTask(log, CONFIG) for log in logs]
    victim = _worker(scheduler, "victim")
    killed: list[str] = []
    with Client(scheduler, timeout="30s") as client:
        client.wait_for_workers(3, timeout=60)
        workers = client.scheduler_info()["workers"]
        address = next(a for a, w in workers.items() if w["name"] == "victim")

        def kill_when_busy(done: int) -> None:
            if killed:
                return
            deadline = time.monotonic() + 10
            while not client.processing().get(address) and time.monotonic() < deadline:
                time.sleep(0.01)
            assert client.processing().get(address), "the victim was given no log"
            victim.send_signal(signal.SIGKILL)
            killed.append(address)

        result = run_fleet(tasks, client, on_done=kill_when_busy)
    victim.wait(10)
    assert killed and victim.returncode == -signal.SIGKILL
    assert [row["path"] for row in result.rows] == logs
    assert all(row["status"] == "ok" for row in result.rows)
    alone = {log: log_rows(LogTask(log, CONFIG))[0]["samples"] for log in set(logs)}
    assert [row["samples"] for row in result.rows] == [alone[log] for log in logs]


# ------------------------------------------------------------------------ Ctrl-C


def test_ctrl_c_writes_the_table_of_what_finished(flights: Path, tmp_path: Path) -> None:
    many = tmp_path / "many"
    many.mkdir()
    for i in range(40):
        shutil.copy(flights / "a.tlog", many / f"f{i:02}.tlog")
    table, out_dir = tmp_path / "fleet.csv", tmp_path / "each"
    command = [sys.executable, "-m", "mavest", "fleet", str(many), "--out", str(table),
               "--out-dir", str(out_dir), "--workers", "1", *SETTLE]  # fmt: skip
    # its own process group, as a terminal's: Ctrl-C reaches the workers too
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 90
    while len(list(out_dir.glob("*.rrd"))) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    lines = table.read_text().splitlines()
    finished = len(lines) - 1
    assert 1 <= finished < 40
    assert err.strip() == (
        f"mavest: interrupted: wrote the {finished} of 40 logs that finished to {table}"
    )
    assert all(line.split(",")[1] == "ok" for line in lines[1:])
    # what the stopped worker was writing is not left behind (hidden, and 190 MB for
    # four logs of 300 s at 1 kHz)
    assert not list(out_dir.glob(".*.partial")), sorted(out_dir.iterdir())


def test_a_log_name_that_is_not_utf8_is_written_with_its_bytes_visible(
    flights: Path, tmp_path: Path
) -> None:
    good = tmp_path / os.fsdecode(b"caf\xe9.tlog")  # a Latin-1 name
    broken = tmp_path / os.fsdecode(b"vid\xe9.tlog")
    shutil.copyfile(flights / "a.tlog", good)
    shutil.copyfile(flights / "empty.tlog", broken)
    rows = [*log_rows(LogTask(str(good), CONFIG)), *log_rows(LogTask(str(broken), CONFIG))]
    assert [row["status"] for row in rows] == ["ok", "error"]
    shown = [f"{tmp_path}/caf\\xe9.tlog", f"{tmp_path}/vid\\xe9.tlog"]
    with io.StringIO(csv_bytes(rows).decode("utf-8")) as text:
        written = list(csv.DictReader(text))
    assert [row["path"] for row in written] == shown
    assert shown[1] in written[1]["error"]  # (the error names the log too)
    table = pq.read_table(io.BytesIO(parquet_bytes(rows))).to_pylist()
    assert [row["path"] for row in table] == shown and shown[1] in table[1]["error"]
    # a name that is UTF-8 is written as it is
    assert csv_bytes([{**rows[0], "path": "café.tlog"}]).decode().count("café.tlog") == 1


def test_an_output_that_cannot_be_written_is_refused_before_any_log_is_replayed(
    flights: Path,
    tmp_path: Path,
    read_only_folder: Path,  # noqa: F811 (the fixture)
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def replayed(*_: Any, **__: Any) -> None:
        raise AssertionError("the logs were replayed before the outputs were checked")

    monkeypatch.setattr(cluster, "run_fleet", replayed)
    log = str(flights / "a.tlog")
    for arguments, option in (
        (["--out", str(read_only_folder / "f.csv")], "--out"),
        (
            ["--out", str(tmp_path / "f.csv"), "--out-dir", str(read_only_folder)],
            "--out-dir's recording",
        ),
    ):
        assert main(["fleet", log, *arguments]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"mavest: {option} {read_only_folder}/"), err
        assert f": cannot write in {read_only_folder}: " in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ro"]


def test_the_csv_of_no_rows_is_its_header() -> None:
    assert csv_bytes([]) == (",".join(COLUMN_NAMES) + "\n").encode()


def test_the_speed_tool_writes_its_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results.md"
    assert load_tool("fleet_speed").main(["--quick", "--results", str(results)]) == 0
    out = capsys.readouterr().out
    assert "| fleet, 2 workers |" in out and "Dask's overhead per log" in out
    section = results.read_text().split("<!-- BEGIN fleet -->\n", 1)[1]
    assert (
        section.startswith("## Fleet\n") and f"\n\n{out.strip()}\n\n<!-- END fleet -->" in section
    )


def test_a_log_that_keeps_killing_workers_is_an_error_row(flights: Path) -> None:
    """With no retry allowed, a worker killed mid-log gives up its logs: their rows say
    so, and the others are whole."""
    logs = [str(flights / name) for name in GOOD] * 2
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        local_cluster(2) as cluster,
        Client(cluster) as client,
    ):
        pids = client.run(os.getpid)
        killed: list[str] = []

        def kill_one(done: int) -> None:
            while not killed:
                busy = [w for w, keys in client.processing().items() if keys]
                if busy:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(busy[0])

        result = run_fleet([LogTask.of(log, CONFIG) for log in logs], client, on_done=kill_one)
    assert [row["path"] for row in result.rows] == logs
    lost = [row for row in result.rows if row["status"] == "error"]
    # the logs the killed worker held (the one it was replaying, those queued on it)
    assert 1 <= len(lost) < len(logs)
    assert all(row["error"].startswith("the workers replaying it died") for row in lost)
    assert all(row["samples"] > 0 for row in result.rows if row["status"] == "ok")


def test_the_progress_bar_says_logs_done_rate_and_time_left() -> None:
    shown = io.StringIO()
    bar = Progress(4, shown, enabled=True)
    bar.update(1)
    bar.update(4)
    bar.finish()
    text = shown.getvalue()
    assert "1 of 4 logs" in text and "4 of 4 logs" in text and "logs/s" in text
    assert "s left" in text
    quiet = io.StringIO()
    Progress(4, quiet).update(1)  # not a terminal: nothing
    assert quiet.getvalue() == ""


def test_fleet_mistakes_are_one_line(
    flights: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    table = str(tmp_path / "t.csv")
    log = str(flights / "a.tlog")
    arguments = ["fleet", log, "--out", table]
    assert main([*arguments, "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"]) == 2
    assert capsys.readouterr().err.startswith("mavest: --workers sizes the local cluster")
    assert main([*arguments, "--scheduler", "nonsense"]) == 2
    assert capsys.readouterr().err.strip() == (
        "mavest: --scheduler nonsense: missing port number in address 'nonsense' (tcp://HOST:PORT)"
    )
    assert main(["fleet", str(flights / "*.ulg"), "--out", table]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == "mavest: no log to replay"
    assert main(["fleet", "nosuch://x/y.tlog", "--out", table]) == 2
    assert (
        capsys.readouterr().err.strip() == "mavest: nosuch://x/y.tlog: Protocol not known: nosuch"
    )
    monkeypatch.setitem(sys.modules, "mavest.fleet.cluster", None)  # Dask not installed
    assert main(arguments) == 2
    assert capsys.readouterr().err.strip() == (
        "mavest: mavest fleet needs Dask: pip install 'mavest[fleet]'"
    )
    assert not Path(table).exists()


def test_local_workers_use_this_process_s_kernel_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """MAVEST_CACHE_DIR reaches the worker processes: they load the kernels compiled
    here (a link to the same cache, so nothing compiles) instead of compiling their own."""
    link = tmp_path / "cache"
    link.symlink_to(jit.CACHE_DIRECTORY.parent)
    monkeypatch.setenv("MAVEST_CACHE_DIR", str(link))
    with local_cluster(1) as cluster, Client(cluster) as client:
        seen = client.run(_cache_directory)
    # (the folder in it is named after the kernels' sources: the same but for an edit)
    assert [Path(folder).parent for folder in seen.values()] == [link]


def _cache_directory() -> str:
    from mavest import _jit

    return str(_jit.CACHE_DIRECTORY)


def test_warm_up_replays_a_log_even_inside_a_running_event_loop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Dask's Client.run calls it in the worker's event loop, where asyncio.run cannot
    # start: the small log is replayed in a thread of its own (else an error row)
    async def inside() -> None:
        warm_up()

    with caplog.at_level(logging.WARNING, logger="mavest"):
        asyncio.run(inside())
    assert "warming up the replay failed" not in caplog.text
