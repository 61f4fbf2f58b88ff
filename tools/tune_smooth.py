"""Choose the smoother's accelerometer averaging time on one half of BROAD, report on the other.

    .venv/bin/python tools/tune_smooth.py [--quick] [--results [FILE]]

``mavest.smooth`` runs its forward pass on the accelerometer low-passed with zero phase
in the gyro's strapdown frame (``EstimatorConfig.smooth_accel_time``, the time constant;
0: as measured, the smoother before the average). The time constant is chosen on one
half of the 22 shared BROAD trials (:func:`mavest.datasets.broad.halves`) as the one of
:data:`GRID` with the lowest mean 6-D inclination RMSE there, and reported on the other
half, both ways round: the smoother with the choice, without the average (0) and
offline VQF (Laidig & Seel 2023's smoother) on the same trials, with the paired
per-trial differences; 9-D total RMSE likewise, with the same choice. Then the rule
applied to all 22 gives the default (its figures on the trials it was chosen on are
not reported as results); the closing line says this run's choice and the default.
The filter's other parameters are mavest's defaults, chosen on the 22 shared trials
(:data:`mavest.datasets.broad.TUNED_ON`): the per-trial table says which trials those
are. ``--results`` writes the tables as the Smoothing cross-validation section of
docs/results.md (or FILE).

Any folder of BROAD-format trials will do (``MAVEST_DATA``): a file that is not a
readable trial, a second copy of a recording, or a trial with nothing to score is left
out with one line; fewer than two trials left, or no BROAD folder, is one line and
exit 2.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Sequence

import mavest
from mavest import EstimatorConfig
from mavest.datasets.broad import (
    TUNED_ON,
    BroadTrial,
    halves,
    trial_labels,
    trials_to_split,
    tuned_on,
)
from mavest.evaluation import report
from mavest.evaluation.metrics import rmse_deg
from mavest.evaluation.peers import PEERS

TITLE = "Smoothing cross-validation"
#: The grid stops at 0.5 s for the covariance's sake, not the accuracy's: the forward
#: pass's model takes its accelerometer as measured, and the longer the average, the more
#: conservative the smoothed covariance. In tools/consistency.py --smooth, 0.5 s keeps 6
#: of the 7 scenarios in band (as many as without the average, 5 of 7, and
#: changing_motion); 1 s leaves 3 (small, large_tilt: ANEES 5.66 and 5.37 of [5.34, 6.70],
#: attitude 2.50 and 2.45 of [2.54, 3.50]). The uncorrected strapdown frame also turns
#: gravity by the gyro bias over the average's span, which a segment's ends, where the
#: average is one-sided, do not cancel.
GRID: tuple[float, ...] = (0.0, 0.25, 0.5)  # s
QUICK_GRID: tuple[float, ...] = (0.0, 0.5)
QUICK_TRIALS = 4

Scores = dict[float, list[float]]  # per time constant, per trial


def scores(trials: Sequence[BroadTrial], grid: Sequence[float], mag: bool) -> Scores:
    """Each time constant's smoothed RMSE per trial: 6-D inclination, or 9-D total."""
    out: Scores = {}
    for tau in grid:
        config = EstimatorConfig(smooth_accel_time=tau)
        out[tau] = []
        for trial in trials:
            series = mavest.smooth(
                trial.t, trial.gyro, trial.accel, trial.mag if mag else None, config
            )
            errors = rmse_deg(series.q, trial.truth_q, trial.movement)
            out[tau].append(errors["total" if mag else "inclination"])
        print(
            f"{'9-D' if mag else '6-D'} τ {tau:g} s: {statistics.fmean(out[tau]):.4f}°",
            file=sys.stderr,
            flush=True,
        )
    return out


def peer(trials: Sequence[BroadTrial], mag: bool) -> list[float]:
    """Offline VQF's RMSE per trial (6-D inclination, or 9-D total)."""
    run = PEERS["offline VQF"]
    return [
        rmse_deg(
            run(trial.t, trial.gyro, trial.accel, trial.mag if mag else None, trial.rate),
            trial.truth_q,
            trial.movement,
        )["total" if mag else "inclination"]
        for trial in trials
    ]


def choose(table: Scores, subset: Sequence[int]) -> float:
    """The time constant with the lowest mean RMSE over ``subset`` (ties: the first)."""
    return min(table, key=lambda tau: statistics.fmean(table[tau][i] for i in subset))


