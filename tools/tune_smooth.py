"""Choose the smoother's averaging time and IMU delay on one half of BROAD, report on the other.

    .venv/bin/python tools/tune_smooth.py [--quick] [--results [FILE]]

``mavest.smooth`` runs its forward pass on the accelerometer low-passed with zero phase
in the gyro's strapdown frame (``EstimatorConfig.smooth_accel_time``, the time constant;
0: as measured, the smoother before the average), and the attitude reported is carried
forward by how long the IMU's samples lag the truth's (``EstimatorConfig.imu_delay``,
docs/design.md#the-imus-delay; one smoother run serves every delay). The pair is chosen
on one half of the 22 shared BROAD trials (:func:`mavest.datasets.broad.halves`) as the
one of :data:`GRID` × :data:`mavest.datasets.broad.DELAYS` with the lowest mean 6-D
inclination RMSE there, and reported on the other half, both ways round: the smoother
with the choice, with neither (0, 0), offline VQF (Laidig & Seel 2023's smoother) and
offline VQF's attitude carried forward by the same delay (it has no such setting: the
figure says how much of the difference is the delay) on the same trials, with the
paired per-trial differences; 9-D total RMSE likewise, with the same choice. Then the
rule applied to all 22 gives the default averaging time (its figures on the trials it
was chosen on are not reported as results); the closing line says this run's choice
and the default.
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

import functools
import statistics
import sys
import time
from collections.abc import Sequence

import mavest
from mavest import EstimatorConfig
from mavest.datasets.broad import (
    DELAYS,
    TUNED_ON,
    BroadTrial,
    halves,
    halves_named,
    lowest_mean,
    trials_to_split,
    tuned_on,
)
from mavest.estimator.frames import lead
from mavest.evaluation import report
from mavest.evaluation.accuracy import peer_led
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
QUICK_DELAYS: tuple[float, ...] = DELAYS[::5]  # 0, 2.5 and 5 ms
QUICK_TRIALS = 4

Choice = tuple[float, float]  # (smooth_accel_time, imu_delay), s
Scores = dict[Choice, list[float]]  # per choice, per trial
PeerScores = dict[float, list[float]]  # per delay, per trial
NEITHER: Choice = (0.0, 0.0)


def scores(
    trials: Sequence[BroadTrial], grid: Sequence[float], delays: Sequence[float], mag: bool
) -> Scores:
    """Each choice's smoothed RMSE per trial: 6-D inclination, or 9-D total. One
    smoother run per time constant serves every delay: its attitudes, smoothed without
    one, carried forward by the delay with the smoothed bias
    (:func:`mavest.estimator.frames.lead`). :func:`mavest.smooth` given the delay fuses
    the passes at the filter's own attitudes, taken back by it, which differs from this
    by 2e-5 in a quaternion's components (median; tests/test_imu_delay.py)."""
    metric = "total" if mag else "inclination"
    out: Scores = {}
    for tau in grid:
        config = EstimatorConfig(smooth_accel_time=tau)
        for delay in delays:
            out[(tau, delay)] = []
        for trial in trials:
            series = mavest.smooth(
                trial.t, trial.gyro, trial.accel, trial.mag if mag else None, config
            )
            for delay in delays:
                q = lead(series.q, trial.gyro, series.bias, delay)
                out[(tau, delay)].append(rmse_deg(q, trial.truth_q, trial.movement)[metric])
        print(
            f"{'9-D' if mag else '6-D'} τ {tau:g} s: "
            + ", ".join(
                f"{delay * 1e3:g} ms {statistics.fmean(out[(tau, delay)]):.4f}°" for delay in delays
            ),
            file=sys.stderr,
            flush=True,
        )
    return out


def peer(trials: Sequence[BroadTrial], delays: Sequence[float], mag: bool) -> PeerScores:
    """Offline VQF's RMSE per trial (6-D inclination, or 9-D total), its attitude
    carried forward by each delay (:func:`mavest.evaluation.accuracy.peer_led`)."""
    run = PEERS["offline VQF"]
    metric = "total" if mag else "inclination"
    out: PeerScores = {delay: [] for delay in delays}
    for trial in trials:
        q = run(trial.t, trial.gyro, trial.accel, trial.mag if mag else None, trial.rate)
        for delay in delays:
            led = peer_led(q, trial.gyro, delay)
            out[delay].append(rmse_deg(led, trial.truth_q, trial.movement)[metric])
    return out


def describe(choice: Choice) -> str:
    tau, delay = choice
    return f"{tau:g} s, {delay * 1e3:g} ms"


Direction = tuple[str, str, list[int], Choice]  # tuned on, reported on, its trials, choice


