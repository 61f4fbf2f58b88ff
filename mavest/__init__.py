"""mavest: live attitude estimation for MAVLink vehicles.

An error-state Kalman filter on SO(3) × R³ (attitude and gyro bias). The
public entry points are :func:`estimate` (a whole recording),
:class:`Estimator` (one sample at a time) and :func:`smooth` (a whole
recording, each sample given all of it).

They are loaded on first use (PEP 562): the filter brings numba with it, which
takes seconds to import, and the ``mavest`` command must answer Ctrl-C (or
``--help``) meanwhile.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mavest.estimator import (
        ConfigError,
        Estimate,
        EstimateSeries,
        Estimator,
        EstimatorConfig,
        StepFlags,
        estimate,
        smooth,
    )

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "Estimate",
    "EstimateSeries",
    "Estimator",
    "EstimatorConfig",
    "StepFlags",
    "__version__",
    "estimate",
    "smooth",
]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("mavest.estimator"), name)
    raise AttributeError(f"module 'mavest' has no attribute {name!r}")
