"""Many tlog records at once: the replay's compiled fast path through MAVLink bytes.

A replay spends its time per message, not per byte: pymavlink builds a Python
object for every packet it decodes and packs, at tens of µs each. Here the
same work is done on whole runs of records, on the index that
:func:`mavest.mavlink.framing.scan` makes of a clean stretch of a tlog:

* :func:`decode_payloads` turns the payloads of one message type into a NumPy
  record array laid out as the message's wire format (MAVLink 2's trailing
  zeros restored, as pymavlink does), from which IMU samples and reference
  attitudes are read in bulk (:func:`imu_fields`, :func:`simstate_euler`).
* :func:`attitude_packets` packs ATTITUDE and ATTITUDE_QUATERNION as the
  encoder does (:func:`mavest.mavlink.framing.pack_rows`, the packer the encoder
  uses too, with the encoder's sequence numbers; MAVLink 1 for samples that came
  so), and :func:`interleave` lays the input records and the answers out as the
  output tlog's records.
* :func:`packets` packs any message of wire-format records, each with its own
  sequence number (an onboard log's samples made MAVLink, :mod:`mavest.onboard.convert`).

``tests/test_bulk.py`` checks each against pymavlink on the same bytes
(``tests/test_onboard_replay.py`` :func:`packets`, through the conversion).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from mavest import so3
from mavest._jit import inplace_exact_kernel
from mavest.mavlink.framing import NO_PACKETS, Packets, RecordIndex, pack_rows
from mavest.mavlink.messages import (
    HIGHRES_INERTIAL_BITS,
    HIGHRES_MAG_BITS,
    IMU_FORMATS,
    SCALED_IMU_INSTANCE,
    all_fresh,
    at_limit,
    mavlink2,
)

# struct format characters → NumPy (little-endian, as MAVLink's wire)
_STRUCT_TO_NUMPY = {
    "Q": "<u8",
    "q": "<i8",
    "I": "<u4",
    "i": "<i4",
    "H": "<u2",
    "h": "<i2",
    "B": "u1",
    "b": "i1",
    "f": "<f4",
    "d": "<f8",
    "c": "S1",
}


def wire_dtype(message_class: Any) -> np.dtype:
    """The NumPy record type of a message's payload on the wire (fields in wire order).

    Built from the message class's own ``struct`` format, so it is pymavlink's
    layout by construction; arrays (``4f``) become sub-arrays, strings bytes.
    """
    fmt: str = message_class.unpacker.format
    names: list[str] = message_class.ordered_fieldnames
    fields: list[tuple[Any, ...]] = []
    count = ""
    for char in fmt.lstrip("<"):
        if char.isdigit():
            count += char
            continue
        n = int(count) if count else 1
        count = ""
        name = names[len(fields)]
        if char == "s":
            fields.append((name, f"S{n}"))
        elif n > 1:
            fields.append((name, _STRUCT_TO_NUMPY[char], (n,)))
        else:
            fields.append((name, _STRUCT_TO_NUMPY[char]))
    dtype = np.dtype(fields)
    assert dtype.itemsize == message_class.unpacker.size
    return dtype


@inplace_exact_kernel
def _gather(data: np.ndarray, payload: np.ndarray, length: np.ndarray, out: np.ndarray) -> None:
    # (unsigned indices, as _interleave's copies)
    width = np.uint64(out.shape[1])
    for i in range(payload.shape[0]):
        row = out[i]
        used = min(np.uint64(length[i]), width)
        start = np.uint64(payload[i])
        for k in range(used):
            row[k] = data[start + k]
        for k in range(used, width):
            row[k] = 0


def decode_payloads(data: np.ndarray, records: RecordIndex, dtype: np.dtype) -> np.ndarray:
    """The payloads of these records (all one message type) as records of ``dtype``.

    As pymavlink: a payload shorter than the format (MAVLink 2 cuts trailing
    zeros; MAVLink 1 senders omit extensions) is padded with zeros, a longer
    one cut.
    """
    raw = np.empty((len(records), dtype.itemsize), dtype=np.uint8)
    _gather(data, records.payload, records.payload_length, raw)
    return raw.view(dtype)[:, 0]


class ImuFields(NamedTuple):
    """IMU messages of one type decoded in bulk, as :func:`~mavest.mavlink.messages.decode_imu`."""

    ticks: np.ndarray  # int64, the raw time field
    gyro: np.ndarray  # (n, 3) rad/s
    accel: np.ndarray  # (n, 3) m/s²
    mag: np.ndarray  # (n, 3) µT
    mag_fresh: np.ndarray  # bool: the message carries a magnetometer reading
    inertial_fresh: np.ndarray  # bool: gyro and accelerometer are new (HIGHRES_IMU's bits)
    instance: np.ndarray  # int64
    saturated: np.ndarray  # bool


def imu_fields(name: str, payloads: np.ndarray) -> ImuFields:
    """Decode IMU payloads of message ``name`` (one of ``IMU_FORMATS``) to SI units."""
    fmt = IMU_FORMATS[name]
    n = payloads.shape[0]

    def columns(sensor: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x, y, z = (payloads[f"{axis}{sensor}"] for axis in "xyz")
        return x, y, z

    def axes(sensor: str, scale: float) -> np.ndarray:
        return np.stack(columns(sensor), axis=1).astype(np.float64) * scale

    if fmt.limits is not None:
        saturated = at_limit(columns("gyro"), fmt.limits) | at_limit(columns("acc"), fmt.limits)
    else:
        saturated = np.zeros(n, dtype=bool)
    if name == "HIGHRES_IMU":
        updated = payloads["fields_updated"].astype(np.int64)
        inertial_fresh = all_fresh(updated, HIGHRES_INERTIAL_BITS)
        mag_fresh = all_fresh(updated, HIGHRES_MAG_BITS)
        instance = payloads["id"].astype(np.int64)
    else:
        inertial_fresh = np.ones(n, dtype=bool)
        mag_fresh = np.ones(n, dtype=bool)
        if name == "RAW_IMU":
            instance = payloads["id"].astype(np.int64)
        else:
            instance = np.full(n, SCALED_IMU_INSTANCE[name], dtype=np.int64)
    return ImuFields(
        payloads[fmt.time_field].astype(np.int64),
        axes("gyro", fmt.gyro_scale),
        axes("acc", fmt.accel_scale),
        axes("mag", fmt.mag_scale),
        mag_fresh,
        inertial_fresh,
        instance,
        saturated,
    )


def simstate_euler(payloads: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw of SIMSTATE payloads (rad), as float64 like pymavlink's."""
    return np.stack([payloads[name] for name in ("roll", "pitch", "yaw")], axis=1).astype(
        np.float64
    )


