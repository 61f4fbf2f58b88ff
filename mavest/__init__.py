"""mavest: live attitude estimation for MAVLink vehicles.

An error-state Kalman filter on SO(3) × R³ (attitude and gyro bias). The
public entry points are :func:`estimate` (a whole recording) and
:class:`Estimator` (one sample at a time).
"""

from mavest.estimator import (
    ConfigError,
    Estimate,
    EstimateSeries,
    Estimator,
    EstimatorConfig,
    StepFlags,
    estimate,
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
]
