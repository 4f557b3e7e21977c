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
terms, :func:`residual_term` (a new term is a decorated function) with the :class:`TermWindow` its factory is
given, the five term kinds, and the robust losses. The frontend, the simulator,
the pipeline and the file readers are in their subpackages (``bcmocap.frontend``, ``bcmocap.sim``,
``bcmocap.pipeline``, ``bcmocap.io``).
"""

from .lazy_exports import lazy_exports

# The public API, imported on first use (the viewer and `bcmocap --help` do not pay for JAX).
_PUBLIC = {
    "CameraPairTerm": "residuals",
    "CameraTerm": "residuals",
    "CameraView": "residuals",
    "CauchyLoss": "residuals",
    "Correspondences": "correspondences",
    "FOVCamera": "cameras",
    "FrameTerm": "residuals",
    "HomographyTransfer": "residuals",
    "HuberLoss": "residuals",
    "JointSmoothness": "residuals",
    "JointType": "kinematics",
    "Motion": "kinematics",
    "MultiFrameTerm": "residuals",
    "ObjectiveWeights": "solver.objective",
    "OpenCVFisheyeCamera": "cameras",
    "PairTerm": "residuals",
    "PinholeCamera": "cameras",
    "Problem": "solver",
    "Reprojection": "residuals",
    "Rig": "kinematics",
    "RootSmoothness": "residuals",
    "SE3": "geometry",
    "SO3": "geometry",
    "Skeleton": "kinematics",
    "Solution": "solver",
    "SolverOptions": "solver",
    "StoredProblem": "solver.objective",
    "Term": "residuals",
    "TermWindow": "residuals",
    "enable_float64": "precision",
    "forward_kinematics": "kinematics",
    "joint_positions": "kinematics",
    "paper_problem": "solver.objective",
    "paper_terms": "solver.objective",
    "residual_term": "residuals",
    "require_float64": "precision",
    "solve": "solver",
    "solve_with_refinement": "solver",
}

__version__ = "0.1.0"

__getattr__, __dir__, __all__ = lazy_exports(__name__, _PUBLIC)
