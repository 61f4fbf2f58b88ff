"""Autopilot onboard logs: the logged IMU samples beside the autopilot's own attitude.

Two formats, one loader each, both returning an :class:`AutopilotLog` in mavest's
conventions (docs/design.md#conventions): body FRD, world NED, quaternions (w, x, y, z)
body → NED, SI units, float64, time in seconds from the first IMU sample.

* ArduPilot dataflash (``.bin``), :func:`load_dataflash`, read in bulk by
  :mod:`mavest.onboard.dataflash` (the values pymavlink's DFReader reads). IMU samples
  from ``IMU``/``IMU2``/``IMU3`` (or ``IMU`` with an instance field ``I`` in newer
  firmware): ``GyrX..Z`` rad/s, ``AccX..Z`` m/s², already rotated
  by ``AHRS_ORIENTATION`` into the vehicle's FRD frame and corrected by the stored
  accelerometer/gyro calibration. The reference is ``ATT`` (``Roll``, ``Pitch``,
  ``Yaw`` in degrees, ZYX Euler angles of the NED attitude). Where logged, ``EKF1``
  (the EKF's own angles) and ``AHR2`` (the secondary AHRS: DCM when the EKF is
  primary) come along as further references, same angles and trim. Time is ``TimeUS``
  (µs) or, in older firmware such as ArduCopter 3.3, ``TimeMS`` (ms) since boot.
* PX4 ULog (``.ulg``), :func:`load_ulog`, read with pyulog. IMU samples from
  ``sensor_combined`` (``gyro_rad`` rad/s, ``accelerometer_m_s2`` m/s², FRD, board
  rotation already applied), time ``timestamp`` (µs since boot) plus, for the
  accelerometer, ``accelerometer_timestamp_relative`` (µs). The reference is
  ``vehicle_attitude.q`` (w, x, y, z, FRD → NED); simulator logs may also hold
  ``vehicle_attitude_groundtruth`` (same layout), the simulator's true attitude.

ArduPilot's AHRS trim. ``ATT`` is not the attitude of the IMU frame: ArduPilot's EKF
reports its Euler angles with the ``AHRS_TRIM_X``/``AHRS_TRIM_Y`` parameters (rad)
subtracted from roll and pitch (``getEulerAngles``: ``euler - trim``), so that a
level-trimmed vehicle shows 0°. The logged IMU samples are in the untrimmed frame, so
the loader adds the trim back (``apply_ahrs_trim=True``): on log171 this removes a
1.18° roll / 0.30° pitch offset that otherwise appears at rest between the
accelerometer's gravity direction and ``ATT``. Until the EKF is ready (log171: its first
~9 s) ``ATT`` comes from ArduPilot's DCM filter, which applies the trim as a rotation
rather than to the angles; near level, with trims of about a degree, the two agree to
~0.01°. ``EKF1`` and ``AHR2`` carry the same trim (measured on log171 at rest: the
accelerometer's gravity direction is 1.27° and 1.15° off without it, 0.06° and 0.20°
with it). On log171 ``EKF1`` equals ``ATT`` to the logged 0.01° from 10 s on (before
that ``ATT`` is DCM's); its first 24 rows, logged before the EKF had an attitude, are
dropped.

The samples are kept as logged, calibration errors included: at rest log171's ``IMU``
reads 9.59 m/s² (``IMU2`` 9.41, ``IMU3`` 9.13), PX4's real board 9.70 m/s².

pyulog is imported inside :func:`load_ulog`, where it is needed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mavest.datasets import require_data
from mavest.onboard import OnboardLogError
from mavest.onboard.dataflash import DataflashRecords, instances, logged_parameters, read_records
from mavest.so3 import quats_from_euler_zyx

__all__ = [
    "DATAFLASH_LOG171",
    "ULOG_REAL",
    "ULOG_SIMULATOR",
    "AutopilotLog",
    "Reference",
    "load_dataflash",
    "load_ulog",
    "log_path",
]

#: The shared logs, relative to the data root (see :func:`log_path`).
DATAFLASH_LOG171 = "dataflash/dronekit-la-testdata_log171.bin"
ULOG_REAL = "ulog/pyulog_sample.ulg"
ULOG_SIMULATOR = "ulog/pyulog_sample_logging_tagged_and_default_params.ulg"

# ArduPilot's older logs have one message type per IMU; newer ones one type with "I".
_DATAFLASH_IMU_TYPES = {"IMU": 0, "IMU2": 1, "IMU3": 2}

_DATAFLASH_MESSAGE_HEADER = bytes([0xA3, 0x95])

# PX4 marks an accelerometer sample that is missing from a sensor_combined message
# with this relative timestamp (RELATIVE_TIMESTAMP_INVALID, INT32_MAX).
_PX4_RELATIVE_TIMESTAMP_INVALID = 2**31 - 1


# Dataflash messages with the autopilot's Roll, Pitch, Yaw (degrees) read besides ATT.
_DATAFLASH_OTHER_REFERENCES = ("EKF1", "AHR2")


@dataclass(frozen=True)
class Reference:
    """One more attitude the autopilot logged, beside the main reference.

    Attributes:
        source: what it was read from, e.g. ``"AHR2 + AHRS_TRIM"``.
        t: (M,) times in s, the log's time base.
        q: (M, 4) attitude (w, x, y, z), FRD body → NED, in the IMU samples' body frame.
    """

    source: str
    t: np.ndarray
    q: np.ndarray


@dataclass(frozen=True)
class AutopilotLog:
    """IMU samples and the autopilot's attitude from one onboard log, in mavest conventions.

    Attributes:
        name: file name without its suffix.
        autopilot: ``"ArduPilot"`` or ``"PX4"``.
        t: (N,) IMU sample times in s since the first IMU sample, strictly increasing.
        gyro: (N, 3) angular rate in rad/s, body FRD.
        accel: (N, 3) specific force in m/s², body FRD; about (0, 0, −g) at rest, level.
        reference_t: (M,) times of the autopilot's attitude, s, same time base as ``t``.
        reference_q: (M, 4) the autopilot's attitude (w, x, y, z), FRD body → NED, in
            the same body frame as the IMU samples (ArduPilot: trim added back).
        reference_source: what the reference was read from, e.g. ``"ATT"``.
        truth_t: (K,) times of the simulator's true attitude, or None if not logged.
        truth_q: (K, 4) true attitude (w, x, y, z), FRD → NED, or None.
        boot_time: autopilot time (s since boot) of ``t = 0``.
        notes: what the loader chose or found (IMU instance, trim, dropped samples).
        other_references: further attitudes the autopilot logged (ArduPilot: ``EKF1``,
            ``AHR2``), each in the same frame and time base as ``reference_q``.
    """

    name: str
    autopilot: str
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    reference_t: np.ndarray
    reference_q: np.ndarray
    reference_source: str
    truth_t: np.ndarray | None
    truth_q: np.ndarray | None
    boot_time: float
    notes: tuple[str, ...]
    other_references: tuple[Reference, ...] = ()

    @property
    def rate(self) -> float:
        """IMU sampling rate in Hz, from the median step (logs drop the odd sample)."""
        return 1.0 / float(np.median(np.diff(self.t)))

    @property
    def duration(self) -> float:
        """Span of the IMU samples in s."""
        return float(self.t[-1] - self.t[0])

    def __len__(self) -> int:
        return len(self.t)


def log_path(relative: str) -> Path:
    """The file ``<data root>/<relative>``, e.g. ``log_path(DATAFLASH_LOG171)``.

    FileNotFoundError naming MAVEST_DATA when the data folder or the file is absent.
    """
    folder, _, rest = relative.partition("/")
    path = require_data(folder) / rest
    if not path.is_file():
        raise FileNotFoundError(f"log file {path} does not exist")
    return path


def _existing_file(path: Path | str, kind: str) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{kind} {path} does not exist")
    return path


def _increasing(t: np.ndarray) -> np.ndarray:
    """Mask of the samples whose time is later than every earlier sample's.

    Logs occasionally repeat or reorder a sample; the estimator needs strictly
    increasing time, so such samples are dropped rather than sorted in.
    """
    if t.size == 0:
        return np.zeros(0, dtype=bool)
    previous_max = np.maximum.accumulate(np.concatenate(([-np.inf], t[:-1])))
    return t > previous_max


# --------------------------------------------------------------------------
# ArduPilot dataflash
# --------------------------------------------------------------------------


def _dataflash_seconds(records: DataflashRecords, name: str) -> np.ndarray:
    """Time since boot in s: ``TimeUS`` (µs) in newer firmware, ``TimeMS`` (ms) in older."""
    table = records.table(name)
    if "TimeUS" in records.columns(name):
        return table["TimeUS"].astype(np.float64) * 1e-6
    if "TimeMS" in records.columns(name):
        return table["TimeMS"].astype(np.float64) * 1e-3
    raise ValueError(f"{name} messages have neither TimeUS nor TimeMS")


def _read_dataflash(path: Path) -> DataflashRecords:
    """The log's records, indexed (decoded per message type when asked for)."""
    try:
        return read_records(path)
    except OnboardLogError as error:
        raise ValueError(f"not a readable dataflash log ({error})") from error


