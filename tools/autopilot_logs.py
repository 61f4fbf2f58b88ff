"""Real autopilot logs: mavest and peers from the logged IMU against the autopilot's attitude.

    .venv/bin/python tools/autopilot_logs.py [--peers VQF Fusion] [--imu 0] [--no-ahrs-trim]
                                             [--markdown]

Reads the ArduPilot dataflash log171 and the two PX4 ULogs from $MAVEST_DATA (default
../shared/data), runs every filter in 6-D (gyro and accelerometer) on the logged IMU
samples and scores it, per log and per time segment, against the autopilot's own
estimate (ArduPilot ATT with the AHRS trim added back, PX4 vehicle_attitude) and, for
the PX4 simulator log, against the simulator's true attitude, where the autopilot's
own error is shown too. Roll and pitch: RMSE of the ZYX Euler angle differences;
inclination: RMSE of the tilt error (BROAD's scoring). Heading is not scored: a 6-D
filter has none.

Each estimate is interpolated onto the times of what it is scored against (slerp
between the two neighbouring samples); the reference is never interpolated. Segment
times are seconds from the log's first IMU sample (log171: boot time 11.46 s).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mavest import estimate
from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.datasets.autopilot_logs import (
    DATAFLASH_LOG171,
    ULOG_REAL,
    ULOG_SIMULATOR,
    AutopilotLog,
    load_dataflash,
    load_ulog,
    log_path,
)
from mavest.evaluation.metrics import attitude_errors, wrap_angles
from mavest.evaluation.peers import PEERS
from mavest.so3 import euler_zyx_from_quats

Segment = tuple[str, float, float]  # label, start s, end s

#: Log file → (label in the table, segments); every log also gets a whole-log row. The
#: log171 segments follow the data README (at rest, flying, crash and flip); the
#: pyulog_sample log is moved by hand for its first 10 s, then rests.
LOGS: dict[str, tuple[str, list[Segment]]] = {
    DATAFLASH_LOG171: (
        "ArduCopter log171",
        [("rest", 0.0, 60.0), ("flight", 60.0, 200.0), ("crash", 200.0, np.inf)],
    ),
    ULOG_REAL: ("PX4 pyulog_sample", [("moved by hand", 0.0, 10.0), ("rest", 10.0, np.inf)]),
    ULOG_SIMULATOR: ("PX4 simulator", []),
}

AUTOPILOT = "autopilot"

Filter = Callable[[AutopilotLog], np.ndarray]


def mavest_filter(log: AutopilotLog) -> np.ndarray:
    """mavest with its default configuration, 6-D."""
    return estimate(log.t, log.gyro, log.accel).q


def peer_filter(name: str) -> Filter:
    """A peer from :data:`mavest.evaluation.peers.PEERS`, 6-D, at the log's median rate."""
    adapter = PEERS[name]

    def run(log: AutopilotLog) -> np.ndarray:
        return adapter(log.t, log.gyro, log.accel, None, log.rate)

    return run


