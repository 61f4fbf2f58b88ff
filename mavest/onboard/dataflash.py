"""ArduPilot DataFlash logs (``.bin``) read in bulk.

A DataFlash log is a stream of records, each ``A3 95`` then a type byte then a payload
whose layout the log itself defines: a ``FMT`` record (type 128) gives a type's total
length, name, format characters and column names. There is no checksum, so damage is
found by structure alone.

Reading is in two steps, neither record by record in Python:

1. :func:`_walk`, a compiled loop, indexes every record (offset, type), learning lengths
   from FMT records as it goes. Where the stream is damaged (a byte that is not the
   header, an unknown type, a record that would run past the end, or a record not
   followed by another header) it counts the bad record and resumes at the next offset
   where a record with a known type starts and is followed by another header; a record
   cut off at the end of the file counts as truncated.
2. :class:`DataflashRecords` gathers the payloads of one type at once and views them as a
   NumPy structured array built from the format characters (as pymavlink's DFReader
   reads them, its multipliers included: ``c C e E`` are hundredths, ``L`` degrees × 1e7).

:func:`load_dataflash` then turns the records into an :class:`~mavest.onboard.model.OnboardLog`
in SI units. Units come from the log's ``FMTU``/``UNIT``/``MULT`` records where it has
them (ArduPilot 3.5 and later); for older logs they are ArduPilot's fixed conventions
(gyro rad/s, accelerometer m/s², magnetometer milligauss, GPS speed m/s and course
degrees, attitude degrees), and a note says so.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mavest._jit import inplace_kernel
from mavest.mavlink.messages import mavlink2
from mavest.onboard.errors import FieldError, OnboardLogError
from mavest.onboard.model import ImuStream, LogDamage, OnboardLog, Series
from mavest.onboard.series import Collector, boot_times

__all__ = [
    "ColumnError",
    "DataflashFormat",
    "DataflashRecords",
    "boot_time_us",
    "instances",
    "load_dataflash",
    "logged_parameters",
    "read_records",
]

_HEADER_1 = 0xA3
_HEADER_2 = 0x95
_FMT_TYPE = 128
_FMT_LENGTH = 89  # header 3 + Type 1 + Length 1 + Name 4 + Format 16 + Columns 64
_FMT_DTYPE = np.dtype(
    [("Type", "u1"), ("Length", "u1"), ("Name", "S4"), ("Format", "S16"), ("Columns", "S64")]
)

# Format characters → NumPy (little-endian), as pymavlink's DFReader.FORMAT_TO_STRUCT.
_FORMAT_TO_NUMPY = {
    "a": ("<i2", (32,)),
    "b": "i1",
    "B": "u1",
    "g": "<f2",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "f": "<f4",
    "d": "<f8",
    "n": "S4",
    "N": "S16",
    "Z": "S64",
    "c": "<i2",
    "C": "<u2",
    "e": "<i4",
    "E": "<u4",
    "L": "<i4",
    "M": "i1",
    "q": "<i8",
    "Q": "<u8",
}
# Integer formats whose value is a fixed fraction: hundredths, and lat/lon in 1e-7 degrees.
# Divided rather than multiplied, as DFReader does, so values are equal to the last bit.
_FORMAT_DIVISOR = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}
_STRING_FORMATS = frozenset("nNZ")


# --------------------------------------------------------------------------
# The record index (compiled)
# --------------------------------------------------------------------------


@inplace_kernel
def _record_length(data: np.ndarray, lengths: np.ndarray, p: int) -> int:
    """Length of a record with the header, a known type, that ends within the file,
    starting at ``p``; else -1."""
    n = data.shape[0]
    if p + 3 > n or data[p] != _HEADER_1 or data[p + 1] != _HEADER_2:
        return -1
    length = lengths[data[p + 2]]
    return length if length > 0 and p + length <= n else -1


@inplace_kernel
def _followed(data: np.ndarray, lengths: np.ndarray, p: int, length: int) -> bool:
    """Whether the record at ``p`` is followed by another header (or the file's end)."""
    q = p + length
    if q + 3 > data.shape[0]:  # the end, or a last record too short to check
        return True
    if data[q] != _HEADER_1 or data[q + 1] != _HEADER_2:
        return False
    # after a FMT, the next record may be of the type it has just defined
    return data[p + 2] == _FMT_TYPE or lengths[data[q + 2]] > 0


@inplace_kernel
def _next_record(data: np.ndarray, lengths: np.ndarray, p: int) -> int:
    """The first offset after ``p`` where a record starts that another header follows
    (the file's length if none)."""
    n = data.shape[0]
    q = p + 1
    while q < n:
        length = _record_length(data, lengths, q)
        if length > 0 and _followed(data, lengths, q, length):
            return q
        q += 1
    return n


@inplace_kernel
def _walk(
    data: np.ndarray,
    p: int,
    lengths: np.ndarray,
    offsets: np.ndarray,
    types: np.ndarray,
    damage: np.ndarray,
) -> tuple[int, int]:
    """Index the records of ``data`` from offset ``p`` into ``offsets``/``types``, until
    the end or until they are full; returns how many, and where to go on from.

    ``lengths`` (256,) holds each type's record length (-1: unknown), FMT's on entry; the
    FMT records met extend it. ``damage`` receives bad records, skipped bytes and
    truncated bytes.
    """
    n = data.shape[0]
    count = 0
    while p < n and count < offsets.shape[0]:
        length = _record_length(data, lengths, p)
        resume = p + length
        if length <= 0 or not _followed(data, lengths, p, length):
            # Damage here or right after: resume where the next record starts. A record
            # that ends before it is kept (the damage follows it); one that runs into
            # it is not a record (its header or type byte was hit).
            resume = _next_record(data, lengths, p)
            if length > 0 and p + length > resume:
                length = -1
        if length > 0:
            kind = data[p + 2]
            offsets[count] = p
            types[count] = kind
            count += 1
            if kind == _FMT_TYPE:
                defined = data[p + 3]
                new_length = np.int16(data[p + 4])
                if new_length >= 3 and (defined != _FMT_TYPE or new_length == _FMT_LENGTH):
                    lengths[defined] = new_length
            p += length
        if resume >= n and p < n:
            # Nothing readable from p on: a last record cut off by the file's end, or not.
            kind_known = p + 2 >= n or lengths[data[p + 2]] > 0
            header = data[p] == _HEADER_1 and (p + 1 >= n or data[p + 1] == _HEADER_2)
            if header and kind_known and (p + 3 > n or p + lengths[data[p + 2]] > n):
                damage[2] += n - p
            else:
                damage[0] += 1
                damage[1] += n - p
            return count, n
        if resume > p:
            damage[0] += 1
            damage[1] += resume - p
        p = resume
    return count, p


# --------------------------------------------------------------------------
# Records of one type as arrays
# --------------------------------------------------------------------------


def _text(raw: bytes) -> str:
    """A fixed-width string field: up to its first NUL, UTF-8 or else Latin-1 (as DFReader)."""
    raw = raw.split(b"\0", 1)[0]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


@dataclass(frozen=True)
class DataflashFormat:
    """One FMT record: a type's name, length (header included), format and columns.

    ``dtype`` is the payload's layout, None if a format character is unknown or the
    layout's size disagrees with the length (such records are indexed but not decoded).
    """

    type: int
    length: int
    name: str
    format: str
    columns: tuple[str, ...]
    dtype: np.dtype | None

    @staticmethod
    def from_record(record: np.void) -> DataflashFormat:
        name, fmt = _text(record["Name"]), _text(record["Format"])
        columns = tuple(c for c in _text(record["Columns"]).split(",") if c) or ()
        length = int(record["Length"])
        dtype: np.dtype | None = None
        if (
            len(columns) == len(fmt)
            and len(set(columns)) == len(columns)  # (checked first: NumPy refuses it)
            and all(c in _FORMAT_TO_NUMPY for c in fmt)
        ):
            candidate = np.dtype(
                [(col, _FORMAT_TO_NUMPY[c]) for col, c in zip(columns, fmt, strict=True)]
            )
            if candidate.itemsize == length - 3:
                dtype = candidate
        return DataflashFormat(int(record["Type"]), length, name, fmt, columns, dtype)

    @property
    def key(self) -> tuple[int, str, int, str, tuple[str, ...]]:
        """What a record's reading depends on: two definitions with one key read alike."""
        return (self.type, self.name, self.length, self.format, self.columns)


class ColumnError(FieldError):
    """A column a message type lacks, or holds as something other than asked (a number,
    or text): a damaged or odd FMT record."""


@dataclass(frozen=True)
class FieldUnit:
    """A column's unit and multiplier from the log's FMTU, UNIT and MULT records.

    ``label`` is the UNIT text (``"rad/s"``, ``"Gauss"``…), None when not given;
    ``multiplier`` scales the stored value into that unit, None when not given.
    """

    label: str | None
    multiplier: float | None


@dataclass
class DataflashRecords:
    """The records of one DataFlash log, indexed; each type decoded when first asked for.

    Values as pymavlink's DFReader gives them: the format's own multipliers applied
    (:meth:`column`), nothing else.
    """

    data: np.ndarray
    offsets: np.ndarray  # (R,) int64 start of every record
    types: np.ndarray  # (R,) uint8 its type
    damage: LogDamage
    formats: dict[str, DataflashFormat] = field(default_factory=dict)
    _by_type: dict[int, np.ndarray] = field(default_factory=dict)
    _of_name: dict[str, np.ndarray] = field(default_factory=dict)  # the records read as it
    _tables: dict[str, np.ndarray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        order = np.argsort(self.types, kind="stable")
        bounds = np.concatenate(([0], np.cumsum(np.bincount(self.types, minlength=256))))
        for kind in np.flatnonzero(np.diff(bounds)):
            self._by_type[int(kind)] = self.offsets[order[bounds[kind] : bounds[kind + 1]]]
        fmt_offsets = self._by_type.get(_FMT_TYPE, np.zeros(0, dtype=np.int64))
        found = [DataflashFormat.from_record(r) for r in self._gather(fmt_offsets, _FMT_DTYPE)]
        defining: dict[int, list[int]] = {}  # per type, its FMT records (indices into found)
        for k, definition in enumerate(found):
            defining.setdefault(definition.type, []).append(k)
            if definition.name:
                self.formats[definition.name] = definition  # the last one of each name
        # Each record is read by its name's last definition. The FMT in force where a
        # record is (the index took its length from it) must read alike: a log that
        # redefines a type (damaged, or reusing a type number) has records that the
        # last definition cannot read, which are left out.
        kept: dict[str, list[np.ndarray]] = {}
        left_out: dict[str, int] = {}
        for kind, offsets in self._by_type.items():
            indices = defining.get(kind)
            if not indices:
                continue
            # (a FMT record before FMT's own definition: read as the first one)
            governing = np.searchsorted(fmt_offsets[indices], offsets, side="right") - 1
            governing = np.maximum(governing, 0)
            for g in np.unique(governing):
                definition = found[indices[g]]
                last = self.formats.get(definition.name)
                if last is None:
                    continue
                mine = offsets[governing == g]
                if definition.key == last.key:
                    kept.setdefault(definition.name, []).append(mine)
                else:
                    left_out[definition.name] = left_out.get(definition.name, 0) + len(mine)
        for name in self.formats:
            # (in file order: a name's records are of one type, their FMTs in order)
            parts = kept.get(name, [np.zeros(0, dtype=np.int64)])
            self._of_name[name] = parts[0] if len(parts) == 1 else np.concatenate(parts)
        for name, count in left_out.items():
            self.notes.append(
                f"{name} is defined more than once: {count} of its records, under another "
                "definition than its last, left out"
            )
        if left_out:  # records that cannot be read: the log's damage
            self.damage = dataclasses.replace(
                self.damage, bad_records=self.damage.bad_records + sum(left_out.values())
            )

    def _gather(self, offsets: np.ndarray, dtype: np.dtype) -> np.ndarray:
        """Payloads at ``offsets`` (records of one length) as a (N,) array of ``dtype``."""
        columns = np.arange(3, 3 + dtype.itemsize)
        raw = self.data[offsets[:, None] + columns] if len(offsets) else np.zeros((0, 0), "u1")
        return np.ascontiguousarray(raw).view(dtype).reshape(len(offsets))

    def count(self, name: str) -> int:
        return len(self._of_name.get(name, ()))

    def has(self, name: str) -> bool:
        """Whether the log holds decodable records of this name."""
        definition = self.formats.get(name)
        return definition is not None and definition.dtype is not None and self.count(name) > 0

    def table(self, name: str) -> np.ndarray:
        """The records of ``name`` as a structured array (raw stored values); empty if none."""
        if name not in self._tables:
            definition = self.formats.get(name)
            if definition is None or definition.dtype is None:
                self._tables[name] = np.zeros(0, dtype=np.dtype([]))
            else:
                self._tables[name] = self._gather(self._of_name[name], definition.dtype)
        return self._tables[name]

    def column(self, name: str, column: str, rows: np.ndarray | None = None) -> np.ndarray:
        """One numeric column as float64, its format's multiplier applied (as DFReader).

        ColumnError if the message type has no such column or holds it as text."""
        self._check(name, column, numeric=True)
        values = self.table(name)[column]
        if rows is not None:
            values = values[rows]
        divisor = _FORMAT_DIVISOR.get(self.format_char(name, column))
        with np.errstate(invalid="ignore"):  # a damaged float: NaN, as DFReader gives it
            values = values.astype(np.float64)
        return values / divisor if divisor is not None else values

    def stored(self, name: str, column: str) -> np.ndarray:
        """One numeric column as stored, no multiplier applied (a 64-bit integer time
        exact, not through float64). ColumnError as :meth:`column`."""
        self._check(name, column, numeric=True)
        return self.table(name)[column]

    def strings(self, name: str, column: str) -> list[str]:
        """One string column, each value up to its first NUL. ColumnError if the message
        type has no such column or holds it as something other than text."""
        self._check(name, column, numeric=False)
        return [_text(bytes(v)) for v in self.table(name)[column]]

    def _check(self, name: str, column: str, numeric: bool) -> None:
        """The one rule for a column asked of a message type: it must be there, and a
        number (one value, not text nor an array) or text as asked."""
        if column not in self.columns(name):
            raise ColumnError(f"{name} has no column {column}")
        text = self.format_char(name, column) in _STRING_FORMATS
        if numeric and (text or self.format_char(name, column) == "a"):
            raise ColumnError(f"{name}.{column} is not a number")
        if not numeric and not text:
            raise ColumnError(f"{name}.{column} is not text")

    def format_char(self, name: str, column: str) -> str:
        definition = self.formats[name]
        return definition.format[definition.columns.index(column)]

    def columns(self, name: str) -> tuple[str, ...]:
        definition = self.formats.get(name)
        return definition.columns if definition is not None else ()

    def units(self) -> dict[str, dict[str, FieldUnit]]:
        """Per message name, per column: the unit FMTU/UNIT/MULT give it (empty: no FMTU)."""
        if not self.has("FMTU"):
            return {}
        labels: dict[str, str] = {}
        if self.has("UNIT"):
            labels = {
                chr(int(i) & 0xFF): label
                for i, label in zip(
                    self.column("UNIT", "Id"), self.strings("UNIT", "Label"), strict=True
                )
                if math.isfinite(i)
            }
        multipliers: dict[str, float] = {}
        if self.has("MULT"):
            multipliers = {
                chr(int(i) & 0xFF): float(m)
                for i, m in zip(self.column("MULT", "Id"), self.column("MULT", "Mult"), strict=True)
                if math.isfinite(i)
            }
        by_type = {d.type: d for d in self.formats.values()}
        result: dict[str, dict[str, FieldUnit]] = {}
        kinds = self.column("FMTU", "FmtType")
        unit_ids, mult_ids = self.strings("FMTU", "UnitIds"), self.strings("FMTU", "MultIds")
        for kind, units, mults in zip(kinds, unit_ids, mult_ids, strict=True):
            definition = by_type.get(int(kind)) if math.isfinite(kind) else None
            if definition is None:
                continue
            per_column = {}
            for k, column in enumerate(definition.columns):
                unit = units[k] if k < len(units) else "-"
                mult = mults[k] if k < len(mults) else "-"
                # '-': no unit / no multiplier; '#': the instance column; '?': unknown
                per_column[column] = FieldUnit(
                    labels.get(unit) if unit not in "-#?" else None,
                    multipliers.get(mult) if mult not in "-?" else None,
                )
            result[definition.name] = per_column
        return result


def read_records(path: Path | str) -> DataflashRecords:
    """Index a DataFlash log's records (the file is only read).

    OnboardLogError if the file cannot be read or holds no FMT record.
    """
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise OnboardLogError(f"{path.name}: an empty file")
        # Mapped, read-only: the file is never opened for writing, nor copied whole.
        data = np.asarray(np.memmap(path, dtype=np.uint8, mode="r"))
    except (OSError, ValueError) as error:
        reason = getattr(error, "strerror", None) or error
        raise OnboardLogError(f"{path.name}: cannot read ({reason})") from error
    lengths = np.full(256, -1, dtype=np.int16)
    lengths[_FMT_TYPE] = _FMT_LENGTH
    counters = np.zeros(3, dtype=np.int64)
    # ArduPilot's records are 20–100 bytes long; a log of shorter ones takes more rounds.
    capacity = len(data) // 16 + 1024
    offsets, types = [], []
    position = 0
    while position < len(data):
        chunk_offsets = np.empty(capacity, dtype=np.int64)
        chunk_types = np.empty(capacity, dtype=np.uint8)
        count, position = _walk(data, position, lengths, chunk_offsets, chunk_types, counters)
        offsets.append(chunk_offsets[:count])
        types.append(chunk_types[:count])
    damage = LogDamage(int(counters[0]), int(counters[1]), int(counters[2]))
    records = DataflashRecords(data, np.concatenate(offsets), np.concatenate(types), damage)
    if not records.formats:
        raise OnboardLogError(f"{path.name}: no DataFlash format (FMT) records")
    return records


# --------------------------------------------------------------------------
# Units
# --------------------------------------------------------------------------

# UNIT labels ArduPilot uses, by the quantity mavest wants, as factors to its unit.
_RATE = {"rad/s": 1.0, "deg/s": math.pi / 180}
_ACCELERATION = {"m/s/s": 1.0, "m/s²": 1.0}
_MAGNETIC = {"Gauss": 100.0, "mGauss": 0.1, "mG": 0.1, "uT": 1.0, "µT": 1.0, "nT": 1e-3}
_SPEED = {"m/s": 1.0, "cm/s": 0.01}
_ANGLE = {"deg": math.pi / 180, "degheading": math.pi / 180, "rad": 1.0, "cdeg": math.pi / 18000}


@dataclass(frozen=True)
class _Quantity:
    """A quantity read from DataFlash columns: what its unit may be, and what a log
    without FMTU is taken to hold (ArduPilot's fixed units before FMTU existed)."""

    what: str
    known: dict[str, float]
    assumed: str


_GYRO = _Quantity("gyro", _RATE, "rad/s")
_ACCEL = _Quantity("accelerometer", _ACCELERATION, "m/s/s")
_MAG = _Quantity("magnetometer", _MAGNETIC, "mGauss")
_GPS_SPEED = _Quantity("GPS speed", _SPEED, "m/s")
_GPS_COURSE = _Quantity("GPS course", _ANGLE, "deg")
_AIRSPEED = _Quantity("airspeed", _SPEED, "m/s")
_ATTITUDE = _Quantity("attitude", _ANGLE, "deg")


class _UnitError(ColumnError):
    """A column whose unit the log gives as something the quantity cannot be."""


def _si(
    records: DataflashRecords,
    units: dict[str, dict[str, FieldUnit]],
    name: str,
    columns: tuple[str, ...],
    quantity: _Quantity,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """(N, len(columns)) float64 in mavest's unit for ``quantity`` (rad/s, m/s², µT, m/s,
    rad): the format's multiplier, then the FMTU multiplier and unit where the log has
    them, else the assumed unit. _UnitError if FMTU gives a unit it cannot be."""
    out = np.empty((len(rows) if rows is not None else records.count(name), len(columns)))
    for k, column in enumerate(columns):
        values = records.column(name, column, rows)
        given = units.get(name, {}).get(column)
        label = quantity.assumed
        if given is not None:
            if given.label is not None:
                label = given.label
            # The format's own multiplier (c, e, L…) already says the same as FMTU's.
            if given.multiplier and records.format_char(name, column) not in _FORMAT_DIVISOR:
                values = values * given.multiplier
        if label not in quantity.known:
            raise _UnitError(f"{name}.{column} is in {label!r}, not a unit of {quantity.what}")
        out[:, k] = values * quantity.known[label]
    return out


# --------------------------------------------------------------------------
# The log in mavest's terms
# --------------------------------------------------------------------------

# Older firmware logs each sensor instance as its own message; newer one message with "I".
_IMU_NAMES = ("IMU", "IMU2", "IMU3")
_MAG_NAMES = ("MAG", "MAG2", "MAG3")
_GPS_NAMES = ("GPS", "GPS2")
_AIRSPEED_NAMES = ("ARSP", "ASP2")

_VEHICLES = {
    "Plane": mavlink2.MAV_TYPE_FIXED_WING,
    "Copter": mavlink2.MAV_TYPE_QUADROTOR,
    "Heli": mavlink2.MAV_TYPE_HELICOPTER,
    "Rover": mavlink2.MAV_TYPE_GROUND_ROVER,
    "rover": mavlink2.MAV_TYPE_GROUND_ROVER,
    "Sub": mavlink2.MAV_TYPE_SUBMARINE,
    "Tracker": mavlink2.MAV_TYPE_ANTENNA_TRACKER,
    "Blimp": mavlink2.MAV_TYPE_AIRSHIP,
}
_FIRMWARE = re.compile(r"(?:Ardu|APM:|APM)(Plane|Copter|Heli|Rover|rover|Sub|Tracker|Blimp)")
# A copter's "Frame: …" message names its motor layout.
_COPTER_FRAMES = {
    "QUAD": mavlink2.MAV_TYPE_QUADROTOR,
    "HEXA": mavlink2.MAV_TYPE_HEXAROTOR,
    "Y6": mavlink2.MAV_TYPE_HEXAROTOR,
    "OCTA": mavlink2.MAV_TYPE_OCTOROTOR,
    "OCTAQUAD": mavlink2.MAV_TYPE_OCTOROTOR,
    "TRI": mavlink2.MAV_TYPE_TRICOPTER,
    "HELI": mavlink2.MAV_TYPE_HELICOPTER,
    "DODECAHEXA": mavlink2.MAV_TYPE_DODECAROTOR,
    "DECA": mavlink2.MAV_TYPE_DECAROTOR,
}


def boot_time_us(records: DataflashRecords, name: str) -> np.ndarray:
    """Record times in µs since boot: ``TimeUS``, or ``TimeMS`` (ms) in older firmware,
    where a GPS message's ``TimeMS`` is the GPS week's time and ``T`` the boot time.
    A value that is no boot time is :data:`~mavest.onboard.series.NO_TIME`.

    ColumnError if the message type has none of them, or not as a number."""
    columns = records.columns(name)
    if "TimeUS" in columns:
        return boot_times(_exact(records, name, "TimeUS"))
    if name.startswith("GPS") and "T" in columns:
        return boot_times(_exact(records, name, "T"), 1000)
    if "TimeMS" in columns:
        return boot_times(_exact(records, name, "TimeMS"), 1000)
    raise ColumnError(f"{name} has neither TimeUS nor TimeMS")


def _exact(records: DataflashRecords, name: str, column: str) -> np.ndarray:
    """A numeric column as stored: a 64-bit integer time, exact (not through float64)."""
    if records.format_char(name, column) in _FORMAT_DIVISOR:
        return records.column(name, column)
    return records.stored(name, column)


# The instances a MAVLink message can carry (HIGHRES_IMU's id, a uint8).
_LAST_INSTANCE = 255


def instances(
    records: DataflashRecords, names: tuple[str, ...], notes: list[str] | None = None
) -> list[tuple[str, int, np.ndarray]]:
    """(message name, instance, rows) of a sensor logged per message (IMU, IMU2…) or in
    one message with an instance column ``I``.

    Left out, each with a line in ``notes``: records whose instance is not one of
    0…255, a message type whose ``I`` is not a number, and an instance that another
    of ``names`` already gives (two sensors' samples are never merged into one stream).
    """
    notes = notes if notes is not None else []
    found: list[tuple[str, int, np.ndarray]] = []
    for number, name in enumerate(names):
        if not records.has(name):
            continue
        if "I" not in records.columns(name):
            given = [(number, np.arange(records.count(name)))]
        else:
            try:
                instance = records.column(name, "I")
            except ColumnError as error:
                notes.append(f"{error}: left out")
                continue
            possible = np.isin(instance, np.arange(_LAST_INSTANCE + 1))
            if not np.all(possible):
                notes.append(
                    f"{name}: {int(np.count_nonzero(~possible))} records with an instance I "
                    f"outside 0…{_LAST_INSTANCE} left out"
                )
            given = [
                (int(value), np.flatnonzero(instance == value))
                for value in np.unique(instance[possible])
            ]
        for value, rows in given:
            clash = next((other for other, taken, _ in found if taken == value), None)
            if clash is not None:
                notes.append(
                    f"{name} left out as instance {value}: {clash}'s instance {value} "
                    "is another sensor"
                )
                continue
            found.append((name, value, rows))
    return found


class _Builder(Collector):
    """Collects the series of one log and its notes, with its records and their units."""

    def __init__(self, records: DataflashRecords) -> None:
        super().__init__(records.notes)
        self.records = records
        units = self.attempt(records.units)
        self.units = units if units is not None else {}

    def quantity(
        self, name: str, columns: tuple[str, ...], quantity: _Quantity, rows: np.ndarray
    ) -> np.ndarray | None:
        """One quantity of some of a message type's records, or None with a note."""
        return self.attempt(
            _si, self.records, self.units, name, columns, quantity, rows, part=quantity.what
        )


def logged_parameters(records: DataflashRecords) -> dict[str, float]:
    """The last value logged for each parameter. ColumnError if PARM's Name is not text
    or its Value not a number."""
    if not records.has("PARM"):
        return {}
    values = records.column("PARM", "Value")
    return dict(zip(records.strings("PARM", "Name"), (float(v) for v in values), strict=True))


def _vehicle_type(records: DataflashRecords) -> tuple[int, str | None]:
    """MAV_TYPE from the firmware name in VER's or MSG's text, and what said so."""
    texts: list[str] = []
    if records.has("VER") and "FWS" in records.columns("VER"):
        texts += records.strings("VER", "FWS")
    if records.has("MSG"):
        texts += records.strings("MSG", "Message")
    firmware = next((t for t in texts if _FIRMWARE.search(t)), None)
    if firmware is None:
        return mavlink2.MAV_TYPE_GENERIC, None
    kind = _FIRMWARE.search(firmware)
    assert kind is not None
    vehicle = _VEHICLES[kind.group(1)]
    if vehicle == mavlink2.MAV_TYPE_QUADROTOR:
        for text in texts:
            if text.startswith("Frame:"):
                layout = text.removeprefix("Frame:").strip().split("/")[0].split()
                if layout and layout[0].upper() in _COPTER_FRAMES:
                    vehicle = _COPTER_FRAMES[layout[0].upper()]
                    firmware += f", {text}"
                break
    return vehicle, firmware


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles in rad into [-π, π)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def load_dataflash(path: Path | str) -> OnboardLog:
    """An ArduPilot DataFlash log as an :class:`OnboardLog` (see the module docstring).

    ATT's roll and pitch get ``AHRS_TRIM_X``/``_Y`` added back, so the attitude is that
    of the IMU samples' frame (as :mod:`mavest.datasets.autopilot_logs` explains); yaw is
    wrapped into [-π, π). ``SIM`` (ArduPilot's simulator) is the truth where logged.

    OnboardLogError if the file cannot be read or holds no usable IMU samples.
    """
    path = Path(path)
    records = read_records(path)
    build = _Builder(records)
    if not build.units:
        build.notes.append("no FMTU records: ArduPilot's fixed units assumed")

    imus = []
    before = len(build.notes)
    for name, instance, rows in instances(records, _IMU_NAMES, build.notes):
        stream = build.attempt(_imu, build, name, instance, rows)
        if stream is not None and not len(stream.t_us):
            # (one corrupt record can name an instance the log never had: not a stream)
            build.notes.append(f"IMU instance {instance} ({name}): no usable sample, left out")
        elif stream is not None:
            imus.append(stream)
            build.notes.append(f"IMU instance {instance} ({name}): {len(stream.t_us)} samples")
    if not imus:
        why = "; ".join(build.notes[before:])
        raise OnboardLogError(
            f"{path.name}: no IMU samples in this DataFlash log" + (f" ({why})" if why else "")
        )

    mag = {}
    for name, instance, rows in instances(records, _MAG_NAMES, build.notes):
        field_ut = build.attempt(_sensor, build, name, ("MagX", "MagY", "MagZ"), _MAG, rows)
        if field_ut is not None:
            mag[instance] = field_ut

    parameters = build.attempt(logged_parameters, records) or {}
    attitude = build.attempt(_attitude, build, "ATT", parameters)
    truth = build.attempt(_attitude, build, "SIM", {}) if records.has("SIM") else None
    gps_fix, gps_velocity = _gps(build)
    airspeed = None
    for name, instance, rows in instances(records, _AIRSPEED_NAMES, build.notes):
        if instance == 0:
            airspeed = build.attempt(_sensor, build, name, ("Airspeed",), _AIRSPEED, rows)

    vehicle, firmware = build.attempt(_vehicle_type, records) or (mavlink2.MAV_TYPE_GENERIC, None)
    build.notes.append(
        f"vehicle type {vehicle} from {firmware!r}"
        if firmware
        else "vehicle type unknown (no firmware name in MSG or VER)"
    )
    declination = parameters.get("COMPASS_DEC")
    if declination == 0.0 and parameters.get("COMPASS_AUTODEC"):
        # The autopilot works the declination out from its position and does not save it:
        # the logged 0 is not the declination it used.
        declination = None
        build.notes.append("declination not logged (COMPASS_AUTODEC: from the position)")
    damage = LogDamage(
        records.damage.bad_records + build.timeline.unreadable,
        records.damage.skipped_bytes,
        records.damage.truncated_bytes,
        build.timeline.dropped + build.timeline.off_timeline,
    )
    return OnboardLog(
        format="dataflash",
        autopilot="ArduPilot",
        vehicle_type=int(vehicle),
        imus=tuple(imus),
        mag=mag,
        attitude=attitude,
        truth=truth,
        gps_velocity=gps_velocity,
        gps_fix=gps_fix,
        airspeed=airspeed,
        declination=declination,
        damage=damage,
        notes=build.final_notes(),
    )


def _imu(build: _Builder, name: str, instance: int, rows: np.ndarray) -> ImuStream:
    gyro = _si(build.records, build.units, name, ("GyrX", "GyrY", "GyrZ"), _GYRO, rows)
    accel = _si(build.records, build.units, name, ("AccX", "AccY", "AccZ"), _ACCEL, rows)
    both = build.series(boot_time_us(build.records, name)[rows], np.hstack((gyro, accel)))
    return ImuStream(instance, both.t_us, both.values[:, :3], both.values[:, 3:], both.restarts)


def _sensor(
    build: _Builder, name: str, columns: tuple[str, ...], quantity: _Quantity, rows: np.ndarray
) -> Series:
    """The series of one sensor's instance: ``columns`` of ``rows`` of ``name``."""
    values = _si(build.records, build.units, name, columns, quantity, rows)
    return build.series(boot_time_us(build.records, name)[rows], values)


def _attitude(build: _Builder, name: str, parameters: dict[str, float]) -> Series | None:
    """Roll, pitch, yaw (rad) of ATT-like records, the AHRS trim added back to roll/pitch."""
    records = build.records
    if not records.has(name):
        return None
    rows = np.arange(records.count(name))
    t_us = boot_time_us(records, name)
    euler = _si(records, build.units, name, ("Roll", "Pitch", "Yaw"), _ATTITUDE, rows)
    trim = np.array([parameters.get("AHRS_TRIM_X", 0.0), parameters.get("AHRS_TRIM_Y", 0.0)])
    if np.any(trim):
        # ArduPilot logs euler − trim; adding it back gives the IMU frame's attitude.
        # (In degrees first, as the log's values are, so results equal the dataset loader's.)
        euler = np.radians(np.degrees(euler))
        euler[:, :2] = np.radians(np.degrees(euler[:, :2]) + np.degrees(trim))
        build.notes.append(
            f"AHRS_TRIM_X {math.degrees(trim[0]):.2f}°, AHRS_TRIM_Y {math.degrees(trim[1]):.2f}° "
            f"added to {name}'s roll, pitch"
        )
    euler[:, 2] = _wrap(euler[:, 2])
    return build.series(t_us, euler)


def _gps(build: _Builder) -> tuple[Series | None, Series | None]:
    """Fix type (all samples) and NED velocity (3-D fixes) of the first GPS with a 3-D fix.

    ArduPilot's GPS Status counts as MAVLink's GPS_FIX_TYPE (3: 3-D fix and better); the
    velocity is ground speed ``Spd`` along course ``GCrs`` and ``VZ`` (down).
    """
    records = build.records
    chosen: tuple[Series, Series | None] | None = None
    for name, instance, rows in instances(records, _GPS_NAMES, build.notes):
        status = build.attempt(records.column, name, "Status", rows)
        times = build.attempt(boot_time_us, records, name)
        if status is None or times is None:
            continue
        t_us = times[rows]
        fix = Series(t_us, status[:, None])
        fixed = rows[status >= 3]
        velocity = None
        if len(fixed):
            speed = build.quantity(name, ("Spd", "VZ"), _GPS_SPEED, fixed)
            course = build.quantity(name, ("GCrs",), _GPS_COURSE, fixed)
            if speed is not None and course is not None:
                ned = np.column_stack(
                    (
                        speed[:, 0] * np.cos(course[:, 0]),
                        speed[:, 0] * np.sin(course[:, 0]),
                        speed[:, 1],
                    )
                )
                velocity = build.series(times[fixed], ned)
        if chosen is None or (chosen[1] is None and velocity is not None):
            chosen = (fix, velocity)
            build.notes.append(f"GPS instance {instance} ({name}) for fix and velocity")
    if chosen is None:
        return None, None
    fix, velocity = chosen
    return build.series(fix.t_us, fix.values), velocity
