"""Onboard logs read per second: mavest's bulk readers beside pymavlink's DFReader and pyulog.

    .venv/bin/python tools/onboard_speed.py [LOG.bin|LOG.ulg ...] [--rounds 5]
                                            [--no-replay] [--markdown] [--results [FILE]]

For each log (default: the shared ``dataflash/*.bin`` and ``ulog/*.ulg`` files under the
data folder, see MAVEST_DATA) one row, figures in IMU samples per second of wall time:

* ``mavest.onboard.load``: the whole log decoded, every IMU, magnetometer, GPS, airspeed
  and attitude series in SI units;
* DataFlash: pymavlink's ``DFReader_binary`` reading every message (``recv_msg``), and
  only the IMU messages (``recv_match(type=IMU, IMU2, IMU3)``);
* ULog: pyulog's ``ULog()`` reading every topic;
* ``mavest replay LOG``: the whole command in a fresh process (start-up, decoding,
  estimation, scoring), unless ``--no-replay``.

The samples counted are the log's IMU samples of every instance (what a reader hands
over), the same count for every column of a row; ``mavest replay`` estimates one
instance. Each figure is the median of ``--rounds`` interleaved rounds, in the same run;
the numba cache is warmed first, so compilation is not counted. ``×`` is mavest's load
over the slower reading-everything figure (DFReader recv_msg, pyulog).
--results writes the table as the Onboard logs section of docs/results.md (or FILE).
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.evaluation import report
from mavest.onboard import OnboardLogError, detect, load

_IMU_TYPES = ["IMU", "IMU2", "IMU3"]


def _dfreader_all(path: Path) -> None:
    from pymavlink.DFReader import DFReader_binary

    reader = DFReader_binary(str(path))
    while reader.recv_msg() is not None:
        pass


def _dfreader_imu(path: Path) -> None:
    from pymavlink.DFReader import DFReader_binary

    reader = DFReader_binary(str(path))
    while reader.recv_match(type=_IMU_TYPES) is not None:
        pass


def _pyulog(path: Path) -> None:
    from pyulog import ULog

    ULog(str(path))


def _replay(path: Path) -> None:
    command = [sys.executable, "-m", "mavest", "replay", str(path), "--quiet"]
    finished = subprocess.run(command, capture_output=True, text=True, check=False)
    if finished.returncode != 0:
        last = (finished.stderr.strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"mavest replay {path.name} failed ({finished.returncode}): {last}")


def default_logs() -> list[Path]:
    """The shared .bin and .ulg files; SystemExit naming MAVEST_DATA when there are none."""
    root = data_root()
    logs: list[Path] = []
    if root is not None:
        logs += sorted(p for p in (root / "dataflash").glob("*") if p.suffix.lower() == ".bin")
        logs += sorted((root / "ulog").glob("*.ulg"))
    if not logs:
        raise SystemExit(
            f"no onboard logs given and none found: set {DATA_ENV_VAR} to a folder "
            "containing dataflash/ and ulog/, or name the logs"
        )
    return logs


def contenders(kind: str, replay: bool) -> dict[str, Callable[[Path], object] | None]:
    """The columns, each a reader of the file (None: not for this format)."""
    columns: dict[str, Callable[[Path], object] | None] = {
        "mavest.onboard.load": load,
        "DFReader recv_msg (all)": _dfreader_all if kind == "dataflash" else None,
        "DFReader recv_match (IMU)": _dfreader_imu if kind == "dataflash" else None,
        "pyulog ULog()": _pyulog if kind == "ulog" else None,
    }
    if replay:
        columns["mavest replay"] = _replay
    return columns


def measure(path: Path, rounds: int, replay: bool) -> tuple[int, dict[str, float | None]]:
    """IMU samples of the log and the median seconds of each column's reading."""
    kind = detect(path)
    if kind is None:
        raise OnboardLogError(f"{path.name}: neither an ArduPilot DataFlash log nor a PX4 ULog")
    samples = sum(len(imu.t_us) for imu in load(path).imus)  # (also warms the numba cache)
    readers = contenders(kind, replay)
    times: dict[str, list[float]] = {name: [] for name, r in readers.items() if r is not None}
    for _ in range(rounds):
        for name in times:
            reader = readers[name]
            assert reader is not None
            start = time.perf_counter()
            reader(path)
            times[name].append(time.perf_counter() - start)
    return samples, {
        name: statistics.median(times[name]) if name in times else None for name in readers
    }


def print_table(
    rows: list[tuple[Path, int, dict[str, float | None]]], rounds: int, markdown: bool
) -> None:
    names = list(rows[0][2])
    print(f"IMU samples per second (thousands), median of {rounds} interleaved rounds")
    header = ["log", "IMU samples", *names, "× (load / read-all)"]
    if markdown:
        print("\n| " + " | ".join(header) + " |")
        print("|---|" + "---:|" * (len(header) - 1))
    else:
        print("  ".join(f"{h:>26}" if i else f"{h:<40}" for i, h in enumerate(header)))
    for path, samples, seconds in rows:
        rates = [f"{samples / s / 1e3:,.0f}" if s else "–" for s in seconds.values()]
        read_all = seconds.get("DFReader recv_msg (all)") or seconds.get("pyulog ULog()")
        ours = seconds["mavest.onboard.load"]
        ratio = f"{read_all / ours:.0f}" if read_all and ours else "–"
        cells = [path.name, str(samples), *rates, ratio]
        if markdown:
            print("| " + " | ".join(cells) + " |")
        else:
            print("  ".join(f"{c:>26}" if i else f"{c:<40}" for i, c in enumerate(cells)))


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("logs", type=Path, nargs="*", help="onboard logs (default: shared)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    parser.add_argument(
        "--no-replay", action="store_true", help="leave out the whole `mavest replay` column"
    )
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    markdown = args.markdown or args.results is not None
    logs = args.logs or default_logs()
    try:
        rows = [(path, *measure(path, args.rounds, not args.no_replay)) for path in logs]
    except (OnboardLogError, RuntimeError) as error:
        report.progress("onboard_speed", str(error))
        return 2
    with report.results_section(args.results, "Onboard logs", __file__, argv, __doc__):
        print_table(rows, args.rounds, markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
