"""Scoring attitude estimates against ground truth, and running peer filters beside ours.

``metrics`` reimplements the BROAD dataset's own scoring (total / heading / inclination
RMSE over the movement phases). ``peers`` runs VQF, x-io Fusion and the ``ahrs``
package's Madgwick and Mahony filters on mavest's conventions (FRD body, NED world), so
that every number in a comparison comes from the same data and the same scoring.
"""

from __future__ import annotations

from mavest.evaluation.metrics import (
    AttitudeErrors,
    attitude_errors,
    heading_offset,
    remove_heading_offset,
    rmse_deg,
)

__all__ = [
    "AttitudeErrors",
    "attitude_errors",
    "heading_offset",
    "remove_heading_offset",
    "rmse_deg",
]
