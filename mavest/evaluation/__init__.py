"""Scoring attitude estimates against ground truth, and running peer filters beside ours.

``metrics`` reimplements the BROAD dataset's own scoring (total / heading / inclination
RMSE over the movement phases). ``peers`` runs VQF, x-io Fusion and the ``ahrs``
package's Madgwick and Mahony filters on mavest's conventions (FRD body, NED world), so
that every number in a comparison comes from the same data and the same scoring.
``accuracy`` scores them on BROAD; ``logs`` against an attitude logged at other times (an
autopilot's own, a simulator's truth).
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "AttitudeErrors",
    "attitude_errors",
    "heading_offset",
    "remove_heading_offset",
    "rmse_deg",
]


def __getattr__(name: str) -> Any:
    # the scoring pulls in scipy.optimize (a second to import); the service imports this
    # package for its online comparison only, so the scoring loads when first asked for
    if name in __all__:
        from mavest.evaluation import metrics

        return getattr(metrics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