def held_out_rows(
    table: Scores, offline: list[float], directions: list[tuple[str, str, list[int], float]]
) -> list[str]:
    """One row per direction, on the half not tuned on."""
    rows = []
    for chosen_on, reported_on, subset, tau in directions:
        chosen = [table[tau][i] for i in subset]
        plain = [table[0.0][i] for i in subset]
        theirs = [offline[i] for i in subset]
        mean, mean_plain, mean_theirs = (statistics.fmean(v) for v in (chosen, plain, theirs))
        rows.append(
            f"| {chosen_on} → {reported_on} | {tau:g} s | {mean:.3f}° / {mean_plain:.3f}° / "
            f"{mean_theirs:.3f}° ({mean / mean_theirs:.2f}×) | {report.paired(chosen, theirs)} "
            f"| {report.paired(chosen, plain)} |"
        )
    return rows


def per_trial_rows(
    trials: Sequence[BroadTrial],
    table: Scores,
    offline: list[float],
    directions: list[tuple[str, str, list[int], float]],
) -> list[str]:
    rows = []
    for _, reported_on, subset, tau in directions:
        for i in subset:
            rows.append(
                f"| {trials[i].name} | {reported_on} | {tau:g} s | {table[tau][i]:.3f}° | "
                f"{table[0.0][i]:.3f}° | {offline[i]:.3f}° "
                f"| {'yes' if tuned_on(trials[i].name) else 'no'} |"
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--quick", action="store_true", help="two time constants, four trials")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    trials = _load(args.quick)
    if trials is None:
        return 2
    grid = QUICK_GRID if args.quick else GRID
    table_6d, table_9d = scores(trials, grid, False), scores(trials, grid, True)
    offline_6d, offline_9d = peer(trials, False), peer(trials, True)
    a, b = halves(trials)
    directions = [("A", "B", b, choose(table_6d, a)), ("B", "A", a, choose(table_6d, b))]
    overall = choose(table_6d, range(len(trials)))
    header = (
        "| tuned on → reported on | chosen | {what}: smoothed / without the average / "
        "offline VQF | smoothed − offline VQF, paired | smoothed − without the average, "
        "paired |\n|---|---|---|---|---|"
    )
    labels = trial_labels([t.name for t in trials])
    in_sample = sum(tuned_on(t.name) for t in trials)
    with report.results_section(args.results, TITLE, __file__, argv, __doc__):
        print(
            f"Halves of the {len(trials)} BROAD trials ({in_sample} of them among the "
            f"{len(TUNED_ON)} mavest's defaults were chosen on): A = "
            + ", ".join(labels[i] for i in a)
            + "; B = "
            + ", ".join(labels[i] for i in b)
            + ". Every figure below is on the half the time constant was **not** chosen on "
            "(by mean 6-D inclination); the 9-D rows use the same choice. The filter's "
            "other parameters are mavest's defaults, chosen on the "
            f"{len(TUNED_ON)} trials of mavest.datasets.broad.TUNED_ON: on those (column "
            "'defaults chosen on it') they are in-sample.\n"
        )
        print(header.format(what="6-D inclination RMSE"))
        print("\n".join(held_out_rows(table_6d, offline_6d, directions)))
        print()
        print(header.format(what="9-D total RMSE"))
        print("\n".join(held_out_rows(table_9d, offline_9d, directions)))
        print()
        print(
            "| trial | held out in | chosen | 6-D inclination: smoothed | without the "
            "average | offline VQF | defaults chosen on it |\n|---|---|---|---|---|---|---|"
        )
        print("\n".join(per_trial_rows(trials, table_6d, offline_6d, directions)))
        default = EstimatorConfig().smooth_accel_time
        print(
            f"\nThe rule applied to all {len(trials)} trials, this run's choice: {overall:g} s "
            f"(the default, EstimatorConfig.smooth_accel_time, is {default:g} s"
            + (", the same" if overall == default else "")
            + "). Mean 6-D inclination of "
            "every time constant over all the trials (tuned on, not results): "
            + ", ".join(f"{tau:g} s {statistics.fmean(table_6d[tau]):.3f}°" for tau in grid)
            + "."
        )
    print(f"({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


def _load(quick: bool) -> list[BroadTrial] | None:
    """The trials to tune on (the first :data:`QUICK_TRIALS` usable ones with
    ``quick``), or None after one line saying why there are too few to split."""

    def say(line: str) -> None:
        print(f"tune_smooth: {line}", file=sys.stderr, flush=True)

    return trials_to_split(say, QUICK_TRIALS if quick else None)


if __name__ == "__main__":
    raise SystemExit(main())
