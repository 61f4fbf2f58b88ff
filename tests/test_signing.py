"""MAVLink 2 signing: mavest's signatures checked by pymavlink as the independent reference,
the key formats, verification of what mavest hears (in process and over loopback UDP with
the simulated vehicle signing), and that the only command mavest sends is the
message-interval request."""

from __future__ import annotations

import ast
import asyncio
import hashlib
import socket
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil

import mavest
from mavest.cli import EXIT_NO_IMU, main
from mavest.estimator import ConfigError
from mavest.mavlink.links import Endpoint, Link
from mavest.mavlink.messages import Encoder, MAVLink, mavlink2
from mavest.mavlink.signing import KEY_ENVIRONMENT_VARIABLE, Signing, key_from_file
from mavest.service.config import ServiceConfig, SigningConfig
from mavest.service.pipeline import Pipeline
from mavest.service.process import ServiceProcess, free_port
from mavest.service.runners import replay
from mavest.sim import vehicle as vehicle_module
from mavest.sim.vehicle import AUTOPILOTS, Autopilot, VehicleEncoder, write_flight_tlog

KEY = hashlib.sha256(b"the vehicle's key").digest()
OTHER_KEY = hashlib.sha256(b"somebody else's key").digest()
EPOCH_2015 = datetime(2015, 1, 1, tzinfo=timezone.utc).timestamp()
OURS = 191  # mavest's component id


def _ticks(unix_time: float | None = None) -> int:
    """MAVLink's signing clock, computed here independently: 10 µs since 2015-01-01 UTC."""
    return int(((time.time() if unix_time is None else unix_time) - EPOCH_2015) * 100_000)


def _signature_fields(packet: bytes) -> tuple[int, int]:
    """(link id, timestamp) of a signed MAVLink 2 packet, read from its signature block."""
    assert packet[0] == 0xFD and packet[2] & 0x01, "not a signed MAVLink 2 packet"
    return packet[-13], int.from_bytes(packet[-12:-6], "little")


def _reference(key: bytes) -> Any:
    """A plain pymavlink parser holding ``key``: refuses unsigned and badly signed packets."""
    parser = MAVLink(None)
    parser.signing.secret_key = key
    return parser


def _verified(packets: list[bytes], key: bytes) -> list[Any]:
    parser = _reference(key)
    messages = []
    for packet in packets:
        messages += parser.parse_buffer(packet) or []  # raises MAVError when refused
    assert all(m._signed for m in messages)
    return messages


def _signed_mavlink(key: bytes, timestamp: int | None = None) -> type:
    """pymavlink's MAVLink, signing with ``key`` (link id 1) and refusing unsigned input,
    set up by hand here rather than with mavest's helpers."""

    class SignedMAVLink(MAVLink):  # type: ignore[misc, valid-type]
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.signing.secret_key = key
            self.signing.sign_outgoing = True
            self.signing.link_id = 1
            self.signing.timestamp = _ticks() if timestamp is None else timestamp

    return SignedMAVLink


def _vehicle(
    monkeypatch: pytest.MonkeyPatch, system: int, key: bytes | None, timestamp: int | None = None
) -> VehicleEncoder:
    """The simulated vehicle's encoder for vehicle ``system``, signing with ``key`` (or not)."""
    with monkeypatch.context() as patch:
        if key is not None:
            patch.setattr(vehicle_module, "MAVLink", _signed_mavlink(key, timestamp))
        autopilot = Autopilot("ardupilot", "RAW_IMU", mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, system)
        return VehicleEncoder(autopilot)


def _imu(encoder: VehicleEncoder, i: int) -> bytes:
    """RAW_IMU sample ``i`` at 100 Hz of a vehicle at rest, level."""
    return encoder.imu(
        20.0 + 0.01 * i, np.zeros(3), np.array([0.0, 0.0, -9.80665]), np.array([20.0, 0.0, 40.0])
    )


class _Capture(Link):
    """A link that keeps what the pipeline sends."""

    def __init__(self) -> None:
        super().__init__(Endpoint("udpout", "127.0.0.1", 9))
        self.packets: list[bytes] = []

    def send(self, packet: bytes) -> None:
        self.packets.append(packet)


# ------------------------------------------------------------------ outgoing


