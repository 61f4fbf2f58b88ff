"""The live path's packet decoding and packing against pymavlink's own, message for message."""

from __future__ import annotations

import math
import random
import struct
from typing import Any

import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink1

from mavest.mavlink import wire
from mavest.mavlink.messages import Encoder, MAVLink, mavlink2
from mavest.mavlink.signing import enable_outgoing

# struct codes of the dialect's scalar field types, and how to draw a value of each
_DRAW = {
    "b": lambda r: r.randint(-128, 127),
    "B": lambda r: r.randint(0, 255),
    "h": lambda r: r.randint(-(1 << 15), (1 << 15) - 1),
    "H": lambda r: r.randint(0, (1 << 16) - 1),
    "i": lambda r: r.randint(-(1 << 31), (1 << 31) - 1),
    "I": lambda r: r.randint(0, (1 << 32) - 1),
    "q": lambda r: r.randint(-(1 << 63), (1 << 63) - 1),
    "Q": lambda r: r.randint(0, (1 << 64) - 1),
    "f": lambda r: struct.unpack("<f", struct.pack("<f", r.uniform(-1e6, 1e6)))[0],
    "d": lambda r: r.uniform(-1e12, 1e12),
}


def _random_message(message_class: type[Any], rng: random.Random) -> Any:
    """An instance with random field values; about a third of them zero, so that some
    payloads end in zeros (which MAVLink 2 cuts off)."""
    codes = message_class.unpacker.format.lstrip("<")
    wire_values = [0 if rng.random() < 0.3 else _DRAW[code](rng) for code in codes]
    # the constructor takes the fields in definition order; orders[i] is field i's wire slot
    return message_class(*[wire_values[slot] for slot in message_class.orders])


def _pymavlink_packet(message: Any, seq: int, mavlink1: bool = False) -> bytes:
    mav = MAVLink(None, srcSystem=random.randint(1, 255), srcComponent=random.randint(0, 255))
    mav.seq = seq
    return message.pack(mav, force_mavlink1=mavlink1)


def _pymavlink_messages(data: bytes) -> list[Any]:
    parser = MAVLink(None)
    parser.robust_parsing = True
    return parser.parse_buffer(data) or []


def _assert_same_message(ours: Any, theirs: Any) -> None:
    assert ours.get_type() == theirs.get_type()
    assert ours.get_msgbuf() == theirs.get_msgbuf()
    assert ours._payload == theirs._payload and ours._crc == theirs._crc
    assert ours._signed == theirs._signed
    assert vars(ours._header) == vars(theirs._header)
    for name in theirs.get_fieldnames():
        a, b = getattr(ours, name), getattr(theirs, name)
        assert type(a) is type(b) and (a == b or (math.isnan(a) and math.isnan(b))), name


def test_only_single_number_messages_are_taken() -> None:
    taken = {layout.message_class.msgname for layout in wire._LAYOUTS.values()}
    for name in (
        "RAW_IMU",
        "SCALED_IMU",
        "SCALED_IMU2",
        "SCALED_IMU3",
        "HIGHRES_IMU",
        "SIMSTATE",
        "ATTITUDE",
        "GLOBAL_POSITION_INT",
        "GPS_RAW_INT",
        "VFR_HUD",
        "HEARTBEAT",
    ):
        assert name in taken
    # arrays (ATTITUDE_QUATERNION's repr_offset_q) and text (PARAM_VALUE's param_id)
    assert "ATTITUDE_QUATERNION" not in taken and "PARAM_VALUE" not in taken


@pytest.mark.parametrize("mavlink1", [False, True])
def test_every_taken_message_decodes_as_pymavlink_decodes_it(mavlink1: bool) -> None:
    rng = random.Random(11 + mavlink1)
    checked = 0
    for message_id, layout in sorted(wire._LAYOUTS.items()):
        if mavlink1 and message_id > 255:
            continue  # MAVLink 1 has one byte of message id
        for _ in range(5):
            packet = _pymavlink_packet(
                _random_message(layout.message_class, rng), rng.randrange(256), mavlink1
            )
            ours = wire.decode_datagram(packet)
            theirs = _pymavlink_messages(packet)
            assert ours is not None and len(ours) == len(theirs) == 1, layout.message_class
            _assert_same_message(ours[0], theirs[0])
            checked += 1
    assert checked > (100 if mavlink1 else 200)


def test_a_datagram_of_several_packets_gives_them_all_in_order() -> None:
    rng = random.Random(5)
    layouts = list(wire._LAYOUTS.values())
    packets = []
    for i in range(40):
        message_class = rng.choice(layouts).message_class
        mavlink1 = i % 3 == 0 and message_class.id <= 255  # MAVLink 1 and 2 mixed
        packets.append(_pymavlink_packet(_random_message(message_class, rng), i, mavlink1))
    data = b"".join(packets)
    ours = wire.decode_datagram(data)
    theirs = _pymavlink_messages(data)
    assert ours is not None and len(ours) == len(theirs) == len(packets)
    for a, b in zip(ours, theirs, strict=True):
        _assert_same_message(a, b)


def _imu_packet() -> bytes:
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    return mav.raw_imu_encode(123456, 10, -20, -1000, 1, 2, 3, 200, 10, 400, 0, 30).pack(mav)


