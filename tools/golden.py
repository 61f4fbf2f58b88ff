"""Golden outputs: what mavest gives for a few fixed inputs, committed to compare against.

    .venv/bin/python tools/golden.py            # compare with tests/golden/, print a table
    .venv/bin/python tools/golden.py --write    # replace tests/golden/'s outputs (a change
                                                # meant to alter the estimates: commit them
                                                # with the change, and say why in its message)
    .venv/bin/python tools/golden.py --write-input  # re-make the input flight (rarely)

The input is ``tests/golden/flight.tlog``: a 12 s simulated flight at 100 Hz (ArduPilot
RAW_IMU with the magnetometer, SIMSTATE, ATTITUDE, HEARTBEAT), made once with
``mavest sim`` and committed, so that neither JSBSim nor NumPy's random streams can
change it. The outputs, CSV to be read in a diff:

- ``estimate_<variant>.csv``: :func:`mavest.estimate` on the flight's RAW_IMU samples
  (decoded by pymavlink) for each of :data:`VARIANTS` (6-D and 9-D, each update kind,
  the right error), every :data:`EVERY`-th sample and the last: q, bias, the covariance's upper
  triangle, the flags, and the gravity update's NIS;
- ``smooth_<variant>.csv``: :func:`mavest.smooth` alike, for each of
  :data:`SMOOTHED` (its flags and NIS are its forward pass's);
- ``replay_attitude.csv``: the ATTITUDE and ATTITUDE_QUATERNION messages that
  ``mavest replay flight.tlog --out-tlog OUT`` writes (decoded by pymavlink);
- ``replay_estimates.csv``: its ``--estimates`` table;

the replay's files with every :data:`EVERY`-th row and the last.

The filter's arithmetic is the same on every machine (compiled without fast-math or
FMA contraction), so the comparison asks for agreement to :data:`TOLERANCE`, far below
any change of the filter's rules; the table shows the largest difference per file.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

import mavest
from mavest.estimator import EstimatorConfig
from mavest.mavlink.messages import decode_imu
from mavest.paths import write_atomically
from mavest.service.config import ServiceConfig
from mavest.service.runners import Outputs, replay

GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "golden"
FLIGHT = GOLDEN / "flight.tlog"
FLIGHT_SECONDS = 12.0
FLIGHT_RATE = 100.0
FLIGHT_SEED = 5
EVERY = 25  # of the filter's samples, those kept in the files
# absolute, in each file's units (rad, rad/s, their squares, degrees): a changed rule
# moves the estimates by orders of magnitude more; machines agree to the last bit
TOLERANCE = 1e-9


@dataclass(frozen=True)
class Variant:
    name: str
    config: EstimatorConfig
    mag: bool


VARIANTS = (
    Variant("6d", EstimatorConfig(), mag=False),
    Variant("9d", EstimatorConfig(), mag=True),
    Variant("6d_ekf", EstimatorConfig(update="ekf"), mag=False),
    Variant("6d_sigma_point", EstimatorConfig(update="sigma_point"), mag=False),
    Variant("9d_right_error", EstimatorConfig(error="right", chart="exp"), mag=True),
)
SMOOTHED = VARIANTS[:2]  # the smoother's own rules show in the default configuration


def write_input() -> str:
    from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

    GOLDEN.mkdir(exist_ok=True)
    return write_flight_tlog(
        FLIGHT, FLIGHT_SECONDS, FLIGHT_RATE, AUTOPILOTS["ardupilot"], FLIGHT_SEED
    )


def imu_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """t (s), gyro (rad/s), accel (m/s²), mag (µT) of the first IMU stream in the tlog,
    decoded by pymavlink."""
    connection = mavutil.mavlink_connection(str(path))
    rows = []
    first = None
    try:
        while (message := connection.recv_match(type="RAW_IMU")) is not None:
            sample = decode_imu(message)
            if sample is None or sample.mag is None:
                continue
            first = first or sample.stream
            if sample.stream == first:
                rows.append((sample.ticks * sample.tick, *sample.gyro, *sample.accel, *sample.mag))
    finally:
        connection.close()
    table = np.array(rows, dtype=float)
    return table[:, 0], table[:, 1:4], table[:, 4:7], table[:, 7:10]


def _csv(header: list[str], columns: list[np.ndarray]) -> str:
    out = io.StringIO()
    out.write(",".join(header) + "\n")
    for row in zip(*columns, strict=True):
        out.write(",".join(_number(value) for value in row) + "\n")
    return out.getvalue()


def _number(value: float | int | np.generic) -> str:
    if isinstance(value, np.integer | int | np.bool_):
        return str(int(value))
    return repr(float(value))  # shortest text that reads back as the same double


def estimate_csv(
    variant: Variant,
    inputs: tuple[np.ndarray, ...],
    estimator: Callable[..., Any] = mavest.estimate,
) -> str:
    """``estimator`` (:func:`mavest.estimate` or :func:`mavest.smooth`) on the inputs."""
    t, gyro, accel, mag = inputs
    series = estimator(t, gyro, accel, mag if variant.mag else None, variant.config)
    keep = np.unique(np.r_[np.arange(0, len(series), EVERY), len(series) - 1])
    upper = np.triu_indices(6)
    cov = series.cov[keep][:, upper[0], upper[1]]
    header = ["t", "qw", "qx", "qy", "qz", "bx", "by", "bz"]
    header += [f"P{i}{j}" for i, j in zip(*upper, strict=True)]
    header += ["flags", "nis"]
    columns = [series.t[keep], *series.q[keep].T, *series.bias[keep].T, *cov.T]
    columns += [series.flags[keep], series.nis[keep]]
    return _csv(header, columns)


def replay_outputs(flight: Path) -> dict[str, str]:
    """The replay's ATTITUDE messages and estimates table, as CSV text."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "out.tlog"
        table = Path(folder) / "estimates.csv"
        outputs = Outputs(tlog=out, estimates=table)
        asyncio.run(replay(flight, ServiceConfig(), outputs, progress=False))
        connection = mavutil.mavlink_connection(str(out))
        rows = []
        try:
            while (
                message := connection.recv_match(type=["ATTITUDE", "ATTITUDE_QUATERNION"])
            ) is not None:
                if message.get_type() == "ATTITUDE":
                    values = (message.roll, message.pitch, message.yaw, np.nan)
                else:
                    values = (message.q1, message.q2, message.q3, message.q4)
                rows.append((message.get_msgId(), message.time_boot_ms, *values))
        finally:
            connection.close()
        columns = list(np.array(rows, dtype=float).T)
        columns[0] = columns[0].astype(int)
        columns[1] = columns[1].astype(int)
        attitude = _csv(["msgid", "time_boot_ms", "a", "b", "c", "d"], columns)
        return {
            "replay_attitude.csv": _every_nth(attitude),
            "replay_estimates.csv": _every_nth(table.read_text()),
        }


