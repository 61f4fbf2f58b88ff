"""Hostile peers on the live links: noise from many addresses, false packet starts on a
byte stream, well-framed packets of ids no dialect here defines. The vehicle's good
packets keep being estimated and answered, the damage is counted, and nothing of it
becomes a peer, a message or a record in the output tlog."""

from __future__ import annotations

import asyncio
import logging
import random
import socket
import struct
import time
import tracemalloc
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.generator.mavcrc import x25crc

import mavest.mavlink.links as links
import mavest.service.pipeline as pipeline_module
from mavest.mavlink.links import TcpServerLink, UdpLink, parse_endpoint
from mavest.mavlink.messages import MAVLink
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Pipeline
from mavest.service.process import free_port
from mavest.service.runners import Outputs, RunReport, run_live

NOISE = b"\xfd\x00junk"  # a MAVLink 2 start byte and a few bytes: no packet


class _Vehicle:
    """HIGHRES_IMU packets (fresh, level, 200 Hz on the vehicle's clock) from 1/1."""

    def __init__(self) -> None:
        self.mav = MAVLink(None, srcSystem=1, srcComponent=1)
        self.t_us = 0

    def imu(self) -> bytes:
        self.t_us += 5000
        message = self.mav.highres_imu_encode(
            *(self.t_us, 0.0, 0.0, -9.80665, 0.001, -0.002, 0.0005, 0.2, 0.0, 0.4),
            *(1013.0, 0.0, 0.0, 25.0, 0x1FFF, 0),
        )
        return bytes(message.pack(self.mav))

    def heartbeat(self) -> bytes:
        return bytes(self.mav.heartbeat_encode(2, 3, 0, 0, 0).pack(self.mav))


def _unknown_id_packet(sequence: int) -> bytes:
    """A MAVLink 2 packet, CRC valid over its bytes, of an id the dialect does not
    define: without the id's CRC extra byte nothing can tell it from noise."""
    header = bytes([0xFD, 10, 0, 0, sequence & 0xFF, 1, 1]) + struct.pack("<I", 40000)[:3]
    body = header + bytes(10)
    return body + struct.pack("<H", x25crc(body[1:]).crc)


def _false_starts(vehicle: _Vehicle, packets: int, seed: int) -> tuple[bytes, int]:
    """``packets`` IMU packets, every tenth after a MAVLink 1 start byte and 29 bytes of
    noise (none of them a start byte): a noisy serial line's; and how many false starts."""
    noise = random.Random(seed)
    data = bytearray()
    false_starts = 0
    for i in range(packets):
        if i % 10 == 5:
            data += b"\xfe" + bytes(noise.randrange(0, 0xFC) for _ in range(29))
            false_starts += 1
        data += vehicle.imu()
    return bytes(data), false_starts


def _replies(data: bytes) -> list[Any]:
    parser = MAVLink(None)
    parser.robust_parsing = True
    return [m for m in parser.parse_buffer(data) or () if m.get_type() != "BAD_DATA"]


async def _until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.01)


async def _serve(
    connection: str, scenario: Callable[[], Awaitable[None]], outputs: Outputs | None = None
) -> RunReport:
    """Run the live service on ``connection`` while ``scenario`` plays; its report."""
    stop, ready = asyncio.Event(), asyncio.Event()
    service = asyncio.create_task(
        run_live(
            connection, ServiceConfig(), outputs=outputs, stop=stop, ready=ready, status_period=0
        )
    )
    await asyncio.wait_for(ready.wait(), 120)
    await scenario()
    stop.set()
    return await service


def _udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    return sock


def _received(sock: socket.socket) -> bytes:
    data = b""
    while True:
        try:
            data += sock.recv(65536)
        except BlockingIOError:
            return data


# ------------------------------------------------------------------ noise from many addresses


