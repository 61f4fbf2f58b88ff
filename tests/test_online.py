"""The online step's two paths: the extension ``_online`` (Cython, the filter step as a C
function) and the Python path (numba's entry point) that runs where the extension did not
build. They must give the same estimates bit for bit and take the same inputs."""

from __future__ import annotations

import copy
import math
import os
import pickle
import sys

import numpy as np
import pytest

import mavest
from mavest import Estimator, EstimatorConfig, StepFlags
from mavest.estimator import estimator as estimator_module
from mavest.estimator import online
from mavest.sim import Motion, simulate

# A machine without a C compiler installs mavest without the extension; there (and only
# there) this says so, and the test that it was built is skipped instead of failing.
WITHOUT_EXTENSION = os.environ.get("MAVEST_WITHOUT_EXTENSION") == "1"

FIELDS = (
    "t",
    "q",
    "bias",
    "cov",
    "innovation",
    "nis",
    "accel_used",
    "flags",
    "iterations",
    "at_rest",
    "heading_innovation",
    "heading_nis",
    "mag_used",
    "euler",
    "status",
)
TYPES = {
    "t": float,
    "nis": float,
    "heading_innovation": float,
    "heading_nis": float,
    "accel_used": bool,
    "at_rest": bool,
    "mag_used": bool,
    "flags": int,
    "iterations": int,
    "status": list,
}
SHAPES = {"q": (4,), "bias": (3,), "euler": (3,), "innovation": (2,), "cov": (6, 6)}


def test_the_extension_is_built_from_this_source() -> None:
    """CI builds the extension: a silent fallback to the Python path would hide a loss of
    several µs a sample. Set MAVEST_WITHOUT_EXTENSION=1 only where it cannot build."""
    if WITHOUT_EXTENSION:
        pytest.skip("MAVEST_WITHOUT_EXTENSION=1: this machine runs the Python path")
    from mavest.estimator import _online

    assert online.compiled() is _online
    assert estimator_module._ONLINE is _online.Online
    assert mavest.Estimate is _online.Estimate
    assert type(Estimator().update(0.01, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))) is _online.Estimate


def test_a_missing_or_stale_extension_leaves_the_python_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "mavest.estimator._online", None)  # import fails
    monkeypatch.delattr(mavest.estimator, "_online", raising=False)
    assert online.compiled() is None
    if WITHOUT_EXTENSION:
        return
    monkeypatch.undo()
    from mavest.estimator import _online

    monkeypatch.setattr(_online, "SOURCE_DIGEST", "0" * 64)
    with pytest.warns(RuntimeWarning, match="built from another _online.pyx"):
        assert online.compiled() is None


def _python_estimator(config: EstimatorConfig | None = None) -> Estimator:
    chosen = estimator_module._ONLINE
    estimator_module._ONLINE = online.PythonOnline
    try:
        return Estimator(config)
    finally:
        estimator_module._ONLINE = chosen


def _assert_same(a: object, b: object, where: str) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert type(x) is type(y), (name, where)
        if name in TYPES:
            assert type(x) is TYPES[name], (name, where)
        else:
            assert x.shape == SHAPES[name] and x.dtype == np.float64, (name, where)
        np.testing.assert_array_equal(x, y, err_msg=f"{name} at {where}")
    assert repr(a) == repr(b)


def _inputs(i: int, vector: np.ndarray) -> object:
    """The same vector in each of the forms callers pass, by sample."""
    forms = (
        lambda v: v,  # float64 array
        lambda v: tuple(v.tolist()),  # tuple of floats
        lambda v: v.tolist(),  # list of floats
        lambda v: np.stack([v, v], axis=1)[:, 0],  # strided view
        lambda v: v.astype(">f8"),  # big-endian
        lambda v: tuple(np.float64(x) for x in v),  # tuple of NumPy floats
    )
    return forms[i % len(forms)](vector)


