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

Only heading is corrected: the gain's rows for the two horizontal world axes
are zeroed (they are *considered*, Schmidt), so a disturbed field can never
tilt the estimate, and of the bias only the component about the world
vertical (the one that turns heading) is moved; the horizontal bias is
gravity's to correct. The gain comes from the heading term of H alone, with
the tilt leak H_τ τ counted as noise in the innovation's variance; the leak
is a slowly varying error (tilt changes as fast as gravity corrects it), so
it is counted as white noise of the same low-frequency power, its variance ×
``mag_tilt_leak_time``/Δt (3 s, the accelerometer low-pass's time). The
covariance is the Joseph form for that gain with the *full* H — C = P Hᵀ,
S = H P Hᵀ + R — the true covariance of the estimate this gain makes, leak
and tilt–heading correlation included.

Two things make that H the right one. It is taken at the prediction, the
reference field (the learned dip), not at the sample's own dip: that one
carries the tilt error along the field (the dip seen moves by it) and the
noise, so a gain made from it counted less leak exactly when the tilt made
the leak large one way and more when it was the other, and heading followed
the tilt — a rectified error no linear covariance holds. And the noise the
filter claims is a random turn of the horizontal field (variance
σ² = density²/Δt per sample, 0.8 rad at 100 Hz with the default), which
turns the direction the tilt leaks along with it: on average the leak is
e^(−σ²/2) H_τ τ (the expected Jacobian over that noise) and the rest of
its variance, the fraction 1 − e^(−σ²), is white as the noise is. H_τ is
scaled by the first, R grows by the second.

In turn, once a magnetometer references heading, a gravity update without
a known acceleration leaves heading alone (its gain loses its component
about the vertical, the covariance again the Joseph form): the honest
tilt–heading correlation would otherwise let every tilt correction move
heading. Each update moves only
what it measures and both covariances stay exact for the gains used. (With
the acceleration known, gravity does see heading in turns and keeps its
gain; without a magnetometer the 6-D filter is unchanged.)

Measured (tools/consistency.py --quick --runs 20; BROAD 9-D mean total /
heading, docs/results.md): the heading-only gain with the leak as white noise per
sample and the covariance from H_ψ was accurate (2.000° / 1.869°) but
optimistic while a large heading error converged (``large_heading_9d``
ANEES 11.0, out of band); the Joseph form with the full H and that gain
diverged, in simulation as on BROAD (18°): the gain's horizontal-bias rows
fed the leak into the bias and gravity's gain moved heading along the
correlation. The full H's gain (Schmidt-optimal) leans on the tilt–heading
correlation × tan(dip) (2.6 on BROAD): with the honest covariance it is
far out of band in simulation (ANEES 79 in ``small_9d``) and BROAD 9-D goes
to 3.07° (its first trial, on BROAD's fast rotations with magnetometer
azimuth errors of 17° RMS against the truth, pulled heading 20° off).
Without the leak's inflation the honest covariance is in band but the gain,
now seeing heading's true variance, follows the leak (BROAD 4.7°); with it
(and gravity leaving heading alone) BROAD 9-D is 1.90° / 1.75°, both
scenarios in band (6.1 / 3.3, 6.9 / 3.7), and simulated heading RMSE 3.5° /
6.8° against the white-leak gain's 2.6° / 4.2°. At 100 runs that left
``large_heading_9d`` optimistic while heading converged (6.79 / 3.48,
heading's own NEES 2–3 over 2–10 s, its error correlated with the tilt
along the field twice as much as P said), which H at the measured dip did
and the same field averaged to 10 Hz did not; with H at the reference dip
and the noise's mean both scenarios are in band (seed 0: 5.93 / 2.86,
5.83 / 2.83; seed 100: 5.77 / 2.88, 5.49 / 2.84), heading RMSE 2.6° / 4.0°,
BROAD 9-D 1.897° / 1.750°. This is
the magnetometer half of VQF's idea (Laidig & Seel 2023: heading corrected
in the 6-D earth frame), made a Kalman update.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_kernel, kernel
from mavest.estimator.layout import ERROR_LEFT

# Below this ratio of horizontal to total field the azimuth says nothing (at a
# magnetic pole, or with a sensor that reads along gravity only).
MIN_HORIZONTAL_FRACTION = 0.05


@inplace_kernel
def wrap(angle: float) -> float:
    """angle wrapped to [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@inplace_kernel
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


@inplace_kernel
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


@inplace_kernel
def heading_jacobians_into(
    q: np.ndarray,
    dip: float,
    declination: float,
    error: int,
    R: np.ndarray,
    H: np.ndarray,
    H_heading: np.ndarray,
) -> None:
    """H (3) of the azimuth with respect to the attitude error at ``dip``, and into
    H_heading the same at zero dip (heading's term alone), sharing the
    declination's trig and R̄; R (3×3) is scratch.

    Evaluated at the reference field (azimuth = declination, and the dip
    given: mag_update passes the reference's), the linearisation point the
    filter believes in.
    """
    cos_d = math.cos(declination)
    sin_d = math.sin(declination)
    slope = math.tan(dip)
    h0 = slope * cos_d
    h1 = slope * sin_d
    f0 = 0.0 * cos_d  # tan(0) = 0 times the same trig, as H at zero dip is formed
    f1 = 0.0 * sin_d
    h2 = -1.0
    if error == ERROR_LEFT:
        H[0], H[1], H[2] = h0, h1, h2
        H_heading[0], H_heading[1], H_heading[2] = f0, f1, h2
        return
    so3.matrix_from_quat_into(q, R)
    for j in range(3):  # H_world R̄
        H[j] = h0 * R[0, j] + h1 * R[1, j] + h2 * R[2, j]
        H_heading[j] = f0 * R[0, j] + f1 * R[1, j] + h2 * R[2, j]


@kernel  # (it allocates the discarded term: not for the filter's own kernels)
def heading_jacobian_into(
    q: np.ndarray, dip: float, declination: float, error: int, R: np.ndarray, H: np.ndarray
) -> None:
    """H alone (:func:`heading_jacobians_into`, its heading term discarded)."""
    heading_jacobians_into(q, dip, declination, error, R, H, np.empty(3))
