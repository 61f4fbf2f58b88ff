"""``mavest fleet``'s cluster at its edges: a scheduler address Dask cannot use, a stop
while the local cluster starts, workers that die mid-log (their hidden partial files,
Dask's words about them)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("distributed", reason="mavest fleet needs mavest[fleet]")
pytest.importorskip("jsbsim", reason="jsbsim is needed for the simulated flights")

import dask
from distributed import LocalCluster, Security
from test_fleet import SETTLE

from mavest.fleet.cluster import FleetError, run_fleet
from mavest.fleet.rows import LogTask
from mavest.service.config import ServiceConfig
from mavest.sim.vehicle import write_flight_tlog

PARTIAL = re.compile(r"\.(\d+)\.partial$")
# in --out-dir beside the outputs: a user's file named like a partial file, and a
# partial file of another process's (pid 1, never a worker)
DECOYS = (".long.rrd.backup.partial", ".long.rrd.1.partial")


@pytest.fixture(scope="module")
def long_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A flight long enough (30 s at 400 Hz) for its outputs to be half-written a while."""
    path = tmp_path_factory.mktemp("long") / "long.tlog"
    write_flight_tlog(path, 30.0, 400.0, seed=7)
    return path


def _mavest(*arguments: str, **popen: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "mavest", *arguments],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,  # type: ignore[call-overload]
    )


# ------------------------------------------------------------- --scheduler addresses


@pytest.mark.parametrize("address", ["http://127.0.0.1:1", "inproc://x", "tls://127.0.0.1:1"])
def test_a_scheduler_address_dask_cannot_use_is_one_line_at_once(
    address: str, tmp_path: Path
) -> None:
    log, table = tmp_path / "a.tlog", tmp_path / "t.csv"
    log.write_bytes(b"\xfe" * 64)
    started = time.monotonic()
    process = _mavest("fleet", str(log), "--out", str(table), "--scheduler", address)
    out, err = process.communicate(timeout=90)
    # no Client left half-made: nothing 20 s later from its closing, no traceback
    assert time.monotonic() - started < 15, err
    assert process.returncode == 2, err
    assert out == "" and err.count("\n") == 1, err
    assert err.startswith(f"mavest: --scheduler {address}: "), err
    assert "tcp://HOST:PORT" in err or "distributed.comm.tls.ca-file" in err, err
    assert not table.exists()


def test_tls_needs_dask_s_tls_settings_and_connects_with_them(tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make the cluster's certificate")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
         "-subj", "/CN=fleet", "-keyout", str(key), "-out", str(cert)],
        check=True,
        capture_output=True,
    )  # fmt: skip
    log = tmp_path / "empty.tlog"
    log.write_bytes(b"")
    tasks = [LogTask(str(log), ServiceConfig())]
    with pytest.raises(FleetError, match=r"^--scheduler tls://127.0.0.1:1: tls:// needs Dask"):
        run_fleet(tasks, "tls://127.0.0.1:1")
    settings = {"distributed.comm.tls.ca-file": str(tmp_path / "none.pem")}
    settings |= {"distributed.comm.tls.client.cert": str(cert)}
    with (
        dask.config.set(settings),
        pytest.raises(FleetError, match=r"^--scheduler tls://127.0.0.1:1: Dask's TLS settings:"),
    ):
        run_fleet(tasks, "tls://127.0.0.1:1")
    security = Security(
        tls_ca_file=str(cert),
        tls_scheduler_cert=str(cert),
        tls_scheduler_key=str(key),
        tls_worker_cert=str(cert),
        tls_worker_key=str(key),
        tls_client_cert=str(cert),  # (the cluster's own Client)
        tls_client_key=str(key),
        require_encryption=True,
    )
    settings = {
        "distributed.comm.tls.ca-file": str(cert),
        "distributed.comm.tls.client.cert": str(cert),
        "distributed.comm.tls.client.key": str(key),
    }
    with (
        LocalCluster(
            n_workers=1,
            processes=False,
            protocol="tls",
            security=security,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        ) as cluster,
        dask.config.set(settings),
    ):
        assert cluster.scheduler_address.startswith("tls://")
        result = run_fleet(tasks, cluster.scheduler_address)
    (row,) = result.rows
    assert row["error"] == f"{log} is empty"


# ------------------------------------------------- a stop while the cluster starts