def held_out_rows(table: Scores, offline: PeerScores, directions: list[Direction]) -> list[str]:
    """One row per direction, on the half not tuned on."""
    rows = []
    for chosen_on, reported_on, subset, choice in directions:
        chosen = [table[choice][i] for i in subset]
        plain = [table[NEITHER][i] for i in subset]
        theirs = [offline[0.0][i] for i in subset]
        led = [offline[choice[1]][i] for i in subset]
        mean, mean_plain, mean_theirs, mean_led = (
            statistics.fmean(v) for v in (chosen, plain, theirs, led)
        )
        rows.append(
            f"| {chosen_on} → {reported_on} | {describe(choice)} | {mean:.3f}° / "
            f"{mean_plain:.3f}° / {mean_theirs:.3f}° ({mean / mean_theirs:.2f}×) "
            f"| {report.paired(chosen, theirs)} "
            f"| {mean_led:.3f}° ({mean / mean_led:.2f}×), {report.paired(chosen, led)} "
            f"| {report.paired(chosen, plain)} |"
        )
    return rows


def per_trial_rows(
    trials: Sequence[BroadTrial],
    table: Scores,
    offline: PeerScores,
    directions: list[Direction],
) -> list[str]:
    rows = []
    for _, reported_on, subset, choice in directions:
        for i in subset:
            rows.append(
                f"| {trials[i].name} | {reported_on} | {describe(choice)} "
                f"| {table[choice][i]:.3f}° | {table[NEITHER][i]:.3f}° | {offline[0.0][i]:.3f}° "
                f"| {offline[choice[1]][i]:.3f}° "
                f"| {'yes' if tuned_on(trials[i].name) else 'no'} |"
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument(
        "--quick", action="store_true", help="two time constants, three delays, four trials"
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    trials = _load(args.quick)
    if trials is None:
        return 2
    grid = QUICK_GRID if args.quick else GRID
    delays = QUICK_DELAYS if args.quick else DELAYS
    table_6d = scores(trials, grid, delays, False)
    table_9d = scores(trials, grid, delays, True)
    offline_6d, offline_9d = peer(trials, delays, False), peer(trials, delays, True)
    a, b = halves(trials)
    directions: list[Direction] = [
        ("A", "B", b, lowest_mean(table_6d, a)),
        ("B", "A", a, lowest_mean(table_6d, b)),
    ]
    overall = lowest_mean(table_6d, range(len(trials)))
    header = (
        "| tuned on → reported on | chosen (averaging, delay) | {what}: smoothed / with "
        "neither / offline VQF | smoothed − offline VQF, paired | offline VQF carried "
        "forward by the same delay, smoothed − it, paired | smoothed − with neither, "
        "paired |\n|---|---|---|---|---|---|"
    )
    in_sample = sum(tuned_on(t.name) for t in trials)
    with report.results_section(args.results, TITLE, __file__, argv, __doc__):
        print(
            f"Halves of the {len(trials)} BROAD trials ({in_sample} of them among the "
            f"{len(TUNED_ON)} mavest's defaults were chosen on): "
            + halves_named([t.name for t in trials], a, b)
            + ". Every figure below is on the half the averaging time and delay were "
            "**not** chosen on (by mean 6-D inclination); the 9-D rows use the same "
            "choice. The filter's "
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
            "| trial | held out in | chosen | 6-D inclination: smoothed | with neither "
            "| offline VQF | offline VQF carried forward | defaults chosen on it |\n"
            "|---|---|---|---|---|---|---|---|"
        )
        print("\n".join(per_trial_rows(trials, table_6d, offline_6d, directions)))
        default = EstimatorConfig().smooth_accel_time
        print(
            f"\nThe rule applied to all {len(trials)} trials, this run's choice: "
            f"{describe(overall)} (the default averaging time, "
            f"EstimatorConfig.smooth_accel_time, is {default:g} s"
            + (", the same" if overall[0] == default else "")
            + "; the delay is the sensor's, which a user sets: none by default). Mean 6-D "
            "inclination of every choice over all the trials (tuned on, not results): "
            + ", ".join(f"{describe(k)} {statistics.fmean(v):.3f}°" for k, v in table_6d.items())
            + f". Offline VQF's: {statistics.fmean(offline_6d[0.0]):.3f}°; carried forward "
            + ", ".join(
                f"{delay * 1e3:g} ms {statistics.fmean(v):.3f}°"
                for delay, v in offline_6d.items()
                if delay
            )
            + "."
        )
    print(f"({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


def _load(quick: bool) -> list[BroadTrial] | None:
    """The trials to tune on (the first :data:`QUICK_TRIALS` usable ones with
    ``quick``), or None after one line saying why there are too few to split."""

    say = functools.partial(report.progress, "tune_smooth")

    return trials_to_split(say, QUICK_TRIALS if quick else None)


if __name__ == "__main__":
    raise SystemExit(main())