@pytest.mark.parametrize("update", ["iterated", "ekf", "sigma_point"])
def test_both_paths_give_the_same_estimates_bit_for_bit(update: str) -> None:
    """Every field of every step, the inputs in every form, with the magnetometer and the
    known acceleration coming and going: the extension's estimates equal the Python
    path's, and both equal update_batch's. Estimates are compared after all are made:
    each must stay as it was made while later ones fill the output blocks."""
    if estimator_module._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")
    data = simulate(12.0, 100.0, motion=Motion(velocity_sigma=2.0, burst_magnitude=4.0), seed=5)
    n = len(data.t)
    mag = data.mag.copy()
    mag[1::3] = np.nan
    linear_accel = data.linear_accel.copy()
    linear_accel[: n // 4] = np.nan
    config = EstimatorConfig(update=update)
    compiled, python = Estimator(config), _python_estimator(config)
    made: list[tuple[object, object]] = []
    for i in range(n):
        t = data.t[i] if i % 2 else float(data.t[i])
        gyro, accel = _inputs(i, data.gyro[i]), _inputs(i + 3, data.accel[i])
        m = None if i % 5 == 0 else _inputs(i + 1, mag[i])  # NaN rows too: none
        a = None if np.isnan(linear_accel[i, 0]) else _inputs(i + 2, linear_accel[i])
        made.append((compiled.update(t, gyro, accel, m, a), python.update(t, gyro, accel, m, a)))
    mag_given = mag.copy()
    mag_given[::5] = np.nan
    batch = Estimator(config).update_batch(data.t, data.gyro, data.accel, mag_given, linear_accel)
    assert any(e.mag_used for e, _ in made) and any(
        e.flags & StepFlags.ACCEL_AIDED for e, _ in made
    )
    for i, (e, p) in enumerate(made):
        _assert_same(e, p, f"sample {i}")
        for name in FIELDS:
            if name not in ("euler", "status"):
                np.testing.assert_array_equal(getattr(e, name), getattr(batch, name)[i])
    # the angles, made when first read, are those of the batch's quaternions
    np.testing.assert_array_equal([e.euler for e, _ in made], batch.euler)
    np.testing.assert_array_equal(compiled.cov, python.cov)
    assert compiled.samples == python.samples == n


@pytest.mark.parametrize("online_path", ["compiled", "python"])
def test_samples_without_an_estimate_are_stepped_as_update_batch_steps_them(
    online_path: str,
) -> None:
    """Samples the filter cannot start on (2 g), then estimated ones, one whose time goes
    back (skipped) and a gap it re-aligns after: every field of each online estimate is
    update_batch's, its time the sample's (not the filter's last, -inf before the first)."""
    if online_path == "compiled" and estimator_module._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")
    data = simulate(6.0, 100.0, seed=8)
    t, gyro, accel = data.t.copy(), data.gyro.copy(), data.accel.copy()
    accel[:20] *= 2.0
    t[300] = t[299] - 0.5
    t[400:] += 5.0
    filter_ = Estimator() if online_path == "compiled" else _python_estimator(EstimatorConfig())
    made = [filter_.update(t[i], gyro[i], accel[i]) for i in range(len(t))]
    batch = Estimator().update_batch(t, gyro, accel)
    flags = batch.flags
    assert np.all(flags[:20] & StepFlags.NOT_INITIALISED) and flags[300] & StepFlags.SKIPPED
    for i, e in enumerate(made):
        for name in FIELDS:
            if name not in ("euler", "status"):
                np.testing.assert_array_equal(
                    getattr(e, name), getattr(batch, name)[i], err_msg=f"{name} at {i}"
                )
    np.testing.assert_array_equal([e.t for e in made], t)


def test_a_batch_fed_estimator_steps_lone_samples_as_batches_then_online() -> None:
    """Estimator(batch_fed=True), as mavest replay makes them: its first updates run the
    batch loop on the one sample (the online step is not even made), later ones the
    online step; the estimates are the plain estimator's, bit for bit."""
    data = simulate(6.0, 100.0, motion=Motion(velocity_sigma=2.0), seed=6)
    n = len(data.t)
    assert n > estimator_module._LONE_BATCHES + 100
    fed, plain = Estimator(batch_fed=True), Estimator()
    for i in range(n):
        m = None if i % 4 else data.mag[i]
        a = None if i < n // 2 else tuple(data.linear_accel[i].tolist())
        inputs = (data.t[i], data.gyro[i], data.accel[i], m, a)
        _assert_same(fed.update(*inputs), plain.update(*inputs), f"sample {i}")
        assert (fed._online is None) == (i < estimator_module._LONE_BATCHES), i
    np.testing.assert_array_equal(fed.cov, plain.cov)
    fresh = Estimator(batch_fed=True)
    with pytest.raises(ValueError, match="gyro must have 3 components"):
        fresh.update(0.0, [0.0, 0.0], [0.0, 0.0, -9.8])
    with pytest.raises(ValueError, match="linear_accel must have 3 components"):
        fresh.update(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, -9.8], None, [1.0])
    assert fresh.samples == 0


