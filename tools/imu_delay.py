"""How long BROAD's IMU samples lag its optical truth, as every filter sees it.

    .venv/bin/python tools/imu_delay.py [--quick] [--results [FILE]]

Each filter is run once per trial on the samples as recorded (6-D: gyroscope and
accelerometer) and its attitude is carried forward by each delay τ of
:data:`mavest.datasets.broad.DELAYS`, q ⊗ Exp((ω − b) τ), as ``EstimatorConfig.imu_delay``
carries mavest's
(:func:`mavest.estimator.frames.lead`; a peer's with the gyro's rate,
:func:`mavest.evaluation.accuracy.peer_led`). The mean 6-D inclination RMSE over the
trials, per delay, for mavest's filter and smoother (defaults) and for VQF and offline
VQF: if the lag is the data's, every filter's error is least at the same delay, and
carrying them all forward by it leaves their differences to what they estimate.

Then the delay is chosen as ``tools/tune_smooth.py`` chooses it, on one half of the
trials (:func:`mavest.datasets.broad.halves`), by the mean inclination of mavest's
filter for the filter rows and of its smoother for the smoother rows, and each filter
reported on the other half with it: the paired
per-trial differences of mavest against each peer carried forward alike. Figures on
the half a delay was chosen on are not results. ``--results`` writes the tables as the
IMU delay section of docs/results.md (or FILE).

Any folder of BROAD-format trials will do (``MAVEST_DATA``): a file that is not a
readable trial, a second copy of a recording, or a trial with nothing to score is left
out with one line; fewer than two trials left, or no BROAD folder, is one line and
exit 2.
"""

from __future__ import annotations

import functools
import statistics
import sys
import time
from collections.abc import Sequence

from mavest.datasets.broad import (
    DELAYS,
    BroadTrial,
    halves,
    halves_named,
    lowest_mean,
    trials_to_split,
)
from mavest.evaluation import report
from mavest.evaluation.accuracy import carried_runs
from mavest.evaluation.metrics import rmse_deg

TITLE = "IMU delay"
QUICK_TRIALS = 4


def score(trials: Sequence[BroadTrial]) -> dict[str, dict[float, list[float]]]:
    """Each filter's 6-D inclination RMSE (°) per delay, per trial."""
    table: dict[str, dict[float, list[float]]] = {}
    for trial in trials:
        for name, carried in carried_runs(trial).items():
            per_delay = table.setdefault(name, {d: [] for d in DELAYS})
            for delay in DELAYS:
                errors = rmse_deg(carried(delay), trial.truth_q, trial.movement)
                per_delay[delay].append(errors["inclination"])
        report.progress("imu_delay", trial.name)
    return table


def curve_table(table: dict[str, dict[float, list[float]]]) -> str:
    names = list(table)
    lines = [
        "| delay | " + " | ".join(names) + " |",
        "|---" * (len(names) + 1) + "|",
    ]
    best = {name: min(DELAYS, key=lambda d: statistics.fmean(table[name][d])) for name in names}
    for delay in DELAYS:
        cells = []
        for name in names:
            cell = f"{statistics.fmean(table[name][delay]):.3f}°"
            cells.append(f"**{cell}**" if delay == best[name] else cell)
        lines.append(f"| {delay * 1e3:.1f} ms | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def held_out_table(table: dict[str, dict[float, list[float]]], a: list[int], b: list[int]) -> str:
    lines = [
        "| tuned on → reported on | mavest's delay, by | ours | peer | ours / peer "
        "| carried forward alike: ours − peer, paired | against the peer as it runs (0 ms): "
        "ours / peer |",
        "|---|---|---|---|---|---|---|",
    ]
    for tuned, reported, on, subset in (("A", "B", a, b), ("B", "A", b, a)):
        for ours, peer in (("mavest", "VQF"), ("mavest.smooth", "offline VQF")):
            delay = lowest_mean(table[ours], on)
            mine = [table[ours][delay][i] for i in subset]
            theirs = [table[peer][delay][i] for i in subset]
            raw = [table[peer][0.0][i] for i in subset]
            lines.append(
                f"| {tuned} → {reported} | {delay * 1e3:.1f} ms, {ours} | {ours} "
                f"{statistics.fmean(mine):.3f}° | {peer} {statistics.fmean(theirs):.3f}° "
                f"| {statistics.fmean(mine) / statistics.fmean(theirs):.2f}× "
                f"| {report.paired(mine, theirs)} "
                f"| {statistics.fmean(mine) / statistics.fmean(raw):.2f}× |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--quick", action="store_true", help="four trials")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    start = time.perf_counter()

    say = functools.partial(report.progress, "imu_delay")

    trials = trials_to_split(say, QUICK_TRIALS if args.quick else None)
    if trials is None:
        return 2
    table = score(trials)
    a, b = halves(trials)
    with report.results_section(args.results, TITLE, __file__, argv, __doc__):
        print(
            f"Mean 6-D inclination RMSE over the {len(trials)} BROAD trials, each filter's "
            "attitude carried forward by the delay (mavest's defaults; VQF and offline VQF "
            "with theirs). Bold: each filter's least. Over all the trials: the delay is "
            "chosen on these figures, so they are not results.\n"
        )
        print(curve_table(table))
        print(
            "\nHeld out: the delay chosen on one half by the mean of the row's mavest "
            "filter or smoother ("
            + halves_named([t.name for t in trials], a, b)
            + "), every figure on the other half, each peer carried forward by the same "
            "delay; the last column sets ours against the peer as it is.\n"
        )
        print(held_out_table(table, a, b))
    print(f"({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