def test_a_udp_sender_of_noise_is_no_peer() -> None:
    port = free_port(socket.SOCK_DGRAM)

    async def scenario() -> tuple[bytes, bytes]:
        link = UdpLink(parse_endpoint(f"udpin:127.0.0.1:{port}"))
        heard: list[Any] = []
        await link.start(lambda _link, data, peer: heard.append(peer))
        noisy, vehicle = _udp_socket(), _udp_socket()
        noisy.sendto(NOISE, ("127.0.0.1", port))
        vehicle.sendto(_Vehicle().heartbeat(), ("127.0.0.1", port))
        await _until(lambda: len(heard) == 2, 5, "both datagrams")
        link.send(b"an answer")
        await asyncio.sleep(0.2)
        link.close()
        return _received(noisy), _received(vehicle)

    to_noisy, to_vehicle = asyncio.run(scenario())
    assert to_vehicle == b"an answer"
    assert to_noisy == b"", "a sender of noise was sent the answer"


def test_the_silent_peers_remembered_are_the_latest_few(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(links, "UDP_PEER_TIMEOUT", 0.05)
    monkeypatch.setattr(links, "SILENT_PEERS_KEPT", 1)
    port = free_port(socket.SOCK_DGRAM)
    first, second = _udp_socket(), _udp_socket()
    names = [f"127.0.0.1:{s.getsockname()[1]}" for s in (first, second)]

    async def scenario() -> None:
        link = UdpLink(parse_endpoint(f"udpin:127.0.0.1:{port}"))
        heard: list[Any] = []
        await link.start(lambda _link, data, peer: heard.append(peer))
        for sock in (first, second):
            sock.sendto(_Vehicle().heartbeat(), ("127.0.0.1", port))
        await _until(lambda: len(heard) == 2, 5, "both peers")
        await asyncio.sleep(0.1)
        link.send(b"x")  # both silent: the first is forgotten, the second remembered
        for sock in (first, second):
            sock.sendto(_Vehicle().heartbeat(), ("127.0.0.1", port))
        await _until(lambda: len(heard) == 4, 5, "both peers again")
        link.close()

    with caplog.at_level(logging.INFO, logger="mavest"):
        asyncio.run(scenario())
    text = caplog.text
    assert text.count(f"hearing from {names[0]}") == 2, text
    assert f"{names[1]} is back after" in text, text


def test_noise_from_many_addresses_leaves_nothing_behind() -> None:
    pipeline = Pipeline(ServiceConfig())
    link = UdpLink(parse_endpoint("udpin:127.0.0.1:14550"))  # never opened: fed directly
    pipeline.on_bytes(link, NOISE, ("127.0.0.1", 1))  # what is made once is not counted
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for port in range(2, 3002):
            pipeline.on_bytes(link, NOISE, ("127.0.0.1", port))
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert pipeline.bad_packets == 3001
    assert pipeline.skipped_bytes == 3001 * len(NOISE)
    assert grown < 100_000, f"{grown} bytes kept for 3000 senders of noise"


def test_the_live_service_answers_its_vehicle_on_time_after_noise_from_many_ports() -> None:
    port = free_port(socket.SOCK_DGRAM)
    samples = 300  # 1.5 s at 200 Hz
    listening: list[socket.socket] = []  # some of the noisy senders, to see what they get
    heard = bytearray()

    async def scenario() -> None:
        for i in range(500):  # each from a port of its own
            sock = _udp_socket()
            sock.sendto(NOISE, ("127.0.0.1", port))
            if i % 25 == 0:
                listening.append(sock)
            else:
                sock.close()
        vehicle, source = _Vehicle(), _udp_socket()
        start = time.perf_counter()
        for i in range(samples):
            source.sendto(vehicle.imu(), ("127.0.0.1", port))
            heard.extend(_received(source))
            await asyncio.sleep(max(0.0, start + (i + 1) / 200 - time.perf_counter()))
        await asyncio.sleep(0.3)  # the last answers
        heard.extend(_received(source))

    report = asyncio.run(_serve(f"udpin:127.0.0.1:{port}", scenario))
    (stream,) = report.pipeline.streams.values()
    assert stream.stats.estimated == samples
    answered = {m.time_boot_ms for m in _replies(bytes(heard)) if m.get_type() == "ATTITUDE"}
    assert len(answered) >= samples - 2, f"{len(answered)} of {samples} answered"
    assert report.pipeline.bad_packets == 500
    assert report.skipped_bytes == 500 * len(NOISE)  # what the summary says
    for sock in listening:
        assert _received(sock) == b"", "a sender of noise was answered"
        sock.close()


# ------------------------------------------------------------------ byte streams


def test_a_false_start_on_tcp_costs_only_its_noise() -> None:
    port = free_port()
    data, false_starts = _false_starts(_Vehicle(), 300, seed=5)

    async def scenario() -> None:
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        for offset in range(0, len(data), 400):  # ~5 packets at a time, as a radio's bursts
            writer.write(data[offset : offset + 400])
            await writer.drain()
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.3)
        writer.close()

    report = asyncio.run(_serve(f"tcpin:127.0.0.1:{port}", scenario))
    pipeline = report.pipeline
    (stream,) = pipeline.streams.values()
    assert stream.stats.estimated == 300
    assert pipeline.messages_in == 300, "noise was taken for messages"
    assert pipeline.bad_packets == false_starts == 30
    assert report.skipped_bytes == 30 * false_starts


