"""Faults around the service: a peer that vanishes and comes back (UDP silence, a TCP
drop), a port already taken, a disk that fills while the .tlog and .rrd are written,
SIGINT/SIGTERM at any moment. Whatever happens: one clear line, no traceback, the
estimates keep coming, and the files left behind are valid."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import itertools
import logging
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil

import mavest.mavlink.links as links
import mavest.service.runners as runners
import mavest.viz.viewer as viewer
from mavest.cli import EXIT_INTERRUPTED, EXIT_NO_IMU
from mavest.mavlink.links import TcpClientLink, TcpServerLink, make_link, parse_endpoint
from mavest.mavlink.tlog import TlogWriter
from mavest.service.config import ServiceConfig
from mavest.service.process import MAVEST, ServiceProcess, free_port
from mavest.service.runners import Outputs, replay, run_live
from mavest.service.signals import STOP_SIGNALS, stop_on_signals
from mavest.sim.vehicle import AUTOPILOTS, StreamingVehicle, stream_flight, write_flight_tlog
from mavest.viz.viewer import rerun_binary

RATE = 100.0  # Hz: the simulated vehicles' IMU rate (enough to see answers, cheap on 2 cores)


# ------------------------------------------------------------------ helpers


def _rrd_verifies(path: Path) -> None:
    binary = rerun_binary()
    assert binary is not None
    result = subprocess.run([binary, "rrd", "verify", str(path)], capture_output=True, text=True)
    assert result.returncode == 0 and "1 file verified without error" in result.stderr, (
        f"{path} ({path.stat().st_size} bytes): {result.stderr}"
    )


def _tlog_messages(path: Path) -> list[Any]:
    """Every message of a tlog, read by pymavlink; the file must be whole records only."""
    connection = mavutil.mavlink_connection(str(path))
    messages = []
    while (message := connection.recv_msg()) is not None:
        messages.append(message)
    kinds = {m.get_type() for m in messages}
    assert "BAD_DATA" not in kinds, f"{path}: damaged records"
    # 8-byte timestamp + packet per record: nothing left over (no record cut short)
    assert sum(8 + len(m.get_msgbuf()) for m in messages) == path.stat().st_size, path
    return messages


class _Log(logging.Handler):
    """What the service logs in this process (the "mavest" logger may not propagate)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def text(self) -> str:
        return "\n".join(r.getMessage() for r in self.records)

    def errors(self) -> list[str]:
        return [r.getMessage() for r in self.records if r.levelno >= logging.ERROR]


