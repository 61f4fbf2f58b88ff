"""tools/replay_split.py: its stages do the replay's own work, its split adds up, and
it prints and writes its tables.

Timing is the tool's business, not the tests': these check structure and arithmetic.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from tool_module import load_tool

from mavest.evaluation import report
from mavest.mavlink import bulk
from mavest.mavlink.messages import mavlink2
from mavest.mavlink.tlog import TlogReader
from mavest.sim.vehicle import write_autopilot_tlog

pytest.importorskip("jsbsim", reason="jsbsim is needed for the simulated flights")

split_tool = load_tool("replay_split")

MAVEST_COMPONENT = 191  # the answers' (output.component_id)


def _answers(path: Path, message_class: type) -> np.ndarray:
    """The payloads of mavest's answers of one type in a tlog, in order."""
    reader = TlogReader.open(path)
    parts = []
    while len(records := reader.scan(4096)):
        rows = np.flatnonzero(
            (records.message_id == message_class.id) & (records.component == MAVEST_COMPONENT)
        )
        parts.append(
            bulk.decode_payloads(reader.array, records.part(rows), bulk.wire_dtype(message_class))
        )
    return np.concatenate(parts)


def test_the_stages_give_the_replays_own_answers(tmp_path: Path) -> None:
    log = tmp_path / "flight.tlog"
    write_autopilot_tlog(log, 2.0, 1000.0, attitude_every=20)
    replayed, staged = tmp_path / "replayed.tlog", tmp_path / "staged.tlog"
    split_tool.run_timed(split_tool.replay_command(log, replayed))
    stages = split_tool.time_stages(log, staged)
    assert stages.samples == 2001
    assert stages.records == 2001 + 101 + 3  # RAW_IMU, ATTITUDE every 20th, HEARTBEAT
    assert stages.answers == 2 * stages.samples
    assert all(stages.wall[name] > 0.0 for name in split_tool.STAGES)
    for message_class in (
        mavlink2.MAVLink_attitude_message,
        mavlink2.MAVLink_attitude_quaternion_message,
    ):
        ours, theirs = _answers(staged, message_class), _answers(replayed, message_class)
        assert ours.shape[0] == stages.samples
        np.testing.assert_array_equal(ours, theirs)
    # the replay wrote the same records and its HEARTBEATs (one a second)
    assert split_tool.records_in(replayed) - split_tool.records_in(staged) in (2, 3)


def _timed(wall: float, cpu: float) -> object:
    return split_tool.Timed(wall, cpu, "")


def _stages(seconds: float, samples: int) -> object:
    each = dict.fromkeys(split_tool.STAGES, seconds)
    return split_tool.StageTimes(each, dict(each), samples + 10, samples, 2 * samples)


def test_the_split_takes_the_short_logs_samples_out_of_start_up_and_adds_up() -> None:
    # 10 001 samples; the 1 s log's 1 001 at 2 µs each past a start-up of 0.4 s
    measured = split_tool.Rounds(
        whole=[_timed(0.42, 0.44), _timed(0.43, 0.45)],
        startup=[_timed(0.402, 0.4022), _timed(0.403, 0.4032)],
        pymavlink=[_timed(4.2, 4.2), _timed(4.3, 4.3)],
        stages=[_stages(0.002, 10_001), _stages(0.003, 10_001)],
        startup_samples=1001,
    )
    parts = split_tool.split(measured)
    assert list(parts) == [
        "start-up",
        *split_tool.STAGES,
        "bookkeeping/other",
        "whole command",
    ]
    # start-up less 1 001 samples at (whole − start-up) / 9 000 each
    fixed = [0.402 - 1001 * 0.018 / 9000, 0.403 - 1001 * 0.027 / 9000]
    assert parts["start-up"]["wall"] == pytest.approx(np.median(fixed))
    assert parts["start-up"]["low"] == pytest.approx(min(fixed))
    remainder = [0.42 - fixed[0] - 4 * 0.002, 0.43 - fixed[1] - 4 * 0.003]
    assert parts["bookkeeping/other"]["wall"] == pytest.approx(np.median(remainder))
    for k in range(2):  # round by round, the rows add up to the whole command
        total = fixed[k] + 4 * (0.002, 0.003)[k] + remainder[k]
        assert total == pytest.approx((0.42, 0.43)[k])
    np.testing.assert_allclose(split_tool.ratios(measured), [4.2 / 0.42, 4.3 / 0.43])


def _table(lines: list[str], header: str) -> list[list[str]]:
    """The rows of the Markdown table whose header starts with ``header``, as cells."""
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows


def test_the_tool_prints_the_split_beside_pymavlink_and_writes_its_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results.md"
    report.write_section(results, "Long runs", "| a later table |", "tools/long_run.py")
    arguments = ["--seconds", "2", "--rounds", "1", "--results", str(results)]
    assert split_tool.main(arguments) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    commands = _table(lines, "| command |")
    assert len(commands) == 3 and "pymavlink" in commands[2][0]
    assert all(float(row[1]) > 0.0 for row in commands)
    assert re.search(r"pymavlink's loop / mavest's whole command: \*\*[\d.]+×\*\*", out)
    assert re.search(r"; 10× is (reached|\*\*not reached\*\*): it needs the whole command in", out)
    split = _table(lines, "| stage |")
    names = [row[0].strip("*") for row in split]
    assert names == ["start-up", *split_tool.STAGES, "bookkeeping/other", "whole command"]
    wall = {name: float(row[2].strip("*")) for name, row in zip(names, split, strict=True)}
    assert all(wall[name] > 0.0 for name in ["start-up", *split_tool.STAGES])
    # the rows (printed to 0.01 µs) add up to the whole command
    parts = sum(value for name, value in wall.items() if name != "whole command")
    assert parts == pytest.approx(wall["whole command"], abs=0.01 * len(names))
    assert split[-1][4] == "100 %"
    section = results.read_text()
    # in the document's order, after the service's section and before the long runs
    assert section.index("## Replay time split\n") < section.index("## Long runs\n")
    assert f"Regenerate: `.venv/bin/python tools/replay_split.py {' '.join(arguments)}`" in section
    assert out.strip() in section