_ATTITUDE = mavlink2.MAVLink_attitude_message
_ATTITUDE_QUATERNION = mavlink2.MAVLink_attitude_quaternion_message
ATTITUDE_DTYPE = wire_dtype(_ATTITUDE)
ATTITUDE_QUATERNION_DTYPE = wire_dtype(_ATTITUDE_QUATERNION)


@inplace_exact_kernel
def _euler_rows(q: np.ndarray, out: np.ndarray) -> None:
    for i in range(q.shape[0]):
        so3.euler_zyx_from_quat_into(q[i], out[i])


def euler_rows(q: np.ndarray) -> np.ndarray:
    """(n, 3) ZYX angles of (n, 4) quaternions, by the very function the estimate uses."""
    out = np.empty((q.shape[0], 3))
    _euler_rows(np.ascontiguousarray(q), out)
    return out


def packets_per_answer(with_quaternion: bool) -> int:
    """The packets an answered sample takes: ATTITUDE, and ATTITUDE_QUATERNION with it
    when that is sent."""
    return 2 if with_quaternion else 1


def attitude_packets(
    time_boot_ms: np.ndarray,
    euler: np.ndarray,
    rates: np.ndarray,
    q: np.ndarray | None,
    system: int,
    component: int,
    first_seq: int,
    mavlink1: np.ndarray | None = None,
    skips: np.ndarray | None = None,
) -> tuple[Packets, Packets | None]:
    """ATTITUDE (and ATTITUDE_QUATERNION if ``q`` is given) for each row.

    Sequence numbers go on from ``first_seq`` as the encoder hands them out:
    ATTITUDE then ATTITUDE_QUATERNION per sample, or ATTITUDE alone, row i's
    ``skips[i]`` further on (the packets of others sent before it). MAVLink 2
    packets, or MAVLink 1 for the rows where ``mavlink1`` is set.
    """
    n = time_boot_ms.shape[0]
    if mavlink1 is None:
        mavlink1 = np.zeros(n, dtype=np.bool_)
    step = packets_per_answer(q is not None)
    attitude = np.zeros(n, dtype=ATTITUDE_DTYPE)
    attitude["time_boot_ms"] = time_boot_ms
    for k, name in enumerate(("roll", "pitch", "yaw")):
        attitude[name] = euler[:, k]
    for k, name in enumerate(("rollspeed", "pitchspeed", "yawspeed")):
        attitude[name] = rates[:, k]
    seqs = first_seq + step * np.arange(n, dtype=np.int64)
    if skips is not None:
        seqs += skips
    first = _packed(attitude, _ATTITUDE, mavlink1, system, component, seqs)
    if q is None:
        return first, None
    quaternion = np.zeros(n, dtype=ATTITUDE_QUATERNION_DTYPE)
    quaternion["time_boot_ms"] = time_boot_ms
    for k, name in enumerate(("q1", "q2", "q3", "q4")):
        quaternion[name] = q[:, k]
    for k, name in enumerate(("rollspeed", "pitchspeed", "yawspeed")):
        quaternion[name] = rates[:, k]
    second = _packed(quaternion, _ATTITUDE_QUATERNION, mavlink1, system, component, seqs + 1)
    return first, second


