"""Eq. (1) of the body-mounted cameras paper, solved by structured Levenberg–Marquardt in windows."""

from .block_tridiagonal import solve_block_tridiagonal
from .levenberg_marquardt import StructuredDampedNewtonDescent, StructuredLevenbergMarquardt
from .solve import (
    Problem,
    Solution,
    SolverOptions,
    WindowReport,
    motion_from_tangent,
    solve,
    whole_sequence_residual_function,
    window_starts,
)
from .window import NormalEquations, WindowProblem, cost, normal_equations, residuals

__all__ = [
    "NormalEquations",
    "Problem",
    "Solution",
    "SolverOptions",
    "StructuredDampedNewtonDescent",
    "StructuredLevenbergMarquardt",
    "WindowProblem",
    "WindowReport",
    "cost",
    "motion_from_tangent",
    "normal_equations",
    "residuals",
    "solve",
    "solve_block_tridiagonal",
    "whole_sequence_residual_function",
    "window_starts",
]
