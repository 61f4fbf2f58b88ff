"""The pipeline: MAVLink messages in → IMU streams → estimators → messages and records out.

One :class:`Pipeline` serves the live service and the replay alike; what
differs is where bytes come from and what "now" means (the wall clock, or the
tlog's record time). Per vehicle stream (system, component, IMU message,
instance) there is one estimator with its own clock, so two IMUs or two
vehicles never mix. The vehicle's best stream is the one answered with
ATTITUDE and ATTITUDE_QUATERNION, stamped with the vehicle's own
``time_boot_ms``, from mavest's system and component id, in the MAVLink
version the vehicle speaks. Requests addressed to that system and component
(commands, FTP, parameters) are answered as a component that has none of them
answers them.

Everything here is synchronous and quick (tens of µs per sample); the runners
call it from the event loop.

Where each rule is written, once: a function (here unless named) that takes one
sample's numbers or a block's arrays alike, which the replay's fast path
(:mod:`mavest.service.bulk`) calls as the pipeline does; how that path holds the
pipeline's state across a block is in its own docstring.

=========================================  =========================================
which stream an IMU sample goes to         :meth:`Pipeline.route_imu`
which samples are estimated                :func:`valid_sample` (why not:
                                           ``_rejection_reason``; counted by
                                           :func:`reject_sample`)
which magnetometer readings are used       :func:`usable_mag`
saturated fields, HIGHRES_IMU's fresh bits :func:`mavest.mavlink.messages.at_limit`,
                                           :func:`~mavest.mavlink.messages.all_fresh`
whether GPS or airspeed aiding applies     :meth:`Pipeline.gps_aiding`,
                                           :meth:`Pipeline.airspeed_aiding`,
                                           :func:`is_fixed_wing`
what a GPS or airspeed message changes     :meth:`Vehicle.follow` (:class:`AidingFields`)
whether that is fresh for a sample         :func:`mavest.service.aiding.gps_fresh`,
                                           :func:`~mavest.service.aiding.airspeed_fresh`
which estimates are answered               :func:`answerable`, :func:`answers_due`,
                                           :func:`next_output_after`
when mavest's HEARTBEAT goes out (replay)  :func:`heartbeats_after`
which stream an ATTITUDE is compared with  :meth:`Pipeline.autopilot_stream`,
                                           :func:`autopilot_time`,
                                           :func:`autopilot_restarted`;
                                           SIMSTATE: :meth:`Pipeline.truth_vehicle`
what is said and counted of the steps      :func:`book_step` (:func:`is_news`,
                                           :func:`heading_source_due`),
                                           :func:`count_estimated`,
                                           :func:`report_health`, :func:`report_realigned`,
                                           :func:`report_heading`,
                                           :func:`report_accel_unit`
whose messages are followed at all         :meth:`Pipeline.is_ours`, :meth:`Pipeline.follows`,
                                           :meth:`Pipeline.stream_declined`
packets found, checked, packed             :mod:`mavest.mavlink.framing`
=========================================  =========================================
"""

from __future__ import annotations

import enum
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np

from mavest.estimator import Estimator
from mavest.estimator.config import MAX_ANGULAR_RATE, MAX_SPECIFIC_FORCE, STANDARD_GRAVITY
from mavest.estimator.layout import StepFlags
from mavest.estimator.online import accel_unit_named
from mavest.evaluation.online import EulerComparison
from mavest.mavlink import framing, wire
from mavest.mavlink.clock import ClockEvent, StreamClock
from mavest.mavlink.links import Link, UdpLink
from mavest.mavlink.messages import (
    IMU_MESSAGES,
    Encoder,
    ImuSample,
    MAVLink,
    StreamKey,
    ftp_opcode,
    imu_sample,
    imu_stream,
    is_mavlink1,
    mavlink2,
    time_boot_ms,
)
from mavest.mavlink.signing import Signing, Verifier
from mavest.mavlink.tlog import TlogWriter
from mavest.service.aiding import GpsAcceleration, airspeed_fresh, without_centripetal
from mavest.service.config import ServiceConfig
from mavest.service.smoothing import RecordedComparison, RecordedInputs

log = logging.getLogger("mavest")

# A sample beyond these is a broken sensor or a corrupt packet, never flight.
MAX_GYRO = MAX_ANGULAR_RATE  # rad/s (≈ 2900°/s; the filter skips such a sample too)
MAX_ACCEL = MAX_SPECIFIC_FORCE  # m/s² (50 g)
# s: no vehicle's clock reads 285 years (since boot, or since 1970), and a Rerun
# recording's time, int64 nanoseconds, ends at 292: its rows would be lost there
MAX_TIME = 9.0e9
# The IMU streams a run follows at most: each holds a filter and its comparisons (and
# a replay's smoothing its inputs); ids without end (spoofed, or damage that passes the
# checksum) must not grow the service without end, nor its summary.
MAX_STREAMS = 64
MAX_MAG = 1000.0  # µT (10 gauss; the Earth's field is 25–65 µT)
# Without a magnetometer for this long, a stream is reported as 6-D (once).
MAG_WAIT = 2.0  # s
# An autopilot's ATTITUDE this far before its stream's last estimate was sent before the
# autopilot restarted (its IMU not back yet): it is not compared.
AUTOPILOT_RESTART_LAG = 60.0  # s

# Message preference for input.imu = "auto": SI floats first, then ArduPilot's primary IMU.
_PREFERENCE = {name: rank for rank, name in enumerate(IMU_MESSAGES)}

# The IMU message to ask each autopilot for (MAV_CMD_SET_MESSAGE_INTERVAL).
_NATIVE_IMU = {
    mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "RAW_IMU",
    mavlink2.MAV_AUTOPILOT_PX4: "HIGHRES_IMU",
}


class ImuRoute(enum.Enum):
    """What is done with an IMU sample (:meth:`Pipeline.route_imu`)."""

    IGNORED = "ignored"  # from a system not followed: counted, said once
    PASSED_BY = "passed by"  # not fresh (HIGHRES_IMU), or its stream is not followed
    ESTIMATED = "estimated"  # by its stream, which is known
    NEW = "new"  # its stream is seen for the first time: followed or declined now


