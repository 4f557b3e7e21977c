"""Add your own residual term: a joint-limit prior on the hinge joints (knees, elbows).

A term is ``residual(x, data, variables) -> (r, valid)`` over the frames it spans, here one frame's state. Written as
a class (this one holds the skeleton and the limits as fields and has a method of its own); a plain function
decorated with ``bcmocap.residual_term`` is the same term (examples/gyro_term). The solver differentiates it with
JAX and places it in the block-tridiagonal normal equations by its footprint (here: one frame).

    python examples/custom_residual.py [--seconds 1.0]
"""

from __future__ import annotations

import argparse

import jax.numpy as jnp
import numpy as np

from bcmocap import FrameTerm, JointType, Problem, SolverOptions, enable_float64, paper_terms, solve
from bcmocap.eval import evaluate_motion
from bcmocap.sim import standard_capture


class HingeLimits(FrameTerm):
    """Penalise hinge angles outside ``[lower, upper]`` (rad); ``data`` is a ``(T,)`` on/off mask."""

    skeleton: object = None
    lower: float = 0.0
    upper: float = 2.6

    def hinge_angles(self, rotations):
        """Signed angle of every hinge about its axis, ``(..., J)`` from ``(..., J, 4)`` (0 for other joints)."""
        along_axis = jnp.sum(rotations[..., 1:] * self.skeleton.hinge_axes, axis=-1)
        return 2.0 * jnp.arctan2(along_axis, rotations[..., 0])

    def residual(self, x, data, variables):
        hinge = np.array([t == JointType.HINGE for t in self.skeleton.joint_types])
        angle = self.hinge_angles(x.motion.rotations)
        excess = jnp.maximum(angle - self.upper, 0.0) + jnp.minimum(angle - self.lower, 0.0)
        return excess[:, None], jnp.asarray(hinge) & (data > 0)


def main(argv=None):
    enable_float64()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1.0)
    args = parser.parse_args(argv)

    capture = standard_capture("walk", seconds=args.seconds)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    limits = HingeLimits(np.ones(capture.num_frames), skeleton=capture.skeleton, weight=1e6, name="hinge limits")
    problem = Problem(capture.skeleton, capture.rig, [*paper_terms(correspondences, capture.skeleton), limits])
    solution = solve(problem, initial, SolverOptions(window=min(40, capture.num_frames), overlap=10))

    angles = np.asarray(limits.hinge_angles(solution.motion.rotations))
    hinges = [j for j, t in enumerate(capture.skeleton.joint_types) if t == JointType.HINGE]
    errors = evaluate_motion(capture.skeleton, solution.motion, capture.motion, capture.rig)
    print("hinge angle range (deg):", {capture.skeleton.names[j]: tuple(np.rad2deg([angles[:, j].min(), angles[:, j].max()]).round(1)) for j in hinges})
    print(f"mean joint position error {errors['joint_position_error_cm']['mean']:.3f} cm, "
          f"joint angle error {errors['joint_angle_error_deg']['mean']:.3f} deg")
    return solution


if __name__ == "__main__":
    main()
