"""mavest's one MAVLink scanner, CRC and packer (mavest.mavlink.framing) against
pymavlink on the same bytes: tlog records as its TlogReader finds them, bare packets
as its parser finds them in a datagram, the CRC as its x25crc, packets as it packs."""

from __future__ import annotations

import random

import numpy as np
import pytest
from pymavlink.mavutil import x25crc
from test_hostile_input import Flight, _tlog_bytes, clean_flights
from test_wire import _DRAW, _random_message

from mavest.mavlink import framing
from mavest.mavlink.messages import MAVLink, mavlink2
from mavest.mavlink.tlog import TlogReader


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Flight]:
    return clean_flights(tmp_path_factory)


def test_scan_finds_the_records_the_reader_finds(flights: dict[str, Flight]) -> None:
    data = _tlog_bytes(flights["ardupilot"].chunks())
    careful = [(r.timestamp_us, r.packet) for r in TlogReader(data)]
    index = framing.scan(np.frombuffer(data, dtype=np.uint8), 0, -1, 1 << 20)
    scanned = [
        (int(stamp), data[int(start) + 8 : int(end)])
        for start, end, stamp in zip(index.start, index.end, index.stamp, strict=True)
    ]
    assert scanned == careful
    headers = [MAVLink(None).decode(bytearray(packet)).get_header() for _, packet in careful]
    assert index.system.tolist() == [h.srcSystem for h in headers]
    assert index.component.tolist() == [h.srcComponent for h in headers]
    assert index.message_id.tolist() == [h.msgId for h in headers]


