"""The magnetometer as a measurement of heading only.

The field seen in the body, m (calibrated), turned into the estimated world
frame, u = R̄ m, should point along the reference field: magnetic north turned
east by the declination d, dipping below the horizon by the dip angle. Its
horizontal azimuth

    y = atan2(u_y, u_x)

is the measurement, and the model is y = d − ψ + (tilt terms) + noise for the
error R = Rz(ψ) Exp(τ) R̄ (or, to first order, Exp(δθ) R̄, δθ = (τx, τy, ψ)):
turning the estimate by ψ about the vertical turns the field's azimuth by −ψ.
With u ≈ Exp(−δθ) m_ref = m_ref + [m_ref]× δθ and ∂y/∂u = (−sin d, cos d, 0)/m_h
at the reference (m_h the horizontal field), the Jacobian in the world frame is

    H_world = (tan(dip) cos d, tan(dip) sin d, −1),

the tilt entries being how a tilt error leaks into the azimuth through the
field's vertical part (the dip). For the right error (δθ in the body frame,
δθ_world = R̄ δθ) H = H_world R̄.

Only heading is corrected: the filter's gain rows for the two horizontal
world axes are zeroed (they are *considered*, Schmidt), so a disturbed field
can never tilt the estimate. The gain itself comes from the heading term of H
alone, with the tilt leak H_τ τ counted as independent noise in the
innovation's variance. The full H's gain (the Schmidt-optimal one) was
measured first: on BROAD's fast rotations (600 °/s, magnetometer azimuth
errors of 17° RMS against the truth) the tilt–heading correlation it leans on,
amplified by tan(dip) ≈ 2.6, pulled heading 20° off, against 1.7° for this
gain. The price: the leak is a slowly varying error, not white, and treating
it as white leaves the heading variance optimistic while a large heading
error converges (tools/consistency.py: ``small_9d`` in band, ``large_heading_9d``
not); the Joseph form with the full H and this gain is honest but diverges on
BROAD. This is the magnetometer half of
VQF's idea (Laidig & Seel 2023: heading corrected in the 6-D earth frame),
made a Kalman update.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import kernel
from mavest.estimator.layout import ERROR_LEFT

# Below this ratio of horizontal to total field the azimuth says nothing (at a
# magnetic pole, or with a sensor that reads along gravity only).
MIN_HORIZONTAL_FRACTION = 0.05


@kernel
def wrap(angle: float) -> float:
    """angle wrapped to [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@kernel
def calibrate_into(
    raw: np.ndarray, offsets: np.ndarray, soft_iron: np.ndarray, out: np.ndarray
) -> None:
    """ArduPilot's correction: m = A (raw + offsets), A the soft-iron matrix from DIA/ODI.

    (AP_Compass_Backend::correct_field: COMPASS_OFS is *added*, then the
    symmetric matrix [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]
    is applied.)
    """
    x = raw[0] + offsets[0]
    y = raw[1] + offsets[1]
    z = raw[2] + offsets[2]
    for i in range(3):
        out[i] = soft_iron[i, 0] * x + soft_iron[i, 1] * y + soft_iron[i, 2] * z


@kernel
def field_geometry(q: np.ndarray, m: np.ndarray, u: np.ndarray) -> tuple[float, float, float]:
    """(azimuth, dip, norm) of the body field m seen in the estimated world frame.

    u receives R̄ m. The azimuth is NaN when the field is (nearly) vertical.
    Dip is positive below the horizon (NED z down), as on the northern hemisphere.
    """
    so3.quat_rotate_into(q, m, u)
    horizontal = math.hypot(u[0], u[1])
    norm = math.sqrt(horizontal * horizontal + u[2] * u[2])
    dip = math.atan2(u[2], horizontal)
    if not horizontal > MIN_HORIZONTAL_FRACTION * norm:
        return math.nan, dip, norm
    return math.atan2(u[1], u[0]), dip, norm


@kernel
def heading_jacobian_into(
    q: np.ndarray, dip: float, declination: float, error: int, R: np.ndarray, H: np.ndarray
) -> None:
    """H (3) of the azimuth with respect to the attitude error; R (3×3) is scratch.

    Evaluated at the reference field with the measured dip: the linearisation
    point the filter believes in (azimuth = declination).
    """
    slope = math.tan(dip)
    h0 = slope * math.cos(declination)
    h1 = slope * math.sin(declination)
    h2 = -1.0
    if error == ERROR_LEFT:
        H[0], H[1], H[2] = h0, h1, h2
        return
    so3.matrix_from_quat_into(q, R)
    for j in range(3):  # H_world R̄
        H[j] = h0 * R[0, j] + h1 * R[1, j] + h2 * R[2, j]
