"""IMU messages in, estimates out: MAVLink's units made SI, and mavest's own messages.

Units come from the message definitions (pymavlink's generated
``fieldunits_by_name``, i.e. the ``units`` attribute of the XML), never guessed
from the values in a file: ArduPilot's RAW_IMU and SCALED_IMU* are in mG,
mrad/s and mgauss; HIGHRES_IMU in m/s², rad/s and gauss.

SI here means what the estimator takes: m/s², rad/s, seconds, and µT for the
magnetic field (the unit of BROAD and of most magnetometer literature).
"""

from __future__ import annotations

import math
import struct
from typing import Any, NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavest.estimator.config import STANDARD_GRAVITY
from mavest.mavlink import wire
from mavest.mavlink.signing import Signing, advance_clock, enable_outgoing

MAVLink = mavlink2.MAVLink
MAVLinkMessage = mavlink2.MAVLink_message
_ATTITUDE = mavlink2.MAVLink_attitude_message
_ATTITUDE_QUATERNION = mavlink2.MAVLink_attitude_quaternion_message

# Factor from a MAVLink unit string to SI (µT for the magnetic field).
UNIT_TO_SI: dict[str, float] = {
    "mG": STANDARD_GRAVITY * 1e-3,  # milli standard gravity → m/s²
    "m/s/s": 1.0,
    "mrad/s": 1e-3,
    "rad/s": 1.0,
    "mgauss": 0.1,  # 1 gauss = 100 µT
    "gauss": 100.0,
    "us": 1e-6,
    "ms": 1e-3,
}

IMU_MESSAGES: tuple[str, ...] = (
    "HIGHRES_IMU",
    "RAW_IMU",
    "SCALED_IMU",
    "SCALED_IMU2",
    "SCALED_IMU3",
)

