"""An onboard log as a telemetry log: its samples as MAVLink records, packed in bulk.

Replaying a DataFlash or ULog file goes through the very machinery a tlog goes
through (sample checks, stream clocks, aiding, comparisons, recorder, output tlog,
the compiled fast path): :func:`to_tlog_bytes` writes the log's samples as the
messages a vehicle would send with them, and the replay reads those bytes as it
reads a tlog's. Nothing about the estimate is decided here.

What each sample becomes (MAVLink 2, ardupilotmega dialect, all from one
``system``/``component``):

* an IMU sample: HIGHRES_IMU, ``time_usec`` its boot time (from the log's first
  millisecond when the log's clock is beyond ``time_boot_ms``'s 49.7 days: a PX4
  simulator's Unix time; every message's own time alike), ``id`` its instance,
  accelerometer m/s², gyro rad/s, and the magnetometer (gauss) of the latest
  field sample at or before it: of the same instance, or else of the lowest
  instance logged (every magnetometer is logged in the body frame; an autopilot
  uses its primary compass whichever IMU it takes). ``fields_updated`` marks gyro
  and accelerometer always, the magnetometer only on the first IMU sample after
  each new field sample (as PX4 sends HIGHRES_IMU): a reading is taken once, not
  once per IMU sample. Before the first field sample the magnetometer fields are NaN;
* the autopilot's attitude: ATTITUDE (``time_boot_ms``, roll, pitch, yaw);
* a simulator's truth: SIMSTATE (roll, pitch, yaw);
* a GPS fix report: GPS_RAW_INT (``fix_type``); a GPS velocity: GLOBAL_POSITION_INT
  (vx, vy, vz in cm/s, rounded, within int16);
* an airspeed: VFR_HUD (``airspeed``);
* HEARTBEAT (``type`` the vehicle type, ``autopilot`` ARDUPILOTMEGA or PX4) at the
  first sample's time and every second after (through a gap of up to a minute, not a
  longer one); PARAM_VALUE COMPASS_DEC (rad) at the first sample's time when the log
  gives the declination.

Records are in time order; at equal times in the order of that list, HEARTBEAT and
PARAM_VALUE first (a SIMSTATE, GPS or airspeed message is taken at the time of the
IMU sample before it, so it follows the IMU sample of its own time). Sequence numbers
count the records in that order. The record stamps (a tlog's Unix time, µs) are the
boot times plus a fixed base, 2000-01-01T00:00:00Z: an onboard log's clock is the
autopilot's boot clock, and a fixed base makes the same log give the same bytes. Where
the boot clock went back and stayed (a new timeline), the stamps go on: the new
timeline's first record a second after the last of the one before, its messages' own
times as logged, as a ground station records a vehicle that restarted.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mavest import timeline
from mavest._jit import inplace_exact_kernel
from mavest.mavlink import bulk
from mavest.mavlink.messages import HIGHRES_INERTIAL_BITS, HIGHRES_MAG_BITS, UNIT_TO_SI, mavlink2
from mavest.onboard.model import OnboardLog, Series

__all__ = ["RECORD_EPOCH_US", "to_tlog_bytes"]

#: The Unix time (µs) a log's boot time 0 is stamped with: 2000-01-01T00:00:00Z.
RECORD_EPOCH_US = 946_684_800 * 10**6

_HEARTBEAT_PERIOD_US = 1_000_000
_TIMELINE_GAP_US = _HEARTBEAT_PERIOD_US  # between a timeline's last record and the next's first
_LATEST_OFFSET_US = 2**62

_AUTOPILOTS = {
    "ArduPilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
    "PX4": mavlink2.MAV_AUTOPILOT_PX4,
}

_GAUSS_PER_MICROTESLA = 1.0 / UNIT_TO_SI["gauss"]  # the unit HIGHRES_IMU's mag fields are in
_UINT16_UNKNOWN = 0xFFFF  # GPS_RAW_INT's eph, epv, vel, cog; GLOBAL_POSITION_INT's hdg
_INT16_LIMIT = 32767


def _message_class(name: str) -> Any:
    return mavlink2.mavlink_map[getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")]


# The kinds of record, in their order at equal times.
_KINDS = (
    "HEARTBEAT",
    "PARAM_VALUE",
    "HIGHRES_IMU",
    "ATTITUDE",
    "SIMSTATE",
    "GPS_RAW_INT",
    "GLOBAL_POSITION_INT",
    "VFR_HUD",
)
_CLASSES = {name: _message_class(name) for name in _KINDS}
_DTYPES = {name: bulk.wire_dtype(message_class) for name, message_class in _CLASSES.items()}


def to_tlog_bytes(log: OnboardLog, system: int = 1, component: int = 1) -> bytes:
    """The tlog of ``log``: every sample as a MAVLink 2 record, in time order (see the
    module's docstring for what each becomes). The same log gives the same bytes."""
    clock = _Clock(log)
    base = _boot_base(log)
    parts: list[tuple[str, np.ndarray, np.ndarray]] = []  # (kind, record clock µs, payloads)
    for stream in log.imus:
        t = clock.of(stream.t_us, stream.restarts)
        parts.append(("HIGHRES_IMU", t, _highres_imu(log, stream, t, clock, base)))
    if log.attitude is not None and len(log.attitude.t_us):
        parts.append(("ATTITUDE", clock.series(log.attitude), _attitude(log.attitude, base)))
    if log.truth is not None and len(log.truth.t_us):
        parts.append(("SIMSTATE", clock.series(log.truth), _simstate(log.truth)))
    if log.gps_fix is not None and len(log.gps_fix.t_us):
        parts.append(("GPS_RAW_INT", clock.series(log.gps_fix), _gps_raw_int(log.gps_fix, base)))
    if log.gps_velocity is not None and len(log.gps_velocity.t_us):
        parts.append(
            (
                "GLOBAL_POSITION_INT",
                clock.series(log.gps_velocity),
                _global_position(log.gps_velocity, base),
            )
        )
    if log.airspeed is not None and len(log.airspeed.t_us):
        parts.append(("VFR_HUD", clock.series(log.airspeed), _vfr_hud(log.airspeed)))
    sampled = [t for _, t, _ in parts if len(t)]
    if not sampled:
        return b""
    beats = _heartbeat_times(np.concatenate(sampled))
    parts.append(("HEARTBEAT", beats, _heartbeats(log, len(beats))))
    if log.declination is not None:
        parts.append(("PARAM_VALUE", beats[:1], _declination(log)))

    # One merged order: by time, then by kind, then as each kind came (lexsort is stable).
    times = np.concatenate([np.asarray(t, dtype=np.int64) for _, t, _ in parts])
    rank = np.concatenate([np.full(len(t), _KINDS.index(kind)) for kind, t, _ in parts])
    order = np.lexsort((rank, times))
    seqs = np.empty(len(order), dtype=np.int64)
    seqs[order] = np.arange(len(order), dtype=np.int64)

    packed: list[np.ndarray] = []
    lengths: list[np.ndarray] = []
    start = 0
    for kind, t, payloads in parts:
        packets = bulk.packets(
            payloads, _CLASSES[kind], seqs[start : start + len(t)], system, component
        )
        packed.append(packets.data)
        lengths.append(packets.length)
        start += len(t)
    width = max(p.shape[1] for p in packed)
    rows = np.zeros((len(order), width), dtype=np.uint8)
    length = np.concatenate(lengths)
    start = 0
    for p in packed:
        rows[start : start + p.shape[0], : p.shape[1]] = p
        start += p.shape[0]
    del packed
    out = np.empty(int(length.sum()) + 8 * len(order), dtype=np.uint8)
    _records(rows, length, order, times + RECORD_EPOCH_US, out)
    return out.tobytes()


@inplace_exact_kernel
def _records(
    rows: np.ndarray, length: np.ndarray, order: np.ndarray, stamps: np.ndarray, out: np.ndarray
) -> None:
    """Each packet (``rows[i, :length[i]]``) in ``order``, after its stamp (8 bytes,
    big-endian): the tlog's records."""
    position = 0
    for k in range(order.shape[0]):
        i = order[k]
        stamp = stamps[i]
        for b in range(8):
            out[position + b] = (stamp >> (8 * (7 - b))) & 0xFF
        position += 8
        for b in range(length[i]):
            out[position + b] = rows[i, b]
        position += length[i]


def _payloads(kind: str, n: int) -> np.ndarray:
    return np.zeros(n, dtype=_DTYPES[kind])


class _Clock:
    """The record clock of a log's samples: their boot time on the first timeline; on
    each later one (a clock that went back and stayed) going on from the one before,
    its first record a second after the previous timeline's last, so that the records
    of every series fall into one order as a tlog of a restarted vehicle holds them."""

    def __init__(self, log: OnboardLog) -> None:
        pieces = [(s.t_us, s.restarts) for s in _every_series(log) if len(s.t_us)]
        count = 1 + max((len(r) for _, r in pieces), default=0)
        first = [None] * count
        last = [None] * count
        for t, restarts in pieces:
            bounds = np.concatenate(([0], restarts, [len(t)]))
            for k in range(len(bounds) - 1):
                a, b = int(t[bounds[k]]), int(t[bounds[k + 1] - 1])
                first[k] = a if first[k] is None else min(first[k], a)
                last[k] = b if last[k] is None else max(last[k], b)
        offsets = [0] * count
        for k in range(1, count):
            following = offsets[k - 1] + last[k - 1] - first[k] + _TIMELINE_GAP_US
            # (bounded, so that a record's Unix time stays within int64 whatever a log holds)
            offsets[k] = min(following, _LATEST_OFFSET_US)
        self.offsets = np.array(offsets, dtype=np.int64)

    def of(self, t_us: np.ndarray, restarts: np.ndarray) -> np.ndarray:
        """The record clock of samples at ``t_us`` with new timelines at ``restarts``."""
        if not len(restarts):
            return np.asarray(t_us, dtype=np.int64)
        timeline = np.searchsorted(restarts, np.arange(len(t_us)), side="right")
        return np.asarray(t_us, dtype=np.int64) + self.offsets[timeline]

    def series(self, series: Series) -> np.ndarray:
        return self.of(series.t_us, series.restarts)


def _every_series(log: OnboardLog) -> list[Any]:
    found: list[Any] = list(log.imus) + list(log.mag.values())
    for series in (log.attitude, log.truth, log.gps_fix, log.gps_velocity, log.airspeed):
        if series is not None:
            found.append(series)
    return found


def _heartbeat_times(clock: np.ndarray) -> np.ndarray:
    """A HEARTBEAT at the first sample's time and every second after, through any gap a
    stream has (:data:`mavest.timeline.MAX_JUMP`) but not through a longer one: so the
    records stay bounded by the samples, whatever times a log gives."""
    first = int(clock.min())
    seconds = np.unique((clock - first) // _HEARTBEAT_PERIOD_US)
    span = int(timeline.MAX_JUMP * 1e6) // _HEARTBEAT_PERIOD_US
    following = np.diff(seconds, append=seconds[-1] + 1)
    each = np.where(following <= span, following, 1)
    starts = np.repeat(seconds, each)
    within = np.arange(len(starts)) - np.repeat(np.cumsum(each) - each, each)
    return first + (starts + within) * _HEARTBEAT_PERIOD_US


def _latest_at_or_before(t_samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """For each time of ``t``, the index of the last of ``t_samples`` at or before it
    (−1: none yet)."""
    return np.searchsorted(t_samples, t, side="right") - 1


def _mag_for(log: OnboardLog, instance: int) -> Series | None:
    if instance in log.mag:
        return log.mag[instance]
    return log.mag[min(log.mag)] if log.mag else None


def _highres_imu(
    log: OnboardLog, stream: Any, t: np.ndarray, clock: _Clock, base: int
) -> np.ndarray:
    """``t``: the samples' record clock, on which each is paired with a field sample."""
    n = len(stream.t_us)
    p = _payloads("HIGHRES_IMU", n)
    p["time_usec"] = stream.t_us - base
    for k, axis in enumerate("xyz"):
        p[f"{axis}acc"] = stream.accel[:, k]
        p[f"{axis}gyro"] = stream.gyro[:, k]
    updated = np.full(n, HIGHRES_INERTIAL_BITS, dtype=np.int64)
    mag = _mag_for(log, stream.instance)
    field = np.full((n, 3), np.nan)
    if mag is not None and len(mag.t_us):
        latest = _latest_at_or_before(clock.series(mag), t)
        known = latest >= 0
        field[known] = mag.values[latest[known]] * _GAUSS_PER_MICROTESLA
        # fresh: the first IMU sample that sees this field sample
        previous = np.concatenate(([-1], latest[:-1]))
        updated[known & (latest != previous)] |= HIGHRES_MAG_BITS
    for k, axis in enumerate("xyz"):
        p[f"{axis}mag"] = field[:, k]
    p["fields_updated"] = updated
    p["id"] = stream.instance
    return p


def _boot_base(log: OnboardLog) -> int:
    """What the messages' own times (``time_usec``, ``time_boot_ms``) are counted from: 0,
    the log's boot clock as it is; or, for a clock beyond what ``time_boot_ms`` holds
    (2³² ms, 49.7 days: a PX4 simulator stamps its log with Unix time), the log's first
    whole millisecond, so that every message's time is from there and all still agree
    (an ATTITUDE's 32-bit time wrapped otherwise, never matching the IMU's)."""
    times = [s.t_us for s in _every_series(log) if len(s.t_us)]
    if not times or max(int(t.max()) for t in times) // 1000 <= 0xFFFFFFFF:
        return 0
    return min(int(t.min()) for t in times) // 1000 * 1000


def _time_boot_ms(t_us: np.ndarray, base: int) -> np.ndarray:
    return ((np.asarray(t_us, dtype=np.int64) - base) // 1000) & 0xFFFFFFFF


def _euler_into(p: np.ndarray, values: np.ndarray) -> None:
    for k, name in enumerate(("roll", "pitch", "yaw")):
        p[name] = values[:, k]


def _attitude(series: Series, base: int) -> np.ndarray:
    p = _payloads("ATTITUDE", len(series.t_us))
    p["time_boot_ms"] = _time_boot_ms(series.t_us, base)
    _euler_into(p, series.values)
    return p


def _simstate(series: Series) -> np.ndarray:
    p = _payloads("SIMSTATE", len(series.t_us))
    _euler_into(p, series.values)
    return p


def _gps_raw_int(series: Series, base: int) -> np.ndarray:
    p = _payloads("GPS_RAW_INT", len(series.t_us))
    p["time_usec"] = series.t_us - base
    p["fix_type"] = np.clip(series.values[:, 0], 0, 255).astype(np.uint8)
    for name in ("eph", "epv", "vel", "cog"):
        p[name] = _UINT16_UNKNOWN
    p["satellites_visible"] = 255  # unknown
    return p


def _global_position(series: Series, base: int) -> np.ndarray:
    p = _payloads("GLOBAL_POSITION_INT", len(series.t_us))
    p["time_boot_ms"] = _time_boot_ms(series.t_us, base)
    cm_s = np.clip(np.rint(series.values * 100.0), -_INT16_LIMIT, _INT16_LIMIT)
    for k, name in enumerate(("vx", "vy", "vz")):
        p[name] = cm_s[:, k]
    p["hdg"] = _UINT16_UNKNOWN
    return p


def _vfr_hud(series: Series) -> np.ndarray:
    p = _payloads("VFR_HUD", len(series.t_us))
    p["airspeed"] = series.values[:, 0]
    return p


def _heartbeats(log: OnboardLog, n: int) -> np.ndarray:
    p = _payloads("HEARTBEAT", n)
    p["type"] = log.vehicle_type
    p["autopilot"] = _AUTOPILOTS.get(log.autopilot, mavlink2.MAV_AUTOPILOT_GENERIC)
    p["system_status"] = mavlink2.MAV_STATE_ACTIVE
    p["mavlink_version"] = 3
    return p


def _declination(log: OnboardLog) -> np.ndarray:
    p = _payloads("PARAM_VALUE", 1)
    p["param_id"] = b"COMPASS_DEC"
    p["param_value"] = log.declination
    p["param_type"] = mavlink2.MAV_PARAM_TYPE_REAL32
    p["param_count"] = 1
    p["param_index"] = 0
    return p
