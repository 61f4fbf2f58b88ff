"""Monte Carlo consistency of every filter variant: ANEES, NIS, tilt and heading RMSE.

    .venv/bin/python tools/consistency.py [--runs 100] [--scenario NAME ...] [--quick]
                                          [--config FILE ...] [--smooth] [--results [FILE]]

For each scenario (mavest.evaluation.consistency.SCENARIOS) and every variant
— update EKF / iterated / sigma-point × reset none / first-order / full × error
left / right with the exponential chart, and the left heading-tilt chart — it
prints ANEES (6 dof, and attitude alone) over the whole run with the χ² 95 %
band, ANEES over the first and last 10 s, the mean NIS of the gravity updates,
and tilt and heading RMSE. Everything but the structure is mavest's default
configuration, and the simulated flights carry exactly the noise and vehicle
motion that configuration claims (bursts and changing_motion's levels excepted);
configs/adaptive.toml (the motion level measured) is scored on the same flights,
whose gyro noise has no part ∝ the rate, so it errs safe there; so are
configs/handheld.toml, whose velocity decorrelates in 0.1 s where these flights' does
in 1 s, so it errs small, and each configuration given with --config FILE (keys not
given take the defaults). "ok": the whole-run ANEES, 6 dof and attitude, inside the
band. --results writes the printed tables as the
Consistency section of docs/results.md (or FILE).

--smooth: the smoother (mavest.smooth) instead, on the default configuration (or the
one --config gives): the filter and the smoothed estimate on the same flights, the
forward pass started from a prior drawn around the truth and the backward pass, as
mavest.smooth starts it, from the forward pass's end; --results writes them as the
Smoothing consistency section.
"""

from __future__ import annotations

import itertools
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from mavest import ConfigError, EstimatorConfig
from mavest.evaluation import report
from mavest.evaluation.consistency import SCENARIOS, Scenario, Summary, monte_carlo


def variants(base: EstimatorConfig) -> list[EstimatorConfig]:
    """All structural variants, with the default's other parameters."""
    classic = [
        base.replace(update=update, reset=reset, error=error, chart="exp")
        for update, error, reset in itertools.product(
            ("ekf", "iterated", "sigma_point"), ("left", "right"), ("none", "first_order", "full")
        )
    ]
    heading_tilt = [
        base.replace(update=update, reset=reset, error="left", chart="heading_tilt")
        for update, reset in itertools.product(
            ("ekf", "iterated", "sigma_point"), ("none", "first_order", "full")
        )
    ]
    return classic + heading_tilt


CONFIGS = Path(__file__).resolve().parents[1] / "configs"
# The configuration files scored beside the variants, on the default's flights.
FILES = (
    (CONFIGS / "adaptive.toml", "configs/adaptive.toml (motion level measured)"),
    # (its velocity decorrelates in 0.1 s; these flights' in 1 s)
    (CONFIGS / "handheld.toml", "configs/handheld.toml (hand-held motion)"),
)


def _job(args: tuple[list[EstimatorConfig], Scenario, int, int, bool]) -> list[Summary]:
    configs, scenario, runs, seed, smooth = args
    if smooth:  # the filter, then the smoother on the same flights
        return monte_carlo(configs, scenario, runs, seed) + monte_carlo(
            configs, scenario, runs, seed, smoothed=True
        )
    return monte_carlo(configs, scenario, runs, seed)