def test_anything_else_is_left_to_pymavlink() -> None:
    imu = _imu_packet()
    assert wire.decode_datagram(imu) is not None
    bad_crc = bytearray(imu)
    bad_crc[-1] ^= 0x55
    corrupted = bytearray(imu)
    corrupted[14] ^= 0x01  # a payload bit: the CRC no longer matches
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    param = mav.param_value_encode(b"COMPASS_DEC", 0.1, 9, 100, 3).pack(mav)
    quaternion = mav.attitude_quaternion_encode(1, 1.0, 0.0, 0.0, 0.0, 0, 0, 0).pack(mav)
    signer = MAVLink(None, srcSystem=1, srcComponent=1)
    enable_outgoing(signer, bytes(range(32)))
    signed = signer.raw_imu_encode(1, 1, 2, 3, 4, 5, 6, 7, 8, 9, 0, 0).pack(signer)
    unknown = bytes((0xFD, 1, 0, 0, 0, 1, 1, 0x39, 0x30, 0x00, 7, 0, 0))  # id 12345
    for data in (
        bytes(bad_crc),
        bytes(corrupted),
        imu[:-1],  # cut short
        imu + b"\x00",  # a stray byte after the packet
        b"\x55" + imu,  # a stray byte before it
        imu + imu[:5],  # a second packet cut inside its header
        param,
        quaternion,
        signed,
        unknown,
        imu + param,  # one packet it takes, one it does not: the whole datagram goes
    ):
        assert wire.decode_datagram(data) is None, data
    assert wire.decode_datagram(b"") == []


def test_encoder_packets_are_pymavlinks_byte_for_byte() -> None:
    rng = random.Random(3)
    ours = Encoder(42, 191)
    assert ours.take_sequence(250) == 0  # on to 250: the sequence number wraps
    theirs = MAVLink(None, srcSystem=42, srcComponent=191)
    theirs.seq = 250
    for i in range(600):
        stamp = rng.randrange(1 << 32)
        euler = [0.0 if rng.random() < 0.2 else rng.uniform(-3.2, 3.2) for _ in range(3)]
        q = [0.0 if rng.random() < 0.2 else rng.uniform(-1.0, 1.0) for _ in range(4)]
        rates = tuple(0.0 if rng.random() < 0.3 else rng.gauss(0.0, 1.0) for _ in range(3))
        if i % 100 == 1:  # an all-zero payload keeps one byte
            stamp, euler, rates = 0, [0.0, 0.0, 0.0], (0.0, 0.0, 0.0)
        if i % 2:
            packet = ours.attitude(stamp, euler, rates)  # type: ignore[arg-type]
            expected = theirs.attitude_encode(stamp, *euler, *rates).pack(theirs)
        else:
            packet = ours.attitude_quaternion(stamp, q, rates)  # type: ignore[arg-type]
            expected = theirs.attitude_quaternion_encode(stamp, *q, *rates).pack(theirs)
        theirs.seq = (theirs.seq + 1) % 256
        assert packet == expected
    assert mavlink2.MAVLINK_MSG_ID_ATTITUDE in wire._LAYOUTS  # ours decode as ATTITUDE again
    assert wire.decode_datagram(ours.attitude(1, (0.1, 0.2, 0.3), (0.0, 0.0, 0.0))) is not None


def test_mavlink1_packets_are_the_mavlink1_dialects_byte_for_byte() -> None:
    """MAVLink 1 is what a MAVLink 1 sender packs: the base fields whole, no extensions
    (pymavlink's MAVLink 2 dialect keeps them when forced to MAVLink 1), CRC the same."""
    rng = random.Random(5)
    checked = 0
    for message_id, message_class in mavlink1.mavlink_map.items():
        if not set(message_class.unpacker.format.lstrip("<")) <= set(_DRAW):
            continue  # arrays and text: the same bytes, but no random values drawn here
        checked += 1
        theirs = _random_message(message_class, rng)
        mav = mavlink1.MAVLink(None, srcSystem=42, srcComponent=191)
        mav.seq = message_id % 256
        expected = theirs.pack(mav)
        payload = expected[mavlink2.HEADER_LEN_V1 : -2]
        extensions = mavlink2.mavlink_map[message_id].unpacker.size - len(payload)
        packet = wire.pack(
            message_id,
            message_class.crc_extra,
            payload + bytes(extensions),
            message_id % 256,
            42,
            191,
            mavlink1=True,
        )
        assert packet == expected, message_class.msgname
    assert checked > 100


def test_encoder_speaks_mavlink1_as_the_mavlink1_dialect() -> None:
    ours = Encoder(42, 191)
    theirs = mavlink1.MAVLink(None, srcSystem=42, srcComponent=191)
    rates = (0.25, -0.5, 0.0)
    expected = [
        theirs.attitude_encode(7, 0.1, 0.2, 0.3, *rates),
        theirs.attitude_quaternion_encode(7, 1.0, 0.0, 0.0, 0.0, *rates),
        theirs.heartbeat_encode(18, 8, 0, 0, 4, 3),
        theirs.command_long_encode(1, 1, 511, 0, 27.0, 5000.0, 0, 0, 0, 0, 0),
        theirs.command_ack_encode(512, 3),
    ]
    packets = [
        ours.attitude(7, (0.1, 0.2, 0.3), rates, mavlink1=True),
        ours.attitude_quaternion(7, (1.0, 0.0, 0.0, 0.0), rates, mavlink1=True),
        ours.heartbeat(mavlink1=True),
        ours.set_message_interval(1, 1, "RAW_IMU", 200.0, mavlink1=True),
        ours.command_ack(512, 3, 255, 190, mavlink1=True),
    ]
    for packet, message in zip(packets, expected, strict=True):
        assert packet == message.pack(theirs)
        theirs.seq = (theirs.seq + 1) % 256
