"""Logs per second through `mavest fleet` on Dask, with 1 and 2 workers, against a plain loop.

    .venv/bin/python tools/fleet_speed.py [--logs 8] [--seconds 60] [--rate 400]
                                          [--quick] [--markdown] [--results [FILE]]

Simulated flights (``--seconds`` long, the IMU at ``--rate`` Hz, with the truth) are
written to a temporary folder, then replayed three ways, each log as the fleet
replays it (:func:`mavest.fleet.rows.log_rows`: the replay, its streams' mean σ, its
row):

* a plain loop in this process, one log after the other;
* a LocalCluster of 1 worker process, then of 2 (``Client.map``, as ``mavest fleet``).

The figures are logs per second of wall time, once the kernels are loaded (the loop
and each worker load them once, first) and the cluster has started (its start-up
time is a column of its own). Dask's overhead per log is (the fleet on 1 worker −
the loop) / logs: the task's round trip, the rows sent back. ``×`` is the logs/s
over the 1-worker fleet's (a machine of N free cores approaches N). ``--quick``:
2 logs of 3 s at 100 Hz per worker count (a check that it runs, not a measurement).
--results writes the table as the Fleet section of docs/results.md (or FILE).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from distributed import Client

from mavest.evaluation import report
from mavest.fleet.cluster import local_cluster, run_fleet
from mavest.fleet.rows import LogTask, log_rows, warm_up
from mavest.service.config import ServiceConfig
from mavest.sim.vehicle import write_flight_tlog

# distinct flights written; more logs are copies of these (the replay's cost does not
# depend on which flight it is)
_DISTINCT = 4


def write_logs(folder: Path, count: int, seconds: float, rate: float) -> list[Path]:
    logs = []
    for i in range(count):
        path = folder / f"flight{i:03}.tlog"
        if i < _DISTINCT:
            write_flight_tlog(path, seconds, rate, seed=i + 1)
        else:
            shutil.copyfile(logs[i % _DISTINCT], path)
        logs.append(path)
    return logs


def measure(tasks: list[LogTask]) -> dict[str, tuple[float, float]]:
    """Per configuration: (seconds for all the logs, start-up seconds)."""
    figures: dict[str, tuple[float, float]] = {}
    warm_up()
    start = time.perf_counter()
    for task in tasks:
        rows = log_rows(task)
        if rows[0]["status"] != "ok":
            raise RuntimeError(f"{task.source}: {rows[0]['error']}")
    figures["plain loop"] = (time.perf_counter() - start, 0.0)
    for workers in (1, 2):
        began = time.perf_counter()
        with local_cluster(workers) as cluster, Client(cluster) as client:
            client.run(warm_up)
            started = time.perf_counter() - began
            start = time.perf_counter()
            result = run_fleet(tasks, client, progress=False)
            took = time.perf_counter() - start
        if result.done != len(tasks) or any(row["status"] != "ok" for row in result.rows):
            raise RuntimeError(f"the fleet on {workers} worker(s) did not replay every log")
        figures[f"fleet, {workers} worker{'s' if workers > 1 else ''}"] = (took, started)
    return figures


def print_table(
    figures: dict[str, tuple[float, float]], logs: int, seconds: float, rate: float, markdown: bool
) -> None:
    one = logs / figures["fleet, 1 worker"][0]
    header = ["", "logs/s", "s per log", "×", "start-up, s"]
    rows = []
    for name, (took, started) in figures.items():
        per_second = logs / took
        rows.append(
            [
                name,
                f"{per_second:.2f}",
                f"{took / logs:.3f}",
                f"{per_second / one:.2f}" if name.startswith("fleet") else "",
                f"{started:.1f}" if name.startswith("fleet") else "",
            ]
        )
    overhead = (figures["fleet, 1 worker"][0] - figures["plain loop"][0]) / logs
    about = (
        f"{logs} simulated flights of {seconds:g} s, IMU at {rate:g} Hz "
        f"({int(seconds * rate) + 1} samples each)"
    )
    closing = f"Dask's overhead per log (1 worker − the loop): {1000 * overhead:.0f} ms"
    if markdown:
        print(about + ".\n")
        print("| " + " | ".join(header) + " |")
        print("|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|")
        for cells in rows:
            print("| " + " | ".join(cells) + " |")
        print(f"\n{closing}.")
    else:
        print(about)
        print(f"{header[0]:<18}" + "".join(f"{c:>13}" for c in header[1:]))
        for cells in rows:
            print(f"{cells[0]:<18}" + "".join(f"{c:>13}" for c in cells[1:]))
        print(closing)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--logs", type=int, default=8, help="how many logs (default 8)")
    parser.add_argument("--seconds", type=float, default=60.0, help="each flight's length")
    parser.add_argument("--rate", type=float, default=400.0, help="IMU rate, Hz")
    parser.add_argument("--quick", action="store_true", help="2 logs of 3 s at 100 Hz")
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.logs, args.seconds, args.rate = 2, 3.0, 100.0
    markdown = args.markdown or args.results is not None
    with tempfile.TemporaryDirectory(prefix="mavest-fleet-speed-") as folder:
        logs = write_logs(Path(folder), args.logs, args.seconds, args.rate)
        tasks = [LogTask(str(log), ServiceConfig()) for log in logs]
        try:
            figures = measure(tasks)
        except RuntimeError as error:
            report.progress("fleet_speed", str(error))
            return 2
    with report.results_section(args.results, "Fleet", __file__, argv, __doc__):
        print_table(figures, args.logs, args.seconds, args.rate, markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
