"""Shared hypothesis strategies and settings, and the online step's paths.

Kernels are compiled on first use; hypothesis' per-example deadline would count
that compile time, so it is off.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

settings.register_profile("mavest", deadline=None, max_examples=200)
settings.load_profile("mavest")

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@st.composite
def unit_vectors(draw: st.DrawFn) -> np.ndarray:
    v = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
    n = np.linalg.norm(v)
    if n < 1e-3:
        v, n = np.array([0.0, 0.0, 1.0]), 1.0
    return v / n


# Angles that exercise the series branches (tiny), the generic range, and θ → π.
angles = st.one_of(
    st.floats(0.0, 1e-6),
    st.floats(1e-6, 0.1),
    st.floats(0.1, np.pi - 1e-3),
    st.floats(np.pi - 1e-3, np.pi),
)


@st.composite
def rotation_vectors(draw: st.DrawFn, max_angle: float = np.pi) -> np.ndarray:
    return draw(unit_vectors()) * min(draw(angles), max_angle)


@st.composite
def rotations(draw: st.DrawFn) -> Rotation:
    return Rotation.from_rotvec(draw(rotation_vectors()))


def scipy_quat(q_wxyz: np.ndarray) -> Rotation:
    """scipy is (x, y, z, w): the conversion happens here and nowhere else in the tests."""
    return Rotation.from_quat(np.roll(q_wxyz, -1))


def wxyz(rotation: Rotation) -> np.ndarray:
    return np.roll(rotation.as_quat(), 1)


@pytest.fixture(params=["extension", "python"])
def online_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """Estimators made in the test take samples on this path of the online step: the
    extension's (skipped where it is not built, which test_online's first test reports)
    or the Python path that runs without it."""
    from mavest.estimator import estimator, online

    if request.param == "python":
        monkeypatch.setattr(estimator, "_ONLINE", online.PythonOnline)
    elif estimator._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")
    yield request.param
