"""The simulated vehicle: a JSBSim flight speaking MAVLink like a flight controller.

Two forms. :func:`write_flight_tlog` writes a flight to a tlog as fast as it
can: HEARTBEAT at 1 Hz, the IMU message per sample and SIMSTATE (the flight
model's true attitude, as ArduPilot's simulator sends it) right after each,
VFR_HUD (airspeed) and GPS (GPS_RAW_INT, GLOBAL_POSITION_INT with noisy
velocity) at 10 Hz, and the vehicle's COMPASS_DEC as a PARAM_VALUE.
:func:`stream_flight` sends the same in real time over a MAVLink link,
honours MAV_CMD_SET_MESSAGE_INTERVAL for its IMU message, and scores every
ATTITUDE that comes back against the truth of the sample it answers (matched
by ``time_boot_ms``): answered fraction, roll/pitch error, latency.

The IMU is what the autopilots send: ArduPilot's RAW_IMU quantised to integer
mG, mrad/s and mgauss, or PX4's HIGHRES_IMU in float SI; each with white noise
and the bias the autopilot leaves in (:class:`~mavest.sim.flight.ImuErrors`). Streaming, the
flight model runs at 1 kHz and each IMU sample is the mean of the model
samples since the last one, the way an autopilot filters before it decimates.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mavest import so3
from mavest.evaluation.online import wrap_angle
from mavest.mavlink.links import Link, make_link, parse_endpoint
from mavest.mavlink.messages import IMU_FORMATS, MAVLink, mavlink2
from mavest.mavlink.tlog import TlogError, TlogWriter
from mavest.service.signals import stop_on_signals
from mavest.sim.flight import Flight, FlightModel, ImuErrors, NoisyImu
from mavest.sim.kinematic import EARTH_FIELD_NED, rotate_to_body

log = logging.getLogger("mavest")

BOOT_OFFSET = 20.0  # s the flight controller had been up when the flight starts
TLOG_EPOCH_US = 1_767_225_600_000_000  # 2026-01-01 00:00 UTC: files are reproducible
STREAM_MODEL_RATE = 1000.0  # Hz: the streaming vehicle's flight model
HUD_PERIOD = 0.1  # s between VFR_HUD messages (airspeed)
GPS_PERIOD = 0.1  # s between GPS_RAW_INT and GLOBAL_POSITION_INT (10 Hz, a u-blox's rate)
GPS_VELOCITY_SIGMA = 0.05  # m/s per NED axis: a GNSS receiver's Doppler velocity noise
# The simulated field's azimuth (EARTH_FIELD_NED), which the vehicle reports as its
# COMPASS_DEC parameter the way an autopilot that looked it up from its position does.
DECLINATION = math.atan2(EARTH_FIELD_NED[1], EARTH_FIELD_NED[0])
GPS_NOISE_STREAM = 7  # the GPS noise's generator: SeedSequence([seed, this])


@dataclass(frozen=True)
class Autopilot:
    """How a flight controller of this kind identifies itself and sends its IMU."""

    name: str
    imu_message: str
    autopilot: int  # MAV_AUTOPILOT_*
    system: int = 1
    component: int = 1


AUTOPILOTS = {
    "ardupilot": Autopilot("ardupilot", "RAW_IMU", mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA),
    "px4": Autopilot("px4", "HIGHRES_IMU", mavlink2.MAV_AUTOPILOT_PX4),
}


class VehicleEncoder:
    """The vehicle's packets: IMU in the autopilot's units, SIMSTATE, HEARTBEAT, COMMAND_ACK."""

    def __init__(self, autopilot: Autopilot) -> None:
        self.autopilot = autopilot
        self._mav = MAVLink(None, srcSystem=autopilot.system, srcComponent=autopilot.component)
        self._format = IMU_FORMATS[autopilot.imu_message]

    def imu(self, t_boot: float, gyro: np.ndarray, accel: np.ndarray, mag: np.ndarray) -> bytes:
        fmt = self._format
        if fmt.message == "RAW_IMU":  # int16 fields: round and saturate, as the firmware does
            a = _int16(accel / fmt.accel_scale)
            g = _int16(gyro / fmt.gyro_scale)
            m = _int16(mag / fmt.mag_scale)
            return self._mav.raw_imu_encode(round(t_boot * 1e6), *a, *g, *m, 0, 3500).pack(
                self._mav
            )
        a = accel / fmt.accel_scale
        g = gyro / fmt.gyro_scale
        m = mag / fmt.mag_scale
        return self._mav.highres_imu_encode(
            round(t_boot * 1e6),
            *map(float, a),
            *map(float, g),
            *map(float, m),
            1013.25,
            0.0,
            400.0,
            35.0,
            0x1FFF,
            0,
        ).pack(self._mav)

    def simstate(
        self, euler: np.ndarray, accel: np.ndarray, gyro: np.ndarray, lat: float, lon: float
    ) -> bytes:
        return self._mav.simstate_encode(
            *map(float, euler),
            *map(float, accel),
            *map(float, gyro),
            round(lat * 1e7),
            round(lon * 1e7),
        ).pack(self._mav)

    def attitude(self, t_boot: float, euler: np.ndarray, rates: np.ndarray) -> bytes:
        """ATTITUDE: the autopilot's own estimate (here the flight model's truth)."""
        return self._mav.attitude_encode(
            math.floor(t_boot * 1e3 + 1e-6), *map(float, euler), *map(float, rates)
        ).pack(self._mav)

    def vfr_hud(self, flight: Flight, i: int, yaw: float) -> bytes:
        """Airspeed and the rest of the head-up display, as autopilots send it (~10 Hz)."""
        velocity = flight.velocity[i]
        heading = math.degrees(yaw) % 360.0
        return self._mav.vfr_hud_encode(
            float(flight.airspeed[i]),
            float(math.hypot(velocity[0], velocity[1])),
            round(heading) % 360,
            60,
            float(flight.altitude[i]),
            float(-velocity[2]),
        ).pack(self._mav)

    def gps(self, t_boot: float, flight: Flight, i: int, velocity: np.ndarray) -> list[bytes]:
        """GPS_RAW_INT (3-D fix) and GLOBAL_POSITION_INT with ``velocity`` (m/s NED)."""
        lat = round(float(flight.latitude[i]) * 1e7)
        lon = round(float(flight.longitude[i]) * 1e7)
        alt = round(float(flight.altitude[i]) * 1000.0)
        cm = [int(v) for v in np.clip(np.rint(velocity * 100.0), -32768, 32767)]
        ground_speed = math.hypot(cm[0], cm[1])
        course = round(math.degrees(math.atan2(cm[1], cm[0])) * 100.0) % 36000
        raw = self._mav.gps_raw_int_encode(
            round(t_boot * 1e6), 3, lat, lon, alt, 90, 150, round(ground_speed), course, 14
        )
        position = self._mav.global_position_int_encode(
            round(t_boot * 1e3), lat, lon, alt, alt, *cm, course
        )
        return [raw.pack(self._mav), position.pack(self._mav)]

    def declination(self) -> bytes:
        """PARAM_VALUE COMPASS_DEC, as an autopilot reports its parameters."""
        return self._mav.param_value_encode(
            b"COMPASS_DEC", DECLINATION, mavlink2.MAV_PARAM_TYPE_REAL32, 1, 0
        ).pack(self._mav)

    def heartbeat(self) -> bytes:
        return self._mav.heartbeat_encode(
            mavlink2.MAV_TYPE_FIXED_WING,
            self.autopilot.autopilot,
            mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            0,
            mavlink2.MAV_STATE_ACTIVE,
        ).pack(self._mav)

    def command_ack(
        self, command: int, result: int, target_system: int, target_component: int
    ) -> bytes:
        return self._mav.command_ack_encode(
            command, result, 0, 0, target_system, target_component
        ).pack(self._mav)


def _int16(values: np.ndarray) -> list[int]:
    return [int(v) for v in np.clip(np.rint(values), -32768, 32767)]


def _magnetometer(q_true: np.ndarray) -> np.ndarray:
    """The Earth's field in the body frame (µT) for (N, 4) attitudes."""
    return rotate_to_body(q_true, np.broadcast_to(EARTH_FIELD_NED, (len(q_true), 3)).copy())


