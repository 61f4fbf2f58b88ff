"""Simulated vehicles: IMU samples with a known truth.

``kinematic``: the filter's own process model (for consistency tests);
``flight``: a JSBSim aircraft under its autopilot; ``vehicle``: that aircraft
speaking MAVLink (streaming, or into a tlog).
"""

from mavest.sim.flight import (
    Flight,
    FlightModel,
    FlightPlan,
    ImuErrors,
    NoisyImu,
    apply_imu_errors,
    fly,
)
from mavest.sim.kinematic import ImuNoise, Motion, SimulatedImu, simulate

__all__ = [
    "Flight",
    "FlightModel",
    "FlightPlan",
    "ImuErrors",
    "ImuNoise",
    "Motion",
    "NoisyImu",
    "SimulatedImu",
    "apply_imu_errors",
    "fly",
    "simulate",
]
