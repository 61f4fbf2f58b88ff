"""The attitude filter: configuration, charts, the recursion, and the public API."""

from mavest.estimator.config import ConfigError, EstimatorConfig
from mavest.estimator.estimator import (
    Estimate,
    EstimateSeries,
    Estimator,
    InputError,
    estimate,
)
from mavest.estimator.layout import StepFlags
from mavest.estimator.online import AccelUnitWarning
from mavest.estimator.smoother import smooth

__all__ = [
    "AccelUnitWarning",
    "ConfigError",
    "Estimate",
    "EstimateSeries",
    "Estimator",
    "EstimatorConfig",
    "InputError",
    "StepFlags",
    "estimate",
    "smooth",
]
