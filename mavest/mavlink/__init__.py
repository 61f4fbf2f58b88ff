"""MAVLink I/O: IMU decoding with units from the definitions, clocks, links, tlogs."""

from mavest.mavlink.clock import ClockEvent, StreamClock
from mavest.mavlink.links import Endpoint, Link, LinkError, make_link, parse_endpoint
from mavest.mavlink.messages import (
    IMU_FORMATS,
    IMU_MESSAGES,
    Encoder,
    ImuSample,
    StreamKey,
    decode_imu,
)
from mavest.mavlink.tlog import TlogError, TlogReader, TlogWriter

__all__ = [
    "IMU_FORMATS",
    "IMU_MESSAGES",
    "ClockEvent",
    "Encoder",
    "Endpoint",
    "ImuSample",
    "Link",
    "LinkError",
    "StreamClock",
    "StreamKey",
    "TlogError",
    "TlogReader",
    "TlogWriter",
    "decode_imu",
    "make_link",
    "parse_endpoint",
]
