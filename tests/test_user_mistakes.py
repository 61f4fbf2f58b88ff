"""What a new user gets wrong, and what mavest says back: outputs never written over
inputs, every option checked, a clear word when nothing useful arrives, one exit
code per outcome."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import subprocess
import sys
import time
import urllib.request
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from numba import njit
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from test_output_files import imu_tlog

import mavest.service.runners as runners
from mavest.cli import COMPILING, EXIT_INTERRUPTED, EXIT_NO_IMU, main
from mavest.estimator import AccelUnitWarning
from mavest.fleet.rows import LogTask, log_rows
from mavest.mavlink.links import LinkError, make_link, parse_endpoint
from mavest.paths import OutputPathError, check_outputs
from mavest.service.config import ServiceConfig
from mavest.service.log_repeats import RepeatLimiter
from mavest.service.pipeline import Pipeline
from mavest.service.process import MAVEST, free_port
from mavest.service.runners import Outputs, replay, run_live
from mavest.sim import simulate
from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog
from mavest.viz.viewer import rerun_binary


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def text(self) -> str:
        return "\n".join(self.lines)


@pytest.fixture
def mavest_log() -> Iterator[_Lines]:
    logger = logging.getLogger("mavest")
    handler = _Lines()
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield handler
    logger.removeHandler(handler)
    logger.setLevel(level)


@pytest.fixture(scope="module")
def short_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("flight") / "flight.tlog"
    write_flight_tlog(path, 12.0, 100.0, AUTOPILOTS["ardupilot"], seed=2)
    return path


def _one_line(err: str, message: str) -> None:
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


# ------------------------------------------------------------------ outputs over inputs


@pytest.mark.parametrize(
    ("outputs", "message"),
    [
        (["--out-tlog", "{log}"], "is the log being replayed"),
        (["--out-tlog", "{link}"], "is the log being replayed"),
        (["--out-tlog", "{hard}"], "is the log being replayed"),
        (["--rrd", "{log}"], "is the log being replayed"),
        (["--out-tlog", "{tmp}/o", "--rrd", "{tmp}/o"], "are both"),
        (["--out-tlog", "{tmp}/cfg.toml", "--config", "{tmp}/cfg.toml"], "is the --config file"),
        (["--rrd", "{tmp}/none/x.rrd"], "no folder"),
        (["--out-tlog", "{tmp}/none/x.tlog"], "no folder"),
        (["--out-tlog", "{tmp}"], "is a folder"),
    ],
)
def test_replay_refuses_outputs_over_its_inputs(
    short_flight: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    outputs: list[str],
    message: str,
) -> None:
    log = tmp_path / "f.tlog"
    log.write_bytes(short_flight.read_bytes())
    (tmp_path / "link.tlog").symlink_to(log)
    (tmp_path / "hard.tlog").hardlink_to(log)
    (tmp_path / "cfg.toml").write_text("[input]\nsettle_time = 2.0\n")
    before = log.read_bytes(), (tmp_path / "cfg.toml").read_bytes()
    names = {"log": log, "link": tmp_path / "link.tlog", "hard": tmp_path / "hard.tlog"}
    arguments = [a.format(tmp=tmp_path, **names) for a in outputs]
    assert main(["replay", str(log), *arguments]) == 2
    _one_line(capsys.readouterr().err, message)
    assert (log.read_bytes(), (tmp_path / "cfg.toml").read_bytes()) == before
    assert not (tmp_path / "none").exists() and not (tmp_path / "o").exists()


def test_every_command_refuses_an_output_that_is_an_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "c.toml"
    config.write_text("[output]\nattitude_rate = 10.0\n")
    csv = tmp_path / "imu.csv"
    data = simulate(2.0, 50.0, seed=1)
    np.savetxt(csv, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    kept = config.read_bytes(), csv.read_bytes()
    for arguments, message in (
        (["run", "udpin:127.0.0.1:1", "--config", str(config), "--rrd", str(config)], "--config"),
        (["sim", "--tlog", str(tmp_path / "x"), "--report", str(tmp_path / "x")], "are both"),
        (["estimate", str(csv), "-o", str(csv)], "is the CSV being read"),
        (["demo", "--config", str(config), "--output-dir", str(tmp_path)], "--config"),
    ):
        if arguments[0] == "demo":  # the demo's files are fixed names in its folder
            (tmp_path / "mavest.tlog").symlink_to(config)
        assert main(arguments) == 2, arguments
        _one_line(capsys.readouterr().err, message)
    assert (config.read_bytes(), csv.read_bytes()) == kept


def test_the_output_rule_is_the_api_rule_too(short_flight: Path, tmp_path: Path) -> None:
    with pytest.raises(OutputPathError, match="is the log being replayed"):
        asyncio.run(replay(short_flight, ServiceConfig(), Outputs(tlog=short_flight)))
    with pytest.raises(OutputPathError, match="are both"):
        check_outputs({}, {"a": tmp_path / "x", "b": tmp_path / "." / "x"})
    check_outputs({"in": tmp_path / "x"}, {"out": tmp_path / "y", "none": None})


# ------------------------------------------------------------------ options


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["run", "/dev/ttyS0", "--baud", "-5"], "argument --baud: -5 is not a whole number"),
        (["run", "/dev/ttyS0", "--baud", "0"], "argument --baud"),
        (["run", "udpin:127.0.0.1:9", "--request-rate", "nan"], "--request-rate"),
        (["run", "udpin:127.0.0.1:9", "--sysid", "0"], "--sysid"),
        (["run", "udpin:127.0.0.1:9", "--rerun-port", "70000"], "--rerun-port"),
        (["replay", "x.tlog", "--speed", "nan"], "argument --speed"),
        (["replay", "x.tlog", "--speed", "0"], "argument --speed"),
        (["replay", "x.tlog", "--instance", "-1"], "argument --instance"),
        (["replay", "x.tlog", "--attitude-rate", "inf"], "--attitude-rate"),
        (["replay", "x.tlog", "--settle", "-1"], "--settle"),
        (["sim", "--rate", "nan"], "argument --rate"),
        (["sim", "--seed", "-1"], "argument --seed"),
        (["demo", "--seconds", "nan"], "argument --seconds"),
        (["replay"], "required"),
    ],
)
def test_every_option_is_checked_in_one_line(
    capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    assert main(arguments) == 2
    _one_line(capsys.readouterr().err, message)


def test_a_config_value_of_the_wrong_type_names_its_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "c.toml"
    for text, key in (
        ('[input]\nrequest_rate = "fast"\n', "[input] request_rate = 'fast': expected number"),
        ("[estimator]\ninitial_bias = [0, 1]\n", "[estimator] initial_bias"),
        ("[output]\ncomponent_id = 1.5\n", "[output] component_id = 1.5: expected whole"),
    ):
        path.write_text(text)
        assert main(["estimate", str(path), "--config", str(path)]) == 2
        _one_line(capsys.readouterr().err, f"{path}: {key}")


# ------------------------------------------------------------------ connection strings


@pytest.mark.parametrize(
    ("text", "kind", "where"),
    [
        ("/dev/ttyUSB0,57600", "serial", ("/dev/ttyUSB0", 57600)),
        ("/dev/ttyUSB0:57600", "serial", ("/dev/ttyUSB0", 57600)),
        ("/dev/ttyACM0", "serial", ("/dev/ttyACM0", 115200)),
        ("udp:127.0.0.1:14550", "udpin", ("127.0.0.1", 14550)),
        ("0.0.0.0:14550", "udpin", ("0.0.0.0", 14550)),
        ("udpbcast:192.168.1.255:14550", "udpbcast", ("192.168.1.255", 14550)),
    ],
)
def test_mavproxy_connection_strings(text: str, kind: str, where: tuple[str, int]) -> None:
    endpoint = parse_endpoint(text)
    assert endpoint.kind == kind
    if kind == "serial":
        assert (endpoint.device, endpoint.baud) == where
    else:
        assert (endpoint.host, endpoint.port) == where


def test_forms_mavest_does_not_take_are_named() -> None:
    with pytest.raises(LinkError, match=r"use udpin:HOST:PORT \(or udp:\).*udpbcast"):
        parse_endpoint("mcast:")


def test_an_unknown_host_is_said_to_be_not_found() -> None:
    async def open_() -> None:
        await make_link(parse_endpoint("udpout:no-such-host.invalid:14550")).start(lambda *_: None)

    with pytest.raises(LinkError, match=r"host 'no-such-host\.invalid' not found"):
        asyncio.run(open_())


@pytest.mark.parametrize("answered", ["MAVLink", "noise"])
def test_udpbcast_sends_to_whoever_answers_with_mavlink(answered: str) -> None:
    """To the broadcast address until a peer answers with a MAVLink packet, then to that
    peer only; an answer of noise (a port scan, another protocol) changes nothing."""
    port = free_port(socket.SOCK_DGRAM)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", port))
    peer.settimeout(5)
    heartbeat = mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3)
    reply = heartbeat.pack(mavlink2.MAVLink(None, 1, 1)) if answered == "MAVLink" else b"answer"

    async def scenario() -> tuple[bytes | None, bytes | None]:
        received: list[bytes] = []
        link = make_link(parse_endpoint(f"udpbcast:127.0.0.1:{port}"))
        await link.start(lambda _link, data, _peer: received.append(data))
        link.send(b"hello")
        _, address = peer.recvfrom(100)
        peer.settimeout(1)
        answer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # from another port
        answer.settimeout(1)
        answer.sendto(reply, address)
        for _ in range(100):
            if received:
                break
            await asyncio.sleep(0.02)
        link.send(b"after")
        loop = asyncio.get_running_loop()
        to_answerer = await loop.run_in_executor(None, _received, answer)
        to_broadcast = await loop.run_in_executor(None, _received, peer)
        link.close()
        answer.close()
        return to_answerer, to_broadcast

    to_answerer, to_broadcast = asyncio.run(scenario())
    peer.close()
    if answered == "MAVLink":
        assert (to_answerer, to_broadcast) == (b"after", None)
    else:
        assert (to_answerer, to_broadcast) == (None, b"after")


def _received(sock: socket.socket) -> bytes | None:
    """The next datagram on ``sock``, None if none comes before its timeout."""
    try:
        return sock.recv(100)
    except TimeoutError:
        return None


# ------------------------------------------------------------------ CSV


def test_estimate_takes_a_header_row_and_its_column_order(tmp_path: Path) -> None:
    data = simulate(4.0, 50.0, seed=1)
    plain, named = tmp_path / "plain.csv", tmp_path / "named.csv"
    columns = np.column_stack([data.t, data.gyro, data.accel])
    np.savetxt(plain, columns, delimiter=",")
    # the same samples under a header, accelerometer columns first
    np.savetxt(
        named,
        np.column_stack([data.accel, data.t, data.gyro]),
        delimiter=",",
        header="ax,ay,az,t,gx,gy,gz",
        comments="",
    )
    assert main(["estimate", str(plain), "-o", str(tmp_path / "a.csv")]) == 0
    assert main(["estimate", str(named), "-o", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_an_empty_csv_is_one_line(tmp_path: Path) -> None:
    for text in ("", "t,gx,gy,gz,ax,ay,az\n", "# nothing\n"):
        path = tmp_path / "empty.csv"
        path.write_text(text)
        done = subprocess.run(
            [*MAVEST, "estimate", str(path)], capture_output=True, text=True, check=False
        )
        assert done.returncode == 2
        _one_line(done.stderr, "no samples")


@pytest.mark.parametrize("damage", ["cut off", "a damaged line"])
def test_a_csv_with_broken_rows_keeps_the_others_and_says_so_in_one_line(
    tmp_path: Path, damage: str
) -> None:
    """A file cut off mid-row, or one line of it damaged, was refused whole (and numpy's
    advice about `usecols` printed): every sample it held was lost."""
    data = simulate(4.0, 50.0, seed=1)
    whole, broken = tmp_path / "whole.csv", tmp_path / "broken.csv"
    np.savetxt(whole, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    lines = whole.read_text().splitlines(keepends=True)
    if damage == "cut off":
        kept = lines[:-1]
        broken.write_text("".join(kept) + lines[-1][:20])
        said = f"1 of {len(lines)} rows left out, not 7 numbers (the first at line {len(lines)}"
    else:
        kept = lines[:99] + lines[100:]
        broken.write_text("".join(lines[:99]) + "0.1,x\n" + "".join(lines[100:]))
        said = f"1 of {len(lines)} rows left out, not 7 numbers (the first at line 100: '0.1,x')"
    (tmp_path / "kept.csv").write_text("".join(kept))
    runs = [
        subprocess.run(
            [*MAVEST, "estimate", str(tmp_path / name), "-o", str(tmp_path / f"{name}.out")],
            capture_output=True,
            text=True,
            check=False,
        )
        for name in ("broken.csv", "kept.csv")
    ]
    assert [run.returncode for run in runs] == [0, 0]
    _one_line(runs[0].stderr, said)
    # the rows read are estimated as a file of those rows alone would be
    assert (tmp_path / "broken.csv.out").read_bytes() == (tmp_path / "kept.csv.out").read_bytes()


def test_a_csv_mostly_not_samples_is_refused_and_a_device_is_not_read(tmp_path: Path) -> None:
    path = tmp_path / "other.csv"
    path.write_text("0,1,2,3,4,5,6\n" + "0;1;2;3;4;5;6\n" * 3)
    for source, said in ((path, "3 of 4 rows are not the 7 numbers"), ("/dev/zero", "device")):
        done = subprocess.run(
            [*MAVEST, "estimate", str(source)], capture_output=True, text=True, check=False
        )
        assert done.returncode == 2
        _one_line(done.stderr, said)


def test_a_gyro_in_degrees_per_second_is_one_line_and_no_table(tmp_path: Path) -> None:
    """A CSV whose gyro is in °/s: one line naming the unit, exit 2, no table written
    (it was read as rad/s and gave 103° of tilt error without a word)."""
    from mavest.sim import Motion, simulate

    flight = simulate(60.0, 200.0, seed=3, motion=Motion(min_period=2.0, max_period=6.0))
    path = tmp_path / "deg.csv"
    table = np.column_stack([flight.t, np.degrees(flight.gyro), flight.accel])
    np.savetxt(path, table, delimiter=",", header="t,gx,gy,gz,ax,ay,az", comments="")
    out = tmp_path / "out.csv"
    done = subprocess.run(
        [*MAVEST, "estimate", str(path), "-o", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2
    _one_line(done.stderr, "in °/s? (× 57.3) mavest takes rad/s")
    assert not out.exists()


# ------------------------------------------------------------------ first run


def test_compiling_is_said_once_and_left_out_of_the_throughput(mavest_log: _Lines) -> None:
    before = COMPILING.seconds

    @njit(cache=False)
    def twice(x: float) -> float:
        return 2.0 * x

    @njit(cache=False)
    def thrice(x: float) -> float:
        return 3.0 * x

    twice(1.0)
    thrice(1.0)
    assert COMPILING.seconds > before
    said = [line for line in mavest_log.lines if "compiling the filter" in line]
    assert len(said) <= 1  # (once per process: an earlier test may have said it)

    report = runners.RunReport(Pipeline(ServiceConfig()), elapsed=10.0, compile_seconds=8.0)
    assert "10.00 s (8 s of it compiling the filter, a first run)" in report.summary()
    # compiled before the run's clock started (a demo's simulator): never more than the
    # whole, and no rate where none was measured (it read "43 s of it", "inf k samples/s")
    report = runners.RunReport(Pipeline(ServiceConfig()), elapsed=40.71, compile_seconds=43.0)
    summary = report.summary()
    assert "40.71 s (41 s of it compiling the filter, a first run)" in summary
    assert "inf" not in summary and "k samples/s" not in summary


# ------------------------------------------------------------------ exit codes


def test_an_interrupted_replay_exits_130_and_a_replay_without_imu_1(
    short_flight: Path, tmp_path: Path
) -> None:
    # a long paced replay, stopped by SIGINT once it runs
    process = subprocess.Popen(
        [*MAVEST, "replay", str(short_flight), "--speed", "0.5", "--out-tlog", str(tmp_path / "o")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    for _ in range(600):
        if (tmp_path / "o").exists() and (tmp_path / "o").stat().st_size > 0:
            break
        if process.poll() is not None:
            break
        time.sleep(0.1)
    process.send_signal(2)
    out, err = process.communicate(timeout=60)
    assert process.returncode == EXIT_INTERRUPTED, err
    assert "(interrupted)" in out and "Traceback" not in err

    no_imu = tmp_path / "no_imu.tlog"  # a vehicle's HEARTBEAT only
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    with no_imu.open("wb") as stream:
        for i in range(20):
            packet = encoder.heartbeat_encode(2, 3, 0, 0, 0).pack(encoder)
            stream.write((1_700_000_000_000_000 + i * 1_000_000).to_bytes(8, "big") + packet)
    assert main(["replay", str(no_imu)]) == EXIT_NO_IMU


class _Counted:
    """An estimate sink that counts the estimates."""

    def __init__(self) -> None:
        self.count = 0

    def on_estimate(self, *_: object) -> None:
        self.count += 1

    def on_estimates(self, stream: object, t: np.ndarray, *_: object) -> None:
        self.count += t.shape[0]

    def on_reference(self, *_: object, **__: object) -> None:
        pass

    def on_references(self, *_: object) -> None:
        pass


def test_a_paced_replay_stops_at_once_in_a_pause_of_its_log(tmp_path: Path) -> None:
    # 4 s at 200 Hz, the recording paused an hour after 2 s
    log = imu_tlog(tmp_path / "paused.tlog", 4.0, pause_s=3600.0)
    counted = _Counted()

    async def stopped_in_the_pause() -> tuple[runners.RunReport, float]:
        stop = asyncio.Event()
        replaying = asyncio.create_task(
            replay(log, ServiceConfig(), progress=False, speed=1.0, stop=stop, sinks=[counted])
        )
        while counted.count < 500 and not replaying.done():  # past the pause: waiting
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
        stop.set()
        stopped = time.perf_counter()
        report = await asyncio.wait_for(replaying, 30)
        return report, time.perf_counter() - stopped

    report, waited = asyncio.run(stopped_in_the_pause())
    assert report.interrupted and waited < 1.0
    assert 500 <= report.streams[0].stats.estimated < 800


# ------------------------------------------------------------------ live, nothing useful


def _serve_for(seconds: float, send: bytes | None, monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(runners, "NO_IMU_FIRST", 0.5)
    monkeypatch.setattr(runners, "NO_IMU_REPEAT", 1.0)
    port = free_port(socket.SOCK_DGRAM)

    async def scenario() -> runners.RunReport:
        stop, ready = asyncio.Event(), asyncio.Event()
        service = asyncio.create_task(
            run_live(
                f"udpin:127.0.0.1:{port}", ServiceConfig(), stop=stop, ready=ready, status_period=0
            )
        )
        await asyncio.wait_for(ready.wait(), 120)
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds
        while loop.time() < end:
            if send is not None:
                sender.sendto(send, ("127.0.0.1", port))
            await asyncio.sleep(0.1)
        sender.close()
        stop.set()
        return await service

    report = asyncio.run(scenario())
    return len(report.pipeline.streams)


def test_live_without_imu_says_what_it_hears_and_what_to_do(
    monkeypatch: pytest.MonkeyPatch, mavest_log: _Lines
) -> None:
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = encoder.heartbeat_encode(2, 3, 0, 0, 0).pack(encoder) + encoder.attitude_encode(
        1000, 0.1, 0.2, 0.3, 0, 0, 0
    ).pack(encoder)
    assert _serve_for(2.8, packets, monkeypatch) == 0
    said = [line for line in mavest_log.lines if "no IMU message yet" in line]
    assert len(said) >= 2, mavest_log.text()  # at 0.5 s, then every second
    assert "heard ATTITUDE, HEARTBEAT from 1/1" in said[0]
    assert "--request-rate" in said[0] and "SRn_RAW_SENS" in said[0]


def test_live_hearing_nothing_says_so(monkeypatch: pytest.MonkeyPatch, mavest_log: _Lines) -> None:
    assert _serve_for(1.5, None, monkeypatch) == 0
    assert "nothing heard on udpin:127.0.0.1:" in mavest_log.text()


def test_a_run_with_no_imu_exits_1(tmp_path: Path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    process = subprocess.Popen(
        [*MAVEST, "run", f"udpin:127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out = ""
    try:
        deadline = time.monotonic() + 120
        assert process.stderr is not None
        while time.monotonic() < deadline:  # until it listens
            line = process.stderr.readline()
            if "listening on" in line or not line:
                break
        process.send_signal(2)
        out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == EXIT_NO_IMU, (out, err)
    assert "no IMU stream found" in out


# ------------------------------------------------------------------ low rates, repeats


def test_a_low_imu_rate_is_warned_once_and_repeats_are_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    slow = tmp_path / "slow.tlog"  # a sample every 2.5 s: each comes after a gap
    write_flight_tlog(slow, 100.0, 0.4, AUTOPILOTS["ardupilot"], seed=1)
    assert main(["replay", str(slow)]) == 0
    err = capsys.readouterr().err
    assert err.count("is too slow for this estimate") == 1, err
    realigned = [line for line in err.splitlines() if "attitude re-aligned" in line]
    assert 1 <= len(realigned) <= 4, err  # three, and the count of the rest
    assert "more lines like this not shown" in err


@contextlib.contextmanager
def _limited(limiter: RepeatLimiter) -> Iterator[tuple[logging.Logger, _Lines]]:
    """A logger of its own whose lines go through ``limiter`` into the handler's list."""
    logger = logging.getLogger(f"mavest.test_repeats_{id(limiter)}")
    handler = _Lines()
    handler.addFilter(limiter)
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield logger, handler
    finally:
        logger.removeHandler(handler)