@pytest.fixture
def service_log() -> Iterator[_Log]:
    handler = _Log()
    loggers = [logging.getLogger("mavest"), logging.getLogger("asyncio")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
    yield handler
    for logger, level in zip(loggers, levels, strict=True):
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert not any(r.exc_info for r in handler.records), "a traceback was logged"


class _Mute:
    """A link that is down: whatever the vehicle sends is lost."""

    def send(self, packet: bytes) -> None:
        pass


class _Radio:
    """The vehicle's side of a link that can go quiet (``silent``), as a radio out of range."""

    def __init__(self, link: Any) -> None:
        self.link = link
        self.silent = False

    def send(self, packet: bytes) -> None:
        if not self.silent:
            self.link.send(packet)


class _Flight:
    """A simulated vehicle flying in real time, its link swapped as the test goes; what
    it hears back is timed, so answers can be told apart by when their sample was sent."""

    def __init__(self, seed: int) -> None:
        self.vehicle = StreamingVehicle(_Mute(), RATE, AUTOPILOTS["ardupilot"], seed)  # type: ignore[arg-type]
        self.start = time.perf_counter()
        self.heard: list[float] = []  # flight times of packets from the service
        self._task: asyncio.Task[None] | None = None

    def now(self) -> float:
        return time.perf_counter() - self.start

    def on_bytes(self, link: Any, data: bytes, peer: Any) -> None:
        self.heard.append(self.now())
        self.vehicle.on_bytes(link, data, peer)

    def begin(self) -> None:
        self._task = asyncio.create_task(self._fly())

    async def _fly(self) -> None:
        next_heartbeat = 0.0
        while True:
            now = self.now()
            if now >= next_heartbeat:
                self.vehicle.heartbeat()
                next_heartbeat += 1.0
            self.vehicle.send_due(now)
            await asyncio.sleep(0.001)

    async def end(self) -> None:
        await asyncio.sleep(0.5)  # the last answers
        assert self._task is not None
        self._task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await self._task

    def answered_between(self, start: float, end: float) -> tuple[int, int]:
        """(answered, sent) for the IMU samples sent between two flight times."""
        vehicle = self.vehicle
        sent = [key for key, entry in vehicle._sent.items() if start <= entry[3] < end]
        return sum(key in vehicle._answered for key in sent), len(sent)


async def _until(condition: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


# ------------------------------------------------------------------ a peer that vanishes


def test_a_udp_peer_that_goes_silent_and_comes_back_is_answered_again(
    monkeypatch: pytest.MonkeyPatch, service_log: _Log
) -> None:
    # the peer timeout lowered from 30 s so that the silence outlasts it in a few seconds
    monkeypatch.setattr(links, "UDP_PEER_TIMEOUT", 1.0)
    port = free_port(socket.SOCK_DGRAM)
    silent_from, back_at, end_at = 2.0, 5.0, 7.5

    async def scenario() -> tuple[_Flight, runners.RunReport]:
        stop, ready = asyncio.Event(), asyncio.Event()
        service = asyncio.create_task(
            run_live(
                f"udpin:127.0.0.1:{port}", ServiceConfig(), stop=stop, ready=ready, status_period=0
            )
        )
        await asyncio.wait_for(ready.wait(), 120)
        flight = _Flight(seed=4)
        link = make_link(parse_endpoint(f"udpout:127.0.0.1:{port}"))
        await link.start(flight.on_bytes)
        radio = _Radio(link)
        flight.vehicle.link = radio  # type: ignore[assignment]
        flight.begin()
        await _until(lambda: flight.now() >= silent_from, 30, "the first leg")
        radio.silent = True
        await _until(lambda: flight.now() >= back_at, 30, "the silence")
        radio.silent = False
        await _until(lambda: flight.now() >= end_at, 30, "the second leg")
        await flight.end()
        link.close()
        stop.set()
        return flight, await service

    flight, report = asyncio.run(scenario())
    answered, sent = flight.answered_between(back_at, end_at)
    assert sent > 0.9 * RATE * (end_at - back_at) and answered >= 0.97 * sent, (answered, sent)
    answered, sent = flight.answered_between(0.5, silent_from)
    assert answered >= 0.97 * sent
    # once the peer timed out, nothing more was sent to it until it spoke again
    quiet = [t for t in flight.heard if silent_from + 2.2 <= t < back_at]
    assert not quiet, f"the service kept sending to a silent peer: {quiet[:5]}"
    text = service_log.text()
    assert "nothing from 127.0.0.1:" in text and "no replies to it until it sends again" in text
    assert re.search(r"127\.0\.0\.1:\d+ is back after [34] s of silence; replying again", text), (
        text
    )
    assert not service_log.errors()
    assert report.pipeline.streams


def test_udp_senders_without_end_are_replied_to_up_to_a_bound(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # 3000 sockets sending one HEARTBEAT each were each sent every reply: the vehicle
    # got 55 % of its answers, seconds late, and mavest reflected all it sent 3000-fold
    port = free_port(socket.SOCK_DGRAM)
    encoder = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = encoder.heartbeat_encode(2, 3, 0, 0, 0).pack(encoder)
    heard: list[int] = []

    async def scenario() -> None:
        link = make_link(parse_endpoint(f"udpin:127.0.0.1:{port}"))
        await link.start(lambda link, data, peer: heard.append(len(data)))
        senders = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(40)]
        try:
            for sender in senders:
                sender.sendto(heartbeat, ("127.0.0.1", port))
                sender.setblocking(False)
            await _until(lambda: len(heard) == 40, 10, "the senders")
            link.send(heartbeat)
            await asyncio.sleep(0.2)
            replied = 0
            for sender in senders:
                with contextlib.suppress(BlockingIOError):
                    replied += len(sender.recv(1024)) > 0
            assert replied == links.UDP_PEERS_MAX
        finally:
            for sender in senders:
                sender.close()
            link.close()

    with caplog.at_level("WARNING", logger="mavest"):
        asyncio.run(scenario())
    said = [r.getMessage() for r in caplog.records if "peers replied to already" in r.getMessage()]
    assert len(said) == 1


def _service_log(service: ServiceProcess) -> str:
    text = "".join(service.log)
    assert "Traceback" not in text, text
    return text


def test_tcp_reconnects_with_back_off_and_estimation_resumes() -> None:
    """``mavest run tcp:`` against a vehicle that is the TCP server: the vehicle drops the
    connection, then (restarting) accepts and closes at once for a while, then is back."""
    port = free_port()
    endpoint = parse_endpoint(f"tcpin:127.0.0.1:{port}")
    accepted: list[float] = []

    async def scenario() -> tuple[_Flight, ServiceProcess, float]:
        flight = _Flight(seed=5)
        server = TcpServerLink(endpoint)
        await server.start(flight.on_bytes)
        flight.vehicle.link = server  # type: ignore[assignment]
        flight.begin()
        service = await asyncio.to_thread(ServiceProcess, f"tcp:127.0.0.1:{port}")
        await _until(lambda: len(flight.vehicle._answered) > RATE, 30, "the first answers")
        await asyncio.sleep(1.0)
        server.close()  # the vehicle goes away…
        flight.vehicle.link = _Mute()  # type: ignore[assignment]
        dropped = flight.now()

        async def accept_and_close(reader: Any, writer: asyncio.StreamWriter) -> None:
            accepted.append(flight.now() - dropped)
            writer.close()

        # …and restarts: it accepts and closes at once, then is refused for a moment
        restarting = await asyncio.start_server(accept_and_close, "127.0.0.1", port)
        await asyncio.sleep(4.5)
        restarting.close()
        await restarting.wait_closed()
        await asyncio.sleep(1.0)
        server = TcpServerLink(endpoint)
        await server.start(flight.on_bytes)
        flight.vehicle.link = server  # type: ignore[assignment]
        back = flight.now()
        await asyncio.sleep(6.0)  # the next attempt is due 7.75 s after the drop
        await flight.end()
        server.close()
        return flight, service, back

    flight, service, back = asyncio.run(scenario())
    code, _ = service.stop()
    text = _service_log(service)
    assert code == 0
    # attempts at 0, 0.25, 0.75, 1.75, 3.75 s after the drop: each wait twice the one before
    assert len(accepted) >= 4, accepted
    waits = [b - a for a, b in itertools.pairwise(accepted)]
    assert waits[0] >= 0.2, waits
    assert all(later > 1.6 * earlier for earlier, later in itertools.pairwise(waits)), waits
    assert "connection lost; reconnecting" in text
    # said once in the outage: whichever came first, a refused connection (the vehicle not
    # listening yet) or one closed at once
    lost = text.index("connection lost; reconnecting")
    end = text.find("connection lost; reconnecting", lost + 1)  # the vehicle's end, if said
    outage = text[lost:end] if end > 0 else text[lost:]
    assert outage.count("retrying with back-off") == 1, text
    # estimation resumed on the new connection: the last two seconds are answered
    end = flight.now() - 0.5
    answered, sent = flight.answered_between(end - 2.0, end)
    assert sent > 0 and answered >= 0.97 * sent, (answered, sent, back, text)


def test_a_tcpin_client_that_drops_and_reconnects_is_served_again() -> None:
    port = free_port()
    service = ServiceProcess(f"tcpin:127.0.0.1:{port}")

    async def scenario() -> _Flight:
        flight = _Flight(seed=6)
        for leg in range(2):
            client = TcpClientLink(parse_endpoint(f"tcp:127.0.0.1:{port}"))
            await client.start(flight.on_bytes)
            flight.vehicle.link = client  # type: ignore[assignment]
            if leg == 0:
                flight.begin()
            await asyncio.sleep(2.5)
            client.close()  # the vehicle's side drops
            flight.vehicle.link = _Mute()  # type: ignore[assignment]
            await asyncio.sleep(1.5)
        await flight.end()
        return flight

    flight = asyncio.run(scenario())
    code, _ = service.stop()
    text = _service_log(service)
    assert code == 0
    # the second connection, 4 s into the flight, is answered like the first
    for start in (0.5, 4.5):
        answered, sent = flight.answered_between(start, start + 1.5)
        assert sent > 0 and answered >= 0.97 * sent, (start, answered, sent, text)
    assert text.count("client") >= 4 and text.count(" left") >= 2, text


def test_a_tcp_client_that_never_reads_costs_a_bounded_backlog(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # what was sent to a client that never reads was held for it, without end (the
    # service's memory grew by the answers' rate); past the backlog it is dropped
    port = free_port()
    packet = bytes(100)

    async def scenario() -> int:
        link = make_link(parse_endpoint(f"tcpin:127.0.0.1:{port}"))
        await link.start(lambda link, data, peer: None)
        client = socket.create_connection(("127.0.0.1", port))
        try:
            await asyncio.sleep(0.2)  # (accepted)
            for _ in range(400):  # 40 MB, given the loop's turn between bursts
                for _ in range(1000):
                    link.send(packet)
                await asyncio.sleep(0)
            await asyncio.sleep(0.2)
            received = 0
            client.setblocking(False)
            loop = asyncio.get_running_loop()
            with contextlib.suppress(TimeoutError):
                while chunk := await asyncio.wait_for(loop.sock_recv(client, 1 << 20), 0.5):
                    received += len(chunk)
            return received
        finally:
            client.close()
            link.close()

    with caplog.at_level("INFO", logger="mavest"):
        received = asyncio.run(scenario())
    # (the backlog, and what the two sockets' buffers took: a few MB)
    assert 0 < received < 20 * 1024 * 1024, received
    said = [r.getMessage() for r in caplog.records if "does not read" in r.getMessage()]
    assert len(said) == 1, said


# ------------------------------------------------------------------ a port already taken


@pytest.mark.parametrize("kind", ["udpin", "tcpin"])
def test_a_port_taken_is_one_line_and_exit_code_2(kind: str, tmp_path: Path) -> None:
    udp = kind == "udpin"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM if udp else socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        if not udp:
            taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [*MAVEST, "run", f"{kind}:127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if "compiling the filter" not in line]
    assert lines == [
        f"mavest: cannot listen on {kind}:127.0.0.1:{port}: Address already in use "
        f"(another program has port {port}: a ground station, another mavest?)"
    ], result.stderr
    assert result.stdout == ""


# ------------------------------------------------------------------ a disk that fills up


@pytest.fixture(scope="module")
def flight_tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("faults") / "flight.tlog"
    write_flight_tlog(path, 12.0, 200.0, AUTOPILOTS["ardupilot"], seed=7)
    return path


class _SmallDisk:
    """A file on a disk with ``free`` bytes left: writes fill it, then fail with ENOSPC."""

    def __init__(self, file: Any, free: int) -> None:
        self._file = file
        self.free = free

    def write(self, data: bytes | memoryview) -> int:
        if not self.free:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        done = int(self._file.write(data[: self.free]))
        self.free -= done
        return done

    def __getattr__(self, name: str) -> Any:  # truncate, close, closed
        return getattr(self._file, name)


def test_a_full_disk_ends_the_tlog_at_a_whole_record_and_replay_goes_on(
    flight_tlog: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, service_log: _Log
) -> None:
    whole = tmp_path / "whole.tlog"
    complete = asyncio.run(replay(flight_tlog, ServiceConfig(), Outputs(tlog=whole)))
    free = 150_001  # room for part of the output, ending inside a record

    class TlogWriterOnASmallDisk(TlogWriter):
        def __init__(self, path: Path) -> None:
            super().__init__(path)
            self._file = _SmallDisk(self._file, free)  # the writer's own file, under it

    monkeypatch.setattr(runners, "TlogWriter", TlogWriterOnASmallDisk)
    cut = tmp_path / "cut.tlog"
    report = asyncio.run(replay(flight_tlog, ServiceConfig(), Outputs(tlog=cut)))
    # estimation went on to the end
    samples = [s.stats.estimated for s in report.streams]
    assert samples == [s.stats.estimated for s in complete.streams] and samples[0] > 2000
    # one line, naming the file and the cause
    assert service_log.errors() == [
        f"cannot write {cut}: No space left on device; the tlog stops here with its first "
        f"{report.pipeline.out_tlog.records} records, whole (estimating on)"  # type: ignore[union-attr]
    ]
    assert "stopped early: cannot write" in report.summary()
    # what is on disk is the start of the complete output, cut after a whole record
    data = cut.read_bytes()
    assert 0.9 * free < len(data) <= free
    assert whole.read_bytes().startswith(data)
    assert len(_tlog_messages(cut)) == report.pipeline.out_tlog.records  # type: ignore[union-attr]


def _batches_land_during_the_replay(monkeypatch: pytest.MonkeyPatch) -> None:
    """Small recorder batches, so that a short replay writes its .rrd as a long one does
    (a file-only recording is otherwise sent in batches of 32768 rows: here, at the end)."""
    from mavest.viz.recorder import RerunRecorder

    monkeypatch.setattr(
        RerunRecorder,
        "for_viewer",
        classmethod(lambda cls, recording, live: cls(recording, batch_rows=1024)),
    )


def test_a_nearly_full_disk_closes_the_rrd_complete_and_replay_goes_on(
    flight_tlog: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, service_log: _Log
) -> None:
    rrd = tmp_path / "ours.rrd"
    real_disk_usage = shutil.disk_usage

    def disk_usage(path: Any) -> Any:
        # the disk fills up once the recording passes 200 kB
        usage = real_disk_usage(path)
        if rrd.exists() and rrd.stat().st_size > 200_000:
            return usage._replace(free=512 * 1024)
        return usage

    monkeypatch.setattr(viewer.shutil, "disk_usage", disk_usage)
    _batches_land_during_the_replay(monkeypatch)
    report = asyncio.run(replay(flight_tlog, ServiceConfig(), Outputs(rrd=rrd)))
    assert report.streams[0].stats.estimated > 2000
    assert service_log.errors() == [
        f"{rrd}: only 512 kB left on its disk: the recording stops here, complete (estimating on)"
    ]
    assert 200_000 < rrd.stat().st_size < 1_000_000
    _rrd_verifies(rrd)
    assert f"wrote {rrd} (Rerun recording, stopped early" in report.summary()


def test_the_rrd_is_judged_on_what_rerun_has_written_once_its_disk_is_near_full(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Rerun's batcher writes on its own clock (held back here): a size read before it
    # has would miss the batch still to come, and the footer after it might not fit.
    import numpy as np
    import rerun as rr

    monkeypatch.setenv("RERUN_FLUSH_TICK_SECS", "1000")
    rrd = tmp_path / "ours.rrd"
    capacity = viewer.RRD_DISK_RESERVE_BYTES + 400_000  # a disk of this size, all ours
    real_disk_usage = shutil.disk_usage

    def disk_usage(path: Any) -> Any:
        return real_disk_usage(path)._replace(free=capacity - rrd.stat().st_size)

    monkeypatch.setattr(viewer.shutil, "disk_usage", disk_usage)
    view = viewer.Viewer(viewer.ViewerRequest(rrd=rrd))
    rng = np.random.default_rng(1)
    for row in range(600):  # about 200 kB: still in the batcher
        view.recording.set_time("t", sequence=row)
        view.recording.log("noise", rr.Scalars(rng.random(40)))
    assert rrd.stat().st_size < 10_000
    view.check_space()
    # written, it leaves less than the reserve and room for another batch as large
    assert view.rrd_error is not None and "left on its disk" in view.rrd_error
    _rrd_verifies(rrd)
    view.close()


def test_dev_full_as_the_output_tlog_is_one_line_and_the_answers_go_on() -> None:
    port = free_port(socket.SOCK_DGRAM)
    service = ServiceProcess(f"udpin:127.0.0.1:{port}", "--out-tlog", "/dev/full")
    report = asyncio.run(stream_flight(f"udpout:127.0.0.1:{port}", RATE, seed=8, seconds=3.0))
    code, summary = service.stop()
    text = _service_log(service)
    assert code == 0
    assert report.answered_fraction >= 0.99, report.describe()
    errors = [line for line in service.log if "/dev/full" in line]
    assert len(errors) == 1 and "cannot write /dev/full: No space left on device" in errors[0]
    assert "wrote /dev/full (tlog, stopped early" in summary, text


@pytest.fixture
def small_disks(tmp_path: Path) -> Iterator[Any]:
    """``mount(name, size)``: a tmpfs of that size (needs root, or CAP_SYS_ADMIN)."""
    mounted: list[Path] = []

    def mount(name: str, size: int) -> Path:
        directory = tmp_path / name
        directory.mkdir()
        result = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)],
            capture_output=True,
            text=True,
        )
        if result.returncode != 0:
            pytest.skip(f"cannot mount a small tmpfs here: {result.stderr.strip()}")
        mounted.append(directory)
        return directory

    yield mount
    for directory in mounted:
        if subprocess.run(["umount", str(directory)], capture_output=True).returncode:
            # still busy (a file the Rerun SDK has not let go of yet): detached now,
            # released by the kernel when the last descriptor closes
            subprocess.run(["umount", "--lazy", str(directory)], check=True)


def test_disks_that_fill_up_while_live_leave_valid_files(small_disks: Any) -> None:
    tlog = small_disks("tlog", 64 * 1024) / "ours.tlog"  # full in about a second
    rrd_disk = small_disks("rrd", viewer.RRD_DISK_RESERVE_BYTES + 256 * 1024)
    rrd = rrd_disk / "ours.rrd"
    port = free_port(socket.SOCK_DGRAM)
    service = ServiceProcess(f"udpin:127.0.0.1:{port}", "--out-tlog", str(tlog), "--rrd", str(rrd))
    report = asyncio.run(stream_flight(f"udpout:127.0.0.1:{port}", 200.0, seed=9, seconds=6.0))
    code, summary = service.stop()
    text = _service_log(service)
    assert code == 0
    assert report.answered_fraction >= 0.99, report.describe()
    # one line for each file, whichever comes first
    (tlog_error,) = [line for line in service.log if str(tlog) in line]
    (rrd_error,) = [line for line in service.log if str(rrd) in line]
    assert f"cannot write {tlog}: No space left on device" in tlog_error, text
    assert f"{rrd}: only" in rrd_error and "stops here, complete" in rrd_error, text
    assert "stopped early" in summary
    assert len(_tlog_messages(tlog)) > 100
    _rrd_verifies(rrd)


def test_one_disk_filling_with_both_files_on_replay(
    flight_tlog: Path, small_disks: Any, service_log: _Log, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a smaller reserve than 1 MiB, so that the output tlog (~0.5 MB) fills what is left
    monkeypatch.setattr(viewer, "RRD_DISK_RESERVE_BYTES", 128 * 1024)
    disk = small_disks("both", 384 * 1024)
    tlog, rrd = disk / "ours.tlog", disk / "ours.rrd"
    _batches_land_during_the_replay(monkeypatch)
    report = asyncio.run(replay(flight_tlog, ServiceConfig(), Outputs(tlog=tlog, rrd=rrd)))
    assert report.streams[0].stats.estimated > 2000
    errors = service_log.errors()
    # the recording closes first, complete, while the reserve is left; the tlog fills the rest
    assert len(errors) == 2 and str(rrd) in errors[0] and str(tlog) in errors[1], errors
    assert "stops here, complete" in errors[0], errors
    assert "No space left on device" in errors[1]
    assert len(_tlog_messages(tlog)) > 1000
    _rrd_verifies(rrd)


# ------------------------------------------------------------------ signals at any moment


def test_a_stopping_run_hands_ctrl_c_from_its_handler_straight_to_ignored(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A second Ctrl-C as a run closes must not end it before its summary: SIGINT goes
    # from the run's handler to "ignored" without the interpreter's default between
    # (which would raise KeyboardInterrupt there); SIGTERM and SIGHUP get their own back.
    installed: list[tuple[int, Any]] = []
    real = signal.signal

    def recording(signum: int, handler: Any) -> Any:
        installed.append((signum, handler))
        return real(signum, handler)

    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}

    async def scenario() -> bool:
        with stop_on_signals() as stop:
            monkeypatch.setattr(signal, "signal", recording)
            signal.raise_signal(signal.SIGINT)
            await asyncio.wait_for(stop.wait(), 5.0)
        return stop.is_set()

    try:
        assert asyncio.run(scenario())
        sigint = [handler for signum, handler in installed if signum == signal.SIGINT]
        assert sigint == [signal.SIG_IGN]
        for signum in STOP_SIGNALS:
            if signum != signal.SIGINT:
                assert signal.getsignal(signum) is before[signum]
    finally:
        monkeypatch.undo()
        for signum, handler in before.items():
            signal.signal(signum, handler)


def test_a_run_that_ends_on_its_own_gives_the_signals_back() -> None:
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}

    async def scenario() -> dict[int, Any]:
        around = {s: signal.getsignal(s) for s in STOP_SIGNALS}
        with stop_on_signals() as stop:
            assert all(signal.getsignal(s) is not around[s] for s in STOP_SIGNALS)
        assert not stop.is_set()
        assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == around
        return around

    asyncio.run(scenario())
    assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == before


def _start(*arguments: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*MAVEST, *arguments],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # SIGINT as a terminal sends it, even when this test runs in a background job
        # (which starts its children with SIGINT ignored)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


async def _when_exists(path: Path, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} never appeared"
        await asyncio.sleep(0.001)


MOMENTS = ["start-up", "mid-stream", "flush"]


@pytest.mark.parametrize("moment", MOMENTS)
@pytest.mark.parametrize(
    "signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["INT", "TERM", "HUP"]
)
@pytest.mark.parametrize("command", ["run", "replay"])
def test_a_signal_at_any_moment_leaves_valid_files(
    command: str, signum: int, moment: str, flight_tlog: Path, tmp_path: Path
) -> None:
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    tlog, rrd = tmp_path / "ours.tlog", tmp_path / "ours.rrd"
    outputs = ("--out-tlog", str(tlog), "--rrd", str(rrd))
    port = free_port(socket.SOCK_DGRAM)
    if command == "run":
        process = _start("run", f"udpin:127.0.0.1:{port}", *outputs)
    else:  # paced, so that it is still running when the signal comes
        process = _start("replay", str(flight_tlog), "--speed", "3", *outputs)
    delay = 0.0

    async def scenario() -> None:
        nonlocal delay
        vehicle = None
        await _when_exists(tlog)  # the files are being opened: start-up
        if command == "run":
            vehicle = asyncio.create_task(
                stream_flight(f"udpout:127.0.0.1:{port}", RATE, seed=10, seconds=6.0, linger=0)
            )
        if moment != "start-up":
            delay = rng.uniform(0.3, 1.5)
            await asyncio.sleep(delay)
        process.send_signal(signum)
        if moment == "flush":  # a second one while it closes its files
            await asyncio.sleep(rng.uniform(0.0, 0.05))
            process.send_signal(signum)
        if vehicle is not None:
            vehicle.cancel()
            with pytest.raises(asyncio.CancelledError):
                await vehicle

    asyncio.run(scenario())
    out, err = process.communicate(timeout=60)
    context = f"seed {seed}, delay {delay:.2f} s: rc {process.returncode}\n{err}"
    assert "Traceback" not in err, context
    # a signal handled stops cleanly: `run` is done (0, or 1 for "no IMU stream found" when
    # stopped before the first), a replay was interrupted (130); a second signal that lands
    # after the files are closed is the interpreter's (KeyboardInterrupt: 130) or the
    # default action (killed)
    handled = {0} if command == "run" else {EXIT_INTERRUPTED}
    if command == "run" and moment == "start-up":
        handled.add(EXIT_NO_IMU)
    allowed = handled if moment != "flush" else handled | {EXIT_INTERRUPTED, -signum}
    assert process.returncode in allowed, context
    if process.returncode in handled:
        assert "wrote" in out, context
    messages = _tlog_messages(tlog)
    if moment == "mid-stream":
        assert any(m.get_type() == "RAW_IMU" for m in messages), context
    _rrd_verifies(rrd)