class EstimateSink(Protocol):
    """Something that takes every estimate (the Rerun recorder, the estimates table, a
    fleet log's σ means, a test).

    A sink that also takes them many at a time (``on_estimates``, ``on_references``:
    see :class:`~mavest.viz.recorder.RerunRecorder`) lets a replay take its fast path.
    """

    def on_estimate(
        self,
        stream: Stream,
        sample: ImuSample,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None: ...

    def on_reference(
        self, stream: Stream, source: str, t: float, euler: tuple, receive_us: int
    ) -> None: ...


@dataclass
class StreamStats:
    received: int = 0
    estimated: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    off_timeline: int = 0  # timestamps far off the stream's timeline, not confirmed
    rejected: int = 0  # values not finite, saturated, beyond any sensor's range, no accel
    rejected_reasons: dict[str, int] = field(default_factory=dict)  # of those, why
    gaps: int = 0
    realigned: int = 0
    tilt_reopened: int = 0  # the accelerometer disturbed too long: tilt uncertain again
    diverged: int = 0  # contradicted again soon after that: re-initialised
    unhealthy: int = 0  # the state failed its health check: re-initialised
    clip_realigned: int = 0  # calm again after a clipped gyro: tilt re-aligned
    gyro_clipped: int = 0  # samples with a gyro axis beyond gyro_clip (rotation missed)
    # samples the filter did not start on: the accelerometer reads g in another unit
    accel_wrong_unit: int = 0
    not_started: int = 0  # samples estimated before the filter had an attitude, any reason
    reboots: int = 0
    wraps: int = 0
    mag_usable: int = 0  # samples estimated with a usable magnetometer reading
    # of those, the readings the filter took (the rest came within the update interval of
    # the last one taken: EstimatorConfig.update_rate)
    mag_taken: int = 0
    mag_used: int = 0  # of those, the ones that corrected (or set) heading
    # the samples at which a gravity update was due, and of those the ones whose
    # (low-passed) specific force was too far from g to be taken as gravity
    updates: int = 0
    accel_far_from_g: int = 0
    gps_aided: int = 0  # samples with the vehicle's acceleration from GPS removed
    airspeed_aided: int = 0  # samples with the centripetal term from airspeed removed
    answered: int = 0  # ATTITUDE messages sent for this stream
    first_t: float | None = None  # the first estimate's time on the current timeline
    last_t: float | None = None
    earlier_span: float = 0.0  # s estimated on the timelines before a reboot

    @property
    def span(self) -> float:
        """How long the stream has been estimated, over every timeline, s."""
        if self.first_t is None or self.last_t is None:
            return self.earlier_span
        return self.earlier_span + self.last_t - self.first_t


@dataclass
class Stream:
    key: StreamKey
    estimator: Estimator
    clock: StreamClock = field(default_factory=StreamClock)
    stats: StreamStats = field(default_factory=StreamStats)
    primary: bool = False
    next_output: float = -math.inf
    vs_autopilot: EulerComparison = field(default_factory=EulerComparison)
    vs_truth: EulerComparison = field(default_factory=EulerComparison)
    heading_source_reported: bool = False
    rate_warned: bool = False  # told the user the stream is too slow to estimate from
    # samples off the stream's timeline, held until the clock confirms or drops theirs
    held: list[ImuSample] = field(default_factory=list)
    # what its filter took, to be smoothed after the run (Pipeline.smoothing); else None
    inputs: RecordedInputs | None = None
    followed_by: StreamKey | None = None  # the stream estimated instead of it from then on

    @property
    def rate(self) -> float:
        period = self.clock.period
        return 1.0 / period if period > 0.0 else 0.0


@dataclass
class Vehicle:
    """What mavest knows of one (system, component) that sends IMU data."""

    system: int
    component: int
    autopilot: int = mavlink2.MAV_AUTOPILOT_GENERIC
    primary: StreamKey | None = None
    last_t: float | None = None  # latest vehicle time seen, s since boot
    interval_requests: int = 0
    interval_asked: str = ""
    interval_ignored: bool = False  # said that the requests did not bring the rate asked
    fixed_wing: bool = False  # from HEARTBEAT.type
    airspeed: float = math.nan  # m/s, from VFR_HUD
    airspeed_t: float = -math.inf  # vehicle time it arrived at
    gps: GpsAcceleration = field(default_factory=GpsAcceleration)
    declination: float | None = None  # rad, its system's COMPASS_DEC (PARAM_VALUE)
    # whether it speaks MAVLink 1 (its HEARTBEAT's, or before one its first IMU message's
    # version): what mavest's HEARTBEAT and commands go to it as; None: not heard yet
    mavlink1: bool | None = None

    def on_airspeed(self, airspeed: float, t: float) -> None:
        """A VFR_HUD airspeed (m/s) arriving at vehicle time t; an implausible one
        (negative, ≥ 400 m/s, NaN) is not taken."""
        if 0.0 <= airspeed < 400.0:  # (NaN fails the range test)
            self.airspeed = airspeed
            self.airspeed_t = t

    def follow(self, fields: AidingFields, t: float | None) -> None:
        """A GPS or airspeed message of the vehicle's, taken at its time ``t`` (its last
        estimate's: the replay's fast path gives each message the one before it); None,
        before it has one: not taken."""
        if t is None:
            return
        if fields.message_id == mavlink2.MAVLINK_MSG_ID_VFR_HUD:
            self.on_airspeed(fields.airspeed, t)
        elif fields.message_id == mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT:
            self.gps.on_fix(fields.fix_type, t)
        else:
            self.gps.on_velocity_report(fields.vx, fields.vy, fields.vz, fields.time_boot_ms, t)


# The messages a vehicle's aiding state follows, and what it takes of each: its fields of
# these names (AidingFields', Vehicle.follow).
AIDING_FIELDS: dict[str, tuple[str, ...]] = {
    "GLOBAL_POSITION_INT": ("vx", "vy", "vz", "time_boot_ms"),
    "GPS_RAW_INT": ("fix_type",),
    "VFR_HUD": ("airspeed",),
}


class AidingFields(NamedTuple):
    """What the aiding state takes of a GPS or airspeed message (:data:`AIDING_FIELDS`),
    as on the wire (pymavlink's numbers: ints, float32 widened exactly); the others'
    fields are 0."""

    message_id: int
    fix_type: int = 0  # GPS_RAW_INT
    vx: int = 0  # GLOBAL_POSITION_INT, cm/s NED
    vy: int = 0
    vz: int = 0
    time_boot_ms: int = 0  # GLOBAL_POSITION_INT's
    airspeed: float = 0.0  # VFR_HUD, m/s

    @classmethod
    def of(cls, message: Any) -> AidingFields:
        """The fields of a decoded GPS_RAW_INT, GLOBAL_POSITION_INT or VFR_HUD."""
        taken = AIDING_FIELDS[message.get_type()]
        return cls(message.get_msgId(), **{name: getattr(message, name) for name in taken})


class Pipeline:
    """Decode, estimate, answer. Feed it bytes (:meth:`on_bytes`) or messages."""

    def __init__(
        self,
        config: ServiceConfig,
        links: list[Link] | None = None,
        out_tlog: TlogWriter | None = None,
        sinks: list[EstimateSink] | None = None,
        now_us: Callable[[], int] | None = None,
        signing: Signing | None = None,
    ) -> None:
        self.config = config
        # MAVLink 2 signing: outgoing packets signed (Encoder), incoming ones checked by
        # the verifier, which also counts what it dropped; None: neither.
        self.signing = signing
        self.verifier = Verifier(signing) if signing is not None else None
        self.links = links if links is not None else []
        self.out_tlog = out_tlog
        self.sinks = sinks if sinks is not None else []
        self.now_us = now_us if now_us is not None else (lambda: 0)
        self.streams: dict[StreamKey, Stream] = {}  # those estimated from now on
        # streams estimated until a better one of their vehicle's came (a lower instance):
        # what they estimated is in the outputs, so the summary and the smoothing keep them
        self.given_up: dict[StreamKey, Stream] = {}
        self.vehicles: dict[tuple[int, int], Vehicle] = {}
        self._encoders: dict[int, Encoder] = {}
        # pymavlink's decoder of every packet found (one: it keeps no state of a peer's;
        # with signing, the verifier's, whose replay check spans peers and links)
        self._decoder = self.verifier.parser() if self.verifier is not None else MAVLink(None)
        # a byte stream's packet cut off at the end of its last bytes, by (link, peer)
        self._partial: dict[tuple[int, Any], bytes] = {}
        self.messages_in = 0
        self.bad_packets = 0
        self.skipped_bytes = 0  # of the bad packets and the noise between packets
        self.sent = 0
        # The record time (µs) of what is written now: packets of ours in the output
        # tlog, estimates and references to the sinks. The last message's
        # (on_message); a replay's bulk feed sets it as the records it takes would.
        self.record_us = 0
        self._not_followed: set[StreamKey] = set()
        self._said_full = False  # that MAX_STREAMS streams are followed
        self.ignored_imu: dict[int, int] = {}  # IMU messages from systems not followed
        self._declinations: dict[int, float] = {}  # rad, each system's COMPASS_DEC
        self._autodec: dict[int, bool] = {}  # each system's COMPASS_AUTODEC, when heard
        self._autodec_warned: set[int] = set()
        # requests to mavest already reported in the log, by (requester, message)
        self._requests_told: set[tuple[int, int, str]] = set()
        # until the first IMU stream: the messages heard, by (system, component), so that
        # a live run that gets none can say what it does get
        self.heard_without_imu: dict[tuple[int, int], set[str]] = {}
        # whether the streams' estimators are fed in batches (a replay's BulkFeed), the
        # few samples that come one at a time too (Estimator's batch_fed)
        self.batch_fed = False
        # whether each stream keeps its filter's inputs and its comparisons' references, to
        # be smoothed after the run (replay --smooth): set before the first sample
        self.smoothing = False

    # ---------------------------------------------------------------- input

    def on_bytes(self, link: Link, data: bytes, peer: Any) -> None:
        """Bytes from a link: find the packets, decode and handle each message.

        A UDP datagram of clean packets is decoded whole (:func:`wire.decode_datagram`:
        the same messages, 0.7 of the CPU); anything else goes through :meth:`_parse`.
        """
        now = self.now_us()
        messages = None
        if self.verifier is None and isinstance(link, UdpLink):
            messages = wire.decode_datagram(data)
        if messages is None:
            messages = self._parse(link, data, peer)
        for message in messages:
            if self.out_tlog is not None:
                self.out_tlog.write(now, message.get_msgbuf())
            self.on_message(message, now)

    def _parse(self, link: Link, data: bytes, peer: Any) -> list[Any]:
        """The messages of the clean packets in ``data``, each decoded by pymavlink (which
        checks the signature, with signing); what is not one is counted as damage and
        skipped (:func:`framing.find_packets`: a false start costs only itself, and an id
        the dialect does not know, having no CRC to check, is damage).

        A packet never spans UDP datagrams; on a byte stream (TCP, serial) a packet cut off
        at the end of what arrived is kept, per peer, for the bytes that follow.
        """
        streamed = not isinstance(link, UdpLink)
        key = (id(link), peer)
        partial = self._partial.pop(key, None) if streamed else None
        if partial:
            data = partial + data
        found = framing.find_packets(
            np.frombuffer(data, dtype=np.uint8), whole=not streamed, after_damage=partial == b""
        )
        self.bad_packets += found.damaged
        self.skipped_bytes += found.skipped
        if found.end < len(data) or (streamed and found.ends_damaged):
            # (empty: the bytes ended in noise, which the next ones may go on)
            self._keep_partial(key, data[found.end :])
        messages = []
        for start, end in found.index[:2].T.tolist():
            message = self._decode(data[start:end])
            if message is not None:
                messages.append(message)
        return messages

    def _keep_partial(self, key: tuple[int, Any], partial: bytes) -> None:
        """Keep a peer's packet cut off at the end of its bytes (at most one packet long;
        empty: they ended in damage) until its next bytes; of more peers than
        :data:`PARTIAL_PEERS` (TCP clients come and go), the one heard from longest ago
        loses its partial packet, as damage."""
        partials = self._partial
        partials[key] = partial  # (last in the dict's order: popped on each use)
        if len(partials) > PARTIAL_PEERS:
            dropped = partials.pop(next(iter(partials)))
            if dropped:
                self.bad_packets += 1
                self.skipped_bytes += len(dropped)

    def _decode(self, packet: bytes) -> Any | None:
        """pymavlink's message of one clean packet; None if it refused it: a signature the
        verifier refused (counted there), else damage (counted here)."""
        verifier = self.verifier
        refused_before = verifier.dropped if verifier is not None else 0
        try:
            return self._decoder.decode(bytearray(packet))
        except Exception:  # pymavlink's MAVError
            if verifier is None or verifier.dropped == refused_before:
                self.bad_packets += 1
                self.skipped_bytes += len(packet)
            return None

    def on_message(self, message: Any, timestamp_us: int) -> None:
        """One decoded message; ``timestamp_us`` is its record time (for files written)."""
        self.messages_in += 1
        self.record_us = timestamp_us
        header = message._header
        system, component = header.srcSystem, header.srcComponent
        if self.is_ours(system, component):
            return
        name = message._type
        if not self.streams:
            self.heard_without_imu.setdefault((system, component), set()).add(name)
        if name in _IMU_NAMES:
            self._on_imu(message, system, component)
        elif name == "ATTITUDE":
            t = autopilot_time(message.time_boot_ms)
            self._on_reference(system, component, message, "autopilot", t)
        elif name == "SIMSTATE":
            vehicle = self.truth_vehicle(system)
            if vehicle is not None and vehicle.last_t is not None:
                self._on_reference(
                    vehicle.system, vehicle.component, message, "truth", vehicle.last_t
                )
        elif name == "PARAM_VALUE" and message.param_id == "COMPASS_DEC":
            self._on_declination(system, component, float(message.param_value))
        elif name == "PARAM_VALUE" and message.param_id == "COMPASS_AUTODEC":
            self._autodec[system] = message.param_value != 0.0
            self._warn_of_autodec(system)
        elif name in AIDING_FIELDS:
            vehicle = self.vehicles.get((system, component))
            if vehicle is not None:
                vehicle.follow(AidingFields.of(message), vehicle.last_t)
        elif name == "HEARTBEAT":
            if self.is_vehicles_heartbeat(system, message):
                vehicle = self._vehicle(system, component)
                vehicle.autopilot = message.autopilot
                vehicle.fixed_wing = is_fixed_wing(message.type)
                vehicle.mavlink1 = is_mavlink1(message)
        elif name in _REQUESTS:
            self._on_request(message, system, component)
        elif name == "COMMAND_ACK" and message.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = mavlink2.enums["MAV_RESULT"].get(message.result)
            log.info(
                "%d/%d answered the message-interval request: %s",
                system,
                component,
                result.name if result is not None else message.result,
            )

    def is_vehicles_heartbeat(self, system: int, message: Any) -> bool:
        """Whether a HEARTBEAT not of ours speaks for a vehicle (its autopilot a real
        one, its system not ignored): it tells the vehicle's type."""
        return (
            system not in self.config.input.ignore_systems
            and message.autopilot != mavlink2.MAV_AUTOPILOT_INVALID
        )

    def is_ours(self, system: int, component: int) -> bool:
        """Whether (system, component) is mavest itself: ``output.component_id`` on
        ``output.system_id``, or on any system when that is 0. What it hears of itself,
        it neither takes nor answers."""
        output = self.config.output
        if component != output.component_id:
            return False
        return output.system_id in (0, system)

    def _vehicle(self, system: int, component: int) -> Vehicle:
        """The vehicle (system, component), known from now on."""
        vehicle = self.vehicles.get((system, component))
        if vehicle is None:
            vehicle = self.vehicles[(system, component)] = Vehicle(system, component)
            vehicle.declination = self._declinations.get(system)
        return vehicle

    def truth_vehicle(self, system: int) -> Vehicle | None:
        """The vehicle a SIMSTATE (the simulator's truth) from ``system`` is for: its
        autopilot (component 1), else one of its vehicles that has a stream."""
        return self.vehicles.get((system, 1)) or self._any_vehicle(system)

    def _any_vehicle(self, system: int) -> Vehicle | None:
        for vehicle in self.vehicles.values():
            if vehicle.system == system and vehicle.primary is not None:
                return vehicle
        return None

    def follows(self, system: int) -> bool:
        """Whether the IMU messages of ``system`` are estimated from (``input.system``,
        or any system not in ``input.ignore_systems``)."""
        wanted = self.config.input.system
        if wanted:
            return system == wanted
        return system not in self.config.input.ignore_systems

    def _on_imu(self, message: Any, system: int, component: int) -> None:
        start = time.perf_counter()
        key, fresh = imu_stream(message)
        route, stream = self.route_imu(key, fresh)
        if route is ImuRoute.IGNORED:
            self._ignore_imu(system)
            return
        if route is ImuRoute.PASSED_BY:
            return
        sample = imu_sample(message, key)
        if stream is None:
            stream = self._new_stream(key)
            if stream is None:
                self._not_followed.add(key)
                return
            vehicle = self.vehicles[(system, component)]
            if vehicle.mavlink1 is None:  # no HEARTBEAT of its own yet
                vehicle.mavlink1 = sample.mavlink1
        self._estimate(stream, sample, start)

    def route_imu(self, key: StreamKey, fresh: bool) -> tuple[ImuRoute, Stream | None]:
        """What is done with an IMU sample of stream ``key`` (``fresh``: its gyro and
        accelerometer are, :func:`~mavest.mavlink.messages.imu_stream`), and the
        stream that estimates from it if there is one yet. In this order: a system not
        followed is ignored (and counted); a sample that is not fresh is passed by; a
        known stream estimates; a stream declined passes it by; else it is new."""
        if not self.follows(key.system):
            return ImuRoute.IGNORED, None
        if not fresh:
            return ImuRoute.PASSED_BY, None
        stream = self.streams.get(key)
        if stream is not None:
            return ImuRoute.ESTIMATED, stream
        if self.stream_declined(key):
            return ImuRoute.PASSED_BY, None
        return ImuRoute.NEW, None

    def stream_declined(self, key: StreamKey) -> bool:
        """Whether a stream was seen and is not followed (the configuration does not
        select it, or a better stream of its vehicle replaced it): its samples are
        passed by."""
        return key in self._not_followed

    def _ignore_imu(self, system: int) -> None:
        """Count an IMU message from a system not followed; say so once per system."""
        count = self.ignored_imu.get(system, 0)
        self.ignored_imu[system] = count + 1
        if count == 0:
            wanted = self.config.input.system
            log.info(
                "ignoring IMU messages from system %d (%s)",
                system,
                f"following system {wanted} only"
                if wanted
                else "in input.ignore_systems: ground stations by default",
            )

    def _new_stream(self, key: StreamKey) -> Stream | None:
        """A stream seen for the first time: follow it if the configuration selects it."""
        wanted = self.config.input
        vehicle = self._vehicle(key.system, key.component)
        if wanted.imu not in ("auto", "all") and key.message != wanted.imu:
            return None
        if wanted.imu_instance >= 0 and key.instance != wanted.imu_instance:
            return None
        if len(self.streams) + len(self.given_up) >= MAX_STREAMS:
            if not self._said_full:
                self._said_full = True
                log.warning(
                    "%s: %d IMU streams followed already: this one and any later are not "
                    "(spoofed ids? --system N follows one vehicle)",
                    key,
                    MAX_STREAMS,
                )
            return None
        better = vehicle.primary is None or (
            (_PREFERENCE[key.message], key.instance)
            < (_PREFERENCE[vehicle.primary.message], vehicle.primary.instance)
        )
        if not better and wanted.imu != "all":
            return None
        # The stream's clock confirms a new timeline before the estimator sees it, and
        # then hands it the samples it held meanwhile: the estimator believes every time.
        estimator_config = self.config.estimator.replace(timeline_confirm=1)
        comparison = RecordedComparison if self.smoothing else EulerComparison
        stream = Stream(
            key,
            Estimator(estimator_config, batch_fed=self.batch_fed),
            vs_autopilot=comparison(wanted.settle_time),
            vs_truth=comparison(wanted.settle_time),
            inputs=RecordedInputs() if self.smoothing else None,
        )
        if vehicle.declination is not None:
            stream.estimator.declination = vehicle.declination
        self.streams[key] = stream
        if better:
            if vehicle.primary is not None:
                self.streams[vehicle.primary].primary = False
                log.info("%s: following %s instead of %s", _who(vehicle), key, vehicle.primary)
                if wanted.imu != "all":
                    given_up = self.streams.pop(vehicle.primary)
                    given_up.followed_by = key
                    self.given_up[vehicle.primary] = given_up
                    self._not_followed.add(vehicle.primary)
            else:
                log.info("%s: estimating from %s", _who(vehicle), key)
            vehicle.primary = key
            stream.primary = True
        return stream

    @property
    def every_stream(self) -> list[Stream]:
        """Every stream estimated: those given up for a better one, then the others."""
        return [*self.given_up.values(), *self.streams.values()]

    # ---------------------------------------------------------------- estimation

    def _estimate(self, stream: Stream, sample: ImuSample, start: float) -> None:
        stats = stream.stats
        stats.received += 1
        gyro, accel = sample.gyro, sample.accel
        # before the clock: a rejected sample's timestamp is not believed either
        if not valid_sample(gyro, accel, sample.saturated, sample.ticks * sample.tick):
            reject_sample(stream, _rejection_reason(sample))
            if sample.gyro_saturated:  # the rotation it missed is unknown
                stream.estimator.gyro_clipped()
                if stream.inputs is not None:  # (nor can smoothing carry an attitude across)
                    stream.inputs.restart()
            return
        clock = stream.clock
        reading = clock.read(sample.ticks, sample.tick)
        event = reading.event
        if not event.used:
            if event is ClockEvent.DUPLICATE:
                stats.duplicates += 1
                if stats.duplicates == 1:
                    log.warning(
                        "%s: a sample with the time of the one before: dropped (all such are "
                        "counted; the same packet by two routes, or two sources sharing an id?)",
                        stream.key,
                    )
            elif event is ClockEvent.OUT_OF_ORDER:
                stats.out_of_order += 1
                if stats.out_of_order == 1:
                    log.warning(
                        "%s: a sample older than the one before: dropped (all such are "
                        "counted; a link that reorders, or two sources sharing an id?)",
                        stream.key,
                    )
            else:
                stats.off_timeline += 1
                # perhaps the start of a new timeline (a reboot, a jump): kept until the
                # clock decides, so that a confirmed one loses none of its samples
                if clock.pending == 1:
                    stream.held.clear()
                stream.held.append(sample)
            return
        held: list[ImuSample] = []
        if stream.held:  # rare: nothing to allocate per sample
            if event is ClockEvent.REBOOT or reading.dt > clock.max_jump:
                held = stream.held  # the new timeline's first samples
                stats.off_timeline -= len(held)
            # else single stamps off the timeline, and the timeline went on: bad ones
            stream.held = []
        t = reading.t
        if event is ClockEvent.REBOOT:
            stats.reboots += 1
            log.warning(
                "%s: time went back from %.3f s to %.3f s (a reboot?): re-initialising",
                stream.key,
                stats.last_t or 0.0,
                t,
            )
            stats.earlier_span, stats.first_t = stats.span, None  # (a new timeline's span)
            stream.estimator.reset()
            stream.next_output = -math.inf
            stream.vs_autopilot.restart()
            stream.vs_truth.restart()
            if stream.inputs is not None:
                stream.inputs.restart()
        elif event is ClockEvent.WRAPPED:
            stats.wraps += 1
            log.info("%s: the 32-bit timestamp wrapped", stream.key)
        elif event is ClockEvent.GAP:
            stats.gaps += 1
        for early in held:  # the new timeline's first samples, in the order they came
            self._step(stream, early, clock.time_of(early.ticks, early.tick), start)
        self._step(stream, sample, t, start)

    def _step(self, stream: Stream, sample: ImuSample, t: float, start: float) -> None:
        """Estimate from a sample the clock has placed at ``t``; answer and record."""
        stats = stream.stats
        gyro, accel = sample.gyro, sample.accel
        vehicle = self.vehicles[(sample.stream.system, sample.stream.component)]
        mag = sample.mag if sample.mag is not None and usable_mag(sample.mag) else None
        linear_accel = self._gps_acceleration(stream, vehicle, t)
        airspeed_aided = linear_accel is None and self._uses_airspeed(vehicle, t)
        if airspeed_aided:
            accel = without_centripetal(accel, gyro, stream.estimator.bias, vehicle.airspeed)
        estimate = stream.estimator.update(t, gyro, accel, mag, linear_accel)
        flags = estimate.flags
        if flags & StepFlags.SKIPPED:
            reject_sample(
                stream, "skipped by the estimator: " + ", ".join(StepFlags.describe(flags))
            )
            return
        if stream.inputs is not None:
            stream.inputs.add(t, gyro, accel, mag, linear_accel)
        if flags & StepFlags.ACCEL_WRONG_UNIT:
            report_accel_unit(stream, 1, stream.estimator.accel_unit_problem)
        count_estimated(stats, flags, mag is not None, estimate.mag_used)
        report_clipped(stream, flags, t)
        if airspeed_aided and not flags & StepFlags.ACCEL_AIDED:
            stats.airspeed_aided += 1
        book_step(stream, flags, t)
        vehicle.last_t = t
        euler = estimate.euler
        euler_tuple = (float(euler[0]), float(euler[1]), float(euler[2]))
        # (the level attitude the filter starts from is no estimate to score: NaN)
        scored = euler_tuple if answerable(flags) else _NO_ATTITUDE
        stream.vs_autopilot.add_estimate(t, scored)
        stream.vs_truth.add_estimate(t, scored)
        if self.sinks:
            processing = time.perf_counter() - start
            for sink in self.sinks:
                sink.on_estimate(stream, sample, estimate, euler_tuple, self.record_us, processing)
        if stream.primary and answerable(flags):
            rate = self.config.output.attitude_rate
            due, stream.next_output = answers_due(t, stream.next_output, rate)
            if due.shape[0]:
                self._answer(stream, t, estimate, euler_tuple, gyro, sample.mavlink1)

    def _warn_of_autodec(self, system: int) -> None:
        """Once per system: a COMPASS_DEC taken while COMPASS_AUTODEC is on. The autopilot
        then works the declination out from its position, after a GPS fix, and sends no
        new value: the one a ground station logged at connection may be stale (tlogs
        seen 20° off)."""
        if (
            self._autodec.get(system)
            and system in self._declinations
            and system not in self._autodec_warned
        ):
            self._autodec_warned.add(system)
            log.warning(
                "system %d: COMPASS_AUTODEC is on: the autopilot takes the declination from "
                "its position, and the COMPASS_DEC used (%.2f°) may be stale (if yaw is off "
                "by a constant, set estimator.compass_dec)",
                system,
                math.degrees(self._declinations[system]),
            )

    def _on_declination(self, system: int, component: int, declination: float) -> None:
        """A system's declination (its autopilot's COMPASS_DEC, whichever component
        reports it: ground stations log the vehicle's parameters under their own
        component), for the vehicles of that system unless the configuration sets one."""
        if (
            system in self.config.input.ignore_systems
            or self.config.estimator.compass_dec != 0.0
            or not math.isfinite(declination)
            or abs(declination) > math.pi
            or declination == self._declinations.get(system)
        ):
            return
        self._declinations[system] = declination
        self._warn_of_autodec(system)
        vehicles = [v for v in self.vehicles.values() if v.system == system]
        for vehicle in vehicles:
            vehicle.declination = declination
        log.info(
            "%s: declination %.2f° from parameter COMPASS_DEC of %d/%d",
            ", ".join(_who(v) for v in vehicles) or f"system {system}",
            math.degrees(declination),
            system,
            component,
        )
        for key, stream in self.streams.items():
            if key.system == system:
                stream.estimator.declination = declination

    def _gps_acceleration(
        self, stream: Stream, vehicle: Vehicle, t: float
    ) -> tuple[float, float, float] | None:
        """The vehicle's acceleration (NED) from GPS for a sample at t, if usable.

        Only with heading from the magnetometer: the acceleration is known in the
        world frame, and a free (6-D) heading cannot turn it into the body.
        """
        return vehicle.gps.at(t) if self.gps_aiding(stream) else None

    def gps_aiding(self, stream: Stream) -> bool:
        """Whether this stream's samples take the GPS acceleration when it is fresh."""
        mode = self.config.input.acceleration_aiding
        return mode in ("auto", "gps") and stream.estimator.heading_referenced

    def airspeed_aiding(self, vehicle: Vehicle) -> bool:
        """Whether this vehicle's samples take the airspeed correction when it is fresh."""
        mode = self.config.input.acceleration_aiding
        return not (mode in ("off", "gps") or (mode == "auto" and not vehicle.fixed_wing))

    def _uses_airspeed(self, vehicle: Vehicle, t: float) -> bool:
        return self.airspeed_aiding(vehicle) and airspeed_fresh(t, vehicle.airspeed_t)

    def _answer(
        self,
        stream: Stream,
        t: float,
        estimate: Any,
        euler: tuple[float, float, float],
        gyro: tuple[float, float, float],
        mavlink1: bool,
    ) -> None:
        """ATTITUDE (and ATTITUDE_QUATERNION) for an estimate, in the MAVLink version of
        the sample it answers."""
        output = self.config.output
        bias = estimate.bias
        rates = (gyro[0] - bias[0], gyro[1] - bias[1], gyro[2] - bias[2])
        encoder = self.encoder(stream.key.system)
        stamp = time_boot_ms(t)
        attitude = encoder.attitude(stamp, euler, rates, mavlink1)
        if output.attitude_quaternion:
            self.emit(attitude, encoder.attitude_quaternion(stamp, estimate.q, rates, mavlink1))
        else:
            self.emit(attitude)
        stream.stats.answered += 1

    def autopilot_stream(self, system: int, component: int) -> Stream | None:
        """The stream an autopilot's ATTITUDE from (system, component) is compared with
        (None: none, or the message is ours)."""
        if self.is_ours(system, component):
            return None
        return self._reference_stream(system, component)

    def _reference_stream(self, system: int, component: int) -> Stream | None:
        """The stream a reference attitude of vehicle (system, component) is compared
        with: the vehicle's primary one, once known."""
        vehicle = self.vehicles.get((system, component))
        if vehicle is None or vehicle.primary is None:
            return None
        return self.streams.get(vehicle.primary)

    def _on_reference(
        self, system: int, component: int, message: Any, source: str, t: float
    ) -> None:
        stream = self._reference_stream(system, component)
        if stream is None:
            return
        euler = (float(message.roll), float(message.pitch), float(message.yaw))
        if not usable_reference(euler):
            return
        if source == "truth":
            stream.vs_truth.add_reference(t, euler)
        elif autopilot_restarted(t, stream.stats.last_t):
            return
        else:
            stream.vs_autopilot.add_reference(t, euler)
        for sink in self.sinks:
            sink.on_reference(stream, source, t, euler, self.record_us)

    # ---------------------------------------------------------------- output

    def encoder(self, vehicle_system: int) -> Encoder:
        """The encoder of what mavest sends for a vehicle of this system: from
        ``output.system_id``, or the vehicle's system when that is 0; one per system,
        so that each system's packets keep their own sequence numbers."""
        system = self.config.output.system_id or vehicle_system
        encoder = self._encoders.get(system)
        if encoder is None:
            encoder = self._encoders[system] = Encoder(
                system, self.config.output.component_id, self.signing
            )
        return encoder

    def emit(self, *packets: bytes, to_vehicle: bool = False) -> None:
        """Send packets of ours on every link, together (one datagram on UDP, which
        MAVLink receivers take as they take a byte stream: a send is the costliest
        step of an answer), and record each.

        The first link is the one listened on (the vehicle's); with
        ``output.reply_on_input`` off, estimates and HEARTBEAT go to the others only,
        and only what is meant for the vehicle or a requester (``to_vehicle``: the
        message-interval request, answers to requests) goes back on it too."""
        self.sent += len(packets)
        data = packets[0] if len(packets) == 1 else b"".join(packets)
        links = self.links if to_vehicle or self.config.output.reply_on_input else self.links[1:]
        for link in links:
            link.send(data)
        if self.out_tlog is not None:
            for packet in packets:
                self.out_tlog.write(self.record_us, packet)

    def _speaking(self) -> dict[int, bool]:
        """The systems mavest speaks as (none until a vehicle's IMU is followed), each
        with whether to speak MAVLink 1 there (every vehicle it speaks for there does)."""
        own = self.config.output.system_id
        speaking: dict[int, bool] = {}
        for vehicle in self.vehicles.values():
            if vehicle.primary is not None:
                system = own or vehicle.system
                speaking[system] = speaking.get(system, True) and vehicle.mavlink1 is True
        return speaking

    def heartbeat(self) -> None:
        """One HEARTBEAT per system mavest speaks as (none until a vehicle is heard)."""
        for system, mavlink1 in sorted(self._speaking().items()):
            self.emit(self.encoder(system).heartbeat(mavlink1))

    def _on_request(self, message: Any, system: int, component: int) -> None:
        """Answer a request addressed to mavest's own system and component, as a MAVLink
        component without parameters, commands or files does: COMMAND_ACK unsupported,
        an FTP NAK, PARAM_ERROR for a parameter read or set. A list of its parameters
        gets nothing: the parameter protocol has no empty list (any PARAM_VALUE would
        show in ground stations as a parameter). A broadcast (target 0) is the
        autopilot's to answer, never mavest's. The answer goes in the request's version.
        """
        target = message.target_system
        if message.target_component != self.config.output.component_id:
            return
        if target not in self._speaking():
            return
        name = message._type
        mavlink1 = is_mavlink1(message)
        encoder = self.encoder(target)
        if name in ("COMMAND_LONG", "COMMAND_INT"):
            answer = "MAV_RESULT_UNSUPPORTED"
            packet = encoder.command_ack(
                message.command, mavlink2.MAV_RESULT_UNSUPPORTED, system, component, mavlink1
            )
            name = f"{name} {_enum_name('MAV_CMD', message.command)}"
        elif name == "FILE_TRANSFER_PROTOCOL":
            if ftp_opcode(message.payload) >= mavlink2.MAV_FTP_OPCODE_ACK:
                return  # an answer (ACK, NAK), never answered in turn
            answer = "a NAK (MAV_FTP_ERR_UNKNOWNCOMMAND: no files here)"
            packet = encoder.ftp_nak(
                message.payload,
                mavlink2.MAV_FTP_ERR_UNKNOWNCOMMAND,
                message.target_network,
                system,
                component,
                mavlink1,
            )
        elif name == "PARAM_REQUEST_LIST" or mavlink1:
            # (PARAM_ERROR has no MAVLink 1 form)
            self._tell_request(system, component, name, target, "nothing: it has no parameters")
            return
        else:  # PARAM_REQUEST_READ, PARAM_SET
            answer = "PARAM_ERROR (does not exist)"
            packet = encoder.param_error(
                message.param_id,
                getattr(message, "param_index", -1),
                mavlink2.MAV_PARAM_ERROR_DOES_NOT_EXIST,
                system,
                component,
            )
        self._tell_request(system, component, name, target, answer)
        self.emit(packet, to_vehicle=True)

    def _tell_request(
        self, system: int, component: int, what: str, target: int, answer: str
    ) -> None:
        """Say, once per requester and kind of request, what mavest answers it."""
        key = (system, component, what)
        if key in self._requests_told:
            return
        self._requests_told.add(key)
        log.info(
            "%d/%d sent %s to mavest (%d/%d): answered %s (said once)",
            system,
            component,
            what,
            target,
            self.config.output.component_id,
            answer,
        )

    def request_intervals(self) -> None:
        """Ask every vehicle for its IMU message at ``input.request_rate`` until it comes.

        Called every few seconds on a live link; asks at most five times per vehicle,
        and stops once the stream arrives within 10 % of the asked rate, above or below
        (a stream faster than asked is slowed down: it costs the link and the CPU).
        """
        rate = self.config.input.request_rate
        if rate <= 0.0:
            return
        for vehicle in self.vehicles.values():
            if vehicle.system in self.config.input.ignore_systems:
                continue
            message = self.config.input.imu
            if message in ("auto", "all"):
                message = _NATIVE_IMU.get(vehicle.autopilot, "RAW_IMU")
            stream = self.streams.get(vehicle.primary) if vehicle.primary else None
            if (
                stream is not None
                and stream.key.message == message
                and abs(stream.rate - rate) <= 0.1 * rate
            ):
                continue
            if vehicle.interval_requests >= INTERVAL_REQUESTS:
                if not vehicle.interval_ignored:
                    vehicle.interval_ignored = True
                    now = f"at {stream.rate:.1f} Hz" if stream is not None else "nothing"
                    log.warning(
                        "%s still sends %s %s after %d requests for %g Hz: it does not take "
                        "MAV_CMD_SET_MESSAGE_INTERVAL for this message; set the rate on the "
                        "vehicle (ArduPilot SRn_RAW_SENS, PX4 `mavlink stream`)",
                        _who(vehicle),
                        message,
                        now,
                        INTERVAL_REQUESTS,
                        rate,
                    )
                continue
            vehicle.interval_requests += 1
            vehicle.interval_asked = message
            log.info("asking %s for %s at %g Hz", _who(vehicle), message, rate)
            self.emit(
                self.encoder(vehicle.system).set_message_interval(
                    vehicle.system, vehicle.component, message, rate, vehicle.mavlink1 is True
                ),
                to_vehicle=True,
            )


# How many times a vehicle is asked for its IMU message's rate before mavest gives up.
INTERVAL_REQUESTS = 5

# How many byte streams' cut-off packets are kept at once (one per TCP client or serial
# device that has one: a tcpin server's clients are many only when they come and go).
PARTIAL_PEERS = 64

_IMU_NAMES = frozenset(IMU_MESSAGES)

# Requests a MAVLink component answers when they are addressed to it.
_REQUESTS = frozenset(
    (
        "COMMAND_LONG",
        "COMMAND_INT",
        "FILE_TRANSFER_PROTOCOL",
        "PARAM_REQUEST_LIST",
        "PARAM_REQUEST_READ",
        "PARAM_SET",
    )
)


def next_output_after(next_output: float, t: float, rate: float) -> float:
    """When the next answer is due, the estimate at ``t`` answered (the one due at
    ``next_output``), at ``rate`` answers a second (``output.attitude_rate``; 0: every
    estimate is answered, and nothing changes). The grid is kept; after a pause it
    restarts rather than bursts to catch up."""
    if rate <= 0.0:
        return next_output
    period = 1.0 / rate
    return max(next_output + period, t + 0.5 * period)


def heartbeats_after(stamps: Any, next_us: int, period_us: int) -> tuple[list[int], int]:
    """Of records with these times (µs of record time, in order: one, or a block's), those
    after which a HEARTBEAT of mavest's goes out, while a vehicle is known: the first at
    or past ``next_us``, the next at or past one ``period_us`` after that record's time;
    and when the next is then due. A record from before the last HEARTBEAT's time (the
    recording clock set back) is one too, and the schedule starts again from it: else
    none would go out until the clock came back to where it had been."""
    if isinstance(stamps, int):  # one record: no array to build
        return ([0], stamps + period_us) if _beat_due(stamps, next_us, period_us) else ([], next_us)
    stamps = np.asarray(stamps)
    beats: list[int] = []
    position = 0
    while True:
        due = np.flatnonzero(_beat_due(stamps[position:], next_us, period_us))
        if not due.shape[0]:
            return beats, next_us
        position += int(due[0])
        beats.append(position)
        next_us = int(stamps[position]) + period_us
        position += 1


def _beat_due(stamps: Any, next_us: int, period_us: int) -> Any:
    """Whether a HEARTBEAT is due after a record of this time (a number, or an array):
    at or past ``next_us``, or from before the last one (the clock set back)."""
    return (stamps >= next_us) | (stamps < next_us - period_us)


def usable_reference(euler: Any) -> Any:
    """Whether a reference attitude (the autopilot's, the simulator's truth: its roll,
    pitch, yaw; or an (N, 3) array of them) can be compared with: every angle finite
    and within a turn (a NaN would make the whole comparison NaN, 1e30 rad its RMS)."""
    with np.errstate(invalid="ignore"):
        return np.all(np.abs(np.asarray(euler)) <= 2.0 * math.pi, axis=-1)


# the angles a comparison takes for an estimate made before the filter had an attitude
_NO_ATTITUDE = (math.nan, math.nan, math.nan)


def answerable(flags: Any) -> Any:
    """Whether an estimate is answered to the vehicle at all: only once the filter has
    an attitude (before, it would send the level attitude it starts from as if it knew
    it). The step's flags: a number, or an array of them."""
    return flags & StepFlags.NOT_INITIALISED == 0


def answers_due(t: Any, next_output: float, rate: float) -> tuple[np.ndarray, float]:
    """Which of these answerable estimates (their times, ascending: one, or a block's)
    are answered at ``rate`` answers a second, the next due at ``next_output``; and when
    the next is due after them (:func:`next_output_after`, after each answer)."""
    if isinstance(t, float):  # one estimate (the live path): no arrays to build
        if t >= next_output:
            return _FIRST, next_output_after(next_output, t, rate)
        return _NONE, next_output
    t = np.asarray(t, dtype=np.float64)
    if rate <= 0.0:  # every one (the grid does not move)
        return np.flatnonzero(t >= next_output), next_output
    chosen = []
    for i, ti in enumerate(t.tolist()):
        if ti >= next_output:
            chosen.append(i)
            next_output = next_output_after(next_output, ti, rate)
    return np.array(chosen, dtype=np.int64), next_output


_FIRST = np.zeros(1, dtype=np.int64)
_NONE = np.zeros(0, dtype=np.int64)
_FIRST.flags.writeable = False


def autopilot_time(time_boot_ms: Any) -> Any:
    """An autopilot's ATTITUDE's time (s) on its stream's timeline, from its
    ``time_boot_ms`` (a number, or an array of them)."""
    return time_boot_ms * 1e-3


def autopilot_restarted(t: Any, last_t: Any) -> Any:
    """Whether an autopilot's ATTITUDE at ``t`` was sent before the autopilot restarted,
    its stream's last estimate being at ``last_t`` (None or NaN: none yet, so not);
    numbers, or arrays of them."""
    return last_t is not None and t < last_t - AUTOPILOT_RESTART_LAG


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink2.enums[enum].get(value)
    return entry.name if entry is not None else str(value)


def is_fixed_wing(mav_type: int) -> bool:
    """Whether a HEARTBEAT's ``type`` (MAV_TYPE) flies on wings (fixed wing, the
    VTOLs, gliders): such a vehicle's samples may take the airspeed correction."""
    return mav_type in _FIXED_WING_TYPES


_FIXED_WING_TYPES = frozenset(
    getattr(mavlink2, name)
    for name in (
        "MAV_TYPE_FIXED_WING",
        "MAV_TYPE_VTOL_TAILSITTER_DUOROTOR",
        "MAV_TYPE_VTOL_TAILSITTER_QUADROTOR",
        "MAV_TYPE_VTOL_TILTROTOR",
        "MAV_TYPE_VTOL_FIXEDROTOR",
        "MAV_TYPE_VTOL_TAILSITTER",
        "MAV_TYPE_VTOL_TILTWING",
        "MAV_TYPE_GLIDER",
    )
    if hasattr(mavlink2, name)
)


# the step flags on which a stream's heading source is said again (report_heading)
HEADING_EVENTS = (
    StepFlags.HEADING_ALIGNED | StepFlags.HEADING_REOPENED | StepFlags.MAG_REFERENCE_CHANGED
)


# the magnetometer readings the filter did not take (the rest it took: a magnetometer update
# looked at them)
MAG_NOT_TAKEN = StepFlags.MAG_BETWEEN_UPDATES | StepFlags.MAG_SET_ASIDE

# the step flags of the estimator's health checks: each is news (report_health)
HEALTH_EVENTS = (
    StepFlags.TILT_REOPENED
    | StepFlags.DIVERGED
    | StepFlags.UNHEALTHY_RESET
    | StepFlags.CLIP_REALIGNED
)


def report_health(stream: Stream, flags: int, t: float) -> None:
    """Count and say what the estimator's health checks did (rare: each is news)."""
    stats = stream.stats
    if flags & StepFlags.TILT_REOPENED:
        stats.tilt_reopened += 1
        log.info(
            "%s: t=%.1f s: accelerometer disturbed for %g s: tilt uncertain again",
            *(stream.key, t, stream.estimator.config.accel_max_disturbance_time),
        )
    if flags & StepFlags.DIVERGED:
        stats.diverged += 1
        log.warning(
            "%s: t=%.1f s: diverged (the accelerometer contradicts the attitude again within "
            "%g s of reopening tilt): re-initialised from this sample",
            *(stream.key, t, stream.estimator.config.divergence_window),
        )
    if flags & StepFlags.CLIP_REALIGNED:
        stats.clip_realigned += 1
        log.warning(
            "%s: t=%.1f s: calm again after the gyro clipped: tilt re-aligned from the "
            "accelerometer",
            *(stream.key, t),
        )
    if flags & StepFlags.UNHEALTHY_RESET:
        stats.unhealthy += 1
        log.warning(
            "%s: t=%.1f s: the filter's state failed its health check (not finite, covariance "
            "not positive definite or out of bounds): re-initialised from this sample",
            *(stream.key, t),
        )


def report_accel_unit(stream: Stream, samples: int, problem: str | None) -> None:
    """Count samples the filter did not start on because the accelerometer reads g in
    another unit than m/s²; the first time, say so (``problem``: the estimator's
    :attr:`~mavest.estimator.Estimator.accel_unit_problem`, what unit and the factor)."""
    stats = stream.stats
    if not stats.accel_wrong_unit:
        log.warning("%s: %s: no attitude until it reads m/s²", stream.key, problem)
    stats.accel_wrong_unit += samples


def report_realigned(stream: Stream, t: float) -> None:
    """Count and say that a gap before the sample at t made the filter re-align."""
    stats = stream.stats
    stats.realigned += 1
    gap = t - (stats.last_t if stats.last_t is not None else t)
    log.warning("%s: no samples for %.2f s: attitude re-aligned", stream.key, gap)


# The steps book_step says something of, whatever else holds (besides the heading's
# source, said once when due: heading_source_due).
_NEWS = StepFlags.GAP_REALIGNED | HEALTH_EVENTS | HEADING_EVENTS


def is_news(flags: Any) -> Any:
    """Whether a step (its flags; or a block's, element-wise) is one :func:`book_step`
    reports on, whatever the stream's state."""
    return (flags & _NEWS) != 0


def heading_source_due(stream: Stream, span: Any) -> Any:
    """Whether the heading's source is to be said for want of a magnetometer: not said
    yet, and the stream has estimated for ``span`` s (one time, or a block's) without
    the magnetometer setting heading."""
    return (not stream.heading_source_reported) & (span >= MAG_WAIT)


def book_step(stream: Stream, flags: int, t: float) -> None:
    """Keep and say what one step, estimated at ``t``, did, in this order: a
    realignment after a gap, the health checks' doings, the stream's first and last
    times (which the heading's report reads), the heading's source and changes.

    The replay's fast path calls it for the steps of a block that :func:`is_news` or
    :func:`heading_source_due` single out, with the stream's last time as it stood
    before each; the others change nothing here but the last time."""
    stats = stream.stats
    if flags & StepFlags.GAP_REALIGNED:
        report_realigned(stream, t)
    if flags & HEALTH_EVENTS:
        report_health(stream, flags, t)
    if stats.first_t is None:
        stats.first_t = t
    stats.last_t = t
    if flags & HEADING_EVENTS or not stream.heading_source_reported:
        report_heading(stream, flags)


def _count(mask: Any) -> int:
    """How many are true: a bool, or a block's mask."""
    return int(mask) if isinstance(mask, bool) else int(np.count_nonzero(mask))


def count_estimated(stats: StreamStats, flags: Any, mag_usable: Any, mag_used: Any) -> None:
    """Count estimated steps: one step's flags and whether its sample had a usable
    magnetometer reading and the step used it, or a block's arrays of them; the gravity
    updates due, and those the accelerometer's norm kept out. A reading
    is taken unless the step set it aside or it came between the magnetometer's
    updates (MAG_NOT_TAKEN), or the filter had no attitude to take it into
    (NOT_INITIALISED: an accelerometer it cannot start on); the GPS-aided ones had
    the vehicle's acceleration removed (ACCEL_AIDED)."""
    stats.estimated += 1 if isinstance(mag_usable, bool) else len(mag_usable)
    stats.not_started += _count((flags & StepFlags.NOT_INITIALISED) != 0)
    stats.gps_aided += _count((flags & StepFlags.ACCEL_AIDED) != 0)
    update = (flags & (StepFlags.BETWEEN_UPDATES | StepFlags.NOT_INITIALISED)) == 0
    stats.updates += _count(update)
    # (of those updates: a sample the filter could not start on is none)
    stats.accel_far_from_g += _count(update & ((flags & StepFlags.ACCEL_REJECTED_NORM) != 0))
    taken = mag_usable & ((flags & (MAG_NOT_TAKEN | StepFlags.NOT_INITIALISED)) == 0)
    stats.mag_usable += _count(mag_usable)
    stats.mag_taken += _count(taken)
    stats.mag_used += _count(taken & mag_used)


def report_clipped(stream: Stream, flags: Any, t: Any) -> None:
    """Count the estimated samples whose gyro clipped (one step's flags and time, or a
    block's arrays of them), and say the first: the rotation they missed is unknown, and
    tilt is re-aligned only once the vehicle is calm again (CLIP_REALIGNED), which a gyro
    clipped throughout never is."""
    stats = stream.stats
    clipped = (flags & StepFlags.GYRO_CLIPPED) != 0
    count = _count(clipped)
    if count and not stats.gyro_clipped:
        first = t if isinstance(clipped, bool) else t[np.flatnonzero(clipped)[0]]
        log.warning(
            "%s: t=%.1f s: the gyro clipped (an axis beyond gyro_clip = %g rad/s): the "
            "rotation it missed is unknown; tilt re-aligns when the vehicle is calm again",
            *(stream.key, first, stream.estimator.config.gyro_clip),
        )
    stats.gyro_clipped += count


def report_heading(stream: Stream, flags: int) -> None:
    """Say once where heading comes from, and when the magnetometer's role changes."""
    stats = stream.stats
    if flags & StepFlags.HEADING_ALIGNED:
        if not stream.heading_source_reported:
            log.info("%s: heading from the magnetometer (9-D)", stream.key)
        stream.heading_source_reported = True
    elif heading_source_due(stream, stats.span):
        log.info(
            "%s: no magnetometer in the IMU messages: heading is free (6-D), yaw will drift",
            stream.key,
        )
        stream.heading_source_reported = True
    if flags & StepFlags.HEADING_REOPENED:
        log.info("%s: magnetometer rejected too long: trusting it again", stream.key)
    if flags & StepFlags.MAG_REFERENCE_CHANGED:
        log.info("%s: a steady new magnetic field became the reference", stream.key)


def _rejection_reason(sample: ImuSample) -> str:
    """Why a sample is not one to estimate from (for one that is not)."""
    values = (*sample.gyro, *sample.accel)
    if not all(math.isfinite(v) for v in values):
        return "a value not finite (NaN or infinity)"
    if sample.saturated:
        return "saturated: a gyro or accelerometer axis at its integer field's limit"
    if not reads_something(sample.accel):
        # no real accelerometer reads exactly nothing on three axes (noise alone moves
        # it): the message is empty, e.g. ArduPilot's SCALED_IMU3 without a third IMU
        return "accelerometer all zero: no sensor data"
    if sample.ticks * sample.tick >= MAX_TIME:
        return f"its time beyond {MAX_TIME:.3g} s (285 years): no clock's"
    if within(sample.gyro, MAX_GYRO):
        # one g in another unit, as a vehicle at rest (as logs begin) gives it: the
        # estimator's rule for telling the unit, which it never sees such a sample for
        unit = accel_unit_named(math.hypot(*sample.accel), STANDARD_GRAVITY)
        if unit is not None:
            name, scale = unit
            return (
                f"accelerometer beyond any sensor's range: looks like {name}, mavest wants "
                f"m/s² (multiply by {scale:.6g})"
            )
    return "beyond any sensor's range"


def reject_sample(stream: Stream, reason: str) -> None:
    """Count a rejected sample by its reason; the first of each reason is said in the log."""
    stats = stream.stats
    stats.rejected += 1
    count = stats.rejected_reasons.get(reason, 0)
    stats.rejected_reasons[reason] = count + 1
    if count == 0:
        log.warning(
            "%s: sample rejected, %s (all such are counted as rejected)", stream.key, reason
        )


# The sample rules, written once for one sample (an axis: a number) and for a block of
# them (an axis: a column), so that the live path and the replay's blocks decide alike:
# the element-wise operators give a bool on numbers and a mask on columns.
Axes = tuple[Any, Any, Any]


def within(axes: Axes, limit: float) -> Any:
    """Whether every axis is within ±``limit`` (a NaN fails every comparison: it is not)."""
    x, y, z = axes
    return (abs(x) <= limit) & (abs(y) <= limit) & (abs(z) <= limit)


def reads_something(axes: Axes) -> Any:
    """Whether any axis is not zero: no real sensor reads exactly nothing on three axes
    (noise alone moves it), so all zero is an empty field, not a measurement."""
    x, y, z = axes
    return (x != 0.0) | (y != 0.0) | (z != 0.0)


def valid_sample(gyro: Axes, accel: Axes, saturated: Any, time: Any) -> Any:
    """Whether an IMU sample is one to estimate from: both sensors within any sensor's
    range, neither at its integer field's limit, an accelerometer that reads something,
    a time (s, as its message gives it) that a vehicle's clock can read."""
    not_saturated = saturated ^ True  # (``not``, for a bool and for a mask alike)
    return (
        within(gyro, MAX_GYRO)
        & within(accel, MAX_ACCEL)
        & not_saturated
        & reads_something(accel)
        & (time < MAX_TIME)
    )


def usable_mag(mag: Axes) -> Any:
    """Whether a magnetometer reading is used: not all zero (no compass fitted), not absurd."""
    return reads_something(mag) & within(mag, MAX_MAG)


def _who(vehicle: Vehicle) -> str:
    return f"vehicle {vehicle.system}/{vehicle.component}"


# Beyond this share of the gravity updates kept out by the accelerometer's norm, a run
# says so: tilt was then seldom observed (a vehicle always accelerating, or an attitude
# lost to a gyro offset far beyond the filter's prior, which spins the low-passed force)
ACCEL_FAR_SHARE = 0.5


def never_started(stats: StreamStats) -> bool:
    """Whether a stream was estimated and the filter never had an attitude, for a
    reason not already said (the accelerometer in another unit is said as it comes)."""
    started = stats.not_started < stats.estimated
    return stats.estimated > 0 and not started and not stats.accel_wrong_unit


def accel_seldom_gravity(stats: StreamStats) -> float | None:
    """The share of a stream's gravity updates that its accelerometer's norm kept out,
    when beyond :data:`ACCEL_FAR_SHARE` (a run says so); else None."""
    share = stats.accel_far_from_g / stats.updates if stats.updates else 0.0
    return share if share > ACCEL_FAR_SHARE else None
