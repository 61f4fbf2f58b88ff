"""S² residual, its Jacobian and the rotation between two directions."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import unit_vectors
from hypothesis import assume, example, given
from scipy.spatial.transform import Rotation

from mavest import so3, sphere


@given(unit_vectors())
def test_tangent_basis_is_orthonormal_right_handed_and_normal_to_v(v: np.ndarray) -> None:
    B = sphere.tangent_basis(v)
    np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-14)
    np.testing.assert_allclose(B.T @ v, 0.0, atol=1e-14)
    np.testing.assert_allclose(np.cross(B[:, 0], B[:, 1]), v, atol=1e-14)


@pytest.mark.parametrize("axis", range(3))
def test_tangent_basis_of_coordinate_axes(axis: int) -> None:
    for sign in (1.0, -1.0):
        v = np.zeros(3)
        v[axis] = sign
        B = sphere.tangent_basis(v)
        np.testing.assert_allclose(np.cross(B[:, 0], B[:, 1]), v, atol=1e-15)


@given(unit_vectors(), unit_vectors())
# nearly antipodal with h × z a few denormal steps long: its norm rounds (found by hypothesis)
@example(np.array([0.0, 0.0, 1.0]), np.array([5e-324, 5e-324, -1.0]))
def test_log_is_the_shortest_rotation_onto_z(h: np.ndarray, z: np.ndarray) -> None:
    rho = sphere.log(h, z)
    np.testing.assert_allclose(so3.exp(rho) @ h, z, atol=1e-12)
    angle = np.arctan2(np.linalg.norm(np.cross(h, z)), h @ z)  # not h·z (a common slip)
    assert abs(np.linalg.norm(rho) - angle) < 1e-12
    assert abs(rho @ h) < 1e-12 and abs(rho @ z) < 1e-12


@given(unit_vectors(), unit_vectors())
def test_rotation_between_matches_scipy_align_vectors(u: np.ndarray, v: np.ndarray) -> None:
    assume(u @ v > -1 + 1e-6)  # antipodal: any half-turn is a minimiser
    expected, _ = Rotation.align_vectors(v[None, :], u[None, :])
    np.testing.assert_allclose(sphere.rotation_between(u, v), expected.as_matrix(), atol=1e-9)


def test_angle_is_an_arc_cosine_not_a_dot_product() -> None:
    u = np.array([1.0, 0.0, 0.0])
    v = np.array([np.cos(np.pi / 3), np.sin(np.pi / 3), 0.0])
    assert np.linalg.norm(sphere.log(u, v)) == pytest.approx(np.pi / 3, abs=1e-15)


@pytest.mark.parametrize("tiny", [6.09295507e-162, 2.22507386e-313, 5e-324])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_nearly_parallel_directions_keep_their_axis(tiny: float, sign: float) -> None:
    # found by Hypothesis near h = −z: the cross product's squares are denormal
    # (1e-162), or it is denormal itself (1e-313, where θ/s overflowed to inf)
    h = np.array([0.0, 0.0, 1.0])
    z = np.array([0.0, tiny, sign])
    rho = sphere.log(h, z)
    np.testing.assert_allclose(so3.exp(rho) @ h, z, atol=1e-12)
    assert np.linalg.norm(rho) == pytest.approx(np.pi if sign < 0 else 0.0, abs=1e-12)
    assert rho[1] == 0.0 and rho[2] == 0.0  # about x, the axis h × z points along


def test_antipodal_directions_give_a_half_turn() -> None:
    h = np.array([0.0, 0.0, 1.0])
    rho = sphere.log(h, -h)
    assert np.linalg.norm(rho) == pytest.approx(np.pi)
    np.testing.assert_allclose(so3.exp(rho) @ h, -h, atol=1e-15)


@given(unit_vectors(), unit_vectors())
def test_log_jacobian_by_finite_differences_along_the_sphere(h: np.ndarray, z: np.ndarray) -> None:
    assume(h @ z > -0.99)  # the map is singular at the antipode
    J = sphere.log_jacobian(h, z)
    B = sphere.tangent_basis(h)
    step = 1e-6
    for k in range(2):
        axis = np.cross(h, B[:, k])  # rotating h about this axis moves it along B[:, k]
        plus = sphere.log(so3.exp(step * axis) @ h, z)
        minus = sphere.log(so3.exp(-step * axis) @ h, z)
        np.testing.assert_allclose(J @ B[:, k], (plus - minus) / (2 * step), atol=2e-7)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.00099, 0.00101, 0.3])
def test_log_jacobian_near_coincidence(angle: float) -> None:
    z = np.array([0.0, 0.0, 1.0])
    h = so3.exp(np.array([angle, 0.0, 0.0])) @ z
    J = sphere.log_jacobian(h, z)
    assert np.all(np.isfinite(J))
    if angle == 0.0:  # ρ = h × z to first order, so ∂ρ/∂h = −[z]×
        np.testing.assert_allclose(J, -so3.hat(z), atol=1e-15)