def packets(
    payloads: np.ndarray, message_class: Any, seqs: np.ndarray, system: int, component: int
) -> Packets:
    """MAVLink 2 packets of ``payloads`` (records of :func:`wire_dtype` of ``message_class``)
    from ``system``/``component``, row i with sequence number ``seqs[i]`` (mod 256): what
    pymavlink packs for the same fields, byte for byte, for many messages at once."""
    mavlink1 = np.zeros(payloads.shape[0], dtype=np.bool_)
    return _packed(payloads, message_class, mavlink1, system, component, seqs)


def _packed(
    payloads: np.ndarray,
    message_class: Any,
    mavlink1: np.ndarray,
    system: int,
    component: int,
    seqs: np.ndarray,
) -> Packets:
    raw = payloads.view(np.uint8).reshape(payloads.shape[0], payloads.dtype.itemsize)
    return pack_rows(
        raw, message_class.id, message_class.crc_extra, mavlink1, system, component, seqs
    )


@inplace_exact_kernel
def _interleave(
    data: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    stamp: np.ndarray,
    answer_of: np.ndarray,
    first_packets: np.ndarray,
    first_length: np.ndarray,
    second_packets: np.ndarray,
    second_length: np.ndarray,
    out: np.ndarray,
    out_ends: np.ndarray,
) -> int:
    """Copy each input record; after one answered, its packets as records of its time.

    The copies index with unsigned integers: a signed index may count from the end,
    and the test for that kept LLVM from vectorising them (2.6 times slower)."""
    position = np.uint64(0)
    records = 0
    for i in range(start.shape[0]):
        first = np.uint64(start[i])
        for k in range(np.uint64(end[i]) - first):
            out[position + k] = data[first + k]
        position += np.uint64(end[i]) - first
        out_ends[records] = position
        records += 1
        a = answer_of[i]
        if a < 0:
            continue
        for packets, lengths in ((first_packets, first_length), (second_packets, second_length)):
            if lengths.shape[0] == 0:
                continue
            s = stamp[i]
            for k in range(8):
                out[position + np.uint64(k)] = (s >> (8 * (7 - k))) & 0xFF
            position += np.uint64(8)
            row = packets[a]
            for k in range(np.uint64(lengths[a])):
                out[position + k] = row[k]
            position += np.uint64(lengths[a])
            out_ends[records] = position
            records += 1
    return records


def interleave(
    data: np.ndarray,
    records: RecordIndex,
    answer_of: np.ndarray,
    first: Packets,
    second: Packets | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The output tlog's bytes for these records: each input record as it was, each
    answered one (``answer_of[i]`` ≥ 0: its row in the packets) followed by its
    answers stamped with its time. Returns (bytes, the end of each record in them)."""
    answered = int((answer_of >= 0).sum())
    per_answer = packets_per_answer(second is not None)
    if second is None:
        second = NO_PACKETS
    size = int((records.end - records.start).sum()) + answered * 8 * per_answer
    size += int(first.length[answer_of[answer_of >= 0]].sum())
    size += int(second.length[answer_of[answer_of >= 0]].sum()) if per_answer == 2 else 0
    out = np.empty(size, dtype=np.uint8)
    ends = np.empty(len(records) + answered * per_answer, dtype=np.int64)
    count = _interleave(
        data,
        records.start,
        records.end,
        records.stamp,
        answer_of,
        first.data,
        first.length,
        second.data,
        second.length,
        out,
        ends,
    )
    assert count == ends.shape[0]
    return out, ends
