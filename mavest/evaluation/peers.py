"""Peer attitude filters, run on mavest's conventions, for like-for-like comparisons.

Every adapter has the signature ``run_<peer>(t, gyro, accel, mag=None, rate=None)``:

* inputs in mavest conventions: ``t`` (N,) s, ``gyro`` (N, 3) rad/s, ``accel`` (N, 3)
  m/s² specific force (about (0, 0, −g) at rest), ``mag`` (N, 3) any unit, all in the FRD
  body frame; ``rate`` in Hz (None: from the median step of ``t``);
* output (N, 4) quaternions (w, x, y, z), FRD body → NED world.

Without ``mag`` the peer runs its 6-D (gyro + accelerometer) mode, whose heading is
arbitrary: score it on inclination, or after
:func:`~mavest.evaluation.metrics.remove_heading_offset`.

Each adapter converts to the peer's own conventions internally. All four peers are
indifferent to how the body axes are named (they only need gyro, accelerometer and
magnetometer in the *same* body frame), so the FRD samples are passed as they are, in
the peer's units; what differs is the peer's world frame, and the peer's output is
mapped to NED by a constant left factor, q_NED = q(W → NED) ⊗ q_W:

* VQF (``vqf``, C++ core) and its offline variant (``vqf.offlineVQF``, acausal: each
  sample given the whole recording): world ENU (z up; in 9-D, y towards magnetic
  north); rad/s and m/s².
* x-io Fusion (``imufusion``): world NED, chosen with ``settings.convention``; °/s and g.
* ``ahrs`` Madgwick: world z up; in 9-D NWU (x towards magnetic north), taken as NWU in
  6-D too; rad/s and m/s² (normalised inside).
* ``ahrs`` Mahony: world z up; in 9-D ENU, taken as ENU in 6-D too; rad/s and m/s²
  (normalised inside).

The mappings were checked on all 22 local BROAD trials against the optical truth: 9-D
headings agree within a few degrees on undisturbed trials (a wrong frame gives tens of
degrees); VQF here gives the same scores (to 1e-5°) as VQF run on the raw z-up data and
scored in ENU as the dataset's example code does; Mahony reproduces the dataset authors'
published per-trial scores within 0.2°.

The peers are development extras, so each adapter imports its package inside itself.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mavest.estimator.config import STANDARD_GRAVITY
from mavest.evaluation.metrics import quat_multiply

__all__ = [
    "MADGWICK_BETA",
    "MAHONY_KI",
    "MAHONY_KP",
    "PEERS",
    "PeerAdapter",
    "run_fusion",
    "run_madgwick",
    "run_mahony",
    "run_offline_vqf",
    "run_vqf",
]

PeerAdapter = Callable[..., np.ndarray]

_SQRT_HALF = float(np.sqrt(0.5))
#: q(ENU → NED): 180° about (1, 1, 0)/√2; maps (x, y, z)_ENU to (y, x, −z).
_Q_NED_FROM_ENU = np.array([0.0, _SQRT_HALF, _SQRT_HALF, 0.0])
#: q(NWU → NED): 180° about x; maps (x, y, z)_NWU to (x, −y, −z).
_Q_NED_FROM_NWU = np.array([0.0, 1.0, 0.0, 0.0])

# Gains of the ahrs package's Madgwick and Mahony filters: the BROAD authors' best single
# setting over all 39 trials (the "TAGP", dlaidig/broad example_code/out/
# results_madgwick_average_rmse.json and results_mahony_average_rmse.json). Their C code
# (Madgwick's reference implementation) applies β and Kp, Ki to the same quantities as
# ahrs does: qDot −= β·∇f/‖∇f‖; ω += Kp·e + Ki·∫e dt with e = â × v̂ (the C code's
# "twoKp · halfe" is Kp · e). The grid search tuned the 9-D (MARG) filters; the same
# gains are used in 6-D mode, where the authors published none.
MADGWICK_BETA = 0.12
MAHONY_KP = 0.74
MAHONY_KI = 0.0012


# --------------------------------------------------------------------------
# Input handling shared by the adapters
# --------------------------------------------------------------------------


def _as_samples(name: str, x: np.ndarray, n: int | None = None) -> np.ndarray:
    """(N, 3) float64, C-contiguous, writeable (a copy: peers must never alter our data)."""
    arr = np.array(x, dtype=np.float64, order="C", copy=True)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} samples, expected {n}")
    return arr


def _prepare(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None,
    rate: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Validate shapes and find the rate (Hz): ``rate`` if given, else 1 / median step of t."""
    gyro = _as_samples("gyro", gyro)
    n = gyro.shape[0]
    accel = _as_samples("accel", accel, n)
    mag = None if mag is None else _as_samples("mag", mag, n)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"t has {t.shape[0]} samples, gyro has {n}")
    if rate is None:
        if n < 2:
            raise ValueError("rate is needed when fewer than two samples are given")
        step = float(np.median(np.diff(t)))
        if not step > 0.0:
            raise ValueError("t must increase")
        rate = 1.0 / step
    return t, gyro, accel, mag, float(rate)


