"""Simulated physics: motors, drive loops, reducer bench. Deterministic for a seed.

``BenchWorld`` steps one sample at a time (emulated drives); ``simulate_motor`` and
``simulate_bench`` run whole command arrays into a ``Trace`` with the same kernel and
noise stream; ``efficiency_truth`` is what eq. 18 and P_out/P_in should give.
"""
from . import waveforms
from .batch import simulate_bench, simulate_motor
from .params import CvtParams, MotorParams, PlantParams
from .truth import bench_operating_point, efficiency_truth
from .world import AxisMeasurement, BenchWorld

__all__ = ["AxisMeasurement", "BenchWorld", "CvtParams", "MotorParams", "PlantParams",
           "bench_operating_point", "efficiency_truth", "simulate_bench", "simulate_motor",
           "waveforms"]
