"""mavest among other MAVLink programs: its output tlogs read back whole by pymavlink and
mavlogdump, each vehicle answered in the MAVLink version it speaks, requests addressed
to mavest's component answered as a component without parameters, commands or files
answers them, and a declination taken for the vehicle it belongs to."""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import socket
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1

from mavest.cli import build_parser
from mavest.mavlink.links import make_link, parse_endpoint
from mavest.mavlink.messages import MAVLink, mavlink2
from mavest.mavlink.tlog import TlogReader
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Pipeline
from mavest.service.process import free_port
from mavest.service.runners import Outputs, replay, run_live

OURS = 191  # mavest's component


def _shared_tlogs() -> list[Path]:
    root = Path(os.environ.get("MAVEST_DATA", Path(__file__).parents[2] / "shared" / "data"))
    return sorted((root / "tlogs").glob("*.tlog"))


def _mavlink1_only(path: Path) -> bool:
    return all(record.packet[0] == mavlink2.PROTOCOL_MARKER_V1 for record in TlogReader.open(path))


def _v1_tlogs() -> list[Path]:
    return [path for path in _shared_tlogs() if _mavlink1_only(path)]


def _pymavlink_counts(path: Path) -> Counter[tuple[str, int, int]]:
    """Messages by (type, system, component) as pymavlink's tlog reader reads them."""
    connection = mavutil.mavlink_connection(str(path))
    counts: Counter[tuple[str, int, int]] = Counter()
    while (message := connection.recv_msg()) is not None:
        counts[(message.get_type(), message.get_srcSystem(), message.get_srcComponent())] += 1
    return counts


def _mavlogdump_counts(path: Path, types: set[str]) -> Counter[str]:
    """Messages by type as ``mavlogdump.py --types`` lists them."""
    script = Path(sys.executable).parent / "mavlogdump.py"
    result = subprocess.run(
        [sys.executable, str(script), "--types", ",".join(sorted(types)), str(path)],
        capture_output=True,
        text=True,
        check=True,
    )
    # each line: "DATE TIME: TYPE {fields}"
    return Counter(line.split()[2] for line in result.stdout.splitlines() if ": " in line)


# ------------------------------------------------------------------ output tlogs


@pytest.mark.skipif(not _shared_tlogs(), reason="no tlogs in $MAVEST_DATA/tlogs (shared data)")
@pytest.mark.parametrize("path", _v1_tlogs(), ids=lambda p: p.name)
def test_every_input_message_of_a_mavlink1_log_reads_back_from_the_output(
    path: Path, tmp_path: Path
) -> None:
    """A MAVLink 2 packet among MAVLink 1 records made pymavlink's tlog reader take the
    next short MAVLink 1 record's bytes with the timestamp after it: 41 of 45 082
    messages of squilter_gridlines_logs_mav.tlog lost. mavest answers in MAVLink 1."""
    out = tmp_path / "out.tlog"
    report = asyncio.run(replay(path, ServiceConfig(), Outputs(tlog=out)))
    assert report.pipeline.sent > 0
    source, written = _pymavlink_counts(path), _pymavlink_counts(out)
    ours = Counter({key: n for key, n in written.items() if key[2] == OURS})
    assert written - ours == source
    assert {kind for kind, _, _ in ours} == {"ATTITUDE", "ATTITUDE_QUATERNION", "HEARTBEAT"}
    if shutil.which("mavlogdump.py", path=str(Path(sys.executable).parent)) is None:
        pytest.skip("pymavlink's mavlogdump.py is not installed")
    # (its listing does not say who sent a message: the types mavest sends are left out)
    types = {kind for kind, _, _ in source} - {kind for kind, _, _ in ours}
    assert _mavlogdump_counts(out, types) == _mavlogdump_counts(path, types)


# ------------------------------------------------------------------ live


class _Peer:
    """A vehicle (1/1, ArduPilot) and a ground station (255/190) on one UDP link to the
    service, in MAVLink 1 or 2; what the service sends back is kept, decoded."""

    def __init__(self, port: int, version1: bool) -> None:
        self.version1 = version1
        dialect = mavlink1 if version1 else mavlink2
        self.vehicle = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
        self.ground = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
        self.link = make_link(parse_endpoint(f"udpout:127.0.0.1:{port}"))
        self.parser = MAVLink(None)
        self.parser.robust_parsing = True
        self.heard: list[Any] = []

    async def start(self) -> None:
        await self.link.start(self._on_bytes)

    def _on_bytes(self, link: Any, data: bytes, peer: Any) -> None:
        self.heard.extend(self.parser.parse_buffer(data) or [])

    def send(self, mav: Any, message: Any) -> None:
        self.link.send(message.pack(mav))
        mav.seq = (mav.seq + 1) % 256

    async def fly(self, seconds: float, rate: float = 100.0) -> None:
        """Level and still: HEARTBEAT at 1 Hz, RAW_IMU at ``rate``."""
        vehicle = self.vehicle
        for i in range(int(seconds * rate)):
            if i % int(rate) == 0:
                self.send(vehicle, vehicle.heartbeat_encode(2, 3, 0, 0, 4, 3))
            t_us = int(1e6 * i / rate)
            self.send(vehicle, vehicle.raw_imu_encode(t_us, 0, 0, -1000, 1, -2, 0, 200, 0, 400))
            await asyncio.sleep(1.0 / rate)

    def heard_from(self, kind: str) -> list[Any]:
        return [m for m in self.heard if m.get_type() == kind and m.get_srcComponent() == OURS]