def test_the_repeat_limiter_counts_what_it_holds_back() -> None:
    limiter = RepeatLimiter(burst=2, period=math.inf)
    with _limited(limiter) as (logger, handler):
        for i in range(10):
            logger.warning("gap of %d s", i)
        logger.warning("another kind")
        limiter.report(logger)
    assert handler.lines == [
        "gap of 0 s",
        "gap of 1 s",
        "another kind",
        "8 more lines like this not shown, the last: gap of 9 s",
    ]


def test_the_repeat_limiter_keeps_each_subjects_first_lines() -> None:
    # one vehicle rebooting every second hid another's one reboot: the kind was the
    # template alone; a thousand vehicles are not a thousand lines either
    limiter = RepeatLimiter(burst=2, period=math.inf, subjects=3)
    with _limited(limiter) as (logger, handler):
        for i in range(10):
            logger.warning("%s: time went back %d", "vehicle 8/1", i)
        logger.warning("%s: time went back %d", "vehicle 2/1", 0)
        for k in range(3, 8):
            logger.warning("%s: time went back %d", f"vehicle {k}/1", 0)
        limiter.report(logger)
    assert handler.lines == [
        "vehicle 8/1: time went back 0",
        "vehicle 8/1: time went back 1",
        "vehicle 2/1: time went back 0",
        "vehicle 3/1: time went back 0",
        "8 more lines like this not shown, the last: vehicle 8/1: time went back 9",
        "4 more lines like this not shown, the last: vehicle 7/1: time went back 0",
    ]


