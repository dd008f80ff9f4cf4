"""Benchmark systems and a generic batched simulator."""

from torchfilt.systems import pendulum, reaction, reentry
from torchfilt.systems.registry import SYSTEMS, SystemSpec, get_system
from torchfilt.systems.simulate import Simulation, simulate

__all__ = [
    "SYSTEMS",
    "Simulation",
    "SystemSpec",
    "get_system",
    "pendulum",
    "reaction",
    "reentry",
    "simulate",
]