def test_the_crc_eight_bytes_at_a_time_is_pymavlinks() -> None:
    """Every length around the eight-byte steps, from any offset and register."""
    rng = np.random.default_rng(3)
    for length in [*range(40), 255, 280, 1001]:
        data = rng.integers(0, 256, size=length + 11, dtype=np.uint8)
        offset = int(rng.integers(0, 11))
        chunk = bytes(data[offset : offset + length])
        assert framing.crc_register(data, offset, offset + length, 0xFFFF) == x25crc(chunk).crc
        # from a register part way through: the same as accumulating the rest
        head, tail = chunk[: length // 3], chunk[length // 3 :]
        expected = x25crc(head)
        register = expected.crc
        expected.accumulate(tail)
        start = offset + len(head)
        assert framing.crc_register(data, start, offset + length, register) == expected.crc


def test_scan_stops_at_the_first_record_that_is_not_clean(flights: dict[str, Flight]) -> None:
    records = flights["ardupilot"].records
    damaged = bytearray(_tlog_bytes(records[:100]))
    where = len(damaged)
    stamp, packet = records[100]
    broken = bytearray(packet)
    broken[-3] ^= 0x55  # a payload byte: the CRC no longer matches
    damaged += stamp.to_bytes(8, "big") + bytes(broken) + _tlog_bytes(records[101:200])
    array = np.frombuffer(bytes(damaged), dtype=np.uint8)
    index = framing.scan(array, 0, -1, 1 << 20)
    assert len(index) == 100 and int(index.end[-1]) == where
    # from the next record on it is clean again
    after = where + 8 + len(packet)
    assert len(framing.scan(array, after, stamp, 1 << 20)) == 99
    # nor is a timestamp days away a record, nor a cut packet
    assert len(framing.scan(array, 0, stamp + 4 * 24 * 3600 * 10**6, 10)) == 0
    assert len(framing.scan(array[: where - 3], 0, -1, 1 << 20)) == 99


def test_bare_packets_are_found_as_pymavlinks_parser_finds_them(
    flights: dict[str, Flight],
) -> None:
    """The datagram form: the same packets, positions and ids, and where it stops."""
    packets = [packet for _, packet in flights["ardupilot"].records[:300]]
    data = b"".join(packets)
    index, end = framing.scan_packets(np.frombuffer(data, dtype=np.uint8))
    assert end == len(data)
    parser = MAVLink(None)
    theirs = parser.parse_buffer(data) or []
    assert index.shape[1] == len(theirs) == len(packets)
    starts = np.cumsum([0, *map(len, packets)])
    assert index[0].tolist() == starts[:-1].tolist()
    assert index[1].tolist() == starts[1:].tolist()
    assert index[4].tolist() == [m.get_msgId() for m in theirs]
    assert not index[7].any()  # bare packets carry no time
    # a damaged byte: everything before it, and where it stopped
    damaged = bytearray(data)
    damaged[int(starts[120]) + 4] ^= 0x10
    index, end = framing.scan_packets(np.frombuffer(bytes(damaged), dtype=np.uint8))
    assert index.shape[1] == 120 and end == starts[120]
    assert framing.scan_packets(np.zeros(0, dtype=np.uint8))[1] == 0


def test_packed_rows_are_pymavlinks_packets() -> None:
    """Several messages of a type at once, each with its own sequence number, as
    pymavlink packs each; a message MAVLink 1 cannot carry is refused in MAVLink 1."""
    rng = random.Random(5)
    checked = 0
    for message_id, message_class in sorted(mavlink2.mavlink_map.items()):
        if not set(message_class.unpacker.format.lstrip("<")) <= set(_DRAW):
            continue  # arrays and text: no random values drawn for them
        system, component = rng.randrange(1, 256), rng.randrange(256)
        seqs = np.array([rng.randrange(1000) for _ in range(3)])
        expected, payloads = [], []
        for seq in seqs:
            mav = MAVLink(None, srcSystem=system, srcComponent=component)
            mav.seq = int(seq) & 0xFF
            packet = _random_message(message_class, rng).pack(mav)
            expected.append(packet)
            payload = packet[mavlink2.HEADER_LEN_V2 : -2]
            payloads.append(payload + bytes(message_class.unpacker.size - len(payload)))
        rows = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(3, -1)
        packed = framing.pack_rows(
            rows, message_id, message_class.crc_extra, np.zeros(3, bool), system, component, seqs
        )
        assert [bytes(packed.data[i, : packed.length[i]]) for i in range(3)] == expected
        if message_id not in framing.mavlink1_lengths():
            with pytest.raises(KeyError):
                framing.pack_rows(rows, message_id, 0, np.ones(3, bool), 1, 1, seqs)
        checked += 1
    assert checked > 150


def test_rows_in_both_versions_at_once_are_each_versions_packets() -> None:
    """A mask of MAVLink 1 rows among MAVLink 2 ones (a replay of a vehicle that changed
    version): each row as that version's dialect packs it."""
    from pymavlink.dialects.v10 import ardupilotmega as mavlink1

    rates = (0.25, -0.5, 0.0)
    angles = [(0.1 * k, -0.2 * k, 0.3 * k) for k in range(4)]
    mask = np.array([True, False, True, False])
    seqs = np.arange(250, 254)
    payloads = []
    expected = []
    for k, (euler, one) in enumerate(zip(angles, mask, strict=True)):
        dialect = mavlink1 if one else mavlink2
        mav = dialect.MAVLink(None, srcSystem=7, srcComponent=191)
        mav.seq = int(seqs[k]) & 0xFF
        message = dialect.MAVLink_attitude_message(1000 + k, *euler, *rates)
        expected.append(message.pack(mav))
        payloads.append(mavlink2.MAVLink_attitude_message.unpacker.pack(1000 + k, *euler, *rates))
    rows = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(4, -1)
    attitude = mavlink2.MAVLink_attitude_message
    packed = framing.pack_rows(rows, attitude.id, attitude.crc_extra, mask, 7, 191, seqs)
    assert [bytes(packed.data[i, : packed.length[i]]) for i in range(4)] == expected


def test_the_packer_refuses_what_it_would_garble() -> None:
    """Ids that do not fit a byte, and MAVLink 1 payloads shorter than the message's
    (which it would read past): an error, not a wrong packet."""
    attitude = mavlink2.MAVLink_attitude_message
    payload = bytes(attitude.unpacker.size)
    with pytest.raises(ValueError, match="0–255"):
        framing.pack_one(payload, attitude.id, attitude.crc_extra, 0, 256, 1)
    with pytest.raises(ValueError, match="0–255"):
        framing.pack_rows(
            np.zeros((1, 28), np.uint8), attitude.id, 0, np.zeros(1, bool), 1, -1, np.zeros(1)
        )
    with pytest.raises(ValueError, match="wanted"):
        framing.pack_one(payload[:10], attitude.id, attitude.crc_extra, 0, 1, 1, mavlink1=True)