def slerp_onto(t: np.ndarray, q: np.ndarray, t_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``q`` (w, x, y, z) at times ``t``, slerped onto the ``t_new`` inside [t[0], t[-1]].

    Returns (mask over t_new of the times inside, (M, 4) quaternions at those times).
    """
    inside = (t_new >= t[0]) & (t_new <= t[-1])
    rotations = Slerp(t, Rotation.from_quat(q[:, [1, 2, 3, 0]]))(t_new[inside])
    return inside, rotations.as_quat()[:, [3, 0, 1, 2]]


@dataclass(frozen=True)
class Score:
    """RMSE in degrees of one estimate against one reference over one segment."""

    n: int
    roll: float
    pitch: float
    inclination: float


def score(q_est: np.ndarray, q_ref: np.ndarray) -> Score:
    """Roll, pitch (ZYX Euler differences, wrapped) and inclination RMSE, degrees."""
    if len(q_ref) == 0:
        return Score(0, np.nan, np.nan, np.nan)
    euler_error = wrap_angles(euler_zyx_from_quats(q_est) - euler_zyx_from_quats(q_ref))
    inclination = attitude_errors(q_est, q_ref).inclination

    def rms_deg(x: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(np.square(x)))))

    return Score(
        len(q_ref), rms_deg(euler_error[:, 0]), rms_deg(euler_error[:, 1]), rms_deg(inclination)
    )


def score_log(
    label: str, log: AutopilotLog, filters: dict[str, Filter], segments: list[Segment]
) -> list[list[str]]:
    """Table rows: every filter against the reference (and truth), per segment and whole."""
    estimates = {name: (log.t, run(log)) for name, run in filters.items()}
    references = [(log.reference_source, log.reference_t, log.reference_q, estimates)]
    if log.truth_t is not None and log.truth_q is not None:
        # Against the truth the autopilot is one more estimate, interpolated like ours.
        with_autopilot = estimates | {AUTOPILOT: (log.reference_t, log.reference_q)}
        references.append(("groundtruth", log.truth_t, log.truth_q, with_autopilot))

    whole = ("all", 0.0, np.inf)
    rows = []
    for against, ref_t, ref_q, candidates in references:
        # Score every candidate at the same reference times: those all of them cover
        # (the autopilot's own estimate starts later than the IMU samples).
        common = np.ones(len(ref_t), dtype=bool)
        for t, _ in candidates.values():
            common &= (ref_t >= t[0]) & (ref_t <= t[-1])
        at_ref = {name: slerp_onto(t, q, ref_t[common]) for name, (t, q) in candidates.items()}
        times = ref_t[common]
        for segment_label, start, end in [*segments, whole]:
            shown_end = min(end, float(log.t[-1]))
            segment = f"{segment_label} {start:.0f}–{shown_end:.0f} s"
            chosen = (times >= start) & (times < end)
            for name, (_, q_at_ref) in at_ref.items():
                s = score(q_at_ref[chosen], ref_q[common][chosen])
                rows.append(
                    [
                        label,
                        segment,
                        against,
                        str(s.n),
                        name,
                        f"{s.roll:.2f}",
                        f"{s.pitch:.2f}",
                        f"{s.inclination:.2f}",
                    ]
                )
    return rows


def _load(relative: str, imu: int, ahrs_trim: bool) -> AutopilotLog:
    path = log_path(relative)
    if relative.endswith(".bin"):
        return load_dataflash(path, imu_instance=imu, apply_ahrs_trim=ahrs_trim)
    return load_ulog(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument(
        "--peers",
        nargs="*",
        default=["VQF", "Fusion"],
        choices=sorted(PEERS),
        help="peer filters to run (default: VQF Fusion; Madgwick and Mahony are slow)",
    )
    parser.add_argument(
        "--imu", type=int, default=0, choices=[0, 1, 2], help="ArduPilot IMU instance (default 0)"
    )
    parser.add_argument(
        "--no-ahrs-trim",
        action="store_true",
        help="score against ATT as logged (the trimmed vehicle frame, not the IMU's)",
    )
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    args = parser.parse_args(argv)

    if data_root() is None:
        print(
            f"autopilot_logs: data folder not found: set {DATA_ENV_VAR} to the folder "
            "that holds dataflash/ and ulog/",
            file=sys.stderr,
        )
        return 2
    logs = []
    notes = []
    for relative, (label, segments) in LOGS.items():
        try:
            logs.append((label, _load(relative, args.imu, not args.no_ahrs_trim), segments))
        except (FileNotFoundError, ValueError, ImportError) as error:
            # One unreadable log (or pyulog not installed) should not hide the others.
            print(f"autopilot_logs: {relative}: {error}", file=sys.stderr)
    if not logs:
        print("autopilot_logs: no log could be read (see above)", file=sys.stderr)
        return 2

    filters: dict[str, Filter] = {"mavest": mavest_filter}
    for name in args.peers:
        filters[name] = peer_filter(name)
    rows = []
    for label, log, segments in logs:
        rows += score_log(label, log, filters, segments)
        notes.append(f"{label} = {log.name}: " + "; ".join(log.notes))

    header = [
        "log",
        "segment",
        "against",
        "n",
        "filter",
        "roll RMSE °",
        "pitch RMSE °",
        "inclination RMSE °",
    ]
    _print_table(header, rows, args.markdown)
    for note in notes:
        print(f"\n{note}" if args.markdown else note)
    return 0


def _print_table(header: list[str], rows: list[list[str]], markdown: bool) -> None:
    if markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "|".join("---" for _ in header) + "|")
        for row in rows:
            print("| " + " | ".join(row) + " |")
        return
    text_columns = {0, 1, 2, 4}
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print(
            "  ".join(
                cell.ljust(w) if i in text_columns else cell.rjust(w)
                for i, (cell, w) in enumerate(zip(row, widths, strict=True))
            )
        )


if __name__ == "__main__":
    raise SystemExit(main())