def load_dataflash(
    path: Path | str, imu_instance: int = 0, apply_ahrs_trim: bool = True
) -> AutopilotLog:
    """Load an ArduPilot dataflash log: one IMU instance and the ``ATT`` attitude.

    Args:
        path: the ``.bin`` file.
        imu_instance: 0 for ``IMU`` (the one ArduPilot's EKF uses by default), 1 for
            ``IMU2``, 2 for ``IMU3``.
        apply_ahrs_trim: add ``AHRS_TRIM_X``/``_Y`` back to ATT's roll and pitch, so that
            the reference is the attitude of the IMU frame (see the module docstring).

    Units and frames: ``t`` s since the first sample of that IMU; gyro rad/s and accel
    m/s² FRD, as logged; the reference from ATT's degrees, ZYX Euler, NED.

    FileNotFoundError if the file is absent; ValueError if it is not a dataflash log or
    holds no samples of that IMU or no ATT.
    """
    if imu_instance not in _DATAFLASH_IMU_TYPES.values():
        raise ValueError(f"imu_instance must be 0, 1 or 2, got {imu_instance}")
    path = _existing_file(path, "dataflash log")
    if path.suffix.lower() != ".bin":
        raise ValueError(f"{path.name}: expected an ArduPilot dataflash log (.bin)")
    with path.open("rb") as file:
        # Every binary dataflash message starts with these two bytes; checking the first
        # one spares a wrong file DFReader's byte-by-byte "bad header" complaints.
        if file.read(2) != _DATAFLASH_MESSAGE_HEADER:
            raise ValueError(f"{path.name}: not an ArduPilot dataflash log (bad first header)")
    records = _read_dataflash(path)
    parameters = logged_parameters(records)

    imu = [
        (kind, rows)
        for kind, instance, rows in instances(records, tuple(_DATAFLASH_IMU_TYPES))
        if instance == imu_instance
    ]
    if not imu:
        raise ValueError(f"{path.name}: no samples of IMU instance {imu_instance}")
    if not records.has("ATT"):
        raise ValueError(f"{path.name}: no ATT messages (the autopilot's attitude)")
    imu_kind, rows = imu[0]

    imu_boot_t = _dataflash_seconds(records, imu_kind)[rows]
    keep = _increasing(imu_boot_t)
    rows = rows[keep]
    imu_boot_t = imu_boot_t[keep]
    gyro = np.column_stack([records.column(imu_kind, f"Gyr{a}", rows) for a in "XYZ"])
    accel = np.column_stack([records.column(imu_kind, f"Acc{a}", rows) for a in "XYZ"])

    att_boot_t, euler_deg, att_dropped = _dataflash_angles(records, "ATT")
    notes = [
        f"IMU instance {imu_instance} ({imu_kind}), {len(rows)} samples",
        f"t = 0 is {imu_boot_t[0]:.3f} s after boot",
    ]
    if not np.all(keep) or att_dropped:
        notes.append(
            f"dropped {int(np.sum(~keep))} IMU and {att_dropped} ATT samples "
            "whose time did not increase"
        )
    trim_deg = np.degrees([parameters.get("AHRS_TRIM_X", 0.0), parameters.get("AHRS_TRIM_Y", 0.0)])
    trimmed = apply_ahrs_trim and bool(np.any(trim_deg))
    suffix = " + AHRS_TRIM" if trimmed else ""
    if trimmed:
        logged = ", ".join(["ATT", *(k for k in _DATAFLASH_OTHER_REFERENCES if records.has(k))])
        notes.append(
            f"AHRS_TRIM_X {trim_deg[0]:.2f}°, AHRS_TRIM_Y {trim_deg[1]:.2f}° "
            f"added to the roll, pitch of {logged}"
        )
    elif np.any(trim_deg):
        notes.append("AHRS trim not applied: ATT is the trimmed vehicle frame")

    t0 = float(imu_boot_t[0])

    def attitude(euler: np.ndarray) -> np.ndarray:
        if trimmed:
            # The autopilot logs euler − trim; adding the trim back gives the IMU frame's.
            euler = euler.copy()
            euler[:, :2] += trim_deg
        return quats_from_euler_zyx(np.radians(euler))

    others = []
    for kind in _DATAFLASH_OTHER_REFERENCES:
        if not records.has(kind):
            continue
        boot_t, euler, _ = _dataflash_angles(records, kind)
        waiting = _leading_uninitialised(euler)
        if waiting:
            notes.append(f"{kind}: first {waiting} rows dropped (no attitude yet: zero yaw)")
        boot_t, euler = boot_t[waiting:], euler[waiting:]
        if len(boot_t):
            others.append(Reference(kind + suffix, boot_t - t0, attitude(euler)))

    return AutopilotLog(
        name=path.stem,
        autopilot="ArduPilot",
        t=imu_boot_t - t0,
        gyro=gyro,
        accel=accel,
        reference_t=att_boot_t - t0,
        reference_q=attitude(euler_deg),
        reference_source="ATT" + suffix,
        truth_t=None,
        truth_q=None,
        boot_time=t0,
        notes=tuple(notes),
        other_references=tuple(others),
    )


