"""bcmocap: differentiable articulated bundle adjustment in JAX.

Motion capture from body-mounted cameras: a skeleton whose segments carry cameras is fitted to what
those cameras saw of a static scene (Shiratori et al., SIGGRAPH 2011), with a Levenberg–Marquardt
solver that exploits the problem's structure.

The public API, for scripts::

    import bcmocap
    bcmocap.enable_float64()          # JAX defaults to float32; the solvers refuse to run without float64
    problem = bcmocap.paper_problem(correspondences, skeleton, rig)   # Eq. (1); or Problem(skeleton, rig, terms)
    solution = bcmocap.solve(problem, initial_motion, bcmocap.SolverOptions(window=60))

The model (:class:`Skeleton`, :class:`Motion`, :class:`Rig`, :func:`forward_kinematics`), the camera models,
:class:`Correspondences` (what the frontend measures), the problem and its solvers, the paper's residual
terms, the four term shapes a new term is written in, and the robust losses. The frontend, the simulator,
the pipeline and the file readers are in their subpackages (``bcmocap.frontend``, ``bcmocap.sim``,
``bcmocap.pipeline``, ``bcmocap.io``).
"""

from .cameras import FOVCamera, OpenCVFisheyeCamera, PinholeCamera
from .correspondences import Correspondences
from .geometry import SE3, SO3
from .kinematics import JointType, Motion, Rig, Skeleton, forward_kinematics, joint_positions
from .precision import enable_float64, require_float64
from .residuals import (
    CameraPairTerm,
    CameraTerm,
    CauchyLoss,
    FrameTerm,
    HomographyTransfer,
    HuberLoss,
    JointSmoothness,
    MultiFrameTerm,
    PairTerm,
    Reprojection,
    RootSmoothness,
    Term,
)
from .solver import Problem, Solution, SolverOptions, solve, solve_with_refinement
from .solver.objective import ObjectiveWeights, StoredProblem, paper_problem, paper_terms

__version__ = "0.1.0"

__all__ = [
    "CameraPairTerm",
    "CameraTerm",
    "CauchyLoss",
    "Correspondences",
    "FOVCamera",
    "FrameTerm",
    "HomographyTransfer",
    "HuberLoss",
    "JointSmoothness",
    "JointType",
    "Motion",
    "MultiFrameTerm",
    "ObjectiveWeights",
    "OpenCVFisheyeCamera",
    "PairTerm",
    "PinholeCamera",
    "Problem",
    "Reprojection",
    "Rig",
    "RootSmoothness",
    "SE3",
    "SO3",
    "Skeleton",
    "Solution",
    "SolverOptions",
    "StoredProblem",
    "Term",
    "enable_float64",
    "forward_kinematics",
    "joint_positions",
    "paper_problem",
    "paper_terms",
    "require_float64",
    "solve",
    "solve_with_refinement",
]
