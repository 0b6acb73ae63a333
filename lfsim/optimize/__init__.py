"""Optimization of designs: generic least-squares solvers (Levenberg–Marquardt, Adam),
box bounds, inequality penalties and checkpoints. Pure numpy/scipy; no physics."""

from .solvers import Bounds, OptimizeResult, Problem, adam, levenberg_marquardt, penalty

__all__ = ["Bounds", "OptimizeResult", "Problem", "adam", "levenberg_marquardt", "penalty"]
