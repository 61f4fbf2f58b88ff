"""The rotation group SO(3): Exp/Log, hat/vee, Jacobians, quaternions, Euler angles.

Conventions (docs/design.md#conventions): quaternions are (w, x, y, z), Hamilton product;
a rotation maps body to world, ``v_world = R v_body``; Euler angles are ZYX
(yaw ψ, pitch θ, roll φ), ``R = Rz(ψ) Ry(θ) Rx(φ)``, as MAVLink's ATTITUDE.

Every map is a numba kernel. The ``*_into`` forms write into a caller-owned
``out`` array and allocate nothing: the filter calls them on its hot path, where
one small allocation costs as much as the arithmetic of a whole Jacobian. The
plain forms allocate and return; they are for everything else.

The closed forms divide by the rotation angle θ and lose precision as θ → 0;
below ``SERIES_ANGLE`` their Taylor series are used instead. The forms chosen
stay exact as θ → π as well (Log goes through the quaternion, the inverse
Jacobian through cot(θ/2)). The tests check all of this against scipy and
finite differences.
"""

from __future__ import annotations

import math

import numpy as np

from mavest._jit import inplace_kernel, kernel

# Series expansions are used below this angle (rad). With the terms kept, the
# truncation error there is below 1e-17 relative.
SERIES_ANGLE = 0.05


# --------------------------------------------------------------------------
# Scalar coefficients of the closed forms
# --------------------------------------------------------------------------


@kernel
def sinc(theta: float) -> float:
    """sin(θ)/θ, exact at θ = 0."""
    if abs(theta) < 1e-4:
        return 1.0 - theta * theta / 6.0
    return math.sin(theta) / theta


@kernel
def _coefficient_b(theta: float) -> float:
    """(1 − cos θ)/θ², written as ½ sinc²(θ/2) to avoid cancellation."""
    return _coefficient_b_of_half_sinc(sinc(0.5 * theta))


@kernel
def _coefficient_b_of_half_sinc(half_sinc: float) -> float:
    """:func:`_coefficient_b` from sinc(θ/2)."""
    return 0.5 * half_sinc * half_sinc


@kernel
def _coefficient_c(theta: float) -> float:
    """(θ − sin θ)/θ³."""
    if theta < SERIES_ANGLE:
        t2 = theta * theta
        return 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2 * t2 * t2 / 362880.0
    return (theta - math.sin(theta)) / (theta * theta * theta)


@kernel
def _coefficient_d(theta: float) -> float:
    """(1 − (θ/2) cot(θ/2))/θ², the [φ]×² coefficient of the inverse Jacobians.

    Equal to 1/θ² − (1 + cos θ)/(2θ sin θ) but finite at θ = π; singular only at 2π.
    """
    if theta < SERIES_ANGLE:
        t2 = theta * theta
        return 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0 + t2 * t2 * t2 / 1209600.0
    half = 0.5 * theta
    return (1.0 - half * math.cos(half) / math.sin(half)) / (theta * theta)


@kernel
def jacobian_coefficients(theta: float) -> tuple[float, float]:
    """(B, C) with J_l(φ) = I + B[φ]× + C[φ]×² and J_r(φ) = I − B[φ]× + C[φ]×²."""
    return _coefficient_b(theta), _coefficient_c(theta)


@kernel
def _norm3(v: np.ndarray) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


# --------------------------------------------------------------------------
# hat / vee and the common form I + a[φ]× + b[φ]×²
# --------------------------------------------------------------------------


@kernel
def hat_into(v: np.ndarray, out: np.ndarray) -> None:
    """[v]×, the skew matrix with [v]× w = v × w."""
    out[0, 0] = 0.0
    out[0, 1] = -v[2]
    out[0, 2] = v[1]
    out[1, 0] = v[2]
    out[1, 1] = 0.0
    out[1, 2] = -v[0]
    out[2, 0] = -v[1]
    out[2, 1] = v[0]
    out[2, 2] = 0.0


