"""Where recorded data sets live, and a clear error when they are absent.

The recordings (BROAD, MAVLink logs) are third-party files that are never copied into
the repository. By default they sit beside the project in ``../shared/data``; the
environment variable ``MAVEST_DATA`` points somewhere else. Code that needs them asks
``data_root()`` (optional use, e.g. tests that skip) or ``require_data()`` (a tool that
cannot run without them).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DATA_ENV_VAR", "data_root", "require_data"]

#: Environment variable that overrides the data location.
DATA_ENV_VAR = "MAVEST_DATA"

# mavest/datasets/__init__.py → parents[0] = datasets, [1] = mavest, [2] = project root.
_PROJECT_ROOT = Path(__file__).resolve().parents[2]


def data_root() -> Path | None:
    """The folder holding the shared data sets, or None when it does not exist.

    ``$MAVEST_DATA`` if set (and non-empty), else ``<project root>/../shared/data``,
    where the project root is the folder that contains the ``mavest`` package.
    """
    override = os.environ.get(DATA_ENV_VAR, "").strip()
    root = Path(override).expanduser() if override else _PROJECT_ROOT.parent / "shared" / "data"
    return root.resolve() if root.is_dir() else None


def require_data(subdir: str) -> Path:
    """The folder ``<data root>/<subdir>``; FileNotFoundError naming MAVEST_DATA if missing."""
    root = data_root()
    if root is None:
        override = os.environ.get(DATA_ENV_VAR, "").strip()
        where = (
            f"{DATA_ENV_VAR}={override!r} is not a folder"
            if override
            else f"{DATA_ENV_VAR} is not set and {_PROJECT_ROOT.parent / 'shared' / 'data'} "
            "does not exist"
        )
        raise FileNotFoundError(
            f"data set folder {subdir!r} not found: {where}. "
            f"Set {DATA_ENV_VAR} to the folder that contains {subdir}/."
        )
    path = root / subdir
    if not path.is_dir():
        raise FileNotFoundError(
            f"data set folder {path} does not exist. "
            f"Set {DATA_ENV_VAR} to the folder that contains {subdir}/."
        )
    return path
