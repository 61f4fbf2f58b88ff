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

and ``attrs['sampling_rate']`` in Hz. A file that is not such a trial (unreadable, a key
missing, shapes that disagree) raises :class:`BroadFileError`, whose message is one line
naming the file; :func:`load_trials` loads many, leaving such files out with one line each.

mavest works in FRD body / NED world (docs/design.md#conventions), so the loader converts
explicitly, once, here:

* Body: the BROAD IMU frame has z up. Our FRD body frame is the IMU frame turned 180°
  about its x axis: ``v_frd = (x, −y, −z)``, i.e. ``v_imu = C_IMU_FRD v_frd`` with
  ``C_IMU_FRD = diag(1, −1, −1)``. Gyro, accelerometer and magnetometer all transform
  this way (at rest the accelerometer then reads about (0, 0, −g), as mavest expects).
* World: ``v_ned = (y, x, −z)`` of the ENU vector, ``C_NED_ENU`` below.
* Truth: ``R(FRD → NED) = C_NED_ENU · R_opt(IMU → ENU) · C_IMU_FRD``, in quaternions
  ``q_truth = q(ENU→NED) ⊗ q_opt ⊗ q(FRD→IMU)``. Rows where ``opt_quat`` is NaN stay NaN.

Non-finite IMU samples (a NaN or inf in any axis of the gyroscope, accelerometer or
magnetometer) are filled, each sensor from its own finite samples: linearly interpolated
over time between the nearest finite neighbours, held at the ends. Every filter then runs
on the same samples (a NaN that one filter skips and another propagates would compare
the NaN handling, not the estimation), and the filled samples are left out of the
scoring (their ``movement`` cleared: no filter measured anything there). Interpolation,
not a zero or a hold, because it keeps the rate's and the field's continuity across a
one-sample dropout; across a longer gap no rule knows the motion, and what the filters
make of the bridged samples afterwards is scored, as it would be on a vehicle.

h5py is a development extra, so it is imported inside :func:`load_trial`.
"""

from __future__ import annotations

import hashlib
import itertools
import statistics
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from scipy.spatial.transform import Rotation

from mavest.datasets import require_data

_Key = TypeVar("_Key")

__all__ = [
    "BROAD_RATE_HZ",
    "C_IMU_FRD",
    "C_NED_ENU",
    "DELAYS",
    "TUNED_ON",
    "BroadFileError",
    "BroadTrial",
    "broad_dir",
    "halves",
    "halves_named",
    "list_trials",
    "load_trial",
    "load_trials",
    "lowest_mean",
    "trial_labels",
    "trials_to_split",
    "truth_from_opt_quat",
    "tuned_on",
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


#: The IMU delays (s) the tools choose ``imu_delay`` from on a half of the trials: every
#: 0.5 ms up to 5 ms, a sample and a half at BROAD's 286 Hz, beyond any IMU's own filter
#: delay at its usual bandwidths.
DELAYS: tuple[float, ...] = tuple(round(k * 5e-4, 4) for k in range(11))


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
        movement: (N,) bool, the samples the dataset's scoring uses, less the filled
            ones (``filled``).
        filled: how many samples had a non-finite IMU value (any sensor, any axis) and
            were filled by interpolation (module docstring); 0 for a clean recording,
            which loads exactly as stored.
    """

    name: str
    rate: float
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    mag: np.ndarray
    truth_q: np.ndarray
    movement: np.ndarray
    filled: int = 0

    @property
    def scored(self) -> np.ndarray:
        """(N,) bool: the samples a score counts, ``movement`` where the truth is known
        (:func:`mavest.evaluation.metrics.scored_rows`, the scoring's own rule)."""
        from mavest.evaluation.metrics import scored_rows  # (scipy.optimize: when asked)

        return scored_rows(self.truth_q, self.movement)

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


class BroadFileError(ValueError):
    """A file that cannot be read as a BROAD trial; the message is one line that names
    the file and what is wrong with it."""


def _is_trial_file(path: Path) -> bool:
    return path.suffix.lower() == ".hdf5"


def list_trials(root: Path | None = None, prefixes: Sequence[str] | None = None) -> list[Path]:
    """All BROAD trial files (``*.hdf5``, any case), sorted by name (trial number
    first; a name before its longer variants); with ``prefixes``, those whose names
    start with one of them."""
    paths = sorted(
        (p for p in broad_dir(root).iterdir() if _is_trial_file(p)), key=lambda p: (p.stem, p.name)
    )
    if prefixes:
        paths = [p for p in paths if any(p.stem.startswith(x) for x in prefixes)]
    return paths


def halves(trials: Sequence[object]) -> tuple[list[int], list[int]]:
    """The trials (sorted, as :func:`list_trials` gives them) split in two halves to
    choose parameters on one and report on the other: alternate trials, A (1st, 3rd, …)
    and B (2nd, 4th, …), so that each half holds every kind of motion and disturbance."""
    return list(range(0, len(trials), 2)), list(range(1, len(trials), 2))


def lowest_mean(table: Mapping[_Key, Sequence[float]], subset: Sequence[int]) -> _Key:
    """The choice of ``table`` (per choice, a score per trial; lower is better) with the
    lowest mean over the trials of ``subset`` (ties: the first): how a parameter is
    chosen on one of :func:`halves`."""
    return min(table, key=lambda k: statistics.fmean(table[k][i] for i in subset))


def trial_labels(names: Sequence[str]) -> list[str]:
    """Short labels for these trials in a list: their two-digit numbers (``"07"``) when
    every name starts with its own, else the names themselves."""
    numbers = [name[:2] for name in names]
    numbered = all(n.isdigit() and len(n) == 2 for n in numbers)
    return numbers if numbered and len(set(numbers)) == len(numbers) else list(names)


def halves_named(names: Sequence[str], a: Sequence[int], b: Sequence[int]) -> str:
    """The two halves of these trials (:func:`halves`' indices) as a tool's tables name
    them, ``"A = 02, 05, …; B = 03, 07, …"`` (:func:`trial_labels`)."""
    labels = trial_labels(names)
    return f"A = {', '.join(labels[i] for i in a)}; B = {', '.join(labels[i] for i in b)}"


def _resolve_trial(path_or_name: Path | str) -> Path:
    """A trial file from a path, a full trial name, or a unique name prefix (``"07"``)."""
    path = Path(path_or_name)
    if _is_trial_file(path) and path.is_file():
        return path
    name = path.stem if _is_trial_file(path) else path.name
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


def _fill_non_finite(values: np.ndarray) -> np.ndarray:
    """A copy of the (N, k) ``values`` whose rows holding a non-finite value are linearly
    interpolated over the sample index (the times are uniform) from the finite rows,
    and held at the ends; at least one row must be finite."""
    bad = ~np.all(np.isfinite(values), axis=1)
    index = np.arange(values.shape[0])
    out = values.copy()
    for axis in range(values.shape[1]):
        out[bad, axis] = np.interp(index[bad], index[~bad], values[~bad, axis])
    return out


def load_trial(path_or_name: Path | str) -> BroadTrial:
    """Load one BROAD trial and convert it to FRD/NED (see the module docstring).

    ``path_or_name`` is a path to a ``.hdf5`` file, a trial name such as
    ``"07_undisturbed_fast_rotation_B"``, or a unique prefix such as ``"07"`` (looked up
    in ``<data root>/broad``). Raises :class:`BroadFileError` for a file that is not a
    readable trial, FileNotFoundError (or ValueError, ambiguous) for a name that names
    none.
    """
    import h5py  # development extra: only the loader needs it

    path = _resolve_trial(path_or_name)

    def bad(what: str) -> BroadFileError:
        return BroadFileError(f"{path}: {what}")

    if not path.is_file():  # a broken link, or a folder named like a trial
        raise bad("is not a readable file")
    widths = {"imu_gyr": 3, "imu_acc": 3, "imu_mag": 3, "opt_quat": 4, "movement": 1}
    arrays: dict[str, np.ndarray] = {}
    try:
        with h5py.File(path, "r") as f:
            if "sampling_rate" not in f.attrs:
                raise bad("not a BROAD trial: no 'sampling_rate' attribute")
            stored_rate = np.asarray(f.attrs["sampling_rate"])
            for key in widths:
                if not isinstance(f.get(key), h5py.Dataset):
                    raise bad(f"not a BROAD trial: no {key!r} dataset")
                arrays[key] = np.asarray(f[key][()])
    except BroadFileError:
        raise
    except (OSError, ValueError, TypeError, KeyError, IndexError) as error:
        # h5py's messages are one line ("Unable to synchronously open file (truncated
        # file: …)"); the first line of any other is enough to say what is wrong
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise bad(f"cannot be read as HDF5 ({reason})") from error

    rate = float(stored_rate) if stored_rate.size == 1 and stored_rate.dtype.kind in "iuf" else 0.0
    if not (np.isfinite(rate) and rate > 0.0):
        raise bad(f"sampling_rate {stored_rate!r} is not a rate in Hz")
    n = arrays["imu_gyr"].shape[0] if arrays["imu_gyr"].ndim else 0
    if n == 0:
        raise bad("imu_gyr holds no samples")
    for key, width in widths.items():
        arr = arrays[key]
        shape = (n,) if width == 1 else (n, width)
        if key == "movement":
            arr = arr.reshape(-1) if arr.size == n else arr
        if arr.shape != shape or arr.dtype.kind not in "biuf":
            raise bad(
                f"{key} is {arr.dtype} {arr.shape}, not numbers shaped {shape} "
                f"(imu_gyr has {n} samples)"
            )
        arrays[key] = arr.astype(np.float64) if width > 1 else arr.astype(bool)

    movement = arrays["movement"]
    imu = {}
    filled = np.zeros(n, dtype=bool)
    for key in ("imu_gyr", "imu_acc", "imu_mag"):
        arr = arrays[key]
        finite = np.all(np.isfinite(arr), axis=1)
        if not finite.any():
            raise bad(f"{key} has no finite sample")
        if not finite.all():
            arr = _fill_non_finite(arr)
            filled |= ~finite
        imu[key] = arr
    if filled.any():  # (a clean trial keeps its stored arrays as they are)
        movement = movement & ~filled

    # v_frd = C_IMU_FRD^T v_imu = C_IMU_FRD v_imu (the matrix is its own inverse).
    # Row vectors: v_frd^T = v_imu^T C_IMU_FRD^T.
    def to_frd(v: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(v @ C_IMU_FRD.T)

    return BroadTrial(
        name=path.stem,
        rate=rate,
        t=np.arange(n, dtype=np.float64) / rate,
        gyro=to_frd(imu["imu_gyr"]),
        accel=to_frd(imu["imu_acc"]),
        mag=to_frd(imu["imu_mag"]),
        truth_q=truth_from_opt_quat(arrays["opt_quat"]),
        movement=movement,
        filled=int(filled.sum()),
    )


def _print_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def load_trials(
    paths: Iterable[Path | str],
    say: Callable[[str], None] = _print_line,
    *,
    scored_only: bool = False,
) -> Iterator[BroadTrial]:
    """Load these trials in turn, saying in one line each (``say``; default: on stderr)
    what is left out and why, and going on:

    * a file that is not a readable trial (:class:`BroadFileError`'s line);
    * the same recording as one already loaded under another name (equal IMU arrays):
      the first name is kept, so that a copy cannot fall in both halves of a split;
    * with ``scored_only``, a trial with nothing to score (no movement sample with known
      truth, :attr:`BroadTrial.scored`).

    A trial with filled samples is loaded, with a line saying how many.
    """
    seen: dict[str, str] = {}
    for path in paths:
        try:
            trial = load_trial(path)
        except BroadFileError as error:
            say(f"{error}; left out")
            continue
        except FileNotFoundError as error:  # (gone since it was listed)
            say(f"{path}: {error}; left out")
            continue
        digest = hashlib.sha256()
        for values in (trial.gyro, trial.accel, trial.mag):
            digest.update(values.tobytes())
        key = digest.hexdigest()
        if key in seen:
            say(f"{trial.name}: the same recording as {seen[key]}; left out")
            continue
        seen[key] = trial.name
        if scored_only and not trial.scored.any():
            say(f"{trial.name}: nothing to score (no movement sample with known truth); left out")
            continue
        if trial.filled:
            say(
                f"{trial.name}: {trial.filled} sample(s) with a non-finite IMU value filled "
                "by interpolation and not scored"
            )
        yield trial


def trials_to_split(
    say: Callable[[str], None], limit: int | None = None
) -> list[BroadTrial] | None:
    """The trials of the data root's BROAD folder that a tool splits in halves to choose
    parameters on one and report on the other (the first ``limit`` usable ones, if
    given), loaded as :func:`load_trials` does; or None after one line (``say``) saying
    why there are not two: h5py absent, no BROAD folder, fewer than two to score."""
    import importlib

    try:
        importlib.import_module("h5py")
        paths = list_trials()
    except ImportError:
        say("the package h5py (dev extra) is needed to read BROAD")
        return None
    except FileNotFoundError as error:
        say(str(error))
        return None
    loaded = load_trials(paths, say, scored_only=True)
    trials = list(itertools.islice(loaded, limit) if limit is not None else loaded)
    if len(trials) < 2:
        say(
            f"needs two BROAD trials with something to score to split them, found "
            f"{len(trials)} in {broad_dir()}"
        )
        return None
    return trials
