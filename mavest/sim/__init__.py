"""Simulated vehicles: IMU samples with a known truth."""

from mavest.sim.kinematic import ImuNoise, Motion, SimulatedImu, simulate

__all__ = ["ImuNoise", "Motion", "SimulatedImu", "simulate"]
