"""The golden outputs (tests/golden/, tools/golden.py): the estimates for fixed inputs
and a replay's outputs are what was committed, so a change that moves them is seen."""

from __future__ import annotations

import dataclasses

import pytest
from tool_module import load_tool

golden = load_tool("golden")


@pytest.fixture(scope="module")
def made() -> dict[str, str]:
    return golden.outputs()


def test_every_golden_file_is_computed() -> None:
    committed = {path.name for path in golden.GOLDEN.glob("*.csv")}
    assert committed == set(NAMES)


NAMES = (
    [f"estimate_{v.name}.csv" for v in golden.VARIANTS]
    + [f"smooth_{v.name}.csv" for v in golden.SMOOTHED]
    + ["replay_attitude.csv", "replay_estimates.csv"]
)


@pytest.mark.parametrize("name", NAMES)
def test_outputs_are_the_committed_ones(made: dict[str, str], name: str) -> None:
    difference = golden.compare(name, (golden.GOLDEN / name).read_text(), made[name])
    assert difference.same, (
        f"{name} moved by {difference.largest:.3g} ({difference.where}); if the change "
        "is meant, run tools/golden.py --write and say why in the commit"
    )


def test_a_changed_rule_is_seen() -> None:
    # a noise density 0.1 % off moves the estimates far beyond the tolerance
    variant = golden.VARIANTS[0]
    nudged = dataclasses.replace(
        variant.config, gyro_noise_density=variant.config.gyro_noise_density * 1.001
    )
    inputs = golden.imu_arrays(golden.FLIGHT)
    name = f"estimate_{variant.name}.csv"
    expected = (golden.GOLDEN / name).read_text()
    difference = golden.compare(name, expected, golden.estimate_csv(variant, inputs))
    assert difference.same
    moved = golden.estimate_csv(dataclasses.replace(variant, config=nudged), inputs)
    assert golden.compare(name, expected, moved).largest > 1e3 * golden.TOLERANCE


def test_the_comparison_sees_numbers_text_and_rows() -> None:
    text = "a,b\n1.0,x\n2.0,y\n"
    assert golden.compare("f", text, text).largest == 0.0
    assert golden.compare("f", text, "a,b\n1.0,x\n2.0000001,y\n").largest == pytest.approx(1e-7)
    assert not golden.compare("f", text, "a,b\n1.0,z\n2.0,y\n").same
    assert not golden.compare("f", text, "a,b\n1.0,x\n").same
    assert not golden.compare("f", text, "a,c\n1.0,x\n2.0,y\n").same
    assert not golden.compare("f", text, "a,b\nnan,x\n2.0,y\n").same