@kernel
def hat(v: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    hat_into(v, out)
    return out


@kernel
def vee_into(M: np.ndarray, out: np.ndarray) -> None:
    """The inverse of hat, taken from the skew-symmetric part of M."""
    out[0] = 0.5 * (M[2, 1] - M[1, 2])
    out[1] = 0.5 * (M[0, 2] - M[2, 0])
    out[2] = 0.5 * (M[1, 0] - M[0, 1])


@kernel
def vee(M: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    vee_into(M, out)
    return out


@kernel
def skew_polynomial_into(phi: np.ndarray, a: float, b: float, out: np.ndarray) -> None:
    """out = I + a [φ]× + b [φ]×², using [φ]×² = φφᵀ − θ² I.

    Exp, both Jacobians and both inverse Jacobians are of this form; only the
    coefficients differ.
    """
    x, y, z = phi[0], phi[1], phi[2]
    t2 = x * x + y * y + z * z
    out[0, 0] = 1.0 + b * (x * x - t2)
    out[1, 1] = 1.0 + b * (y * y - t2)
    out[2, 2] = 1.0 + b * (z * z - t2)
    out[0, 1] = -a * z + b * x * y
    out[1, 0] = a * z + b * x * y
    out[0, 2] = a * y + b * x * z
    out[2, 0] = -a * y + b * x * z
    out[1, 2] = -a * x + b * y * z
    out[2, 1] = a * x + b * y * z


# --------------------------------------------------------------------------
# Exp, Log and the Jacobians
# --------------------------------------------------------------------------


@kernel
def exp_into(phi: np.ndarray, out: np.ndarray) -> None:
    """Exp(φ) = I + (sin θ/θ)[φ]× + ((1 − cos θ)/θ²)[φ]×² (Rodrigues), θ = ‖φ‖."""
    theta = _norm3(phi)
    skew_polynomial_into(phi, sinc(theta), _coefficient_b(theta), out)


@kernel
def exp(phi: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    exp_into(phi, out)
    return out


@kernel
def right_jacobian_into(phi: np.ndarray, out: np.ndarray) -> None:
    """J_r(φ) = I − ((1 − cos θ)/θ²)[φ]× + ((θ − sin θ)/θ³)[φ]×².

    Exp(φ + ε) ≈ Exp(φ) Exp(J_r(φ) ε).
    """
    theta = _norm3(phi)
    skew_polynomial_into(phi, -_coefficient_b(theta), _coefficient_c(theta), out)


@kernel
def right_jacobian(phi: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    right_jacobian_into(phi, out)
    return out


@kernel
def left_jacobian_into(phi: np.ndarray, out: np.ndarray) -> None:
    """J_l(φ) = J_r(−φ): Exp(φ + ε) ≈ Exp(J_l(φ) ε) Exp(φ)."""
    theta = _norm3(phi)
    skew_polynomial_into(phi, _coefficient_b(theta), _coefficient_c(theta), out)


@kernel
def quat_exp_and_jacobian_into(
    phi: np.ndarray, q_out: np.ndarray, jacobian_out: np.ndarray, left: bool
) -> None:
    """:func:`quat_exp_into` and :func:`left_jacobian_into` (``left``) or
    :func:`right_jacobian_into` of one φ, bit for bit, in one: a prediction needs both,
    and they share θ and sinc(θ/2) (a sine and a square root fewer a sample)."""
    theta = _norm3(phi)
    half_sinc = sinc(0.5 * theta)
    _quat_exp_components_into(phi, theta, half_sinc, q_out)
    b = _coefficient_b_of_half_sinc(half_sinc)
    skew_polynomial_into(phi, b if left else -b, _coefficient_c(theta), jacobian_out)


@kernel
def left_jacobian(phi: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    left_jacobian_into(phi, out)
    return out


@kernel
def right_jacobian_inverse_into(phi: np.ndarray, out: np.ndarray) -> None:
    """J_r(φ)⁻¹ = I + ½[φ]× + (1/θ² − (1 + cos θ)/(2θ sin θ))[φ]×²."""
    theta = _norm3(phi)
    skew_polynomial_into(phi, 0.5, _coefficient_d(theta), out)


@kernel
def right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    right_jacobian_inverse_into(phi, out)
    return out


@kernel
def left_jacobian_inverse_into(phi: np.ndarray, out: np.ndarray) -> None:
    """J_l(φ)⁻¹ = J_r(−φ)⁻¹."""
    theta = _norm3(phi)
    skew_polynomial_into(phi, -0.5, _coefficient_d(theta), out)


@kernel
def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    left_jacobian_inverse_into(phi, out)
    return out


@kernel
def log_into(R: np.ndarray, out: np.ndarray) -> None:
    """Log(R) ∈ R³ with ‖Log(R)‖ ∈ [0, π].

    Goes through the quaternion (Shepperd's method), which stays accurate where
    the textbook θ/(2 sin θ)(R − Rᵀ)ᵛ formula fails: at θ → π, where sin θ → 0
    and R − Rᵀ carries no information about the axis.
    """
    w, x, y, z = _quaternion_components_from_matrix(R)
    quat_log_components_into(w, x, y, z, out)


@kernel
def log(R: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    log_into(R, out)
    return out


# --------------------------------------------------------------------------
# Quaternions (w, x, y, z)
# --------------------------------------------------------------------------


@kernel
def _quat_product_into(
    pw: float,
    px: float,
    py: float,
    pz: float,
    qw: float,
    qx: float,
    qy: float,
    qz: float,
    out: np.ndarray,
) -> None:
    out[0] = pw * qw - px * qx - py * qy - pz * qz
    out[1] = pw * qx + px * qw + py * qz - pz * qy
    out[2] = pw * qy - px * qz + py * qw + pz * qx
    out[3] = pw * qz + px * qy - py * qx + pz * qw


@kernel
def quat_multiply_into(p: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """Hamilton product p ⊗ q (the rotation q first, then p). ``out`` may not alias p or q."""
    _quat_product_into(p[0], p[1], p[2], p[3], q[0], q[1], q[2], q[3], out)


@kernel
def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    quat_multiply_into(p, q, out)
    return out


@kernel
def quat_divide_right_into(p: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """p ⊗ q⁻¹ for unit q: the rotation from q to p expressed on the left (world side)."""
    _quat_product_into(p[0], p[1], p[2], p[3], q[0], -q[1], -q[2], -q[3], out)


@kernel
def quat_divide_left_into(p: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """p⁻¹ ⊗ q for unit p: the rotation from p to q expressed on the right (body side)."""
    _quat_product_into(p[0], -p[1], -p[2], -p[3], q[0], q[1], q[2], q[3], out)


@kernel
def quat_conjugate_into(q: np.ndarray, out: np.ndarray) -> None:
    out[0] = q[0]
    out[1] = -q[1]
    out[2] = -q[2]
    out[3] = -q[3]


@kernel
def quat_conjugate(q: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    quat_conjugate_into(q, out)
    return out


@kernel
def quat_normalize_into(q: np.ndarray) -> None:
    """Normalise in place; the sign convention w ≥ 0 picks one of the double cover."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    q[0] /= n
    q[1] /= n
    q[2] /= n
    q[3] /= n


@kernel
def quat_exp_into(phi: np.ndarray, out: np.ndarray) -> None:
    """The unit quaternion of the rotation vector φ: (cos θ/2, sin(θ/2)/θ · φ)."""
    theta = _norm3(phi)
    _quat_exp_components_into(phi, theta, sinc(0.5 * theta), out)


@kernel
def _quat_exp_components_into(
    phi: np.ndarray, theta: float, half_sinc: float, out: np.ndarray
) -> None:
    """:func:`quat_exp_into` given θ = ‖φ‖ and sinc(θ/2)."""
    k = 0.5 * half_sinc
    out[0] = math.cos(0.5 * theta)
    out[1] = k * phi[0]
    out[2] = k * phi[1]
    out[3] = k * phi[2]


@kernel
def quat_times_exp_into(q: np.ndarray, px: float, py: float, pz: float, out: np.ndarray) -> None:
    """q ⊗ Exp(φ), φ = (px, py, pz): q turned by φ about its own (body) axes. ``out`` may
    not alias q."""
    theta = math.sqrt(px * px + py * py + pz * pz)
    k = 0.5 * sinc(0.5 * theta)
    _quat_product_into(q[0], q[1], q[2], q[3], math.cos(0.5 * theta), k * px, k * py, k * pz, out)


@kernel
def quat_exp(phi: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    quat_exp_into(phi, out)
    return out


@kernel
def quat_log_components_into(w: float, x: float, y: float, z: float, out: np.ndarray) -> None:
    if w < 0.0:  # the shorter of the two rotation vectors
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # atan2(s, w)/s has no cancellation for small s; only s = 0 needs its limit.
    k = 2.0 / w if s == 0.0 else 2.0 * math.atan2(s, w) / s
    out[0] = k * x
    out[1] = k * y
    out[2] = k * z


@kernel
def quat_log_into(q: np.ndarray, out: np.ndarray) -> None:
    """The rotation vector of a unit quaternion, ‖·‖ ∈ [0, π]."""
    quat_log_components_into(q[0], q[1], q[2], q[3], out)


@kernel
def quat_log(q: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    quat_log_into(q, out)
    return out


@kernel
def matrix_from_quat_into(q: np.ndarray, out: np.ndarray) -> None:
    """Rotation matrix of a quaternion; a non-unit quaternion is normalised implicitly."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    s = 2.0 / (w * w + x * x + y * y + z * z)
    out[0, 0] = 1.0 - s * (y * y + z * z)
    out[0, 1] = s * (x * y - w * z)
    out[0, 2] = s * (x * z + w * y)
    out[1, 0] = s * (x * y + w * z)
    out[1, 1] = 1.0 - s * (x * x + z * z)
    out[1, 2] = s * (y * z - w * x)
    out[2, 0] = s * (x * z - w * y)
    out[2, 1] = s * (y * z + w * x)
    out[2, 2] = 1.0 - s * (x * x + y * y)


@kernel
def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    matrix_from_quat_into(q, out)
    return out


@kernel
def _quaternion_components_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    """Shepperd's method: divide by the largest of 4w², 4x², 4y², 4z² (never small)."""
    r00, r11, r22 = R[0, 0], R[1, 1], R[2, 2]
    trace = r00 + r11 + r22
    if trace >= r00 and trace >= r11 and trace >= r22:
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        f = 0.25 / w
        x, y, z = (R[2, 1] - R[1, 2]) * f, (R[0, 2] - R[2, 0]) * f, (R[1, 0] - R[0, 1]) * f
    elif r00 >= r11 and r00 >= r22:
        x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        f = 0.25 / x
        w, y, z = (R[2, 1] - R[1, 2]) * f, (R[0, 1] + R[1, 0]) * f, (R[0, 2] + R[2, 0]) * f
    elif r11 >= r22:
        y = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        f = 0.25 / y
        w, x, z = (R[0, 2] - R[2, 0]) * f, (R[0, 1] + R[1, 0]) * f, (R[1, 2] + R[2, 1]) * f
    else:
        z = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        f = 0.25 / z
        w, x, y = (R[1, 0] - R[0, 1]) * f, (R[0, 2] + R[2, 0]) * f, (R[1, 2] + R[2, 1]) * f
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    return w / n, x / n, y / n, z / n


@kernel
def quat_from_matrix_into(R: np.ndarray, out: np.ndarray) -> None:
    """Unit quaternion (w ≥ 0) of a rotation matrix."""
    w, x, y, z = _quaternion_components_from_matrix(R)
    out[0] = w
    out[1] = x
    out[2] = y
    out[3] = z


@kernel
def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    quat_from_matrix_into(R, out)
    return out


@kernel
def quat_rotate_into(q: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """out = R(q) v for a unit quaternion, as v + 2w (u × v) + 2u × (u × v); out may alias v."""
    w, ux, uy, uz = q[0], q[1], q[2], q[3]
    vx, vy, vz = v[0], v[1], v[2]
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    out[0] = vx + w * tx + (uy * tz - uz * ty)
    out[1] = vy + w * ty + (uz * tx - ux * tz)
    out[2] = vz + w * tz + (ux * ty - uy * tx)


@kernel
def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q) v."""
    out = np.empty(3)
    quat_rotate_into(q, v, out)
    return out


# --------------------------------------------------------------------------
# ZYX Euler angles (roll, pitch, yaw), MAVLink ATTITUDE's convention
# --------------------------------------------------------------------------

# Below this |cos(pitch)| roll and yaw are no longer separable (gimbal lock);
# roll is then set to 0 and the whole rotation about the vertical goes to yaw.
_GIMBAL_LOCK_COS = 1e-9


@kernel
def _euler_from_elements(
    r00: float, r01: float, r10: float, r11: float, r20: float, r21: float, r22: float
) -> tuple[float, float, float]:
    cos_pitch = math.hypot(r21, r22)
    # atan2 rather than asin(−r20): asin loses half the digits near ±90°.
    pitch = math.atan2(-r20, cos_pitch)
    if cos_pitch < _GIMBAL_LOCK_COS:
        return 0.0, pitch, math.atan2(-r01, r11)
    return math.atan2(r21, r22), pitch, math.atan2(r10, r00)


@kernel
def euler_zyx_from_matrix(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in rad with R = Rz(yaw) Ry(pitch) Rx(roll); pitch ∈ [−π/2, π/2]."""
    roll, pitch, yaw = _euler_from_elements(
        R[0, 0], R[0, 1], R[1, 0], R[1, 1], R[2, 0], R[2, 1], R[2, 2]
    )
    return np.array([roll, pitch, yaw])


@inplace_kernel
def euler_zyx_from_quat_into(q: np.ndarray, out: np.ndarray) -> None:
    """(roll, pitch, yaw) of a unit quaternion, from the matrix elements it needs only."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    roll, pitch, yaw = _euler_from_elements(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )
    out[0] = roll
    out[1] = pitch
    out[2] = yaw


@kernel
def euler_zyx_from_quat(q: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    euler_zyx_from_quat_into(q, out)
    return out


@kernel
def quat_from_euler_zyx_into(roll: float, pitch: float, yaw: float, out: np.ndarray) -> None:
    """q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    out[0] = cy * cp * cr + sy * sp * sr
    out[1] = cy * cp * sr - sy * sp * cr
    out[2] = cy * sp * cr + sy * cp * sr
    out[3] = sy * cp * cr - cy * sp * sr


@kernel
def quat_from_euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    out = np.empty(4)
    quat_from_euler_zyx_into(roll, pitch, yaw, out)
    return out


@kernel
def matrix_from_euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return matrix_from_quat(quat_from_euler_zyx(roll, pitch, yaw))


# --------------------------------------------------------------------------
# Batch helpers (N×4 quaternions)
# --------------------------------------------------------------------------


@kernel
def euler_zyx_from_quats(q: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw of (N, 4) quaternions."""
    out = np.empty((q.shape[0], 3))
    for i in range(q.shape[0]):
        euler_zyx_from_quat_into(q[i], out[i])
    return out


def quats_from_euler_zyx(angles: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions of (N, 3) ZYX angles (roll, pitch, yaw), vectorised.

    The same formula as :func:`quat_from_euler_zyx`, in numpy: for ~10⁵ samples a
    per-sample kernel call would cost more than the conversion.
    """
    half = 0.5 * np.asarray(angles, dtype=float)
    cr, sr = np.cos(half[:, 0]), np.sin(half[:, 0])
    cp, sp = np.cos(half[:, 1]), np.sin(half[:, 1])
    cy, sy = np.cos(half[:, 2]), np.sin(half[:, 2])
    q = np.column_stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ]
    )
    q[q[:, 0] < 0.0] *= -1.0  # w ≥ 0, as so3 normalises
    return q


# Below this cos(pitch) (within ~0.0001° of ±90°) roll and yaw turn about one axis: their
# σ is unbounded, and given as inf.
_GIMBAL_LOCK_COS = 1e-6


def euler_sigmas(q: np.ndarray, cov_attitude: np.ndarray, error: str = "left") -> np.ndarray:
    """(N, 3) 1σ of roll, pitch and yaw (rad) at (N, 4) attitudes ``q`` (body → NED), from
    the (N, 3, 3) covariances of their error δθ: in the world frame (``error="left"``:
    R = Exp(δθ) R̄) or in the body frame (``"right"``: R = R̄ Exp(δθ)), as the estimator's
    ``cov[:3, :3]`` is for its configured error (docs/design.md#state-and-error).

    First order: σ² = diag(J P Jᵀ), J the Jacobian of the ZYX angles with respect to δθ.
    A world-frame rotation δθ turns the angles by E⁻¹ δθ, the columns of E the axes
    each angle turns about, in the world frame (roll about Rz(ψ)Ry(θ)x̂, pitch about
    Rz(ψ)ŷ, yaw about ẑ)::

        left:  J = [[cψ/cθ, sψ/cθ, 0], [−sψ, cψ, 0], [cψ tθ, sψ tθ, 1]]

    and a body-frame one is the world-frame R̄ δθ (J R̄: the body-rate kinematics)::

        right: J = [[1, sφ tθ, cφ tθ], [0, cφ, −sφ], [0, sφ/cθ, cφ/cθ]]

    Both are written with R̄'s elements, without trigonometry: only products, sums,
    quotients and square roots, each rounded exactly, so that a row's σ is the same
    bits whatever rows it is computed with (a replay's fast path and its one-by-one
    path write the same table).
    """
    q = np.asarray(q, dtype=np.float64)
    P = np.asarray(cov_attitude, dtype=np.float64)
    n = q.shape[0]
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    J = np.zeros((n, 3, 3))
    if error == "left":
        r00 = 1.0 - 2.0 * (y * y + z * z)  # cψ cθ
        r10 = 2.0 * (x * y + w * z)  # sψ cθ
        r20 = 2.0 * (x * z - w * y)  # −sθ
        c2 = r00 * r00 + r10 * r10  # cθ²
        c = np.sqrt(c2)
        with np.errstate(divide="ignore", invalid="ignore"):
            J[:, 0, 0], J[:, 0, 1] = r00 / c2, r10 / c2
            J[:, 1, 0], J[:, 1, 1] = -r10 / c, r00 / c
            J[:, 2, 0], J[:, 2, 1], J[:, 2, 2] = -r20 * r00 / c2, -r20 * r10 / c2, 1.0
    elif error == "right":
        r20 = 2.0 * (x * z - w * y)  # −sθ
        r21 = 2.0 * (y * z + w * x)  # cθ sφ
        r22 = 1.0 - 2.0 * (x * x + y * y)  # cθ cφ
        c2 = r21 * r21 + r22 * r22
        c = np.sqrt(c2)
        with np.errstate(divide="ignore", invalid="ignore"):
            J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = 1.0, -r20 * r21 / c2, -r20 * r22 / c2
            J[:, 1, 1], J[:, 1, 2] = r22 / c, -r21 / c
            J[:, 2, 1], J[:, 2, 2] = r21 / c2, r22 / c2
    else:
        raise ValueError(f"error must be 'left' or 'right', not {error!r}")
    variance = np.zeros((n, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                variance[:, i] += J[:, i, j] * J[:, i, k] * P[:, j, k]
    sigma = np.sqrt(np.maximum(variance, 0.0))
    sigma[~(c > _GIMBAL_LOCK_COS)] = math.inf  # (NaN q too)
    return sigma
