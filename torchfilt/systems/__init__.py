"""Benchmark systems and a generic batched simulator."""

from torchfilt.systems import pendulum, reaction, reentry
from torchfilt.systems.simulate import Simulation, simulate

__all__ = ["Simulation", "pendulum", "reaction", "reentry", "simulate"]
