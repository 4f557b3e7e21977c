"""The standard synthetic capture: CMU motion, 18-camera rig, scene, measurements and ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..correspondences import Correspondences
from ..kinematics.ik import motion_from_camera_poses
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton
from ..residuals import Term
from ..solver.objective import ObjectiveWeights, paper_terms
from .motions import load_body_motion
from .observe import NoiseModel, ObservationSimulator
from .rig import standard_rig
from .world import World, make_world


@dataclasses.dataclass
class SyntheticCapture:
    """A simulated capture with its ground truth.

    Attributes:
        skeleton, rig: the true model (skeleton and camera mounts).
        motion: ground-truth motion ``(T, J)``.
        world: scene points.
        noise: measurement model; seed: base random seed; fps: frame rate.
    """

    skeleton: Skeleton
    rig: Rig
    motion: Motion
    world: World
    noise: NoiseModel
    seed: int
    fps: float

    def __post_init__(self):
        self._simulator = ObservationSimulator(self.skeleton, self.rig, self.motion, self.world.points, self.noise, self.seed)

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames

    def correspondences(self, start: int = 0, stop: int | None = None) -> Correspondences:
        """Measurements of frames ``[start, stop)`` (all frames by default)."""
        stop = self.num_frames if stop is None else stop
        arrays = self._simulator.frames(start, stop)
        return Correspondences(points=self.world.points, fps=self.fps, **arrays)

    def registered_poses(self, chunk_frames: int = 256) -> tuple[np.ndarray, np.ndarray]:
        """Noisy registered ``world_from_camera`` ``(T, C, 7)`` and ``registered`` ``(T, C)``.

        Simulated chunk by chunk, keeping only the poses, so memory does not grow with the measurements.
        """
        poses, registered = [], []
        for start in range(0, self.num_frames, chunk_frames):
            part = self._simulator.frames(start, min(start + chunk_frames, self.num_frames))
            poses.append(part["world_from_camera"])
            registered.append(part["registered"])
        return np.concatenate(poses), np.concatenate(registered)

    def initial_motion(self, correspondences: Correspondences | None = None) -> Motion:
        """Motion from the noisy registered camera poses, as the solver's starting point."""
        if correspondences is None:
            poses, registered = self.registered_poses()
        else:
            poses, registered = correspondences.world_from_camera, correspondences.registered
        return motion_from_camera_poses(self.skeleton, self.rig, poses, registered)

    def lazy_problem(self, weights: ObjectiveWeights = ObjectiveWeights()) -> LazyProblem:
        """A problem that simulates each window's measurements when the solver asks for it."""
        return LazyProblem(self, weights)


class LazyProblem:
    """Eq. (1) for a synthetic capture, generating measurements one window at a time (constant memory)."""

    def __init__(self, capture: SyntheticCapture, weights: ObjectiveWeights):
        self.capture, self.weights = capture, weights
        self.skeleton, self.rig = capture.skeleton, capture.rig

    @property
    def num_frames(self) -> int:
        return self.capture.num_frames

    def window(self, start: int, stop: int) -> tuple[Term, ...]:
        c = self.capture.correspondences(start, stop)
        terms = paper_terms(c, self.skeleton, self.weights, first_frame_has_previous=start > 0, include_homography=True)
        return tuple(t.window(0, stop - start) for t in terms)


def standard_capture(
    motion: str = "walk",
    *,
    seconds: float | None = 2.0,
    start_seconds: float = 0.0,
    repeat: bool = False,
    fps: float = 60.0,
    width: int = 640,
    height: int = 360,
    noise: NoiseModel = NoiseModel(),
    seed: int = 0,
) -> SyntheticCapture:
    """The standard synthetic capture of docs/architecture.md.

    Args:
        motion: bundled CMU trial ("walk", "run", "jump", "scoop", "hop": :data:`~bcmocap.sim.motions.CMU_TRIALS`).
        seconds, start_seconds: part of the trial to use (``seconds=None``: to its end).
        repeat: play the trial back and forth when ``seconds`` is longer than it (long benchmarks).
        fps: frame rate (Hz).
        width, height: image size of the 170° FOV-model cameras.
        noise: measurement model (1 px, 10 % outliers, 5 % unregistered by default).
        seed: random seed for the scene and the measurements.
    """
    skeleton, truth = load_body_motion(motion, fps=fps, seconds=seconds, start_seconds=start_seconds, repeat=repeat)
    rig = standard_rig(skeleton, width, height)
    world = make_world(np.asarray(truth.root_position)[:, :2], seed=seed)
    return SyntheticCapture(skeleton, rig, truth, world, noise, seed, fps)
