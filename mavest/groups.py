"""Small immutable Lie-group types over the kernels of :mod:`mavest.so3`.

:class:`SO3` is a rotation; :class:`SO3xR3` is the filter's state group
X = [R, b] with X₁ ∘ X₂ = [R₁R₂, b₁ + b₂] (docs/design.md#state-and-error). Both offer the same
interface — ``identity``, ``exp``, ``log``, ``compose`` (``@``), ``inverse``,
``adjoint`` — and the tests check the group axioms on both alike. The
filter's errors read naturally in these terms: left X = Exp(δ) ∘ X̄, right
X = X̄ ∘ Exp(δ).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, overload

import numpy as np
from numpy.typing import ArrayLike

from mavest import so3


def _frozen(array: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    out = np.array(array, dtype=np.float64)  # a private copy
    if out.shape != shape:
        raise ValueError(f"expected shape {shape}, got {out.shape}")
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class SO3:
    """A rotation, stored as a unit quaternion (w, x, y, z)."""

    wxyz: np.ndarray
    tangent_dim: ClassVar[int] = 3

    def __post_init__(self) -> None:
        q = np.array(self.wxyz, dtype=np.float64)
        if q.shape != (4,):
            raise ValueError(f"a quaternion has 4 components, got shape {q.shape}")
        so3.quat_normalize_into(q)
        object.__setattr__(self, "wxyz", _frozen(q, (4,)))

    @classmethod
    def identity(cls) -> SO3:
        return cls(np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def exp(cls, tangent: ArrayLike) -> SO3:
        return cls(so3.quat_exp(_frozen(tangent, (3,))))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> SO3:
        return cls(so3.quat_from_matrix(_frozen(matrix, (3, 3))))

    @classmethod
    def from_euler_zyx(cls, roll: float, pitch: float, yaw: float) -> SO3:
        return cls(so3.quat_from_euler_zyx(float(roll), float(pitch), float(yaw)))

    def log(self) -> np.ndarray:
        return so3.quat_log(self.wxyz)

    def as_matrix(self) -> np.ndarray:
        return so3.matrix_from_quat(self.wxyz)

    def as_euler_zyx(self) -> np.ndarray:
        """(roll, pitch, yaw), rad."""
        return so3.euler_zyx_from_quat(self.wxyz)

    def inverse(self) -> SO3:
        return SO3(so3.quat_conjugate(self.wxyz))

    def adjoint(self) -> np.ndarray:
        """Ad(R) = R: R Exp(δ) = Exp(R δ) R."""
        return self.as_matrix()

    def compose(self, other: SO3) -> SO3:
        return SO3(so3.quat_multiply(self.wxyz, other.wxyz))

    def apply(self, vector: ArrayLike) -> np.ndarray:
        return self.as_matrix() @ _frozen(vector, (3,))

    @overload
    def __matmul__(self, other: SO3) -> SO3: ...
    @overload
    def __matmul__(self, other: np.ndarray) -> np.ndarray: ...
    def __matmul__(self, other: SO3 | np.ndarray) -> SO3 | np.ndarray:
        if isinstance(other, SO3):
            return self.compose(other)
        return self.apply(other)

    def is_close(self, other: SO3, atol: float = 1e-9) -> bool:
        """Same rotation (either sign of the quaternion)."""
        return bool(np.linalg.norm(self.inverse().compose(other).log()) <= atol)


@dataclass(frozen=True, eq=False)
class SO3xR3:
    """The state group [R, b]: attitude and gyro bias, composed component-wise."""

    rotation: SO3
    vector: np.ndarray
    tangent_dim: ClassVar[int] = 6

    def __post_init__(self) -> None:
        object.__setattr__(self, "vector", _frozen(self.vector, (3,)))

    @classmethod
    def identity(cls) -> SO3xR3:
        return cls(SO3.identity(), np.zeros(3))

    @classmethod
    def exp(cls, tangent: ArrayLike) -> SO3xR3:
        """Λ(δ) = [Exp(δθ), δb], the lifting map of the filter's error."""
        tangent = _frozen(tangent, (6,))
        return cls(SO3.exp(tangent[:3]), tangent[3:])

    def log(self) -> np.ndarray:
        return np.concatenate([self.rotation.log(), self.vector])

    def inverse(self) -> SO3xR3:
        return SO3xR3(self.rotation.inverse(), -self.vector)

    def adjoint(self) -> np.ndarray:
        out = np.eye(6)
        out[:3, :3] = self.rotation.adjoint()
        return out

    def compose(self, other: SO3xR3) -> SO3xR3:
        return SO3xR3(self.rotation.compose(other.rotation), self.vector + other.vector)

    def __matmul__(self, other: SO3xR3) -> SO3xR3:
        return self.compose(other)

    def is_close(self, other: SO3xR3, atol: float = 1e-9) -> bool:
        return self.rotation.is_close(other.rotation, atol) and bool(
            np.allclose(self.vector, other.vector, atol=atol, rtol=0.0)
        )