def _initial_attitude_ned(accel: np.ndarray, mag: np.ndarray | None) -> np.ndarray:
    """q(FRD → NED) from one sample at rest: tilt from gravity, heading from mag (else 0).

    TRIAD: body "down" is −a/‖a‖; body "north" is the horizontal part of the field (or,
    without a field, of the body x axis, i.e. heading 0). The ahrs filters start from
    this, as the BROAD authors' example code does (``quatFromAccMag`` on the first
    sample), so that none of them starts in a frame other than its own.
    """
    from scipy.spatial.transform import Rotation

    down = -accel / np.linalg.norm(accel)
    ref = mag if mag is not None and np.linalg.norm(mag) > 0.0 else np.array([1.0, 0.0, 0.0])
    north = ref - np.dot(ref, down) * down
    if np.linalg.norm(north) < 1e-9:  # reference parallel to gravity: any heading will do
        north = np.array([0.0, 1.0, 0.0]) - down[1] * down
    north /= np.linalg.norm(north)
    east = np.cross(down, north)
    R_world_body = np.vstack([north, east, down])  # rows: world axes in body coordinates
    xyzw = Rotation.from_matrix(R_world_body).as_quat()
    return xyzw[[3, 0, 1, 2]]


# --------------------------------------------------------------------------
# Adapters
# --------------------------------------------------------------------------


def run_vqf(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None = None,
    rate: float | None = None,
) -> np.ndarray:
    """VQF (Laidig & Seel 2023; the ``vqf`` package's C++ core), default parameters.

    VQF estimates body → ENU-type world (z up; in 9-D, y towards magnetic north) from
    rad/s and m/s². One ``updateBatch`` call; ``quat6D`` without ``mag``, ``quat9D``
    with it. The sample time is 1/rate: VQF assumes uniform sampling.
    """
    from vqf import VQF

    _, gyro, accel, mag, rate = _prepare(t, gyro, accel, mag, rate)
    ts = 1.0 / rate
    if mag is None:
        out = VQF(ts).updateBatch(gyro, accel)
        q_enu = out["quat6D"]
    else:
        out = VQF(ts).updateBatch(gyro, accel, mag)
        q_enu = out["quat9D"]
    return quat_multiply(_Q_NED_FROM_ENU, q_enu)


def run_offline_vqf(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None = None,
    rate: float | None = None,
) -> np.ndarray:
    """Offline VQF (``vqf.offlineVQF``, Laidig & Seel 2023), default parameters: the
    acausal variant, which uses the samples after each one as well (the smoother's peer).

    The same world and units as :func:`run_vqf`; ``quat6D`` without ``mag``, ``quat9D``
    with it; the sample time is 1/rate (uniform sampling assumed).
    """
    from vqf import offlineVQF

    _, gyro, accel, mag, rate = _prepare(t, gyro, accel, mag, rate)
    out = offlineVQF(gyro, accel, mag, 1.0 / rate)
    q_enu = out["quat6D"] if mag is None else out["quat9D"]
    return quat_multiply(_Q_NED_FROM_ENU, q_enu)