def _dataflash_angles(records: DataflashRecords, name: str) -> tuple[np.ndarray, np.ndarray, int]:
    """Boot times (s), (M, 3) Roll, Pitch, Yaw in degrees, and how many rows were dropped
    because their time did not increase."""
    boot_t = _dataflash_seconds(records, name)
    keep = _increasing(boot_t)
    euler_deg = np.column_stack([records.column(name, c) for c in ("Roll", "Pitch", "Yaw")])
    return boot_t[keep], euler_deg[keep], int(np.sum(~keep))


def _leading_uninitialised(euler_deg: np.ndarray) -> int:
    """How many first rows an EKF logged before it had an attitude: rows equal to the
    first one while its yaw is exactly 0 (the trim's negative and no heading)."""
    if len(euler_deg) == 0 or euler_deg[0, 2] != 0.0:
        return 0
    same = np.all(euler_deg == euler_deg[0], axis=1)
    return len(same) if np.all(same) else int(np.argmin(same))


# --------------------------------------------------------------------------
# PX4 ULog
# --------------------------------------------------------------------------


def _ulog_columns(data: dict[str, np.ndarray], field: str, count: int) -> np.ndarray:
    """(N, count) float64 from a ULog array field stored as ``field[0]``, ``field[1]``, ..."""
    return np.column_stack([data[f"{field}[{i}]"] for i in range(count)]).astype(np.float64)