def test_packets_cut_anywhere_on_a_byte_stream_are_all_found() -> None:
    data, false_starts = _false_starts(_Vehicle(), 200, seed=7)
    pipeline = Pipeline(ServiceConfig())
    link = TcpServerLink(parse_endpoint("tcpin:127.0.0.1:5760"))  # never opened: fed directly
    cuts = random.Random(3)
    offset = 0
    while offset < len(data):
        size = cuts.randrange(1, 120)
        pipeline.on_bytes(link, data[offset : offset + size], "a serial line")
        offset += size
    assert pipeline.messages_in == 200
    assert pipeline.bad_packets == false_starts
    assert pipeline.skipped_bytes == 30 * false_starts


def test_the_cut_off_packets_kept_are_the_latest_peers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pipeline_module, "PARTIAL_PEERS", 2)
    pipeline = Pipeline(ServiceConfig())
    link = TcpServerLink(parse_endpoint("tcpin:127.0.0.1:5760"))
    packet = _Vehicle().imu()
    for peer in ("first", "second", "third"):
        pipeline.on_bytes(link, packet[:20], peer)
    assert pipeline.bad_packets == 1  # the first's start, dropped for the third's
    assert pipeline.skipped_bytes == 20
    for peer in ("third", "second", "first"):
        pipeline.on_bytes(link, packet[20:], peer)
    assert pipeline.messages_in == 2
    assert pipeline.bad_packets == 2  # and the first's end, alone


# ------------------------------------------------------------------ ids without a CRC extra


def test_packets_of_unknown_ids_are_damage_and_never_recorded(tmp_path: Path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    tlog = tmp_path / "live.tlog"
    noise = random.Random(1)

    async def scenario() -> None:
        vehicle, source = _Vehicle(), _udp_socket()
        for i in range(100):
            source.sendto(vehicle.imu(), ("127.0.0.1", port))
            source.sendto(_unknown_id_packet(i), ("127.0.0.1", port))
            # noise (no start byte in it) after the header of a packet with another id
            start = bytes([0xFD, 10, 0, 0, i, 1, 1, 0x40, 0x9C, 0x00])
            source.sendto(
                start + bytes(noise.randrange(0xFC) for _ in range(12)), ("127.0.0.1", port)
            )
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.3)

    report = asyncio.run(_serve(f"udpin:127.0.0.1:{port}", scenario, Outputs(tlog=tlog)))
    pipeline = report.pipeline
    assert pipeline.messages_in == 100
    assert pipeline.bad_packets == 200
    recorded = mavutil.mavlink_connection(str(tlog))
    kinds = set()
    while (message := recorded.recv_msg()) is not None:
        kinds.add(message.get_type())
    assert kinds <= {"HIGHRES_IMU", "ATTITUDE", "ATTITUDE_QUATERNION", "HEARTBEAT"}, kinds