# The IMU instance of each SCALED_IMU* message: SCALED_IMU2/3 are the second and third
# IMU, their instance in the name.
SCALED_IMU_INSTANCE = {"SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}

# HIGHRES_IMU.fields_updated: gyro and accelerometer must all be fresh to be a sample.
HIGHRES_INERTIAL_BITS = (
    mavlink2.HIGHRES_IMU_UPDATED_XACC
    | mavlink2.HIGHRES_IMU_UPDATED_YACC
    | mavlink2.HIGHRES_IMU_UPDATED_ZACC
    | mavlink2.HIGHRES_IMU_UPDATED_XGYRO
    | mavlink2.HIGHRES_IMU_UPDATED_YGYRO
    | mavlink2.HIGHRES_IMU_UPDATED_ZGYRO
)
HIGHRES_MAG_BITS = (
    mavlink2.HIGHRES_IMU_UPDATED_XMAG
    | mavlink2.HIGHRES_IMU_UPDATED_YMAG
    | mavlink2.HIGHRES_IMU_UPDATED_ZMAG
)


# The message rules below are written once for one message (numbers) and for a block of
# them (columns, mavest.mavlink.bulk.imu_fields): the element-wise operators give a bool
# on numbers and a mask on columns.


def all_fresh(updated: Any, bits: int) -> Any:
    """Whether HIGHRES_IMU's ``fields_updated`` has every one of ``bits`` set."""
    return updated & bits == bits


def at_limit(axes: tuple[Any, Any, Any], limits: tuple[int, int]) -> Any:
    """Whether any of a sensor's three integer fields is at its type's limit: the sensor
    (or the firmware's clip) saturated, and the value is not a measurement."""
    low, high = limits
    x, y, z = axes
    return (x <= low) | (x >= high) | (y <= low) | (y >= high) | (z <= low) | (z >= high)


# The range of the integer field types IMU values come in: a value at either end is a
# reading the sensor (or the firmware's conversion) clipped, not a measurement.
_INTEGER_LIMITS = {
    "int8_t": (-(1 << 7), (1 << 7) - 1),
    "int16_t": (-(1 << 15), (1 << 15) - 1),
    "int32_t": (-(1 << 31), (1 << 31) - 1),
}


class UnitError(LookupError):
    """A message definition whose unit mavest has no conversion for."""


class ImuFormat(NamedTuple):
    """How one IMU message's fields become SI (from its definition)."""

    message: str
    time_field: str
    time_scale: float  # s per tick
    accel_scale: float
    gyro_scale: float
    mag_scale: float
    # (lowest, highest) of the gyro and accelerometer fields' integer type; None for floats
    limits: tuple[int, int] | None


def _format_of(message_class: type[MAVLinkMessage]) -> ImuFormat:
    units: dict[str, str] = message_class.fieldunits_by_name
    time_field = "time_usec" if "time_usec" in units else "time_boot_ms"

    def scale(field: str) -> float:
        unit = units.get(field)
        if unit not in UNIT_TO_SI:
            raise UnitError(f"{message_class.msgname}.{field}: no SI factor for unit {unit!r}")
        return UNIT_TO_SI[unit]

    for axis in "yz":  # the three axes of a sensor share a unit
        assert scale(f"{axis}acc") == scale("xacc") and scale(f"{axis}gyro") == scale("xgyro")
    types = dict(zip(message_class.fieldnames, message_class.fieldtypes, strict=True))
    inertial_types = {types[f"{axis}{sensor}"] for axis in "xyz" for sensor in ("acc", "gyro")}
    assert len(inertial_types) == 1  # one type for all six (int16_t, or float)
    return ImuFormat(
        message_class.msgname,
        time_field,
        scale(time_field),
        scale("xacc"),
        scale("xgyro"),
        scale("xmag"),
        _INTEGER_LIMITS.get(inertial_types.pop()),
    )


IMU_FORMATS: dict[str, ImuFormat] = {
    name: _format_of(mavlink2.mavlink_map[getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")])
    for name in IMU_MESSAGES
}


class StreamKey(NamedTuple):
    """One IMU stream: who sent it, which message, which sensor instance."""

    system: int
    component: int
    message: str
    instance: int

    def __str__(self) -> str:
        return f"{self.message}[{self.instance}] from {self.system}/{self.component}"


class ImuSample(NamedTuple):
    """One IMU message in SI units, with its raw timestamp for the stream's clock."""

    stream: StreamKey
    ticks: int  # the raw timestamp field
    tick: float  # s per tick
    gyro: tuple[float, float, float]  # rad/s, FRD
    accel: tuple[float, float, float]  # m/s², specific force, FRD
    mag: tuple[float, float, float] | None  # µT, None when not sent
    # a gyro / accelerometer axis at its integer field's limit: clipped, not measured
    gyro_saturated: bool = False
    accel_saturated: bool = False
    mavlink1: bool = False  # it came as MAVLink 1 (its answers go the same way)

    @property
    def saturated(self) -> bool:
        """A gyro or accelerometer axis clipped: the sample is not a measurement."""
        return self.gyro_saturated or self.accel_saturated


def imu_stream(message: Any) -> tuple[StreamKey, bool]:
    """An IMU message's stream, and whether it is a sample: its gyro and accelerometer
    fresh (HIGHRES_IMU's ``fields_updated``; the other messages always are)."""
    name = message._type
    header = message._header
    fresh = True
    if name == "HIGHRES_IMU":
        fresh = all_fresh(message.fields_updated, HIGHRES_INERTIAL_BITS)
        instance = message.id
    elif name == "RAW_IMU":
        instance = message.id  # a MAVLink 2 extension: 0 when sent as MAVLink 1
    else:
        instance = SCALED_IMU_INSTANCE[name]
    return StreamKey(header.srcSystem, header.srcComponent, name, instance), fresh


def decode_imu(message: Any) -> ImuSample | None:
    """The IMU sample in an IMU message; None for other messages or a HIGHRES_IMU
    whose ``fields_updated`` says gyro or accelerometer are not fresh."""
    if message._type not in IMU_FORMATS:
        return None
    key, fresh = imu_stream(message)
    return imu_sample(message, key) if fresh else None


def imu_sample(message: Any, key: StreamKey) -> ImuSample:
    """The sample in an IMU message of stream ``key`` whose gyro and accelerometer are
    fresh (:func:`imu_stream` gave both)."""
    name = message._type
    fmt = IMU_FORMATS[name]
    mag_fresh = name != "HIGHRES_IMU" or all_fresh(message.fields_updated, HIGHRES_MAG_BITS)
    a, g, m = fmt.accel_scale, fmt.gyro_scale, fmt.mag_scale
    gx, gy, gz = message.xgyro, message.ygyro, message.zgyro
    ax, ay, az = message.xacc, message.yacc, message.zacc
    limits = fmt.limits
    gyro_saturated = limits is not None and at_limit((gx, gy, gz), limits)
    accel_saturated = limits is not None and at_limit((ax, ay, az), limits)
    return ImuSample(
        key,
        getattr(message, fmt.time_field),
        fmt.time_scale,
        (gx * g, gy * g, gz * g),
        (ax * a, ay * a, az * a),
        (message.xmag * m, message.ymag * m, message.zmag * m) if mag_fresh else None,
        gyro_saturated,
        accel_saturated,
        is_mavlink1(message),
    )


def is_mavlink1(message: Any) -> bool:
    """Whether a received message came as a MAVLink 1 packet."""
    return message.get_msgbuf()[0] == mavlink2.PROTOCOL_MARKER_V1


# The FILE_TRANSFER_PROTOCOL payload's header (MAVLink FTP): seq, session, opcode, size,
# req_opcode, burst_complete, padding, offset; then the data.
_FTP_HEADER = struct.Struct("<HBBBBBBI")


def ftp_opcode(payload: Any) -> int:
    """The opcode of a FILE_TRANSFER_PROTOCOL payload (MAV_FTP_OPCODE)."""
    return int(payload[3])  # after seq (uint16) and session


class Encoder:
    """mavest's outgoing messages, as packets from its own system and component.

    MAVLink 2 unless ``mavlink1`` is asked for (a vehicle heard in MAVLink 1 is
    answered in MAVLink 1, as ground stations do: a MAVLink 2 packet among its
    MAVLink 1 ones trips MAVLink 1 readers, and pymavlink's tlog reader). With
    ``signing`` (and its ``sign_outgoing``), every packet is MAVLink 2, signed by
    pymavlink with the key, mavest's fixed link id and a timestamp kept at the
    signing clock's now: MAVLink 1 cannot be signed.
    """

    def __init__(self, system: int, component: int, signing: Signing | None = None) -> None:
        self.system = system
        self.component = component
        self._mav = MAVLink(None, srcSystem=system, srcComponent=component)
        self.signed = False
        if signing is not None and signing.sign_outgoing:
            enable_outgoing(self._mav, signing.key)
            self.signed = True

    def _pack(self, message: Any, mavlink1: bool = False) -> bytes:
        """The packet of ``message``: signed at the signing clock's now (if it signs), with
        the next sequence number (pymavlink advances it only in ``send``, which a
        packet for several links does not use), so that receivers can count losses."""
        mav = self._mav
        if mavlink1 and not self.signed:
            # pymavlink's MAVLink 1 packet of a MAVLink 2 message keeps the extension
            # fields; its payload, whole, is packed here without them
            whole = message.pack(mav, force_mavlink1=True)
            payload = whole[mavlink2.HEADER_LEN_V1 : -2]
            return self._pack_payload(message.id, message.crc_extra, payload, True)
        if self.signed:
            advance_clock(mav.signing)
        packet = message.pack(mav)  # (with mav.seq, the next sequence number)
        self.take_sequence()
        return packet

    @property
    def sequence(self) -> int:
        """The sequence number the next packet takes."""
        return int(self._mav.seq)

    def take_sequence(self, count: int = 1) -> int:
        """The sequence number of the next packet, for ``count`` packets packed elsewhere
        (they take it and the ones after it, modulo 256: a replay packs its answers in
        bulk); the packets of this encoder go on after them."""
        mav = self._mav
        first = mav.seq
        mav.seq = (first + count) % 256
        return first

    def _pack_payload(
        self, message_id: int, crc_extra: int, payload: bytes, mavlink1: bool
    ) -> bytes:
        """The unsigned packet of a payload (wire order), with the next sequence number."""
        sequence = self.take_sequence()
        return wire.pack(
            message_id, crc_extra, payload, sequence, self.system, self.component, mavlink1
        )

    def _pack_unsigned(
        self, message_class: type[Any], *wire_values: float, mavlink1: bool = False
    ) -> bytes:
        """The packet of ``message_class`` with ``wire_values`` (in wire order), as
        :meth:`_pack` would make it unsigned, without a message object (the hot path)."""
        return self._pack_payload(
            message_class.id,
            message_class.crc_extra,
            message_class.unpacker.pack(*wire_values),
            mavlink1,
        )

    def attitude(
        self,
        time_boot_ms: int,
        euler: Any,
        rates: tuple[float, float, float],
        mavlink1: bool = False,
    ) -> bytes:
        roll, pitch, yaw = float(euler[0]), float(euler[1]), float(euler[2])
        if not self.signed:
            return self._pack_unsigned(
                _ATTITUDE, time_boot_ms, roll, pitch, yaw, *rates, mavlink1=mavlink1
            )
        return self._pack(self._mav.attitude_encode(time_boot_ms, roll, pitch, yaw, *rates))

    def attitude_quaternion(
        self,
        time_boot_ms: int,
        q: Any,
        rates: tuple[float, float, float],
        mavlink1: bool = False,
    ) -> bytes:
        w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
        if not self.signed:  # repr_offset_q (an extension) zero: dropped as trailing zeros
            return self._pack_unsigned(
                _ATTITUDE_QUATERNION,
                time_boot_ms,
                w,
                x,
                y,
                z,
                *rates,
                0.0,
                0.0,
                0.0,
                0.0,
                mavlink1=mavlink1,
            )
        return self._pack(self._mav.attitude_quaternion_encode(time_boot_ms, w, x, y, z, *rates))

    def heartbeat(self, mavlink1: bool = False) -> bytes:
        """A companion component's HEARTBEAT (onboard controller, no autopilot): ground
        stations list it as a component, never as a vehicle to fly."""
        return self._pack(
            self._mav.heartbeat_encode(
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink2.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink2.MAV_STATE_ACTIVE,
            ),
            mavlink1,
        )

    def set_message_interval(
        self,
        target_system: int,
        target_component: int,
        message: str,
        rate_hz: float,
        mavlink1: bool = False,
    ) -> bytes:
        """MAV_CMD_SET_MESSAGE_INTERVAL: the only command mavest ever sends."""
        message_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{message}")
        interval_us = 1e6 / rate_hz if rate_hz > 0 else -1.0
        return self._pack(
            self._mav.command_long_encode(
                target_system,
                target_component,
                mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(message_id),
                float(interval_us),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            ),
            mavlink1,
        )

    def command_ack(
        self,
        command: int,
        result: int,
        target_system: int,
        target_component: int,
        mavlink1: bool = False,
    ) -> bytes:
        """COMMAND_ACK of ``command`` to the component that sent it."""
        return self._pack(
            self._mav.command_ack_encode(command, result, 0, 0, target_system, target_component),
            mavlink1,
        )

    def ftp_nak(
        self,
        request: bytes,
        error: int,
        target_network: int,
        target_system: int,
        target_component: int,
        mavlink1: bool = False,
    ) -> bytes:
        """The FILE_TRANSFER_PROTOCOL NAK of a request (``request``: its payload) with
        an error code (MAV_FTP_ERR): the next sequence number, the request's session
        and opcode, the error as the one byte of data."""
        seq, session, opcode, *_ = _FTP_HEADER.unpack_from(bytes(request[: _FTP_HEADER.size]))
        header = _FTP_HEADER.pack(
            (seq + 1) & 0xFFFF, session, mavlink2.MAV_FTP_OPCODE_NAK, 1, opcode, 0, 0, 0
        )
        payload = header + bytes((error,))
        payload += bytes(251 - len(payload))
        return self._pack(
            self._mav.file_transfer_protocol_encode(
                target_network, target_system, target_component, payload
            ),
            mavlink1,
        )

    def param_error(
        self, param_id: str, param_index: int, error: int, target_system: int, target_component: int
    ) -> bytes:
        """PARAM_ERROR (MAVLink 2 only: its id does not fit MAVLink 1)."""
        return self._pack(
            self._mav.param_error_encode(
                target_system, target_component, param_id.encode(), param_index, error
            )
        )


def time_boot_ms(t: float) -> int:
    """The uint32 ``time_boot_ms`` of a vehicle time in seconds (wrapping as the field does)."""
    return math.floor(t * 1000.0 + 1e-6) & 0xFFFFFFFF


def time_boot_ms_many(t: np.ndarray) -> np.ndarray:
    """:func:`time_boot_ms` of many times (int64), by the same arithmetic."""
    return np.floor(t * 1000.0 + 1e-6).astype(np.int64) & 0xFFFFFFFF