def test_both_paths_skip_the_same_samples_and_reject_the_same_inputs(online_path: str) -> None:
    est = Estimator()
    first = est.update(1.0, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))
    assert first.flags & StepFlags.INITIALISED
    assert est.update(1.0, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8)).flags & StepFlags.TIME_NOT_INCREASING
    assert est.update(1.1, (math.nan, 0.0, 0.0), (0.0, 0.0, -9.8)).flags & StepFlags.GYRO_INVALID
    # what float() takes as a time, both take: an int, a NumPy scalar, a string
    for t in (2, np.float32(2.5), np.int64(3), "3.5"):
        assert est.update(t, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8)).t == float(t)
    for t, error in ((None, TypeError), ("soon", ValueError), (1j, TypeError)):
        with pytest.raises(error):
            est.update(t, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))
    accel = (0.0, 0.0, -9.8)
    for gyro in ((0.0, 0.0), [0.0] * 4, np.zeros((3, 1)), np.zeros((1, 3)), 0.0, None):
        with pytest.raises(ValueError, match="gyro must have 3 components"):
            est.update(5.0, gyro, accel)
    with pytest.raises(ValueError, match="accel must have 3 components"):
        est.update(5.0, (0.0, 0.0, 0.0), np.zeros(4))
    with pytest.raises(ValueError, match="mag must have 3 components"):
        est.update(5.0, (0.0, 0.0, 0.0), accel, mag=[1.0, 2.0])
    with pytest.raises(ValueError, match="linear_accel must have 3 components"):
        est.update(5.0, (0.0, 0.0, 0.0), accel, linear_accel=())
    with pytest.raises(TypeError):  # as numba's unboxing of a complex into a float
        est.update(5.0, np.zeros(3, dtype=complex), accel)
    # components that are not floats are converted as the Python path converts them
    e = est.update(5.0, (0, 0, 0), [0, 0, -10], np.array([20, 0, 40]), (0.0, 0, 0.0))
    assert e.t == 5.0 and np.all(np.isfinite(e.q))


def test_the_same_error_whichever_the_path() -> None:
    if estimator_module._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")
    accel = (0.0, 0.0, -9.8)
    checked = (
        (None, (0.0, 0.0, 0.0), accel, None, None),
        (1.0, (0.0, 0.0), accel, None, None),
        (1.0, (0.0, 0.0), (0.0, 0.0), [1.0], None),  # mag is read first
        (1.0, (0.0, 0.0), (0.0, 0.0), None, np.zeros(2)),
        (1.0, (0.0, 0.0, 0.0), accel, None, {1: 2.0}),
    )
    for args in checked:
        errors = []
        for est in (Estimator(), _python_estimator()):
            with pytest.raises((TypeError, ValueError)) as raised:
                est.update(*args)
            errors.append((type(raised.value), str(raised.value)))
        assert errors[0] == errors[1], args
    # components that are not numbers: numba's unboxing says only "bad argument type"
    # (a TypeError), the extension what float() says of them
    for gyro, error in (
        (np.zeros(3, dtype=complex), TypeError),
        (np.array(["a", "b", "c"]), ValueError),
    ):
        with pytest.raises(error, match="float"):
            Estimator().update(1.0, gyro, accel)
        with pytest.raises(TypeError):
            _python_estimator().update(1.0, gyro, accel)