def run_fusion(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None = None,
    rate: float | None = None,
) -> np.ndarray:
    """x-io Fusion (``imufusion``), its default settings apart from convention and rate.

    Fusion takes °/s and g. Its world convention is chosen by ``AhrsSettings.convention``;
    the ``AhrsSettings(convention=...)`` constructor argument is silently ignored (checked
    with imufusion 1.3.3), so the attribute is set after construction. With the NED
    convention Fusion's quaternion is already body → NED. The sample rate comes from the
    data; if the time stamps are not uniform the sample period is set before every update.
    Defaults kept: gain 0.5, no gyroscope range, acceleration and magnetic rejection off
    (imufusion ≥ 1.3 ships them off), which lets sustained linear acceleration tilt the
    estimate: tens of degrees on BROAD's fast-translation trials.
    """
    import imufusion

    t, gyro, accel, mag, rate = _prepare(t, gyro, accel, mag, rate)
    settings = imufusion.AhrsSettings()
    settings.convention = imufusion.CONVENTION_NED
    settings.sample_rate = rate
    if settings.convention != imufusion.CONVENTION_NED:  # guard against API changes
        raise RuntimeError("imufusion did not accept the NED convention")
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(settings)
    ahrs.set_sample_period(1.0 / rate)

    gyro_dps = np.degrees(gyro)
    accel_g = accel / STANDARD_GRAVITY
    steps = np.diff(t, prepend=t[0] - 1.0 / rate)
    uniform = bool(np.allclose(steps, 1.0 / rate, rtol=1e-6, atol=0.0))
    q = np.empty((gyro.shape[0], 4))
    for i in range(gyro.shape[0]):
        if not uniform:
            ahrs.set_sample_period(float(steps[i]))
        if mag is None:
            ahrs.update_no_magnetometer(gyro_dps[i], accel_g[i])
        else:
            ahrs.update(gyro_dps[i], accel_g[i], mag[i])
        q[i] = ahrs.get_quaternion()
    return q


def _run_ahrs_filter(
    kind: str,
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None,
    rate: float | None,
) -> np.ndarray:
    """Run ``ahrs.filters.Madgwick`` or ``Mahony`` in its own world frame and map to NED.

    Both filters compare the normalised accelerometer with R^T e_z, so their world z is
    up; in 9-D, Madgwick's field reference is (b_x, 0, b_z) (NWU) and Mahony's is
    (0, b_y, b_z) (ENU). In 6-D the heading is free; the z-up world is then taken as NWU
    for Madgwick and ENU for Mahony, merely to have one definite mapping. The initial
    attitude is the first sample's TRIAD (:func:`_initial_attitude_ned`), expressed in
    the filter's frame; the ahrs package would otherwise start Madgwick 9-D from an NED
    e-compass, a frame the filter does not use.
    """
    from ahrs.filters import Madgwick, Mahony

    _, gyro, accel, mag, rate = _prepare(t, gyro, accel, mag, rate)
    q_ned_from_world = _Q_NED_FROM_NWU if kind == "madgwick" else _Q_NED_FROM_ENU
    q0_ned = _initial_attitude_ned(accel[0], None if mag is None else mag[0])
    # q(body → W) = q(NED → W) ⊗ q(body → NED); both constants are 180° turns (self-inverse
    # up to sign), and conjugation makes that explicit.
    q0 = quat_multiply(q_ned_from_world * np.array([1.0, -1.0, -1.0, -1.0]), q0_ned)
    q0 /= np.linalg.norm(q0)
    if kind == "madgwick":
        estimator = Madgwick(
            gyr=gyro, acc=accel, mag=mag, frequency=rate, gain=MADGWICK_BETA, q0=q0
        )
    else:
        estimator = Mahony(
            gyr=gyro, acc=accel, mag=mag, frequency=rate, k_P=MAHONY_KP, k_I=MAHONY_KI, q0=q0
        )
    return quat_multiply(q_ned_from_world, np.asarray(estimator.Q, dtype=np.float64))


def run_madgwick(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None = None,
    rate: float | None = None,
) -> np.ndarray:
    """Madgwick's gradient-descent filter from the ``ahrs`` package, β = MADGWICK_BETA.

    β = 0.12 is the BROAD authors' best single setting (TAGP). The ``ahrs`` implementation
    is pure Python: expect several seconds per BROAD trial. It is not bit-for-bit the
    authors' float32 C code: on the 22 local trials its 9-D total RMSE averages 5.32°
    against their 4.96°, with single trials differing by up to 4.5°.
    """
    return _run_ahrs_filter("madgwick", t, gyro, accel, mag, rate)


def run_mahony(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None = None,
    rate: float | None = None,
) -> np.ndarray:
    """Mahony's explicit complementary filter from the ``ahrs`` package, Kp = 0.74, Ki = 0.0012.

    The gains are the BROAD authors' best single setting (TAGP). Pure Python, like Madgwick.
    """
    return _run_ahrs_filter("mahony", t, gyro, accel, mag, rate)


#: Display name → adapter, for evaluation tools.
PEERS: dict[str, PeerAdapter] = {
    "VQF": run_vqf,
    "offline VQF": run_offline_vqf,
    "Fusion": run_fusion,
    "Madgwick": run_madgwick,
    "Mahony": run_mahony,
}