def _ulog_quaternions(data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Times (µs) and normalised (w, x, y, z) quaternions of a vehicle_attitude-like topic.

    ``timestamp_sample`` (the IMU sample the estimate belongs to) is used where newer
    PX4 fills it in; it is 0 in topics that do not (e.g. the simulator's ground truth),
    and older PX4 has only ``timestamp``.
    """
    sample = data.get("timestamp_sample")
    if sample is not None and np.all(sample > 0):
        t_us = sample.astype(np.int64)
    else:
        t_us = data["timestamp"].astype(np.int64)
    q = _ulog_columns(data, "q", 4)
    q /= np.linalg.norm(q, axis=1, keepdims=True)  # logged as float32
    return t_us, q


def _topics(ulog: Any) -> dict[str, dict[str, np.ndarray]]:
    return {d.name: d.data for d in ulog.data_list if d.multi_id == 0}


def load_ulog(path: Path | str) -> AutopilotLog:
    """Load a PX4 ULog: ``sensor_combined``, ``vehicle_attitude`` and, if logged, truth.

    Units and frames: ``t`` s since the first ``sensor_combined`` sample (gyro time);
    gyro rad/s and accel m/s², FRD, as logged. The accelerometer sample of a message
    may lag or lead the gyro by ``accelerometer_timestamp_relative`` µs; both share the
    gyro's time here (the offset is recorded in ``notes``), and messages whose
    accelerometer part is marked invalid are dropped. ``vehicle_attitude`` and
    ``vehicle_attitude_groundtruth`` quaternions are (w, x, y, z) FRD → NED already.

    FileNotFoundError if the file is absent; ValueError if it is not a ULog or lacks
    ``sensor_combined`` or ``vehicle_attitude``. A missing ground truth is not an error:
    ``truth_t``/``truth_q`` are None and ``notes`` says so.
    """
    from pyulog import ULog  # development extra: only this loader needs it

    path = _existing_file(path, "ULog file")
    wanted = ["sensor_combined", "vehicle_attitude", "vehicle_attitude_groundtruth"]
    try:
        ulog = ULog(str(path), wanted)
    except Exception as error:  # pyulog raises bare Exceptions on a bad header
        raise ValueError(f"{path.name}: not a readable ULog file ({error})") from error
    topics = _topics(ulog)
    for required in ("sensor_combined", "vehicle_attitude"):
        if required not in topics:
            raise ValueError(f"{path.name}: no {required} topic in this log")

    sensors = topics["sensor_combined"]
    gyro_t_us = sensors["timestamp"].astype(np.int64)
    accel_offset_us = sensors.get(
        "accelerometer_timestamp_relative", np.zeros_like(gyro_t_us)
    ).astype(np.int64)
    valid = (accel_offset_us != _PX4_RELATIVE_TIMESTAMP_INVALID) & _increasing(gyro_t_us)
    if not np.any(valid):
        raise ValueError(f"{path.name}: sensor_combined has no valid samples")
    gyro = _ulog_columns(sensors, "gyro_rad", 3)[valid]
    accel = _ulog_columns(sensors, "accelerometer_m_s2", 3)[valid]
    t0_us = int(gyro_t_us[valid][0])

    notes = [
        f"sensor_combined, {int(np.sum(valid))} samples",
        f"t = 0 is {t0_us * 1e-6:.3f} s after boot",
        "accelerometer_timestamp_relative up to "
        f"{int(np.max(np.abs(accel_offset_us[valid])))} µs (accel paired with gyro time)",
    ]
    if not np.all(valid):
        notes.append(f"dropped {int(np.sum(~valid))} sensor_combined samples (invalid/repeated)")

    reference_t_us, reference_q = _ulog_quaternions(topics["vehicle_attitude"])
    keep = _increasing(reference_t_us)
    truth_t = truth_q = None
    if "vehicle_attitude_groundtruth" in topics:
        truth_t_us, truth_q = _ulog_quaternions(topics["vehicle_attitude_groundtruth"])
        truth_keep = _increasing(truth_t_us)
        truth_t, truth_q = (truth_t_us[truth_keep] - t0_us) * 1e-6, truth_q[truth_keep]
    else:
        notes.append("no vehicle_attitude_groundtruth (not a simulator log)")

    return AutopilotLog(
        name=path.stem,
        autopilot="PX4",
        t=(gyro_t_us[valid] - t0_us) * 1e-6,
        gyro=gyro,
        accel=accel,
        reference_t=(reference_t_us[keep] - t0_us) * 1e-6,
        reference_q=reference_q[keep],
        reference_source="vehicle_attitude",
        truth_t=truth_t,
        truth_q=truth_q,
        boot_time=t0_us * 1e-6,
        notes=tuple(notes),
    )
