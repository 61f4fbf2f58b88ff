"""tools/long_run.py on a short flight: its table, its checks and its exit status.

The hour-long run is the tool's job, not CI's; here 24 s of flight go through
both parts (the pipeline in the tool's process, then ``mavest replay`` and
pymavlink's parse as processes of their own).
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tool_module import load_tool

PROJECT = Path(__file__).resolve().parents[1]
TOOL = PROJECT / "tools" / "long_run.py"
MINUTES = 0.4  # 24 s: blocks of 12 s, the first scored after the 10 s settle time
RATE = 500.0


tool = load_tool("long_run")


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The document the short run writes its section to."""
    return tmp_path_factory.mktemp("docs") / "results.md"


@pytest.fixture(scope="module")
def short_run(results: Path) -> tuple[subprocess.CompletedProcess[str], dict[str, str]]:
    # --results alone: the table in Markdown, on the terminal and in the document
    finished = subprocess.run(
        [
            sys.executable,
            str(TOOL),
            "--minutes",
            str(MINUTES),
            "--rate",
            str(RATE),
            "--block-minutes",
            str(MINUTES / 2),
            "--results",
            str(results),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=PROJECT,
    )
    rows = {}
    for line in finished.stdout.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("| ") and len(cells) == 2:
            rows[cells[0]] = cells[1]
    return finished, rows


def _numbers(text: str) -> list[float]:
    return [
        float(n.replace(",", "")) for n in re.findall(r"[-+]?\d[\d,]*\.?\d*(?:e[-+]?\d+)?", text)
    ]


def test_short_run_passes_and_counts_every_sample(short_run) -> None:
    finished, rows = short_run
    assert finished.returncode == 0, finished.stdout + finished.stderr
    expected = round(MINUTES * 60 * RATE) + 1  # write_flight_tlog includes both ends
    received, estimated, answered, said = _numbers(rows["IMU samples in / estimated / answered"])
    assert received == estimated == answered == said == expected
    assert rows["check: no NaN"] == "✓ 0 estimates with a NaN"
    assert rows["check: covariance healthy"].startswith(f"✓ {expected:,} checked: 0 not positive")
    assert not [label for label, value in rows.items() if "FAIL" in value]


def test_short_run_reports_accuracy_per_block(short_run) -> None:
    _, rows = short_run
    blocks = {label: value for label, value in rows.items() if label.startswith("block ")}
    assert list(blocks) == [
        "block 0–0.2 min: roll / pitch / tilt / yaw RMS",
        "block 0.2–0.4 min: roll / pitch / tilt / yaw RMS",
    ]
    for value in blocks.values():
        roll, pitch, tilt, yaw, count = _numbers(value)
        assert count > 0
        # the ArduPilot configuration on this flight: about 1° (docs/results.md)
        assert 0.0 < max(roll, pitch) <= tilt < 3.0
        assert 0.0 < yaw < 5.0
    ratios = _numbers(rows["last / first scored block RMS"])
    assert len(ratios) == 4 and all(math.isfinite(r) and r > 0 for r in ratios)


def test_short_run_reports_memory_and_the_replay(short_run) -> None:
    _, rows = short_run
    rss = _numbers(rows["RSS at flight minute"])
    assert len(rss) == 6 and all(50 < mib < 4096 for mib in rss[1::2])
    peak_mavest, wall_mavest, samples = _numbers(
        rows["`mavest replay FILE --out-tlog OUT`: peak RSS, wall"]
    )
    peak_pymavlink, wall_pymavlink = _numbers(
        rows["pymavlink parse (mavlink_connection + recv_match): peak RSS, wall"]
    )
    assert samples == round(MINUTES * 60 * RATE) + 1
    # the children's own peaks, not this process's: pymavlink alone stays small
    assert 10 < peak_pymavlink < peak_mavest < 2048
    assert wall_mavest > 0 and wall_pymavlink > 0


def test_short_run_writes_its_table_as_the_long_runs_section(short_run, results: Path) -> None:
    finished, rows = short_run
    section = results.read_text().split("<!-- BEGIN long-runs -->\n", 1)[1]
    assert section.startswith("## Long runs\n")
    assert (
        f"Regenerate: `.venv/bin/python tools/long_run.py --minutes {MINUTES} --rate {RATE} "
        f"--block-minutes {MINUTES / 2} --results {results}`"
    ) in section
    assert f"\n\n{finished.stdout.strip()}\n\n<!-- END long-runs -->\n" in section
    assert len(rows) > 10


def test_covariance_health_counts_what_is_wrong() -> None:
    health = tool.CovarianceHealth((1e-3, 30.0), (1e-5, 0.2))
    good = np.diag([1e-4, 1e-4, 1e-3, 1e-7, 1e-7, 1e-7])
    not_pd = good.copy()
    not_pd[0, 1] = not_pd[1, 0] = 1.0  # |off-diagonal| beyond the variances: indefinite
    too_wide = good.copy()
    too_wide[2, 2] = math.radians(40.0) ** 2  # heading σ 40°
    health.check(np.stack([good, not_pd, too_wide]), np.array([True, False, True]))
    assert health.checked == 3
    assert health.not_positive_definite == 1
    assert health.out_of_bounds == 1  # not_pd is not settled: its σ is not judged
    assert health.heading_sigma[1] == pytest.approx(40.0)
    assert health.min_eigenvalue < 0.0
    assert not health.healthy
    healthy = tool.CovarianceHealth((1e-3, 30.0), (1e-5, 0.2))
    healthy.check(good[None], np.array([True]))
    assert healthy.healthy


def test_a_failed_check_fails_the_exit_status(capsys: pytest.CaptureFixture[str]) -> None:
    # RSS cannot fall by 1000 MiB during a 3 s flight: the memory check must fail
    status = tool.main(["--only", "pipeline", "--minutes", "0.05", "--max-growth", "-1000"])
    assert status == 1
    output = capsys.readouterr()
    assert re.search(r"check: memory flat +✗ FAIL", output.out)
    assert "failed: memory flat" in output.err