def _every_nth(text: str) -> str:
    """The header, every :data:`EVERY`-th row and the last, each led by its row number
    (an estimate depends on every sample before it, so a change anywhere shows in the
    rows after it; the last row's number holds the count)."""
    header, *rows = text.splitlines()
    kept = [f"{i},{row}" for i, row in enumerate(rows) if i % EVERY == 0 or i == len(rows) - 1]
    return "\n".join([f"row,{header}", *kept]) + "\n"


def outputs() -> dict[str, str]:
    """Every golden file's expected text, computed by this mavest."""
    inputs = imu_arrays(FLIGHT)
    made = {f"estimate_{v.name}.csv": estimate_csv(v, inputs) for v in VARIANTS}
    made.update({f"smooth_{v.name}.csv": estimate_csv(v, inputs, mavest.smooth) for v in SMOOTHED})
    made.update(replay_outputs(FLIGHT))
    return made


@dataclass(frozen=True)
class Difference:
    name: str
    rows: int
    largest: float  # the largest absolute difference of a number (inf: shapes or text differ)
    where: str  # its column and row

    @property
    def same(self) -> bool:
        return self.largest <= TOLERANCE


def _cells(text: str) -> tuple[list[str], list[list[str]]]:
    lines = text.splitlines()
    return lines[0].split(","), [line.split(",") for line in lines[1:]]


def compare(name: str, expected: str, actual: str) -> Difference:
    """How far ``actual`` is from ``expected``: numbers by value, anything else by text."""
    header, rows = _cells(expected)
    new_header, new_rows = _cells(actual)
    if header != new_header or len(rows) != len(new_rows):
        return Difference(name, len(new_rows), float("inf"), "columns or rows differ")
    largest, where = 0.0, ""
    for i, (row, new_row) in enumerate(zip(rows, new_rows, strict=True)):
        for column, a, b in zip(header, row, new_row, strict=True):
            if a == b:
                continue
            try:
                gap = abs(float(a) - float(b))
            except ValueError:
                gap = float("inf")
            if not gap <= largest:  # NaN against a number counts as a difference
                largest, where = (gap if gap == gap else float("inf")), f"{column}, row {i + 1}"
    return Difference(name, len(rows), largest, where)


def check(made: Callable[[], dict[str, str]] = outputs) -> list[Difference]:
    """Each committed golden file against what this mavest computes."""
    results = []
    for name, text in made().items():
        path = GOLDEN / name
        if not path.exists():
            results.append(Difference(name, 0, float("inf"), "not committed"))
            continue
        results.append(compare(name, path.read_text(), text))
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--write", action="store_true", help="replace the golden outputs")
    parser.add_argument("--write-input", action="store_true", help="re-make the input flight")
    args = parser.parse_args(argv)
    if args.write_input:
        print(write_input())
    if args.write or args.write_input:
        for name, text in outputs().items():
            write_atomically(GOLDEN / name, text.encode())
            print(f"wrote {GOLDEN / name}")
        return 0
    differences = check()
    print(f"{'file':28} {'rows':>5} {'largest difference':>19}  where")
    for d in differences:
        mark = "" if d.same else "  CHANGED"
        print(f"{d.name:28} {d.rows:5d} {d.largest:19.3g}  {d.where}{mark}")
    return 0 if all(d.same for d in differences) else 1


if __name__ == "__main__":
    sys.exit(main())