def _children(pid: int) -> Iterator[tuple[int, str]]:
    """The processes whose parent is ``pid``, with their command lines."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            yield int(entry.name), command


def _in_session(session: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[4]) == session:
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("how", ["SIGTERM", "Ctrl-C"])
def test_a_stop_while_the_local_cluster_starts_ends_the_run_as_interrupted(
    how: str, tmp_path: Path
) -> None:
    log, table = tmp_path / "a.tlog", tmp_path / "t.csv"
    log.write_bytes(b"\xfe" * 64)
    # its own session, as a terminal's process group: Ctrl-C reaches the workers too
    process = _mavest(
        "fleet", str(log), "--out", str(table), "--workers", "1", start_new_session=True
    )
    try:
        deadline = time.monotonic() + 60
        # a worker process spawned: the cluster waits for it to start and say so
        while not any("spawn_main" in c for _, c in _children(process.pid)):
            assert process.poll() is None and time.monotonic() < deadline, "no worker started"
            time.sleep(0.005)
        if how == "SIGTERM":
            process.send_signal(signal.SIGTERM)
        else:
            os.killpg(process.pid, signal.SIGINT)
        out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 130, err
    assert out == ""
    assert err == f"mavest: interrupted: wrote the 0 of 1 logs that finished to {table}\n"
    assert table.read_text().count("\n") == 1  # the header: no log finished
    deadline = time.monotonic() + 10  # the cluster closed: its workers gone with it
    while _in_session(process.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _in_session(process.pid) == []


# ------------------------------------------------------------ workers that die


def _kill_writer(folder: Path, done: threading.Event, killed: list[int]) -> None:
    """Kill the first worker process seen writing a partial file in ``folder`` (its pid
    ends the name; not the decoy's, 1)."""
    while not done.is_set() and not killed:
        for partial in folder.glob(".*.partial"):
            found = PARTIAL.search(partial.name)
            if found and int(found.group(1)) != 1:
                killed.append(int(found.group(1)))
                os.kill(killed[0], signal.SIGKILL)
                break
        time.sleep(0.002)


def _run_killing_a_writer(
    long_log: Path, out_dir: Path, table: Path, allowed_failures: int = 3
) -> tuple[int, str, str]:
    """``mavest fleet`` of the log with its outputs in ``out_dir``, the worker writing
    them killed mid-log (``out_dir`` holds decoys: :func:`_only_decoys_left`): its exit
    code, standard output and error (a process of its own: all that is printed)."""
    out_dir.mkdir()
    for name in DECOYS:
        (out_dir / name).write_text("keep me\n")
    done, killed = threading.Event(), []
    watcher = threading.Thread(target=_kill_writer, args=(out_dir, done, killed), daemon=True)
    watcher.start()
    arguments = [str(long_log), "--out", str(table), "--out-dir", str(out_dir), *SETTLE]
    environment = os.environ | {
        "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": str(allowed_failures)
    }
    process = _mavest("fleet", *arguments, "--workers", "1", env=environment)
    try:
        out, err = process.communicate(timeout=120)
    finally:
        done.set()
        watcher.join()
        if process.poll() is None:
            process.kill()
    assert killed, "no worker was seen writing"
    return process.returncode, out, err


def _only_decoys_left(out_dir: Path) -> None:
    """The dead worker's partial files are gone, and only they."""
    assert sorted(p.name for p in out_dir.glob(".*")) == sorted(DECOYS)
    assert all((out_dir / name).read_text() == "keep me\n" for name in DECOYS)


def test_a_worker_killed_mid_log_leaves_no_partial_file(long_log: Path, tmp_path: Path) -> None:
    out_dir, table = tmp_path / "each", tmp_path / "t.csv"
    code, out, err = _run_killing_a_writer(long_log, out_dir, table)
    # the log given to a new worker, which replayed it whole
    assert code == 0 and err == "", err
    assert out.startswith("1 log replayed: 1 ok, 0 with an error")
    assert table.read_text().splitlines()[1].split(",")[1] == "ok"
    assert (out_dir / "long.rrd").stat().st_size > 0
    assert (out_dir / "long.estimates.csv").stat().st_size > 0
    _only_decoys_left(out_dir)


def test_a_log_that_kills_its_workers_is_said_once_in_mavest_s_words(
    long_log: Path, tmp_path: Path
) -> None:
    out_dir, table = tmp_path / "each", tmp_path / "t.csv"
    # given up at its first worker's death
    code, out, err = _run_killing_a_writer(long_log, out_dir, table, allowed_failures=0)
    assert code == 0
    # not Dask's "… - distributed.scheduler - ERROR - Task … marked as failed because 1
    # workers died while trying to run it" first
    assert err == (
        f"mavest: {long_log}: the workers replaying it died (more than "
        "distributed.scheduler.allowed-failures times): out of memory?\n"
    )
    assert out.startswith("1 log replayed: 0 ok, 1 with an error")
    assert not [p.name for p in out_dir.iterdir() if not p.name.startswith(".")]
    _only_decoys_left(out_dir)