async def _converse(version1: bool, requests: Any) -> _Peer:
    """The service, the vehicle flying for 1.5 s, then ``requests(peer)`` sent by the
    ground station; the peer with everything it heard 0.5 s later."""
    port = free_port(socket.SOCK_DGRAM)
    stop, ready = asyncio.Event(), asyncio.Event()
    service = asyncio.create_task(
        run_live(
            f"udpin:127.0.0.1:{port}", ServiceConfig(), stop=stop, ready=ready, status_period=0
        )
    )
    await asyncio.wait_for(ready.wait(), 120)
    peer = _Peer(port, version1)
    await peer.start()
    await peer.fly(1.5)
    requests(peer)
    await peer.fly(0.5)
    peer.link.close()
    stop.set()
    await service
    return peer


@pytest.fixture
def mavest_log() -> Iterator[list[str]]:
    lines: list[str] = []

    class Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    handler = Handler(logging.INFO)
    logger = logging.getLogger("mavest")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield lines
    logger.removeHandler(handler)
    logger.setLevel(level)


@pytest.mark.parametrize("version1", [True, False], ids=["mavlink1", "mavlink2"])
def test_each_vehicle_is_answered_in_the_mavlink_version_it_speaks(version1: bool) -> None:
    peer = asyncio.run(_converse(version1, lambda peer: None))
    magic = mavlink2.PROTOCOL_MARKER_V1 if version1 else mavlink2.PROTOCOL_MARKER_V2
    for kind in ("ATTITUDE", "ATTITUDE_QUATERNION", "HEARTBEAT"):
        heard = peer.heard_from(kind)
        assert heard, kind
        assert {m.get_msgbuf()[0] for m in heard} == {magic}, kind
    if version1:  # the base fields only, as a MAVLink 1 sender packs them
        quaternion = peer.heard_from("ATTITUDE_QUATERNION")[0]
        assert len(quaternion.get_msgbuf()) == 6 + 32 + 2


def _ftp_open(session: int = 0) -> list[int]:
    """An FTP OpenFileRO request's payload for @PARAM/param.pck (seq 7)."""
    name = b"@PARAM/param.pck"
    header = bytes([7, 0, session, mavlink2.MAV_FTP_OPCODE_OPENFILERO, len(name), 0, 0, 0])
    payload = header + bytes(4) + name
    return list(payload + bytes(251 - len(payload)))


def _ask(peer: _Peer) -> None:
    ground = peer.ground
    request_message = mavlink2.MAV_CMD_REQUEST_MESSAGE
    peer.send(ground, ground.param_request_list_encode(1, OURS))
    peer.send(ground, ground.param_request_read_encode(1, OURS, b"COMPASS_DEC", -1))
    peer.send(
        ground, ground.command_long_encode(1, OURS, request_message, 0, 148, 0, 0, 0, 0, 0, 0)
    )
    # aimed at the autopilot (component 0: every component): the autopilot answers
    peer.send(ground, ground.command_long_encode(1, 0, 520, 0, 1, 0, 0, 0, 0, 0, 0))
    peer.send(ground, ground.file_transfer_protocol_encode(0, 1, OURS, _ftp_open()))


@pytest.mark.parametrize("version1", [True, False], ids=["mavlink1", "mavlink2"])
def test_requests_to_mavests_component_are_answered(version1: bool, mavest_log: list[str]) -> None:
    peer = asyncio.run(_converse(version1, _ask))
    magic = mavlink2.PROTOCOL_MARKER_V1 if version1 else mavlink2.PROTOCOL_MARKER_V2
    # the command to mavest: unsupported; the broadcast one: not mavest's to answer
    (ack,) = peer.heard_from("COMMAND_ACK")
    assert ack.command == mavlink2.MAV_CMD_REQUEST_MESSAGE
    assert ack.result == mavlink2.MAV_RESULT_UNSUPPORTED
    assert ack.get_msgbuf()[0] == magic
    if not version1:  # (MAVLink 1 has no target fields in COMMAND_ACK)
        assert (ack.target_system, ack.target_component) == (255, 190)
    # FTP: a NAK of the open, the next sequence number, the session, "unknown command"
    (ftp,) = peer.heard_from("FILE_TRANSFER_PROTOCOL")
    assert (ftp.target_system, ftp.target_component) == (255, 190)
    payload = bytes(ftp.payload)
    seq, session, opcode, size, req_opcode = payload[0] | payload[1] << 8, *payload[2:6]
    assert (seq, session, opcode, size, req_opcode) == (
        8,
        0,
        mavlink2.MAV_FTP_OPCODE_NAK,
        1,
        mavlink2.MAV_FTP_OPCODE_OPENFILERO,
    )
    assert payload[12] == mavlink2.MAV_FTP_ERR_UNKNOWNCOMMAND
    assert ftp.get_msgbuf()[0] == magic
    # parameters: none to list (no PARAM_VALUE, which a ground station would list);
    # a read of one that does not exist is PARAM_ERROR where MAVLink 2 can carry it
    assert not peer.heard_from("PARAM_VALUE")
    errors = peer.heard_from("PARAM_ERROR")
    if version1:
        assert not errors
    else:
        (error,) = errors
        assert (error.param_id, error.param_index) == ("COMPASS_DEC", -1)
        assert error.error == mavlink2.MAV_PARAM_ERROR_DOES_NOT_EXIST
        assert (error.target_system, error.target_component) == (255, 190)
    text = "\n".join(mavest_log)
    assert "255/190 sent COMMAND_LONG MAV_CMD_REQUEST_MESSAGE to mavest (1/191)" in text
    assert "255/190 sent PARAM_REQUEST_LIST to mavest (1/191): answered nothing" in text