def test_outgoing_messages_verify_with_pymavlink_and_the_same_key_only() -> None:
    encoder = Encoder(1, OURS, Signing(KEY))
    packets = [
        encoder.attitude(1000, (0.1, -0.2, 0.3), (0.01, 0.02, 0.03)),
        encoder.attitude_quaternion(1000, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        encoder.heartbeat(),
        encoder.set_message_interval(1, 1, "RAW_IMU", 200.0),
    ]
    messages = _verified(packets, KEY)
    assert [m.get_type() for m in messages] == [
        "ATTITUDE",
        "ATTITUDE_QUATERNION",
        "HEARTBEAT",
        "COMMAND_LONG",
    ]
    assert messages[0].roll == pytest.approx(0.1) and messages[0].time_boot_ms == 1000
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in messages} == {(1, OURS)}
    for packet in packets:  # another key: every one refused
        with pytest.raises(mavlink2.MAVError, match="Invalid signature"):
            _reference(OTHER_KEY).parse_buffer(packet)
    # the reference refuses what is not signed, so the checks above mean something
    with pytest.raises(mavlink2.MAVError, match="Invalid signature"):
        _reference(KEY).parse_buffer(Encoder(1, OURS).heartbeat())
    # MAVLink's signing clock, one link id, timestamps rising
    fields = [_signature_fields(p) for p in packets]
    assert {link for link, _ in fields} == {0}
    stamps = [stamp for _, stamp in fields]
    assert stamps == sorted(set(stamps))
    assert abs(stamps[0] - _ticks()) < 100_000  # within a second of now


def test_signing_clock_keeps_up_with_time() -> None:
    """pymavlink alone adds one tick (10 µs) per packet; receivers refuse a new stream more
    than a minute behind their clock, so a long run must keep its timestamp at now."""
    encoder = Encoder(1, OURS, Signing(KEY))
    _, first = _signature_fields(encoder.heartbeat())
    time.sleep(0.05)
    _, second = _signature_fields(encoder.heartbeat())
    assert second - first >= 4_000  # ≥ 40 ms later
    assert abs(second - _ticks()) < 100_000


def test_sign_outgoing_off_sends_unsigned() -> None:
    packet = Encoder(1, OURS, Signing(KEY, sign_outgoing=False)).heartbeat()
    assert not packet[2] & 0x01
    assert MAVLink(None).parse_buffer(packet)[0].get_type() == "HEARTBEAT"


# ------------------------------------------------------------------ keys


def _write(path: Path, data: bytes | str) -> Path:
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)
    return path