def format_smooth_table(scenario: Scenario, filtered: Summary, smoothed: Summary) -> str:
    """The filter beside the smoother on one scenario's flights."""
    lines = [
        f"### {scenario.name}: {scenario.description}",
        f"{filtered.runs} runs of {scenario.duration:.0f} s at {scenario.rate:.0f} Hz; 95 % "
        f"band: ANEES [{filtered.band6[0]:.2f}, {filtered.band6[1]:.2f}], attitude "
        f"[{filtered.band3[0]:.2f}, {filtered.band3[1]:.2f}]",
        "",
        "| estimate | ANEES | attitude ANEES | first 10 s | last 10 s | tilt RMSE ° "
        "| heading RMSE ° | in band |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in (("filter", filtered), ("smoother", smoothed)):
        lines.append(
            f"| {name} | {s.anees:.2f} | {s.anees_attitude:.2f} | {s.anees_early:.2f} | "
            f"{s.anees_late:.2f} | {s.tilt_rmse_deg:.2f} | {s.heading_rmse_deg:.1f} | "
            f"{'ok' if s.in_band() else '—'} |"
        )
    return "\n".join(lines)


def format_table(scenario: Scenario, labels: list[str], summaries: list[Summary]) -> str:
    s0 = summaries[0]
    lines = [
        f"### {scenario.name}: {scenario.description}",
        f"{s0.runs} runs of {scenario.duration:.0f} s at {scenario.rate:.0f} Hz; 95 % band: "
        f"ANEES [{s0.band6[0]:.2f}, {s0.band6[1]:.2f}], attitude [{s0.band3[0]:.2f}, "
        f"{s0.band3[1]:.2f}]",
        "",
        "| variant | ANEES | attitude ANEES | first 10 s | last 10 s | NIS | tilt RMSE ° "
        "| heading RMSE ° | in band |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in zip(labels, summaries, strict=True):
        lines.append(
            f"| {name} | {s.anees:.2f} | {s.anees_attitude:.2f} | {s.anees_early:.2f} | "
            f"{s.anees_late:.2f} | {s.nis:.2f} | {s.tilt_rmse_deg:.2f} | "
            f"{s.heading_rmse_deg:.1f} | {'ok' if s.in_band() else '—'} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--runs", type=int, default=100, help="runs per scenario (default 100)")
    parser.add_argument("--scenario", action="append", choices=[s.name for s in SCENARIOS])
    parser.add_argument(
        "--quick", action="store_true", help="only the default and the classic EKFs"
    )
    parser.add_argument(
        "--smooth",
        action="store_true",
        help="the smoother beside the filter (default config, or --config's)",
    )
    report.add_config_option(parser, "also this configuration, on the same flights")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--seed", type=int, default=0)
    report.add_results_option(parser)
    args = parser.parse_args(argv)

    default = EstimatorConfig()
    configs = variants(default)
    if args.quick:
        configs = [c for c in configs if c == default or (c.update == "ekf" and c.chart == "exp")]
    labels = [f"**{c.variant} (default)**" if c == default else c.variant for c in configs]
    # on the default's flights, whose gyro noise has no part ∝ the rate: it errs safe there
    files = [*FILES, *((path, f"{path.name} (--config)") for path in args.config)]
    for path, label in files:
        try:
            configs.append(EstimatorConfig.from_toml(path))
        except ConfigError as error:
            parser.error(f"--config: {error}")
        labels.append(label)
    if args.smooth:  # the smoother with the default configuration, or the one given
        if len(args.config) > 1:
            parser.error("--smooth takes one --config at most")
        configs = [configs[-1] if args.config else default]
    scenarios = [s for s in SCENARIOS if not args.scenario or s.name in args.scenario]

    # jobs: (scenario, slice of runs); every variant sees the same flights
    slices = max(1, min(args.jobs, args.runs))
    per = -(-args.runs // slices)
    jobs = [
        (configs, scenario, min(per, args.runs - k * per), args.seed + k * per, args.smooth)
        for scenario in scenarios
        for k in range(slices)
        if args.runs > k * per
    ]
    start = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(_job, jobs))
    elapsed = time.perf_counter() - start
    title = "Smoothing consistency" if args.smooth else "Consistency"
    with report.results_section(args.results, title, __file__, argv, __doc__):
        if args.smooth:
            given = f" with {args.config[0].name}" if args.config else ""
            print(f"mavest Monte Carlo consistency of the smoother{given}, {elapsed:.0f} s\n")
        else:
            print(f"mavest Monte Carlo consistency: {len(configs)} variants, {elapsed:.0f} s\n")
        for scenario in scenarios:
            parts = [r for job, r in zip(jobs, results, strict=True) if job[1] is scenario]
            combined = [Summary.combine([p[i] for p in parts]) for i in range(len(parts[0]))]
            if args.smooth:
                print(format_smooth_table(scenario, *combined))
            else:
                print(format_table(scenario, labels, combined))
            print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