def test_an_estimate_keeps_its_block_alive_and_stays_as_made(online_path: str) -> None:
    est = Estimator()
    first = est.update(0.01, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))
    q, cov = first.q, first.cov
    made = q.copy(), cov.copy()
    del first  # its arrays keep the block alive
    kept = [est.update(0.01 * i, (0.1, 0.0, 0.0), (0.0, 0.0, -9.8)) for i in range(2, 200)]
    np.testing.assert_array_equal(q, made[0])
    np.testing.assert_array_equal(cov, made[1])
    assert [e.t for e in kept] == [0.01 * i for i in range(2, 200)]
    assert len({id(e.q.base) for e in kept[:96]}) > 1  # several blocks filled


def test_estimate_of_pickle_and_copy_give_the_same_estimate(online_path: str) -> None:
    est = Estimator()
    for i in range(1, 30):
        e = est.update(0.01 * i, (0.01, -0.02, 0.03), (0.1, 0.2, -9.8), (20.0, 1.0, 40.0))
    fields = [getattr(e, name) for name in FIELDS[:13]]
    for other in (
        mavest.Estimate.of(*fields),
        pickle.loads(pickle.dumps(e)),
        copy.copy(e),
        copy.deepcopy(e),
    ):
        _assert_same(other, e, "a copy")
    with pytest.raises(TypeError):
        mavest.Estimate()  # made by update or Estimate.of only  # type: ignore[call-arg]


def test_the_python_estimate_has_the_compiled_ones_interface() -> None:
    if estimator_module._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")

    def public(cls: type) -> set[str]:
        return {name for name in dir(cls) if not name.startswith("_")}

    assert public(online.Estimate) == public(estimator_module._COMPILED.Estimate)
    assert set(FIELDS) | {"of"} == public(online.Estimate)


def test_a_fetched_update_follows_resets_and_copies_step_their_own_state(online_path: str) -> None:
    est = Estimator()
    update = est.update
    update(0.01, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))
    est.reset()
    update(0.02, (0.0, 0.0, 0.0), (0.0, 0.0, -9.8))
    assert est.samples == 1  # the reset state took the sample
    est.initialise(0.02, [1.0, 0.0, 0.0, 0.0])
    update(0.03, (0.1, 0.0, 0.0), (0.0, 0.0, -9.8))
    assert est.samples == 1
    twin = copy.deepcopy(est)
    a = est.update(0.04, (0.2, 0.0, 0.0), (0.0, 0.0, -9.8))
    b = twin.update(0.04, (0.2, 0.0, 0.0), (0.0, 0.0, -9.8))
    _assert_same(a, b, "a deep copy")
    twin.update(0.05, (0.2, 0.0, 0.0), (0.0, 0.0, -9.8))
    assert est.samples == 2 and twin.samples == 3


def test_the_compiled_step_takes_only_its_own_records() -> None:
    """It writes the records through pointers: anything but one record of the layout it
    was compiled for, in writable memory, is refused before a step."""
    if estimator_module._COMPILED is None:
        pytest.skip("the extension is not built (test_the_extension_is_built_from_this_source)")
    Online = estimator_module._COMPILED.Online
    est = Estimator()
    state, coefficients = est._state, est._coefficients
    read_only = state.copy()
    read_only.flags.writeable = False
    for bad in (state[["q", "b"]], np.concatenate([state, state]), read_only, state.view(np.uint8)):
        with pytest.raises(TypeError, match="state must be"):
            Online(bad, coefficients)
    with pytest.raises(TypeError, match="coefficients must be"):
        Online(state, state)