def test_key_formats(tmp_path: Path) -> None:
    raw = bytes(range(32))  # control characters: not text
    assert key_from_file(_write(tmp_path / "raw", raw)) == (raw, "raw")
    assert key_from_file(_write(tmp_path / "hex", KEY.hex())) == (KEY, "hex")
    spaced = " ".join(KEY.hex().upper()[i : i + 8] for i in range(0, 64, 8))
    assert key_from_file(_write(tmp_path / "spaced", f"{spaced[:40]}\n{spaced[40:]}\n"))[0] == KEY
    phrase = "correct horse battery staple"
    expected = hashlib.sha256(phrase.encode()).digest()  # MAVProxy's `signing setup`
    assert key_from_file(_write(tmp_path / "phrase", phrase + "\n")) == (expected, "passphrase")
    # 31 characters and a newline are 32 bytes, but text: a passphrase, not a raw key
    short = "a" * 31
    assert key_from_file(_write(tmp_path / "short", short + "\n"))[0] == (
        hashlib.sha256(short.encode()).digest()
    )


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty"),
        (" \n\t\n", "empty"),
        (bytes(range(128, 159)), "31 bytes of binary data"),
        (bytes(range(128, 161)), "33 bytes of binary data"),
        (KEY.hex()[:63], "63 hexadecimal digits; a hex key has 64"),
        (KEY.hex() + "a", "65 hexadecimal digits"),
        (bytes(32), "all-zero key"),
        ("0" * 64, "all-zero key"),
        ("two\nlines", "one line of printable text"),
    ],
)
def test_bad_key_files_are_refused(tmp_path: Path, content: bytes | str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        key_from_file(_write(tmp_path / "key", content))


def test_key_sources_and_their_order(tmp_path: Path) -> None:
    hex_file = _write(tmp_path / "hex", KEY.hex())
    phrase_file = _write(tmp_path / "phrase", "from the command line")
    env = {KEY_ENVIRONMENT_VARIABLE: "from the environment"}
    table = SigningConfig(key_file=str(hex_file))
    assert SigningConfig().resolve({}) is None
    assert SigningConfig().resolve({KEY_ENVIRONMENT_VARIABLE: ""}) is None  # empty: unset
    assert table.resolve({}).key == KEY
    assert table.resolve(env).key == hashlib.sha256(b"from the environment").digest()
    assert table.resolve(env, phrase_file).key == hashlib.sha256(b"from the command line").digest()
    env_hex = {KEY_ENVIRONMENT_VARIABLE: OTHER_KEY.hex()}
    assert SigningConfig().resolve(env_hex).key == OTHER_KEY
    assert "key=" not in repr(table.resolve({}))  # never printed
    with pytest.raises(ConfigError, match="needs a signing key"):
        SigningConfig(require_signed=True).resolve({})
    with pytest.raises(ConfigError, match="no such file"):
        SigningConfig(key_file=str(tmp_path / "missing")).resolve({})


def test_signing_table_in_a_config_file(tmp_path: Path) -> None:
    (tmp_path / "conf").mkdir()
    _write(tmp_path / "conf" / "vehicle.key", KEY.hex())
    path = _write(
        tmp_path / "conf" / "c.toml",
        '[signing]\nkey_file = "vehicle.key"\nrequire_signed = true\n',
    )
    config = ServiceConfig.from_toml(path)
    assert Path(config.signing.key_file) == tmp_path / "conf" / "vehicle.key"  # next to it
    signing = config.signing.resolve({})
    assert signing is not None and signing.key == KEY and signing.require_signed
    _write(path, "[signing]\nkey = 1\n")
    with pytest.raises(ConfigError, match="unknown signing parameter"):
        ServiceConfig.from_toml(path)
    _write(path, '[signing]\nrequire_signed = "yes"\n')
    with pytest.raises(ConfigError, match="require_signed = 'yes': expected true or false"):
        ServiceConfig.from_toml(path)


@pytest.mark.parametrize(
    ("arguments", "environment", "message"),
    [
        (["--signing-key", "{tmp}/missing"], "", "no such file"),
        (["--signing-key", "{tmp}"], "", "is a directory"),
        (["--signing-key", "{tmp}/empty"], "", "empty"),
        (["--signing-key", "{tmp}/binary"], "", "31 bytes of binary data"),
        (["--require-signed"], "", "require_signed needs a signing key"),
        (["--require-signed"], "0" * 64, "MAVEST_SIGNING_KEY: an all-zero key"),
        (["--config", "{tmp}/c.toml"], "", "no such file"),
    ],
)
def test_cli_key_mistakes_get_one_line_and_exit_code_2(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    arguments: list[str],
    environment: str,
    message: str,
) -> None:
    monkeypatch.setenv(KEY_ENVIRONMENT_VARIABLE, environment)
    _write(tmp_path / "empty", b"")
    _write(tmp_path / "binary", bytes(range(128, 159)))
    _write(tmp_path / "c.toml", '[signing]\nkey_file = "absent.key"\n')
    port = free_port(socket.SOCK_DGRAM)
    command = ["run", f"udpin:127.0.0.1:{port}", *(a.format(tmp=tmp_path) for a in arguments)]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


# ------------------------------------------------------------------ incoming, in process


def test_pipeline_verifies_signed_input_and_accepts_unsigned_unless_required(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    link = _Capture()
    pipeline = Pipeline(ServiceConfig(), links=[link], signing=Signing(KEY))
    signed = _vehicle(monkeypatch, 1, KEY)
    unsigned = _vehicle(monkeypatch, 2, None)
    forged = _vehicle(monkeypatch, 3, OTHER_KEY)
    stale = _vehicle(monkeypatch, 4, KEY, timestamp=_ticks() - 120 * 100_000)  # 2 min old
    first_signed = _imu(signed, 0)
    for i in range(20):
        pipeline.on_bytes(link, first_signed if i == 0 else _imu(signed, i), "peer 1")
        pipeline.on_bytes(link, _imu(unsigned, i), "peer 2")
        pipeline.on_bytes(link, _imu(forged, i), "peer 3")
        pipeline.on_bytes(link, _imu(stale, i), "peer 4")
    # a signed packet heard again, even from another peer, is a replay
    pipeline.on_bytes(link, first_signed, "peer 5")
    damaged = bytearray(_imu(unsigned, 20))
    damaged[12] ^= 0xFF
    pipeline.on_bytes(link, bytes(damaged), "peer 2")

    assert {key.system for key in pipeline.streams} == {1, 2}
    verifier = pipeline.verifier
    assert verifier is not None
    assert verifier.verified == 20
    assert verifier.bad_signatures == 20 + 20 + 1  # forged, stale, replayed
    assert verifier.unsigned_dropped == 0
    assert pipeline.bad_packets == 1  # the damaged one only: refusals are not damage
    # every answer is signed with the key
    answers = _verified(link.packets, KEY)
    counts = Counter((m.get_type(), m.get_srcSystem()) for m in answers)
    assert counts[("ATTITUDE", 1)] > 0 and counts[("ATTITUDE", 2)] > 0

    strict = Pipeline(ServiceConfig(), links=[link], signing=Signing(KEY, require_signed=True))
    signed_again = _vehicle(monkeypatch, 6, KEY)
    for i in range(20):
        strict.on_bytes(link, _imu(signed_again, i), "peer 1")
        strict.on_bytes(link, _imu(unsigned, 30 + i), "peer 2")
        strict.on_bytes(link, Encoder(7, 1).heartbeat(), "peer 3")
    assert {key.system for key in strict.streams} == {6}
    assert strict.verifier is not None and strict.verifier.unsigned_dropped == 40
    assert strict.bad_packets == 0 and not strict.vehicles.get((7, 1))


def test_a_forged_future_timestamp_does_not_lock_the_vehicle_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """pymavlink records a stream's timestamp before comparing the signature; mavest undoes
    that for refused packets, so a forger cannot make the vehicle's packets look replayed."""
    link = _Capture()
    pipeline = Pipeline(ServiceConfig(), links=[link], signing=Signing(KEY))
    vehicle = _vehicle(monkeypatch, 1, KEY)  # link id 1, system 1, component 1
    forger = _vehicle(monkeypatch, 1, OTHER_KEY, timestamp=_ticks() + 3600 * 100_000)
    pipeline.on_bytes(link, _imu(vehicle, 0), "vehicle")
    pipeline.on_bytes(link, _imu(forger, 1), "forger")
    for i in range(1, 10):
        pipeline.on_bytes(link, _imu(vehicle, i), "vehicle")
    assert pipeline.verifier is not None
    assert pipeline.verifier.verified == 10 and pipeline.verifier.bad_signatures == 1
    (stream,) = pipeline.streams.values()
    assert stream.stats.received == 10


def test_replay_reads_signed_tlogs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A recorded flight with signed packets replays like an unsigned one (no key needed)."""
    path = tmp_path / "signed.tlog"
    with monkeypatch.context() as patch:
        patch.setattr(vehicle_module, "MAVLink", _signed_mavlink(KEY))
        write_flight_tlog(path, 4.0, 50.0, AUTOPILOTS["ardupilot"], seed=2)
    packets = [m.get_msgbuf() for m in _tlog_messages(path)]
    assert packets and all(p[2] & 0x01 for p in packets)  # really signed
    report = asyncio.run(replay(path, ServiceConfig()))
    (stream,) = report.streams
    assert stream.stats.estimated == stream.stats.received == 201
    assert report.bad_records == 0


# ------------------------------------------------------------------ live over loopback UDP


def _tlog_messages(path: Path) -> list[Any]:
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    out = []
    while (message := connection.recv_msg()) is not None:
        out.append(message)
    return out


def _send_raw(port: int, packets: list[bytes]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for packet in packets:
            sock.sendto(packet, ("127.0.0.1", port))


def test_live_signed_vehicle_with_require_signed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The simulated vehicle signs with a passphrase's key and refuses unsigned input;
    mavest, given the passphrase file, verifies, answers signed, asks for a rate (signed),
    and drops an intruder's unsigned and wrongly signed IMU."""
    phrase = "a passphrase the vehicle and mavest share"
    key_file = _write(tmp_path / "signing.key", phrase + "\n")
    vehicle_key = hashlib.sha256(phrase.encode()).digest()  # as MAVProxy derives it
    port = free_port(socket.SOCK_DGRAM)
    out = tmp_path / "live.tlog"
    service = ServiceProcess(
        f"udpin:127.0.0.1:{port}",
        "--signing-key",
        str(key_file),
        "--require-signed",
        "--request-rate",
        "200",
        "--out-tlog",
        str(out),
    )
    try:
        with monkeypatch.context() as patch:
            patch.setattr(vehicle_module, "MAVLink", _signed_mavlink(vehicle_key))
            report = asyncio.run(
                vehicle_module.stream_flight(f"udpout:127.0.0.1:{port}", 100.0, seed=3, seconds=5)
            )
        intruder, forger = _vehicle(monkeypatch, 7, None), _vehicle(monkeypatch, 8, OTHER_KEY)
        _send_raw(port, [_imu(intruder, i) for i in range(10)])
        _send_raw(port, [_imu(forger, i) for i in range(10)])
        time.sleep(0.5)
    finally:
        code, summary = service.stop()
    log = "".join(service.log)
    assert code == 0 and "Traceback" not in log, log
    assert "MAVLink signing: signing what it sends" in log and "unsigned input dropped" in log
    assert "key: passphrase from" in log and phrase not in log + summary
    # the vehicle accepts signed packets with its key only: answered means signed right
    assert report.sent > 400
    assert report.answered_fraction >= 0.98, report.describe()
    assert report.answerers == ["1/191"]
    assert report.rates[0] == 100.0 and report.rates[-1] == pytest.approx(200.0)  # obeyed
    # the intruders were dropped, logged once each, counted in the summary
    assert "from 7/1" not in summary and "from 8/1" not in summary
    assert "10 dropped (bad signature or replayed), 10 unsigned dropped" in summary, summary
    assert log.count("dropped unsigned RAW_IMU from 7/1") == 1
    assert log.count("dropped RAW_IMU from 8/1: bad signature") == 1
    # everything mavest sent is signed with the key, and it never heard the intruders
    messages = _tlog_messages(out)
    ours = [m.get_msgbuf() for m in messages if m.get_srcComponent() == OURS]
    assert {m.get_srcSystem() for m in messages} == {1}
    assert len(_verified(ours, vehicle_key)) == len(ours) > report.sent
    assert {_signature_fields(p)[0] for p in ours} == {0}
    _assert_only_the_interval_command(messages)


def test_live_require_signed_drops_an_unsigned_vehicle(tmp_path: Path) -> None:
    key_file = _write(tmp_path / "signing.key", KEY)
    port = free_port(socket.SOCK_DGRAM)
    service = ServiceProcess(
        f"udpin:127.0.0.1:{port}", "--signing-key", str(key_file), "--require-signed"
    )
    try:
        report = asyncio.run(
            vehicle_module.stream_flight(f"udpout:127.0.0.1:{port}", 50.0, seed=1, seconds=2.5)
        )
    finally:
        code, summary = service.stop()
    assert code == EXIT_NO_IMU  # every IMU packet was dropped: no stream
    assert report.sent > 100 and report.answered == 0 and report.unmatched == 0
    assert "no IMU stream found" in summary and "sent" not in summary.split("signing:")[1]
    dropped = int(summary.split("unsigned dropped")[0].rsplit(",", 1)[1])
    assert dropped >= 2 * report.sent  # RAW_IMU and SIMSTATE each, and the rest
    assert "".join(service.log).count("dropped unsigned") == 1


# ------------------------------------------------------------------ commands mavest sends


def _assert_only_the_interval_command(messages: list[Any]) -> None:
    """mavest's own messages: estimates, HEARTBEAT and the message-interval request only."""
    ours = [m for m in messages if m.get_srcComponent() == OURS]
    types = Counter(m.get_type() for m in ours)
    assert set(types) <= {"ATTITUDE", "ATTITUDE_QUATERNION", "HEARTBEAT", "COMMAND_LONG"}, types
    commands = [m for m in ours if m.get_type() == "COMMAND_LONG"]
    assert commands, "the run was meant to send the message-interval request"
    assert {m.command for m in commands} == {mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert {round(m.param1) for m in commands} == {mavlink2.MAVLINK_MSG_ID_RAW_IMU}


def test_the_service_encodes_no_command_but_the_interval_request() -> None:
    """Every MAVLink message the service's code can build (the simulated vehicle aside):
    ``*_encode``/``*_send`` calls and message classes built directly. Besides the
    estimates, HEARTBEAT and the interval request: answers to requests addressed to
    mavest (COMMAND_ACK, an FTP NAK, PARAM_ERROR), which command nothing."""
    package = Path(mavest.__file__).parent
    built: Counter[str] = Counter()
    command_arguments = []
    for path in package.rglob("*.py"):
        if "sim" in path.relative_to(package).parts:
            continue  # the simulated vehicle: a flight controller, not mavest
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            name = node.func.attr if isinstance(node.func, ast.Attribute) else ""
            name = name or (node.func.id if isinstance(node.func, ast.Name) else "")
            is_builder = name.startswith("MAVLink_") and name.endswith("_message")
            if (name.endswith(("_encode", "_send")) and name[0] != "_") or is_builder:
                built[name] += 1
                if name == "command_long_encode":
                    command_arguments.append(ast.unparse(node.args[2]))
    assert set(built) == {
        "attitude_encode",
        "attitude_quaternion_encode",
        "heartbeat_encode",
        "command_long_encode",
        "command_ack_encode",
        "file_transfer_protocol_encode",
        "param_error_encode",
    }, built
    assert command_arguments == ["mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL"]
