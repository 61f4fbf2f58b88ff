"""SO(3) maps and Jacobians against scipy's Rotation and finite differences."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from conftest import rotation_vectors, rotations, scipy_quat, unit_vectors, wxyz
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mavest import so3
from mavest.groups import SO3, SO3xR3


def angle_between(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(R1.T @ R2).as_rotvec()))


# ---------------------------------------------------------------- hat / vee


@given(unit_vectors(), unit_vectors())
def test_hat_is_the_cross_product_and_vee_inverts_it(v: np.ndarray, w: np.ndarray) -> None:
    np.testing.assert_allclose(so3.hat(v) @ w, np.cross(v, w), atol=1e-15)
    np.testing.assert_allclose(so3.vee(so3.hat(3.0 * v)), 3.0 * v, atol=1e-15)


# ---------------------------------------------------------------- Exp / Log


@given(rotation_vectors())
def test_exp_matches_scipy(phi: np.ndarray) -> None:
    expected = Rotation.from_rotvec(phi).as_matrix()
    np.testing.assert_allclose(so3.exp(phi), expected, atol=2e-15)
    np.testing.assert_allclose(so3.matrix_from_quat(so3.quat_exp(phi)), expected, atol=2e-15)


@given(rotations())
def test_log_matches_scipy(rotation: Rotation) -> None:
    R = rotation.as_matrix()
    phi = so3.log(R)
    expected = rotation.as_rotvec()
    theta = np.linalg.norm(expected)
    assert np.linalg.norm(phi) <= np.pi + 1e-15
    assert abs(np.linalg.norm(phi) - theta) < 1e-12
    if theta < np.pi - 1e-6:  # at π, φ and −φ are the same rotation
        np.testing.assert_allclose(phi, expected, atol=1e-12)
    assert angle_between(so3.exp(phi), R) < 1e-12


@pytest.mark.parametrize(
    "theta", [0.0, 1e-300, 1e-12, 1e-8, 1e-5, 0.049999, 0.05, 0.050001, 1.0, np.pi - 1e-9, np.pi]
)
def test_exp_log_are_stable_at_the_ends(theta: float) -> None:
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    phi = theta * axis
    R = so3.exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-15)
    back = so3.log(R)
    if theta < np.pi - 1e-6:
        np.testing.assert_allclose(back, phi, atol=1e-15 + 1e-12 * theta)
    else:  # near π the axis is recovered up to sign
        assert abs(np.linalg.norm(back) - theta) < 1e-8
        assert abs(abs(back @ axis) - theta) < 1e-8
    assert np.all(np.isfinite(so3.left_jacobian_inverse(phi)))


# ---------------------------------------------------------------- quaternions


@given(rotations())
def test_quaternion_matrix_conversions_match_scipy(rotation: Rotation) -> None:
    q = wxyz(rotation)
    np.testing.assert_allclose(so3.matrix_from_quat(q), rotation.as_matrix(), atol=1e-15)
    q_back = so3.quat_from_matrix(rotation.as_matrix())
    assert q_back[0] >= 0.0
    np.testing.assert_allclose(q_back, q if q[0] >= 0 else -q, atol=1e-14)


@given(rotations(), rotations())
def test_quaternion_product_composes_rotations(a: Rotation, b: Rotation) -> None:
    product = so3.quat_multiply(wxyz(a), wxyz(b))
    assert scipy_quat(product).approx_equal(a * b, atol=1e-12)


@given(rotation_vectors())
def test_quaternion_log_inverts_exp(phi: np.ndarray) -> None:
    back = so3.quat_log(so3.quat_exp(phi))
    assert angle_between(so3.exp(back), so3.exp(phi)) < 1e-12


# ---------------------------------------------------------------- Euler ZYX


@given(
    st.floats(-np.pi, np.pi),
    st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3),
    st.floats(-np.pi, np.pi),
)
def test_euler_zyx_matches_scipy(roll: float, pitch: float, yaw: float) -> None:
    expected = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    q = so3.quat_from_euler_zyx(roll, pitch, yaw)
    assert scipy_quat(q).approx_equal(expected, atol=1e-12)
    yaw_s, pitch_s, roll_s = expected.as_euler("ZYX")
    for angles in (so3.euler_zyx_from_matrix(expected.as_matrix()), so3.euler_zyx_from_quat(q)):
        np.testing.assert_allclose(
            np.angle(np.exp(1j * (angles - [roll_s, pitch_s, yaw_s]))), 0.0, atol=1e-9
        )


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-12])
def test_euler_zyx_at_gimbal_lock_still_reconstructs_the_rotation(pitch: float) -> None:
    R = so3.matrix_from_euler_zyx(0.7, pitch, -1.2)
    roll, pitch_back, yaw = so3.euler_zyx_from_matrix(R)
    assert angle_between(so3.matrix_from_euler_zyx(roll, pitch_back, yaw), R) < 1e-6


# ---------------------------------------------------------------- Jacobians

STEP = 1e-6


def numeric_jacobian(f: Callable[[np.ndarray], np.ndarray], n: int = 3) -> np.ndarray:
    out = np.empty((3, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = STEP
        out[:, j] = (f(e) - f(-e)) / (2 * STEP)
    return out


jacobian_arguments = rotation_vectors(max_angle=np.pi - 0.05)


@given(jacobian_arguments)
def test_right_jacobian_by_finite_differences(phi: np.ndarray) -> None:
    # Exp(φ + ε) ≈ Exp(φ) Exp(J_r(φ) ε)
    R = so3.exp(phi)
    numeric = numeric_jacobian(lambda e: so3.log(R.T @ so3.exp(phi + e)))
    np.testing.assert_allclose(so3.right_jacobian(phi), numeric, atol=1e-8)


@given(jacobian_arguments)
def test_left_jacobian_by_finite_differences(phi: np.ndarray) -> None:
    # Exp(φ + ε) ≈ Exp(J_l(φ) ε) Exp(φ)
    R = so3.exp(phi)
    numeric = numeric_jacobian(lambda e: so3.log(so3.exp(phi + e) @ R.T))
    np.testing.assert_allclose(so3.left_jacobian(phi), numeric, atol=1e-8)


@given(jacobian_arguments)
def test_inverse_jacobians_by_finite_differences(phi: np.ndarray) -> None:
    # Log(Exp(φ) Exp(ε)) ≈ φ + J_r⁻¹ ε,  Log(Exp(ε) Exp(φ)) ≈ φ + J_l⁻¹ ε
    R = so3.exp(phi)
    right = numeric_jacobian(lambda e: so3.log(R @ so3.exp(e)))
    left = numeric_jacobian(lambda e: so3.log(so3.exp(e) @ R))
    np.testing.assert_allclose(so3.right_jacobian_inverse(phi), right, atol=1e-7)
    np.testing.assert_allclose(so3.left_jacobian_inverse(phi), left, atol=1e-7)


@given(rotation_vectors())
def test_inverse_jacobians_invert_up_to_pi(phi: np.ndarray) -> None:
    eye = np.eye(3)
    np.testing.assert_allclose(
        so3.right_jacobian(phi) @ so3.right_jacobian_inverse(phi), eye, atol=1e-13
    )
    np.testing.assert_allclose(
        so3.left_jacobian(phi) @ so3.left_jacobian_inverse(phi), eye, atol=1e-13
    )
    np.testing.assert_allclose(so3.left_jacobian(phi), so3.right_jacobian(-phi), atol=1e-15)
    # Exp(φ) J_r(φ) = J_l(φ)
    np.testing.assert_allclose(
        so3.exp(phi) @ so3.right_jacobian(phi), so3.left_jacobian(phi), atol=1e-14
    )


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1e-3, so3.SERIES_ANGLE, 0.5, 3.0])
@given(phi=rotation_vectors())
def test_quat_exp_and_jacobian_in_one_are_the_separate_ones_bit_for_bit(
    scale: float, phi: np.ndarray
) -> None:
    # the prediction's shared form must not move an estimate: the same bits, not merely close
    phi = phi * (scale / max(np.linalg.norm(phi), 1e-300)) if scale else 0.0 * phi
    for left, jacobian in ((True, so3.left_jacobian), (False, so3.right_jacobian)):
        q, J = np.empty(4), np.empty((3, 3))
        so3.quat_exp_and_jacobian_into(phi, q, J, left)
        assert np.array_equal(q, so3.quat_exp(phi))
        assert np.array_equal(J, jacobian(phi))


@pytest.mark.parametrize(
    "jacobian",
    [so3.right_jacobian, so3.left_jacobian, so3.right_jacobian_inverse, so3.left_jacobian_inverse],
)
def test_jacobians_are_continuous_across_the_series_switch(
    jacobian: Callable[[np.ndarray], np.ndarray],
) -> None:
    axis = np.array([0.6, 0.0, 0.8])
    below = jacobian((so3.SERIES_ANGLE * (1 - 1e-12)) * axis)
    above = jacobian((so3.SERIES_ANGLE * (1 + 1e-12)) * axis)
    np.testing.assert_allclose(below, above, atol=1e-14)


# ---------------------------------------------------------------- group axioms, across types


@st.composite
def so3_elements(draw: st.DrawFn) -> SO3:
    return SO3.exp(draw(rotation_vectors()))


@st.composite
def so3xr3_elements(draw: st.DrawFn) -> SO3xR3:
    vector = np.array([draw(st.floats(-10, 10)) for _ in range(3)])
    return SO3xR3(draw(so3_elements()), vector)


GROUPS = {SO3: so3_elements(), SO3xR3: so3xr3_elements()}
group_types = st.sampled_from(list(GROUPS))


@given(st.data(), group_types)
def test_group_identity_and_inverse(data: st.DataObject, group: type) -> None:
    x = data.draw(GROUPS[group])
    identity = group.identity()
    assert (x @ identity).is_close(x) and (identity @ x).is_close(x)
    assert (x @ x.inverse()).is_close(identity) and (x.inverse() @ x).is_close(identity)


@given(st.data(), group_types)
def test_group_associativity(data: st.DataObject, group: type) -> None:
    a, b, c = (data.draw(GROUPS[group]) for _ in range(3))
    assert ((a @ b) @ c).is_close(a @ (b @ c), atol=1e-9)


@given(st.data(), group_types)
def test_group_exp_log_roundtrip(data: st.DataObject, group: type) -> None:
    x = data.draw(GROUPS[group])
    assert group.exp(x.log()).is_close(x)


@given(st.data(), group_types)
def test_group_adjoint_moves_a_tangent_across(data: st.DataObject, group: type) -> None:
    # X ∘ Exp(δ) = Exp(Ad(X) δ) ∘ X
    x = data.draw(GROUPS[group])
    delta = 0.3 * np.tanh(np.array([data.draw(st.floats(-3, 3)) for _ in range(group.tangent_dim)]))
    assert (x @ group.exp(delta)).is_close(group.exp(x.adjoint() @ delta) @ x, atol=1e-9)


def test_so3_type_is_immutable_and_applies_to_vectors() -> None:
    r = SO3.from_euler_zyx(0.1, -0.2, 0.3)
    with pytest.raises(ValueError):
        r.wxyz[0] = 2.0
    v = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(r @ v, r.as_matrix() @ v)
    np.testing.assert_allclose(r.as_euler_zyx(), [0.1, -0.2, 0.3], atol=1e-14)