# --------------------------------------------------------------------------
# a flight written to a tlog
# --------------------------------------------------------------------------


def _flight_chunks(
    model: FlightModel, imu: NoisyImu, seconds: float
) -> Iterator[tuple[Flight, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``seconds`` of ``model``'s flight at its rate (both ends sampled), 10 s at a time
    (an hour at 1 kHz never sits in memory): each chunk's flight, the gyro and
    accelerometer ``imu`` measures, the true ZYX angles and the magnetometer's field."""
    rate = model.rate
    total = round(seconds * rate) + 1
    chunk = max(1, round(10.0 * rate))
    samples = 0
    while samples < total:
        flight = model.advance(min(chunk, total - samples))
        gyro, accel = imu.measure(flight.gyro, flight.accel)
        yield (
            flight,
            gyro,
            accel,
            so3.euler_zyx_from_quats(flight.q_true),
            _magnetometer(flight.q_true),
        )
        samples += len(flight)


def flight_records(
    seconds: float,
    rate: float,
    autopilot: Autopilot = AUTOPILOTS["ardupilot"],
    seed: int = 1,
    errors: ImuErrors | None = None,
    described: list[str] | None = None,
) -> Iterator[tuple[int, bytes]]:
    """A simulated flight's tlog records, (timestamp µs, packet), generated 10 s at a
    time (an hour at 1 kHz never sits in memory); ``described`` gets a line saying
    what was generated once the last record is out."""
    model = FlightModel(rate, seed)  # (before the first record: see write_flight_tlog)
    imu = NoisyImu(errors, rate, seed)
    encoder = VehicleEncoder(autopilot)
    next_heartbeat = 0.0
    next_hud = 0.0
    next_gps = 0.0
    gps_noise = np.random.default_rng([seed, GPS_NOISE_STREAM])
    samples = 0
    yield TLOG_EPOCH_US, encoder.declination()
    for flight, gyro, accel, euler, mag in _flight_chunks(model, imu, seconds):
        for i in range(len(flight)):
            t = float(flight.t[i])
            stamp = TLOG_EPOCH_US + round(t * 1e6)
            if t >= next_heartbeat:
                yield stamp, encoder.heartbeat()
                next_heartbeat += 1.0
            yield stamp, encoder.imu(t + BOOT_OFFSET, gyro[i], accel[i], mag[i])
            yield (
                stamp,
                encoder.simstate(
                    euler[i],
                    flight.accel[i],
                    flight.gyro[i],
                    flight.latitude[i],
                    flight.longitude[i],
                ),
            )
            if t >= next_hud:
                yield stamp, encoder.vfr_hud(flight, i, euler[i, 2])
                next_hud += HUD_PERIOD
            if t >= next_gps:
                velocity = flight.velocity[i] + gps_noise.normal(0.0, GPS_VELOCITY_SIGMA, 3)
                for packet in encoder.gps(t + BOOT_OFFSET, flight, i, velocity):
                    yield stamp, packet
                next_gps += GPS_PERIOD
        samples += len(flight)
    if described is not None:
        described.append(
            f"{samples} {autopilot.imu_message} at {rate:g} Hz over {seconds:g} s, with "
            f"SIMSTATE (truth) per sample, VFR_HUD at {1 / HUD_PERIOD:g} Hz and GPS at "
            f"{1 / GPS_PERIOD:g} Hz; gyro bias "
            f"{', '.join(f'{math.degrees(b):+.2f}' for b in imu.gyro_bias)} °/s"
        )


def write_flight_tlog(
    path: str | Path,
    seconds: float,
    rate: float,
    autopilot: Autopilot = AUTOPILOTS["ardupilot"],
    seed: int = 1,
    errors: ImuErrors | None = None,
) -> str:
    """Write a simulated flight to ``path``; return a line describing it."""
    described: list[str] = []
    _write_records(path, flight_records(seconds, rate, autopilot, seed, errors, described))
    return f"wrote {path}: {described[0]}"


def _write_records(path: str | Path, records: Iterator[tuple[int, bytes]]) -> None:
    """Write a simulated log's records to ``path``. The first record builds the flight
    model before the file is opened: a simulator that cannot start leaves no file."""
    first = next(records, None)
    with TlogWriter(path) as tlog:
        for stamp, packet in itertools.chain([first] if first else [], records):
            tlog.write(stamp, packet)
            if tlog.error is not None:  # (a full disk: the file ends at a whole record)
                break
        tlog.flush()
    if tlog.error is not None:  # (said as it happened; the command ends on it)
        raise TlogError(f"{path}: the simulated flight is not all written")


def autopilot_records(
    seconds: float,
    rate: float,
    autopilot: Autopilot = AUTOPILOTS["ardupilot"],
    seed: int = 1,
    attitude_every: int = 20,
) -> Iterator[tuple[int, bytes]]:
    """What an autopilot's telemetry log holds at a high IMU rate, (timestamp µs,
    packet): HEARTBEAT at 1 Hz, the IMU message per sample, and the autopilot's own
    ATTITUDE (the flight model's truth) after every ``attitude_every``-th sample. No
    simulator truth, GPS or airspeed: a log of what a ground station records."""
    model = FlightModel(rate, seed)
    imu = NoisyImu(None, rate, seed)
    encoder = VehicleEncoder(autopilot)
    next_heartbeat = 0.0
    sample = 0
    for flight, gyro, accel, euler, mag in _flight_chunks(model, imu, seconds):
        for i in range(len(flight)):
            t = float(flight.t[i])
            stamp = TLOG_EPOCH_US + round(t * 1e6)
            if t >= next_heartbeat:
                yield stamp, encoder.heartbeat()
                next_heartbeat += 1.0
            yield stamp, encoder.imu(t + BOOT_OFFSET, gyro[i], accel[i], mag[i])
            if sample % attitude_every == 0:
                yield stamp, encoder.attitude(t + BOOT_OFFSET, euler[i], flight.gyro[i])
            sample += 1


def write_autopilot_tlog(
    path: str | Path,
    seconds: float,
    rate: float,
    autopilot: Autopilot = AUTOPILOTS["ardupilot"],
    seed: int = 1,
    attitude_every: int = 20,
) -> None:
    """Write :func:`autopilot_records` to ``path`` (no file if the simulator cannot start)."""
    _write_records(path, autopilot_records(seconds, rate, autopilot, seed, attitude_every))


def write_resting_tlog(path: str | Path, seconds: float = 2.0, rate: float = 200.0) -> None:
    """A tlog of an ArduPilot vehicle at rest, level: a HEARTBEAT, then RAW_IMU (1 g up
    in mG, no rotation) at ``rate``. No flight model: what warms a replay up."""
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    with TlogWriter(path) as tlog:
        heartbeat = mav.heartbeat_encode(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0
        )
        tlog.write(0, heartbeat.pack(mav))
        for k in range(1, round(seconds * rate) + 1):
            us = round(k * 1e6 / rate)
            raw = mav.raw_imu_encode(us, 0, 0, -1000, 0, 0, 0, 200, 0, 400, 0, 3500)
            tlog.write(us, raw.pack(mav))


# --------------------------------------------------------------------------
# a vehicle streaming in real time
# --------------------------------------------------------------------------


@dataclass
class VehicleReport:
    """What the streaming vehicle saw of the estimates sent back to it."""

    sent: int = 0
    answered: int = 0  # IMU samples answered by at least one ATTITUDE
    duplicates: int = 0  # ATTITUDE for a sample already answered
    unmatched: int = 0  # ATTITUDE for no sample sent (or too old to remember)
    roll_rms: float = math.nan  # deg, after settle_time
    pitch_rms: float = math.nan
    scored: int = 0
    latency_p50_ms: float = math.nan
    latency_p99_ms: float = math.nan
    latency_max_ms: float = math.nan
    rates: list[float] = field(default_factory=list)  # Hz, the initial one and every change
    answerers: list[str] = field(default_factory=list)
    seconds: float = 0.0
    settle_time: float = 5.0

    @property
    def answered_fraction(self) -> float:
        return self.answered / self.sent if self.sent else 0.0

    def describe(self) -> str:
        rates = " → ".join(f"{r:g}" for r in self.rates)
        lines = [
            f"simulated vehicle: {self.sent} IMU samples sent over {self.seconds:.1f} s "
            f"(rate {rates} Hz)",
            f"  answered with ATTITUDE: {self.answered} ({100 * self.answered_fraction:.2f} %)"
            + (f" by {', '.join(self.answerers)}" if self.answerers else ""),
        ]
        if self.scored:
            lines.append(
                f"  vs truth after {self.settle_time:g} s: roll {self.roll_rms:.3f}°, "
                f"pitch {self.pitch_rms:.3f}° RMS (n={self.scored})"
            )
            lines.append(
                f"  latency IMU sent → ATTITUDE received: p50 {self.latency_p50_ms:.3f} ms, "
                f"p99 {self.latency_p99_ms:.3f} ms, max {self.latency_max_ms:.3f} ms"
            )
        return "\n".join(lines)

    def to_json(self) -> str:
        data = asdict(self)
        data["answered_fraction"] = self.answered_fraction
        return json.dumps(data, indent=2, allow_nan=True)


class StreamingVehicle:
    """The vehicle's state while it streams; see :func:`stream_flight`."""

    def __init__(
        self,
        link: Link,
        rate: float,
        autopilot: Autopilot,
        seed: int,
        settle_time: float = 5.0,
    ) -> None:
        self.link = link
        self.autopilot = autopilot
        self.encoder = VehicleEncoder(autopilot)
        self.rate = rate
        self.model = FlightModel(STREAM_MODEL_RATE, seed)
        self.imu = NoisyImu(None, STREAM_MODEL_RATE, seed)
        self.settle_time = settle_time
        self.report = VehicleReport(rates=[rate], settle_time=settle_time)
        self._parsers: dict[Any, Any] = {}
        # time_boot_ms → (perf_counter when sent, true roll, pitch, flight time)
        self._sent: dict[int, tuple[float, float, float, float]] = {}
        self._sent_order: deque[int] = deque()
        self._answered: set[int] = set()
        self._latencies: list[float] = []
        self._squares = [0.0, 0.0]
        self._answerers: set[str] = set()
        self._accumulator = np.zeros(6)
        self._accumulated = 0
        self._next_emit = 0.0
        self._next_hud = 0.0
        self._next_gps = 0.0
        self._gps_noise = np.random.default_rng([seed, GPS_NOISE_STREAM])
        # load the compiled rotation kernels now, not while the first samples are due
        identity = np.array([1.0, 0.0, 0.0, 0.0])
        _magnetometer(identity[None])
        so3.euler_zyx_from_quat(identity)

    # ------------------------------------------------------------ receiving

    def on_bytes(self, link: Link, data: bytes, peer: Any) -> None:
        parser = self._parsers.get(peer)
        if parser is None:
            parser = self._parsers[peer] = MAVLink(None)
            parser.robust_parsing = True
        now = time.perf_counter()
        for message in parser.parse_buffer(data) or ():
            name = message._type
            if name == "ATTITUDE":
                self._on_attitude(message, now)
            elif name == "COMMAND_LONG":
                self._on_command(message)

    def _on_attitude(self, message: Any, now: float) -> None:
        header = message._header
        self._answerers.add(f"{header.srcSystem}/{header.srcComponent}")
        key = message.time_boot_ms
        sent = self._sent.get(key)
        if sent is None:
            self.report.unmatched += 1
            return
        if key in self._answered:
            self.report.duplicates += 1
            return
        self._answered.add(key)
        sent_at, roll, pitch, t = sent
        self._latencies.append(now - sent_at)
        if t >= self.settle_time:
            self._squares[0] += wrap_angle(message.roll - roll) ** 2
            self._squares[1] += (message.pitch - pitch) ** 2
            self.report.scored += 1

    def _on_command(self, message: Any) -> None:
        ours = message.target_system in (0, self.autopilot.system)
        if not ours:
            return
        header = message._header
        result = mavlink2.MAV_RESULT_UNSUPPORTED
        if message.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            wanted = getattr(mavlink2, f"MAVLINK_MSG_ID_{self.autopilot.imu_message}")
            if round(message.param1) != wanted:
                result = mavlink2.MAV_RESULT_DENIED
            elif message.param2 > 0:
                self.rate = min(1e6 / message.param2, STREAM_MODEL_RATE)
                self.report.rates.append(round(self.rate, 3))
                log.info(
                    "simulated vehicle: %s now at %g Hz", self.autopilot.imu_message, self.rate
                )
                result = mavlink2.MAV_RESULT_ACCEPTED
            else:
                result = mavlink2.MAV_RESULT_ACCEPTED  # 0: default rate, −1: off; keep ours
        self.link.send(
            self.encoder.command_ack(message.command, result, header.srcSystem, header.srcComponent)
        )

    # ------------------------------------------------------------ sending

    def send_due(self, now: float) -> None:
        """Step the flight model to ``now`` (s since start) and send the IMU samples due."""
        flight = self.model.advance_to(now)
        if not len(flight):
            return
        gyro, accel = self.imu.measure(flight.gyro, flight.accel)
        for i in range(len(flight)):
            self._accumulator[:3] += gyro[i]
            self._accumulator[3:] += accel[i]
            self._accumulated += 1
            t = float(flight.t[i])
            if t + 1e-9 < self._next_emit:
                continue
            self._next_emit += 1.0 / self.rate
            if self._next_emit < t:  # the rate went up: restart the grid
                self._next_emit = t + 1.0 / self.rate
            mean = self._accumulator / self._accumulated
            self._accumulator[:] = 0.0
            self._accumulated = 0
            self._send_sample(flight, i, t, mean[:3], mean[3:])

    def _send_sample(
        self, flight: Flight, i: int, t: float, gyro: np.ndarray, accel: np.ndarray
    ) -> None:
        euler = so3.euler_zyx_from_quat(flight.q_true[i])
        mag = _magnetometer(flight.q_true[i : i + 1])[0]
        t_boot = t + BOOT_OFFSET
        key = math.floor(t_boot * 1000.0 + 1e-6)
        packet = self.encoder.imu(t_boot, gyro, accel, mag)
        truth = self.encoder.simstate(
            euler, flight.accel[i], flight.gyro[i], flight.latitude[i], flight.longitude[i]
        )
        self._sent[key] = (time.perf_counter(), float(euler[0]), float(euler[1]), t)
        self._sent_order.append(key)
        while len(self._sent_order) > 20_000:  # answers older than that are not waited for
            self._sent.pop(self._sent_order.popleft(), None)
        self.link.send(packet)
        self.link.send(truth)
        if t >= self._next_hud:
            self.link.send(self.encoder.vfr_hud(flight, i, euler[2]))
            self._next_hud = t + HUD_PERIOD
        if t >= self._next_gps:
            velocity = flight.velocity[i] + self._gps_noise.normal(0.0, GPS_VELOCITY_SIGMA, 3)
            for gps_packet in self.encoder.gps(t_boot, flight, i, velocity):
                self.link.send(gps_packet)
            self._next_gps = t + GPS_PERIOD
        self.report.sent += 1

    def heartbeat(self) -> None:
        # COMPASS_DEC with each heartbeat: an autopilot sends it when asked (or when
        # a ground station fetches its parameters), which a late listener may miss
        self.link.send(self.encoder.heartbeat())
        self.link.send(self.encoder.declination())

    def finish(self, seconds: float) -> VehicleReport:
        report = self.report
        report.seconds = seconds
        report.answered = len(self._answered)
        report.answerers = sorted(self._answerers)
        if report.scored:
            report.roll_rms = math.degrees(math.sqrt(self._squares[0] / report.scored))
            report.pitch_rms = math.degrees(math.sqrt(self._squares[1] / report.scored))
        if self._latencies:
            latencies = np.array(self._latencies) * 1e3
            report.latency_p50_ms = float(np.percentile(latencies, 50))
            report.latency_p99_ms = float(np.percentile(latencies, 99))
            report.latency_max_ms = float(latencies.max())
        return report


async def stream_flight(
    connection: str,
    rate: float,
    autopilot: Autopilot = AUTOPILOTS["ardupilot"],
    seed: int = 1,
    seconds: float | None = None,
    stop: asyncio.Event | None = None,
    linger: float = 0.5,
) -> VehicleReport:
    """Fly and stream until ``seconds`` have passed or ``stop`` is set (SIGINT/SIGTERM
    when ``stop`` is not given); then wait ``linger`` s for the last answers."""
    link = make_link(parse_endpoint(connection))
    vehicle = StreamingVehicle(link, rate, autopilot, seed)
    with stop_on_signals(stop) as stopping:
        return await _stream(vehicle, link, autopilot, rate, seconds, stopping, linger)


async def _stream(
    vehicle: StreamingVehicle,
    link: Link,
    autopilot: Autopilot,
    rate: float,
    seconds: float | None,
    stop: asyncio.Event,
    linger: float,
) -> VehicleReport:
    await link.start(vehicle.on_bytes)
    log.info(
        "simulated %s vehicle %d/%d: %s at %g Hz to %s",
        autopilot.name,
        autopilot.system,
        autopilot.component,
        autopilot.imu_message,
        rate,
        link,
    )
    start = time.perf_counter()
    next_heartbeat = 0.0
    try:
        while not stop.is_set():
            now = time.perf_counter() - start
            if seconds is not None and now >= seconds:
                break
            if now >= next_heartbeat:
                vehicle.heartbeat()
                next_heartbeat += 1.0
            vehicle.send_due(now)
            await asyncio.sleep(0.0005)
        await asyncio.sleep(linger)
    finally:
        link.close()
    return vehicle.finish(time.perf_counter() - start)
