"""Eq. (1) of the paper from correspondences: E_r (reprojection + homography) + λ_O E_O + λ_A E_A."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..correspondence_store import CorrespondenceStore
from ..correspondences import Correspondences
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Skeleton
from ..residuals import HomographyTransfer, camera_slot_count, camera_slots, JointSmoothness, Reprojection, RootSmoothness, Term, loss_from_name, pair_mask
from .solve import Problem


@dataclasses.dataclass(frozen=True)
class ObjectiveWeights:
    """Weights and robust loss of Eq. (1).

    Attributes:
        root_smoothness: λ_O in px² per m² (and per rad² of root rotation) of frame-to-frame change.
        joint_smoothness: λ_A in px² per rad² of frame-to-frame joint-angle change.
        homography: weight of the homography-transfer term relative to reprojection.
        loss: robust loss of the image terms ("none", "huber", "cauchy"); loss_scale in px. Cauchy at
            8 px keeps inliers of a 1–2° initial pose error in the convex zone while outliers (uniform
            over the image) get ~1 % of an inlier's influence.
    """

    root_smoothness: float = 1e3
    joint_smoothness: float = 1e1
    homography: float = 1.0
    loss: str = "cauchy"
    loss_scale: float = 8.0


def paper_terms(
    correspondences: Correspondences,
    skeleton: Skeleton,
    weights: ObjectiveWeights = ObjectiveWeights(),
    *,
    first_frame_has_previous: bool = False,
    include_homography: bool | None = None,
    homography_cameras: int | None = None,
) -> list[Term]:
    """The residual terms of Eq. (1) for a capture's correspondences.

    Args:
        correspondences: measurements of consecutive frames.
        skeleton: the model (for the joint smoothness term).
        weights: λ's and robust loss.
        first_frame_has_previous: True when the frames are a window inside a longer sequence, so the
            first frame's smoothness pair (with the frame before it) is used.
        include_homography: force the homography term in or out; by default it is included when
            some camera-frame has matches. Windows of one sequence should agree (one compilation).
        homography_cameras: camera slots of the homography term (see :func:`camera_slots`'s
            ``count``); by default from these frames' matches.
    """
    c = correspondences
    loss = loss_from_name(weights.loss, weights.loss_scale)
    terms: list[Term] = [
        Reprojection(
            {"point_ids": c.point_ids, "pixels": c.pixels, "weights": c.weights},
            points=c.points, loss=loss, name="reprojection",
        ),
    ]
    if include_homography is None:
        include_homography = bool((c.homography_weights > 0).any())
    if include_homography:
        # Matches exist only where a camera did not register: keep those cameras' slots only.
        homography = {"pixels": c.homography_pixels, "pixels_prev": c.homography_pixels_prev, "weights": c.homography_weights}
        terms.append(HomographyTransfer(
            camera_slots(homography, count=homography_cameras),
            weight=weights.homography, loss=loss, name="homography",
        ))
    mask = np.ones(c.num_frames) if first_frame_has_previous else pair_mask(c.num_frames)
    if weights.root_smoothness > 0:
        terms.append(RootSmoothness(mask, weight=weights.root_smoothness, name="root smoothness"))
    if weights.joint_smoothness > 0:
        terms.append(JointSmoothness(mask, skeleton=skeleton, weight=weights.joint_smoothness, name="joint smoothness"))
    return terms


def paper_problem(
    correspondences: Correspondences, skeleton: Skeleton, rig: Rig, weights: ObjectiveWeights = ObjectiveWeights()
) -> Problem:
    """A :class:`Problem` for Eq. (1), checking the correspondences against the rig."""
    if correspondences.num_cameras != rig.num_cameras:
        raise ValueError(f"correspondences have {correspondences.num_cameras} cameras, the rig has {rig.num_cameras}")
    return Problem(skeleton, rig, paper_terms(correspondences, skeleton, weights))


@dataclasses.dataclass
class StoredProblem:
    """Eq. (1) over a trial whose correspondences stay on disk (a
    :class:`~bcmocap.correspondence_store.CorrespondenceStore`): the solver's
    :func:`~bcmocap.solver.solve` reads each window's measurements when it reaches that window, so
    memory does not grow with the trial's length. Every window has the same shapes (one compilation).

    Attributes:
        store: the trial's correspondences (``C`` cameras, matching the rig).
        skeleton, rig: the model; weights: λ's and robust loss.
        include_homography: the homography term in or out; by default in if the trial has any match.
    """

    store: CorrespondenceStore
    skeleton: Skeleton
    rig: Rig
    weights: ObjectiveWeights = ObjectiveWeights()
    include_homography: bool | None = None

    def __post_init__(self):
        if self.store.num_cameras != self.rig.num_cameras:
            raise ValueError(f"{self.store.path}: {self.store.num_cameras} cameras, the rig has {self.rig.num_cameras}")
        self.rig.check(self.skeleton)
        if self.include_homography is None:
            self.include_homography = self.store.homography_cameras > 0
        self._homography_cameras = camera_slot_count(self.store.homography_cameras, self.store.num_cameras)

    @property
    def num_frames(self) -> int:
        return self.store.num_frames

    def window(self, start: int, stop: int) -> tuple[Term, ...]:
        corr = self.store.frames(start, stop)
        terms = paper_terms(corr, self.skeleton, self.weights, first_frame_has_previous=start > 0,
                            include_homography=self.include_homography, homography_cameras=self._homography_cameras)
        return tuple(t.window(0, stop - start) for t in terms)
