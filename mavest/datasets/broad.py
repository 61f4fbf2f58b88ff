"""Loader for BROAD, the Berlin Robust Orientation Estimation Assessment Dataset.

BROAD (Laidig, Caruso, Cereatti, Seel, *Data* 6(7):72, 2021; CC BY 4.0) holds IMU
recordings at 285.714 Hz with optical (motion-capture) ground truth. Each trial is an
HDF5 file with

=============  ======  ================================================================
key            shape   meaning
=============  ======  ================================================================
imu_gyr        N×3     rad/s, IMU frame
imu_acc        N×3     m/s², specific force, IMU frame (+9.81 on z at rest: z points up)
imu_mag        N×3     µT, IMU frame
opt_quat       N×4     (w, x, y, z), IMU → ENU world; NaN where tracking was lost
movement       N       bool, the samples the dataset's scoring uses
=============  ======  ================================================================

and ``attrs['sampling_rate']`` in Hz.

mavest works in FRD body / NED world (docs/design.md#conventions), so the loader converts
explicitly, once, here:

* Body: the BROAD IMU frame has z up. Our FRD body frame is the IMU frame turned 180°
  about its x axis: ``v_frd = (x, −y, −z)``, i.e. ``v_imu = C_IMU_FRD v_frd`` with
  ``C_IMU_FRD = diag(1, −1, −1)``. Gyro, accelerometer and magnetometer all transform
  this way (at rest the accelerometer then reads about (0, 0, −g), as mavest expects).
* World: ``v_ned = (y, x, −z)`` of the ENU vector, ``C_NED_ENU`` below.
* Truth: ``R(FRD → NED) = C_NED_ENU · R_opt(IMU → ENU) · C_IMU_FRD``, in quaternions
  ``q_truth = q(ENU→NED) ⊗ q_opt ⊗ q(FRD→IMU)``. Rows where ``opt_quat`` is NaN stay NaN.

h5py is a development extra, so it is imported inside :func:`load_trial`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mavest.datasets import require_data

__all__ = [
    "BROAD_RATE_HZ",
    "C_IMU_FRD",
    "C_NED_ENU",
    "BroadTrial",
    "broad_dir",
    "list_trials",
    "load_trial",
    "truth_from_opt_quat",
]

#: Nominal BROAD sampling rate (Hz); each file also stores its own.
BROAD_RATE_HZ = 2000.0 / 7.0

#: FRD body vector → BROAD IMU (z-up) vector: a 180° turn about x. Its own inverse.
C_IMU_FRD = np.diag([1.0, -1.0, -1.0])

#: ENU world vector → NED world vector: swap x/y, negate z (180° about (1, 1, 0)/√2).
C_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


#: The BROAD trials mavest's defaults (and its tools' choices) were chosen on: figures on
#: these are in-sample. Any other trial (the dataset has 39) is one they never saw.
TUNED_ON = frozenset(
    {
        "02_undisturbed_slow_rotation_B",
        "03_undisturbed_slow_rotation_C",
        "05_undisturbed_slow_rotation_with_breaks_B",
        "07_undisturbed_fast_rotation_B",
        "09_undisturbed_fast_rotation_with_breaks_B",
        "10_undisturbed_slow_translation_A",
        "11_undisturbed_slow_translation_B",
        "12_undisturbed_slow_translation_C",
        "14_undisturbed_slow_translation_with_breaks_B",
        "15_undisturbed_fast_translation_A",
        "16_undisturbed_fast_translation_B",
        "18_undisturbed_fast_translation_with_breaks_B",
        "24_disturbed_tapping_A",
        "25_disturbed_tapping_B",
        "27_disturbed_phone_vibration_B",
        "30_disturbed_stationary_magnet_C",
        "31_disturbed_stationary_magnet_D",
        "32_disturbed_attached_magnet_1cm",
        "33_disturbed_attached_magnet_2cm",
        "34_disturbed_attached_magnet_3cm",
        "35_disturbed_attached_magnet_4cm",
        "36_disturbed_attached_magnet_5cm",
    }
)


def tuned_on(name: str) -> bool:
    """Whether mavest's defaults were chosen on the BROAD trial of this name
    (:data:`TUNED_ON`): its figures are then in-sample."""
    return name in TUNED_ON


@dataclass(frozen=True)
class BroadTrial:
    """One BROAD trial in mavest conventions (FRD body, NED world, SI, float64).

    Attributes:
        name: trial name, e.g. ``"07_undisturbed_fast_rotation_B"``.
        rate: sampling rate in Hz.
        t: (N,) sample times in seconds, starting at 0.
        gyro: (N, 3) angular rate in rad/s, FRD.
        accel: (N, 3) specific force in m/s², FRD; about (0, 0, −9.81) at rest, level.
        mag: (N, 3) magnetic field in µT, FRD.
        truth_q: (N, 4) optical ground truth (w, x, y, z), FRD body → NED world; rows
            where the motion capture lost track are NaN.
        movement: (N,) bool, the samples the dataset's scoring uses.
    """

    name: str
    rate: float
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    mag: np.ndarray
    truth_q: np.ndarray
    movement: np.ndarray

    @property
    def duration(self) -> float:
        """Length of the recording in seconds."""
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    def __len__(self) -> int:
        return len(self.t)


def broad_dir(root: Path | str | None = None) -> Path:
    """The folder with the BROAD ``.hdf5`` files.

    ``root`` may be that folder itself or a data root containing ``broad/``; None means
    ``<data root>/broad`` (see :func:`mavest.datasets.data_root`).
    """
    if root is None:
        return require_data("broad")
    root = Path(root)
    if (root / "broad").is_dir():
        return root / "broad"
    if not root.is_dir():
        raise FileNotFoundError(f"BROAD folder {root} does not exist")
    return root


def list_trials(root: Path | None = None, prefixes: Sequence[str] | None = None) -> list[Path]:
    """All BROAD trial files (``*.hdf5``), sorted by name (trial number first); with
    ``prefixes``, those whose names start with one of them."""
    paths = sorted(broad_dir(root).glob("*.hdf5"))
    if prefixes:
        paths = [p for p in paths if any(p.stem.startswith(x) for x in prefixes)]
    return paths


def halves(trials: Sequence[object]) -> tuple[list[int], list[int]]:
    """The trials (sorted, as :func:`list_trials` gives them) split in two halves to
    choose parameters on one and report on the other: alternate trials, A (1st, 3rd, …)
    and B (2nd, 4th, …), so that each half holds every kind of motion and disturbance."""
    return list(range(0, len(trials), 2)), list(range(1, len(trials), 2))


def _resolve_trial(path_or_name: Path | str) -> Path:
    """A trial file from a path, a full trial name, or a unique name prefix (``"07"``)."""
    path = Path(path_or_name)
    if path.suffix == ".hdf5" and path.is_file():
        return path
    name = path.name.removesuffix(".hdf5")
    candidates = list_trials(path.parent if path.parent != Path() else None)
    exact = [p for p in candidates if p.stem == name]
    if exact:
        return exact[0]
    matches = [p for p in candidates if p.stem.startswith(name)]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        raise FileNotFoundError(f"no BROAD trial named {name!r}")
    names = ", ".join(p.stem for p in matches)
    raise ValueError(f"BROAD trial name {name!r} is ambiguous: {names}")


def truth_from_opt_quat(opt_quat: np.ndarray) -> np.ndarray:
    """BROAD ``opt_quat`` (w, x, y, z; IMU → ENU) to (w, x, y, z) FRD → NED; NaN rows kept.

    Computes ``R = C_NED_ENU · R_opt · C_IMU_FRD``. scipy's x, y, z, w order is used only
    inside this function.
    """
    opt_quat = np.asarray(opt_quat, dtype=np.float64)
    out = np.full(opt_quat.shape, np.nan)
    valid = np.all(np.isfinite(opt_quat), axis=1) & (np.linalg.norm(opt_quat, axis=1) > 0.0)
    if np.any(valid):
        r_opt = Rotation.from_quat(opt_quat[valid][:, [1, 2, 3, 0]])  # wxyz → xyzw
        r = Rotation.from_matrix(C_NED_ENU) * r_opt * Rotation.from_matrix(C_IMU_FRD)
        out[valid] = r.as_quat(canonical=True)[:, [3, 0, 1, 2]]  # xyzw → wxyz, w ≥ 0
    return out


def load_trial(path_or_name: Path | str) -> BroadTrial:
    """Load one BROAD trial and convert it to FRD/NED (see the module docstring).

    ``path_or_name`` is a path to a ``.hdf5`` file, a trial name such as
    ``"07_undisturbed_fast_rotation_B"``, or a unique prefix such as ``"07"`` (looked up
    in ``<data root>/broad``).
    """
    import h5py  # development extra: only the loader needs it

    path = _resolve_trial(path_or_name)
    with h5py.File(path, "r") as f:
        rate = float(f.attrs["sampling_rate"])
        gyr = np.asarray(f["imu_gyr"][()], dtype=np.float64)
        acc = np.asarray(f["imu_acc"][()], dtype=np.float64)
        mag = np.asarray(f["imu_mag"][()], dtype=np.float64)
        opt_quat = np.asarray(f["opt_quat"][()], dtype=np.float64)
        movement = np.asarray(f["movement"][()]).astype(bool).reshape(-1)

    n = gyr.shape[0]
    for key, arr in (("imu_acc", acc), ("imu_mag", mag), ("opt_quat", opt_quat)):
        if arr.shape[0] != n:
            raise ValueError(f"{path.name}: {key} has {arr.shape[0]} rows, imu_gyr has {n}")

    # v_frd = C_IMU_FRD^T v_imu = C_IMU_FRD v_imu (the matrix is its own inverse).
    # Row vectors: v_frd^T = v_imu^T C_IMU_FRD^T.
    def to_frd(v: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(v @ C_IMU_FRD.T)

    return BroadTrial(
        name=path.stem,
        rate=rate,
        t=np.arange(n, dtype=np.float64) / rate,
        gyro=to_frd(gyr),
        accel=to_frd(acc),
        mag=to_frd(mag),
        truth_q=truth_from_opt_quat(opt_quat),
        movement=movement,
    )
