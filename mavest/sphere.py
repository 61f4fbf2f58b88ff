"""The unit sphere S²: where a direction measurement (gravity, later the magnetic field) lives.

A direction has two degrees of freedom, so its residual is a 2-vector in the
tangent plane, not a 3-D difference of unit vectors (docs/design.md#gravity-update).

The residual of a predicted direction h against a measured direction z is the
rotation vector ρ that turns h onto z along the great circle,

    ρ = θ (h × z)/‖h × z‖,   θ = atan2(‖h × z‖, h·z),

expressed in an orthonormal basis B_z of the plane ⊥ z: r = B_zᵀ ρ. (Not θ = u·v,
a common slip: the angle is the arc-cosine of the dot product, and atan2 of the
sine and cosine keeps it accurate at 0 and π.) Because ρ ⊥ z, the basis tied to
the measurement is constant while the state moves, so r is a smooth function of
the state whose Jacobian is exact: what the iterated filter needs to reach the
true minimiser of its cost.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inlined_kernel, kernel

# Below this ‖h × z‖ the closed forms' divisions are replaced by their limits.
_SMALL_SINE = 1e-3


@inlined_kernel
def _first_tangent(v: np.ndarray) -> tuple[float, float, float]:
    """b1 = e × v / ‖e × v‖ for the coordinate axis e least aligned with the unit vector
    v, so the construction never divides by a small number."""
    ax, ay, az = abs(v[0]), abs(v[1]), abs(v[2])
    if ax <= ay and ax <= az:  # e = x
        b1x, b1y, b1z = 0.0, -v[2], v[1]
    elif ay <= az:  # e = y
        b1x, b1y, b1z = v[2], 0.0, -v[0]
    else:  # e = z
        b1x, b1y, b1z = -v[1], v[0], 0.0
    n = math.sqrt(b1x * b1x + b1y * b1y + b1z * b1z)
    return b1x / n, b1y / n, b1z / n


@kernel
def tangent_basis_into(v: np.ndarray, out: np.ndarray) -> None:
    """Columns of ``out`` (3×2): an orthonormal basis of the plane ⊥ the unit vector v.

    (b1, b2, v) is right-handed, b1 from :func:`_first_tangent`.
    """
    b1x, b1y, b1z = _first_tangent(v)
    out[0, 0], out[1, 0], out[2, 0] = b1x, b1y, b1z
    # b2 = v × b1 is unit and completes the right-handed triad
    out[0, 1] = v[1] * b1z - v[2] * b1y
    out[1, 1] = v[2] * b1x - v[0] * b1z
    out[2, 1] = v[0] * b1y - v[1] * b1x


@kernel
def tangent_basis(v: np.ndarray) -> np.ndarray:
    out = np.empty((3, 2))
    tangent_basis_into(v, out)
    return out


# Below this a norm's squares lose precision to denormals (2⁻⁵¹¹ ≈ 1.5e-154).
_TINY_NORM = 1e-150


@kernel
def log_into(h: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """ρ with Exp(ρ) h = z along the shortest arc, ‖ρ‖ = θ ∈ [0, π], ρ ⊥ h, z.

    For antipodal h = −z every axis ⊥ h is a shortest arc; one is chosen.
    """
    wx = h[1] * z[2] - h[2] * z[1]
    wy = h[2] * z[0] - h[0] * z[2]
    wz = h[0] * z[1] - h[1] * z[0]
    s = math.sqrt(wx * wx + wy * wy + wz * wz)
    c = h[0] * z[0] + h[1] * z[1] + h[2] * z[2]
    if s >= _TINY_NORM:
        k = math.atan2(s, c) / s
        out[0], out[1], out[2] = k * wx, k * wy, k * wz
        return
    # Near h = ±z the cross product can be so small (1e-162) that its squares are
    # denormal and the direction w/s is lost. It can be denormal itself (1e-313),
    # and then θ/s overflows: the direction comes first, from w scaled by its largest
    # component, which is exact even where the components are a few denormal steps
    # (a norm of them rounds: hypot(5e-324, 5e-324) is 5e-324, not 7e-324).
    m = max(abs(wx), abs(wy), abs(wz))
    if m > 0.0:
        ux, uy, uz = wx / m, wy / m, wz / m
        n = math.sqrt(ux * ux + uy * uy + uz * uz)
        theta = math.atan2(m * n, c)
        out[0], out[1], out[2] = theta * (ux / n), theta * (uy / n), theta * (uz / n)
    elif c > 0.0:
        out[0], out[1], out[2] = 0.0, 0.0, 0.0
    else:
        b1x, b1y, b1z = _first_tangent(h)
        out[0], out[1], out[2] = math.pi * b1x, math.pi * b1y, math.pi * b1z


@kernel
def log(h: np.ndarray, z: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    log_into(h, z, out)
    return out


@kernel
def log_jacobian_into(h: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """∂ρ/∂h (3×3) of ρ = log(h, z), for perturbations of h tangent to the sphere.

    With w = h × z, s = ‖w‖, c = h·z, θ = atan2(s, c) and g = θ/s:
    dρ = g dw + w dg, dw = −[z]× dh, dg = (cs − θ)/s³ · wᵀdw − zᵀdh (using s² + c² = 1), so

        ∂ρ/∂h = −g [z]× − ((cs − θ)/s³) w wᵀ [z]× − w zᵀ.

    Near s = 0 (h ≈ z), g → 1 and (cs − θ)/s³ → −2/3 − s²/5. Not defined at h = −z.
    """
    wx = h[1] * z[2] - h[2] * z[1]
    wy = h[2] * z[0] - h[0] * z[2]
    wz = h[0] * z[1] - h[1] * z[0]
    s2 = wx * wx + wy * wy + wz * wz
    s = math.sqrt(s2)
    c = h[0] * z[0] + h[1] * z[1] + h[2] * z[2]
    theta = math.atan2(s, c)
    g = theta / s if s > 0.0 else 1.0
    # m = (cs − θ)/s³ cancels catastrophically for small s; its series instead
    m = -2.0 / 3.0 - s2 / 5.0 if (s < _SMALL_SINE and c > 0.0) else (c * s - theta) / (s2 * s)
    # the row vector wᵀ[z]× is uᵀ with u = [z]×ᵀ w = −z × w = w × z
    zx, zy, zz = z[0], z[1], z[2]
    ux = wy * zz - wz * zy
    uy = wz * zx - wx * zz
    uz = wx * zy - wy * zx
    w = (wx, wy, wz)
    u = (ux, uy, uz)
    zv = (zx, zy, zz)
    # −g[z]×
    out[0, 0] = 0.0
    out[0, 1] = g * zz
    out[0, 2] = -g * zy
    out[1, 0] = -g * zz
    out[1, 1] = 0.0
    out[1, 2] = g * zx
    out[2, 0] = g * zy
    out[2, 1] = -g * zx
    out[2, 2] = 0.0
    for i in range(3):
        for j in range(3):
            out[i, j] += -m * w[i] * u[j] - w[i] * zv[j]


@kernel
def log_jacobian(h: np.ndarray, z: np.ndarray) -> np.ndarray:
    out = np.empty((3, 3))
    log_jacobian_into(h, z, out)
    return out


@kernel
def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R u = v, for unit vectors u, v.

    The closed form I + [u×v]× + ((1 − u·v)/‖u×v‖²)[u×v]×², whose angle has
    cos θ = u·v (not θ = u·v), is Exp of the S² logarithm.
    """
    return so3.exp(log(u, v))
