"""Eq. (1) of the body-mounted cameras paper, solved by structured Levenberg–Marquardt in windows."""

from .block_tridiagonal import solve_block_tridiagonal
from .levenberg_marquardt import (
    Convergence,
    NormalEquations,
    StructuredDampedNewtonDescent,
    StructuredLevenbergMarquardt,
    levenberg_marquardt,
)
from .model_parameters import ModelParameters
from .parallel import WindowSolution, join_windows, seam_windows, solve_window, solve_windows_independently
from .refine import (
    RefineOptions,
    RefineReport,
    RefinedSolution,
    Refinement,
    RoundReport,
    refine_model,
    refine_skeleton_and_rig,
    reprojection_cost,
    solve_with_refinement,
)
from .solve import (
    Problem,
    Solution,
    SolverOptions,
    WindowReport,
    motion_from_tangent,
    sequence_cost,
    solve,
    whole_sequence_residual_function,
    window_starts,
)
from .window import WindowProblem, cost, normal_equations, residuals

__all__ = [
    "ModelParameters",
    "Convergence",
    "NormalEquations",
    "Problem",
    "RefineOptions",
    "RefineReport",
    "RefinedSolution",
    "Refinement",
    "RoundReport",
    "Solution",
    "SolverOptions",
    "StructuredDampedNewtonDescent",
    "StructuredLevenbergMarquardt",
    "WindowProblem",
    "WindowReport",
    "WindowSolution",
    "cost",
    "join_windows",
    "levenberg_marquardt",
    "motion_from_tangent",
    "normal_equations",
    "refine_model",
    "refine_skeleton_and_rig",
    "reprojection_cost",
    "residuals",
    "seam_windows",
    "sequence_cost",
    "solve",
    "solve_block_tridiagonal",
    "solve_window",
    "solve_windows_independently",
    "solve_with_refinement",
    "whole_sequence_residual_function",
    "window_starts",
]