def test_ids_without_end_are_followed_up_to_a_bound(caplog: pytest.LogCaptureFixture) -> None:
    # 5000 spoofed (system, component) ids of 3 RAW_IMU each took the service from 150
    # to 550 MB and its summary to 16,745 lines
    from mavest.service.pipeline import MAX_STREAMS

    pipeline = Pipeline(ServiceConfig())
    decoder = mavlink2.MAVLink(None)
    with caplog.at_level("WARNING", logger="mavest"):
        for system in range(1, 201):
            encoder = mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)
            for k in range(3):
                packet = encoder.raw_imu_encode(1000 * k, 0, 0, -1000, 1, -2, 3, 0, 0, 0)
                pipeline.on_message(decoder.decode(bytearray(packet.pack(encoder))), 1000 * k)
    assert len(pipeline.streams) == MAX_STREAMS
    said = [r.getMessage() for r in caplog.records if "streams followed already" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("RAW_IMU[0] from 65/1: 64 IMU streams")


# ------------------------------------------------------------------ request rate


def test_the_requested_rate_is_asked_for_below_the_stream_rate_too() -> None:
    class Sent:
        def __init__(self) -> None:
            self.packets: list[bytes] = []

        def send(self, packet: bytes) -> None:
            self.packets.append(packet)

    config = ServiceConfig().replace(input={"request_rate": 100.0})
    link = Sent()
    pipeline = Pipeline(config, links=[link])  # type: ignore[list-item]
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    for i in range(800):  # 2 s of RAW_IMU at 400 Hz
        message = encoder.raw_imu_encode(i * 2500, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
        pipeline.on_message(
            mavlink2.MAVLink(None).decode(bytearray(message.pack(encoder))), i * 2500
        )
    (stream,) = pipeline.streams.values()
    assert stream.rate == pytest.approx(400.0, rel=0.01)
    link.packets.clear()  # the estimates sent
    pipeline.request_intervals()
    parser = mavlink2.MAVLink(None)
    (command,) = parser.parse_buffer(b"".join(link.packets))
    assert command.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    assert command.param2 == pytest.approx(1e6 / 100.0)


# ------------------------------------------------------------------ serve


@pytest.mark.skipif(rerun_binary() is None, reason="the rerun viewer executable is not installed")
def test_replay_into_a_served_viewer_serves_until_stopped(short_flight: Path) -> None:
    grpc, web = free_port(), free_port()
    outputs = Outputs(rerun="serve", rerun_port=grpc, rerun_web_port=web)

    async def scenario() -> tuple[runners.RunReport, bool]:
        stop = asyncio.Event()
        seen: list[bool] = []

        async def linger(report: runners.RunReport) -> None:
            assert report.streams and report.streams[0].stats.estimated > 0
            page = await asyncio.get_running_loop().run_in_executor(
                None, lambda: urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10)
            )
            seen.append(page.status == 200)
            stop.set()
            await stop.wait()

        report = await replay(short_flight, ServiceConfig(), outputs, stop=stop, linger=linger)
        return report, bool(seen) and seen[0]

    report, served = asyncio.run(scenario())
    assert served and report.lingered and not report.interrupted
    # the served viewer went with the replay
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", web), timeout=1).close()


# ------------------------------------------------------------------ --out-only


def test_out_only_keeps_the_estimates_off_the_vehicles_link() -> None:
    port, out_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.bind(("127.0.0.1", out_port))
    out.setblocking(False)
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.setblocking(False)
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    config = ServiceConfig().replace(output={"reply_on_input": False})

    def names(sock: socket.socket) -> list[str]:
        parser = mavlink2.MAVLink(None)
        found = []
        while True:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return found
            found += [m.get_type() for m in parser.parse_buffer(data) or []]

    async def scenario() -> tuple[list[str], list[str]]:
        stop, ready = asyncio.Event(), asyncio.Event()
        service = asyncio.create_task(
            run_live(
                f"udpin:127.0.0.1:{port}",
                config,
                (f"udpout:127.0.0.1:{out_port}",),
                stop=stop,
                ready=ready,
                status_period=0,
            )
        )
        await asyncio.wait_for(ready.wait(), 120)
        heard_by_vehicle: list[str] = []
        heard_out: list[str] = []
        for i in range(300):  # 3 s of RAW_IMU at 100 Hz, level, at rest
            packets = encoder.raw_imu_encode(i * 10_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(
                encoder
            )
            if i % 100 == 0:
                packets += encoder.heartbeat_encode(2, 3, 0, 0, 0).pack(encoder)
            vehicle.sendto(packets, ("127.0.0.1", port))
            await asyncio.sleep(0.01)
            heard_by_vehicle += names(vehicle)
            heard_out += names(out)
        stop.set()
        await service
        return heard_by_vehicle + names(vehicle), heard_out + names(out)

    heard_by_vehicle, heard_out = asyncio.run(scenario())
    vehicle.close()
    out.close()
    assert heard_out.count("ATTITUDE") > 200 and "HEARTBEAT" in heard_out
    assert "ATTITUDE" not in heard_by_vehicle and "HEARTBEAT" not in heard_by_vehicle


def test_out_only_needs_an_out(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "udpin:127.0.0.1:14550", "--out-only"]) == 2
    _one_line(capsys.readouterr().err, "--out-only needs an --out")


@pytest.mark.parametrize("command", [["sim", "--tlog", "{dir}/f.tlog", "--seconds", "1"], ["demo"]])
def test_a_missing_simulator_names_the_extra(
    command: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # JSBSim comes with the sim extra: without it, one line says how to get it
    monkeypatch.setitem(sys.modules, "jsbsim", None)  # import fails as if not installed
    monkeypatch.chdir(tmp_path)
    argv = [part.format(dir=tmp_path) for part in command]
    assert main(argv) == 2
    _one_line(capsys.readouterr().err, "pip install 'mavest[sim]'")
    assert not (tmp_path / "f.tlog").exists()


def _tlog_at_rest_in_g(
    path: Path, seconds: float = 3.0, rate: float = 200.0, g: float = 1.0, x_rate: float = 0.0
) -> None:
    """A vehicle at rest whose HIGHRES_IMU accelerometer is in g, not m/s² (``g``: what
    it reads for 1 g), its gyro reading ``x_rate`` rad/s about x besides its noise."""
    rng = np.random.default_rng(1)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    records = [(0, mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav))]
    for k in range(int(seconds * rate)):
        usec = 10_000_000 + round(k * 1e6 / rate)
        gyro = rng.normal(0.0, 0.002, 3) + np.array([x_rate, 0.0, 0.0])
        accel = g * (np.array([0.01, -0.02, -1.0]) + rng.normal(0.0, 0.002, 3))
        message = mav.highres_imu_encode(
            usec, *accel, *gyro, 0.2, 0.0, 0.4, 1013.0, 0.0, 0.0, 20.0, 0x3F | 0x1C0, 0
        )
        records.append((usec, message.pack(mav)))
    path.write_bytes(b"".join(t.to_bytes(8, "big") + packet for t, packet in records))


@pytest.mark.parametrize("fast", [True, False])
def test_an_accelerometer_in_g_is_one_line_and_counted(
    tmp_path: Path, fast: bool, mavest_log: _Lines
) -> None:
    """Both replay paths say it once, name the unit and the factor, count the samples
    and answer nothing; no Python warning on top."""
    log = tmp_path / "in_g.tlog"
    _tlog_at_rest_in_g(log)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.simplefilter("ignore", AccelUnitWarning)  # (as the command line does)
        report = asyncio.run(replay(log, ServiceConfig(), Outputs(), progress=False, fast=fast))
    assert not [w for w in caught if issubclass(w.category, UserWarning)]
    said = [line for line in mavest_log.lines if "looks like g" in line]
    assert len(said) == 1 and "multiply by 9.80665" in said[0], mavest_log.text()
    (stream,) = report.pipeline.streams.values()
    assert 0 < stream.stats.accel_wrong_unit <= stream.stats.received == 600
    assert not stream.estimator.initialised
    summary = report.summary()
    assert f"{stream.stats.accel_wrong_unit} samples with no attitude" in summary
    # its magnetometer readings were not taken into an attitude it did not have
    assert stream.stats.mag_usable == 600 and stream.stats.mag_taken == 0
    assert "heading free (6-D): none of the 600 usable magnetometer readings taken" in summary
    # no attitude, so none said to the vehicle (not the level one the filter starts from)
    assert stream.stats.answered == 0
    assert "600 samples over 3.0 s at 200.0 Hz, 0 answered" in summary


@pytest.mark.parametrize("fast", [True, False])
def test_a_gyro_clipped_throughout_is_said_once_and_counted(
    tmp_path: Path, fast: bool, mavest_log: _Lines
) -> None:
    """A gyro beyond gyro_clip on every sample: the summary said "no resets" and nothing
    was logged (the filter is calm again never, so never re-aligned), while every
    attitude reported was a guess."""
    log = tmp_path / "spinning.tlog"
    _tlog_at_rest_in_g(log, g=9.80665, x_rate=40.0)  # (33.9 rad/s is gyro_clip)
    report = asyncio.run(replay(log, ServiceConfig(), Outputs(), progress=False, fast=fast))
    said = [line for line in mavest_log.lines if "the gyro clipped (an axis beyond" in line]
    assert len(said) == 1 and "t=10.0 s" in said[0], mavest_log.text()
    (stream,) = report.pipeline.streams.values()
    # every sample but the one the filter started on
    assert stream.stats.gyro_clipped == stream.stats.estimated - 1 == 599
    assert "599 samples with the gyro clipped" in report.summary()
    if fast:  # (as a fleet replays a log)
        (row,) = log_rows(LogTask(str(log), ServiceConfig()))
        assert row["gyro_clipped"] == 599


def test_the_command_line_says_a_wrong_unit_without_pythons_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A paced replay takes the samples one at a time, as ``run`` does, where the
    estimator warns: the command shows its own line only."""
    log = tmp_path / "in_g.tlog"
    _tlog_at_rest_in_g(log)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["replay", str(log), "--speed", "1000", "-q"]) == 0
    assert not [w for w in caught if issubclass(w.category, AccelUnitWarning)]
    err = capsys.readouterr().err
    assert err.count("looks like g") == 1 and "Warning" not in err
