"""BROAD 6-D inclination (or 9-D total) RMSE, per trial and mean: mavest beside VQF and others.

    .venv/bin/python tools/accuracy.py [--peers VQF Fusion] [--variants] [--mag] [--markdown]

Reads the BROAD trials from $MAVEST_DATA/broad (default ../shared/data/broad),
runs every filter on the same samples in the same run and scores them as the
dataset does (RMSE over the movement phases, truth from the optical system).
The even- and odd-numbered trials are shown apart as well: mavest's defaults
were chosen looking at all 22 trials, so a split shows whether they carry over
to trials that were not looked at.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mavest import EstimatorConfig
from mavest.datasets.broad import list_trials, load_trial
from mavest.evaluation.accuracy import mavest_filter, peer_filter, score_inclination
from mavest.evaluation.peers import PEERS

VARIANTS = {
    "mavest no rest detection": EstimatorConfig(rest_detection=False),
    "mavest ekf": EstimatorConfig(update="ekf"),
    "mavest sigma_point": EstimatorConfig(update="sigma_point"),
    "mavest without low-pass": EstimatorConfig(accel_lowpass_time=0.0),
}


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
    parser.add_argument("--variants", action="store_true", help="also mavest's variants")
    parser.add_argument(
        "--mag",
        action="store_true",
        help="9-D: every filter also gets the magnetometer; scores total RMSE (see --metric)",
    )
    parser.add_argument(
        "--metric",
        choices=["inclination", "heading", "total"],
        help="what to score (default: inclination in 6-D, total with --mag)",
    )
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    args = parser.parse_args(argv)

    try:
        paths = list_trials()
    except FileNotFoundError as error:
        print(f"accuracy: {error}", file=sys.stderr)
        return 2
    if not paths:
        print("accuracy: no BROAD .hdf5 files found", file=sys.stderr)
        return 2
    trials = [load_trial(p) for p in paths]

    metric = args.metric or ("total" if args.mag else "inclination")
    filters = {"mavest": mavest_filter(mag=args.mag)}
    if args.variants:
        filters |= {name: mavest_filter(config, args.mag) for name, config in VARIANTS.items()}
    for name in args.peers:
        filters[name] = peer_filter(name, args.mag)
    result = score_inclination(trials, filters, metric)

    names = list(filters)
    even = [i for i, t in enumerate(result.trials) if int(t[:2]) % 2 == 0]
    odd = [i for i, t in enumerate(result.trials) if int(t[:2]) % 2 == 1]
    rows = [
        [t, *(f"{result.scores[n][i]:.2f}" for n in names)] for i, t in enumerate(result.trials)
    ]
    summary = [
        ["mean", *(f"{result.mean(n):.3f}" for n in names)],
        ["mean, even trials", *(f"{result.mean(n, even):.3f}" for n in names)],
        ["mean, odd trials", *(f"{result.mean(n, odd):.3f}" for n in names)],
    ]
    if "VQF" in filters:
        summary.append(
            ["mean ÷ VQF's", *(f"{result.mean(n) / result.mean('VQF'):.3f}" for n in names)]
        )
        vqf = result.scores["VQF"]
        summary.append(
            [
                "trials at or below VQF",
                *(f"{int(np.sum(result.scores[n] <= vqf))}/{len(vqf)}" for n in names),
            ]
        )
    header = [f"BROAD trial ({'9' if args.mag else '6'}-D {metric} RMSE, °)", *names]
    _print_table(header, rows + summary, args.markdown)
    return 0


def _print_table(header: list[str], rows: list[list[str]], markdown: bool) -> None:
    if markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "|".join("---" for _ in header) + "|")
        for row in rows:
            print("| " + " | ".join(row) + " |")
        return
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print(
            "  ".join(
                cell.ljust(w) if i == 0 else cell.rjust(w)
                for i, (cell, w) in enumerate(zip(row, widths, strict=True))
            )
        )


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
