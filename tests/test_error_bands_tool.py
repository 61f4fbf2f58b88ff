"""tools/error_bands.py: the band split against sinusoids whose RMS is known exactly."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from tool_module import load_tool

bands = load_tool("error_bands")
RATE = 100.0


def _tone(t: np.ndarray, amplitude: float, frequency: float) -> np.ndarray:
    return amplitude * np.sin(2.0 * math.pi * frequency * t)


@pytest.mark.parametrize("frequency", [0.01, 0.05, 0.2, 0.5, 5.0])
def test_a_tone_lies_in_its_own_band_alone(frequency: float) -> None:
    """A tone of amplitude A has RMS A/√2: all of it in the band that holds its
    frequency, next to nothing in the others, and the whole the same."""
    t = np.arange(0.0, 1200.0, 1.0 / RATE)
    error = np.column_stack([_tone(t, 2.0, frequency), np.zeros_like(t)])
    scored = (t > 200.0) & (t < 1000.0)  # away from the ends, where filtfilt's pad works
    rms = bands.band_rms(error, scored, RATE)
    expected = 2.0 / math.sqrt(2.0)
    band = next(
        k for k, (lo, hi) in enumerate(itertools.pairwise(bands.EDGES)) if lo <= frequency < hi
    )
    assert rms[band] == pytest.approx(expected, rel=0.02)
    assert rms[-1] == pytest.approx(expected, rel=0.01)
    others = [r for k, r in enumerate(rms[:-1]) if k != band]
    assert max(others) < 0.05 * expected


def test_two_tones_add_up_in_quadrature_and_unknown_truth_is_not_scored() -> None:
    """Tones in two bands each keep their own RMS; rows without truth (NaN) are bridged
    for the filters and left out of every RMS: half a second of them moves no band by more
    than the bridge's own leakage (0.005 of a tone of 0.7)."""
    t = np.arange(0.0, 1200.0, 1.0 / RATE)
    error = np.column_stack([_tone(t, 1.0, 0.05), _tone(t, 0.5, 2.0)])
    scored = (t > 200.0) & (t < 1000.0)
    clean = bands.band_rms(error, scored, RATE)
    holed = error.copy()
    holed[50_000:50_050] = np.nan
    with_holes = bands.band_rms(holed, scored, RATE)
    assert clean[1] == pytest.approx(1.0 / math.sqrt(2.0), rel=0.02)
    assert clean[4] == pytest.approx(0.5 / math.sqrt(2.0), rel=0.02)
    assert clean[-1] == pytest.approx(math.sqrt((1.0 + 0.25) / 2.0), rel=0.01)
    np.testing.assert_allclose(with_holes, clean, rtol=0.02, atol=0.005)
    # where the truth is known, a hole is the filter's failure: no figure hides it
    truth = np.ones(t.shape[0], dtype=bool)
    truth[50_000:50_050] = False
    assert bands.band_rms(holed, scored, RATE, truth)[-1] == pytest.approx(clean[-1], rel=0.01)
    failed = bands.band_rms(holed, scored, RATE, np.ones(t.shape[0], dtype=bool))
    assert all(math.isnan(r) for r in failed)
    assert all(math.isnan(r) for r in bands.band_rms(error, np.zeros_like(scored), RATE))