def test_an_ftp_answer_is_never_answered() -> None:
    """Two components that NAK each other's NAKs would never stop."""

    def nak(peer: _Peer) -> None:
        payload = _ftp_open()
        payload[3] = mavlink2.MAV_FTP_OPCODE_NAK
        peer.send(peer.ground, peer.ground.file_transfer_protocol_encode(0, 1, OURS, payload))

    peer = asyncio.run(_converse(False, nak))
    assert peer.heard_from("ATTITUDE") and not peer.heard_from("FILE_TRANSFER_PROTOCOL")


# ------------------------------------------------------------------ declination


def test_a_declination_logged_by_a_ground_station_applies_to_its_vehicle(
    mavest_log: list[str],
) -> None:
    """MAVProxy logs the vehicle's parameters under its own component (1/190): the
    declination is system 1's, for vehicle 1/1, and is said to come from 1/190."""
    pipeline = Pipeline(ServiceConfig())
    vehicle = MAVLink(None, srcSystem=1, srcComponent=1)
    ground = MAVLink(None, srcSystem=1, srcComponent=190)

    def receive(mav: Any, message: Any) -> None:
        pipeline.on_message(mav.decode(bytearray(message.pack(mav))), 0)

    receive(vehicle, vehicle.heartbeat_encode(2, 3, 0, 0, 4, 3))
    for i in range(3):
        receive(vehicle, vehicle.raw_imu_encode(i * 10_000, 0, 0, -1000, 0, 0, 0, 200, 0, 400))
    receive(ground, ground.param_value_encode(b"COMPASS_DEC", 0.25, 9, 885, 103))
    (stream,) = pipeline.streams.values()
    assert stream.estimator.declination == pytest.approx(0.25)
    assert (1, 190) not in pipeline.vehicles  # it sent no IMU, no HEARTBEAT
    said = "vehicle 1/1: declination 14.32° from parameter COMPASS_DEC of 1/190"
    assert any(line.startswith(said) for line in mavest_log), mavest_log


@pytest.mark.parametrize("autodec_first", [True, False])
def test_a_declination_the_autopilot_may_have_replaced_is_said_so(
    autodec_first: bool, mavest_log: list[str]
) -> None:
    """With COMPASS_AUTODEC on, ArduPilot works the declination out from its position
    after a fix and sends no new COMPASS_DEC: the one logged at connection may be stale
    (a real tlog's was −9.19° where the vehicle's was 11.4°: yaw 20° off). It is used,
    and said to be doubtful, once, whichever parameter comes first."""
    pipeline = Pipeline(ServiceConfig())
    ground = MAVLink(None, srcSystem=1, srcComponent=190)
    params = [(b"COMPASS_DEC", -0.16), (b"COMPASS_AUTODEC", 1.0)]
    for name, value in (params[::-1] if autodec_first else params) * 2:
        message = ground.param_value_encode(name, value, 9, 885, 103)
        pipeline.on_message(ground.decode(bytearray(message.pack(ground))), 0)
    doubtful = [line for line in mavest_log if "COMPASS_AUTODEC is on" in line]
    assert len(doubtful) == 1 and "(-9.17°) may be stale" in doubtful[0], mavest_log
    # off: the parameter is the declination used, nothing to say
    quiet = Pipeline(ServiceConfig())
    for name, value in ((b"COMPASS_AUTODEC", 0.0), (b"COMPASS_DEC", 0.2)):
        message = ground.param_value_encode(name, value, 9, 885, 103)
        quiet.on_message(ground.decode(bytearray(message.pack(ground))), 0)
    assert len([line for line in mavest_log if "COMPASS_AUTODEC" in line]) == 1


@pytest.mark.parametrize("command", ["run", "replay"])
def test_out_tlog_help_says_what_the_file_holds(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "every input message" in text and "HEARTBEAT" in text
