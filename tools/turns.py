"""Tilt in turns: JSBSim flights replayed through the service with each acceleration aiding.

    .venv/bin/python tools/turns.py [--seconds 120] [--seeds 1 2 3 4] [--config FILE] [--markdown]
                                    [--results [FILE]]

Each seed is a Cessna 172 flight (90° heading changes every 25–35 s, 30° of
bank, light turbulence) written as ArduPilot RAW_IMU at 400 Hz with GPS at
10 Hz, VFR_HUD and the truth (SIMSTATE), then replayed with
``acceleration_aiding`` auto (GPS velocity), airspeed (ω × V) and off, the
same samples in the same run, with the ArduPilot configuration
(configs/ardupilot.toml; ``--config`` another). Roll, pitch and tilt RMS
against the truth after the replay's settle time (10 s). ``--perturb N`` replays each
flight unaided N more times with ``accel_noise_density`` changed by k·1e-9 (relative,
k = 1 … N): whether an unaided turning flight re-opens tilt must not hang on the last
bits of a coefficient, so the tilt RMS's spread over them is printed. --results writes
the table (as Markdown) as the Tilt in turns section of docs/results.md (or FILE).
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
from pathlib import Path

from mavest.evaluation import report
from mavest.service.config import ServiceConfig
from mavest.service.runners import replay
from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

MODES = ("auto", "airspeed", "off")
ARDUPILOT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "ardupilot.toml"
RATE = 400.0  # Hz, as `make demo`


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=120.0, help="flight length (s)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument(
        "--config", type=Path, default=ARDUPILOT_CONFIG, help="mavest configuration (TOML)"
    )
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    parser.add_argument(
        "--perturb", type=int, default=0, help="unaided replays with perturbed coefficients"
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    markdown = args.markdown or args.results is not None

    base = ServiceConfig.from_toml(args.config)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in args.seeds:
            path = Path(folder) / f"flight{seed}.tlog"
            write_flight_tlog(path, args.seconds, RATE, AUTOPILOTS["ardupilot"], seed=seed)
            cells = []
            for mode in MODES:
                config = base.replace(input={"acceleration_aiding": mode})
                (stream,) = asyncio.run(replay(path, config)).streams
                result = stream.vs_truth.result()
                cells.append((result.roll_rms, result.pitch_rms, result.inclination_rms))
            spread = _perturbed(path, base, args.perturb)
            rows.append((seed, cells, spread))
            print(f"seed {seed} done", file=sys.stderr, flush=True)

    header = ["seed"] + [f"{mode}: roll / pitch / tilt (°)" for mode in MODES]
    if args.perturb:
        header.append(f"off, {args.perturb} perturbations: tilt min–max (°), resets")
    lines = [" | ".join(header)]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for seed, cells, spread in rows:
        texts = [str(seed)] + [f"{r:.2f} / {p:.2f} / {t:.2f}" for r, p, t in cells]
        if spread:
            tilts = [tilt for tilt, _ in spread]
            resets = sorted({reopened for _, reopened in spread})
            texts.append(
                f"{min(tilts):.3f}–{max(tilts):.3f} ({', '.join(map(str, resets))} reopened)"
            )
        lines.append("| " + " | ".join(texts) + " |" if markdown else " | ".join(texts))
    with report.results_section(args.results, "Tilt in turns", __file__, argv, __doc__):
        print("\n".join(lines))
    return 0


def _perturbed(path: Path, base: ServiceConfig, count: int) -> list[tuple[float, int]]:
    """Tilt RMS and tilt re-openings of unaided replays with ``accel_noise_density``
    moved by k·1e-9 of itself, k = 1 … ``count``."""
    density = base.estimator.accel_noise_density
    out = []
    for k in range(1, count + 1):
        config = base.replace(
            input={"acceleration_aiding": "off"},
            estimator={"accel_noise_density": density * (1.0 + k * 1e-9)},
        )
        (stream,) = asyncio.run(replay(path, config)).streams
        out.append((stream.vs_truth.result().inclination_rms, stream.stats.tilt_reopened))
    return out


if __name__ == "__main__":
    sys.exit(main())
