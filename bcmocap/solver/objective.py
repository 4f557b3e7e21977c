"""The objective of a capture: Eq. (1) of the paper from correspondences — E_r (reprojection +
homography) + λ_O E_O + λ_A E_A — plus any terms a user adds.

A user adds terms through a *term factory*: a callable ``factory(window: TermWindow, **settings)``
returning one :class:`~bcmocap.residuals.Term` or a list of them, with data over the window's frames.
The window tells it which frames (``start``, ``stop``, ``times`` in seconds since the trial's first
clap), the model, the window's correspondences and the capture's trial folder (for the user's own
measurement files). The same factory serves :func:`paper_problem`, :class:`StoredProblem` and
``bcmocap run``, whose config names it by import path (``"mypackage.terms:imu_terms"``, see
:func:`import_term_factory`). Every window of a sequence must get terms of the same kinds and data
shapes (one compilation serves them all).
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..correspondence_store import CorrespondenceStore
from ..correspondences import Correspondences
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Skeleton
from ..residuals import HomographyTransfer, camera_slot_count, camera_slots, JointSmoothness, Reprojection, RootSmoothness, Term, loss_from_name, pair_mask
from ..residuals.mount_compliance import MountCompliance, MountSmoothness
from ..residuals.registered_pose import RegisteredPose, registered_pose_data
from ..residuals.rolling_shutter import READOUT, TIME_OFFSET, RollingShutterReprojection, time_offsets
from ..residuals.term_window import TermWindow
from ..residuals.self_calibration import INTRINSICS_CORRECTION, SelfCalibratingReprojection, StaticPrior, intrinsics_correction
from ..residuals.variables import Euclidean
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
        registered_pose: ``(m, rad)`` σ of the camera centre and rotation of a prior holding a registered
            camera-frame with fewer than ``registered_pose_below`` measurements at its registered pose
            (:class:`~bcmocap.residuals.registered_pose.RegisteredPose`, with the image terms' loss, its scale read
            in σ: a pose more than ~8σ off its registration is down-weighted as an outlier; (0, 0): off).
    """

    root_smoothness: float = 1e3
    joint_smoothness: float = 1e1
    homography: float = 1.0
    loss: str = "cauchy"
    loss_scale: float = 8.0
    registered_pose: tuple[float, float] = (0.0, 0.0)
    registered_pose_below: int = 20

    def __post_init__(self):
        sigma = tuple(self.registered_pose)
        if len(sigma) != 2 or any(not v >= 0 for v in sigma) or (any(sigma) and not all(sigma)):
            raise ValueError(f"ObjectiveWeights.registered_pose must be (m, rad), both 0 or both > 0, got {self.registered_pose}")


@dataclasses.dataclass(frozen=True)
class CameraEffects:
    """What the objective models beyond the paper's rigid, global-shutter, exactly calibrated cameras.

    Attributes:
        readout_seconds: rolling-shutter readout, first row to last (0: global shutter). With it (or
            ``estimate_readout``) the reprojection is :class:`~bcmocap.residuals.rolling_shutter.RollingShutterReprojection`.
        estimate_readout: also solve for a correction to the readout (a static variable, prior σ
            ``readout_sigma_seconds``).
        self_calibration: solve for each camera's focal scale and principal point with the motion (static
            variables with a prior σ ``intrinsics_sigma``: log focal scale, px).
        estimate_time_offsets: solve for each camera's time offset, when its frames are exposed after the
            frames' times (sub-frame starts, audio latencies; a per-camera static variable of the rolling-shutter
            reprojection, prior σ ``time_offset_sigma_seconds``: s, one for all cameras or ``(C,)``).
        time_offsets_measured: ``(C,)`` s, the cameras' time offsets as measured (e.g. by their gyros,
            :mod:`bcmocap.frontend.gyro_timing`): the prior's centre (None: 0); ``bcmocap run`` also starts the
            solve there.
        mount_sigma: ``(m, rad)`` σ of each camera's per-frame offset from its mount
            (:class:`~bcmocap.residuals.mount_compliance.MountCompliance`; (0, 0): rigid mounts); offsets change
            between frames with σ half as large.
    """

    readout_seconds: float = 0.0
    estimate_readout: bool = False
    readout_sigma_seconds: float = 0.01
    self_calibration: bool = False
    intrinsics_sigma: tuple[float, float] = (0.01, 5.0)
    estimate_time_offsets: bool = False
    time_offset_sigma_seconds: float | tuple[float, ...] = 0.01
    time_offsets_measured: tuple[float, ...] | None = None
    mount_sigma: tuple[float, float] = (0.0, 0.0)

    @property
    def rolling_shutter(self) -> bool:
        return self.readout_seconds > 0 or self.estimate_readout or self.estimate_time_offsets


def _camera_terms(c: Correspondences, effects: CameraEffects, loss, mask: np.ndarray) -> list[Term]:
    """The reprojection term of ``effects`` (global or rolling shutter, fixed or self-calibrated intrinsics), the
    priors of the static variables it estimates, and the mount compliance terms."""
    data = {"point_ids": c.point_ids, "pixels": c.pixels, "weights": c.weights}
    share = np.full(c.num_frames, 1.0 / c.num_frames)  # a static prior counts once over these frames
    if effects.rolling_shutter:
        terms: list[Term] = [RollingShutterReprojection(
            data, points=c.points, readout=effects.readout_seconds * c.fps, estimate_readout=effects.estimate_readout,
            estimate_time_offsets=effects.estimate_time_offsets, calibrate=effects.self_calibration,
            num_cameras=c.num_cameras, loss=loss, name="reprojection")]
        if effects.estimate_readout:
            terms.append(StaticPrior(share, block=READOUT, variable=Euclidean(1),
                                     sigma=effects.readout_sigma_seconds * c.fps, name="readout prior"))
        if effects.estimate_time_offsets:
            measured = effects.time_offsets_measured
            if measured is not None and len(measured) != c.num_cameras:
                raise ValueError(f"CameraEffects.time_offsets_measured: {len(measured)} values for {c.num_cameras} cameras")
            mean = 0.0 if measured is None else np.asarray(measured, np.float64)[:, None] * c.fps
            sigma = np.asarray(effects.time_offset_sigma_seconds, np.float64)
            if sigma.ndim and sigma.shape != (c.num_cameras,):
                raise ValueError(f"CameraEffects.time_offset_sigma_seconds: {sigma.shape[0]} values for {c.num_cameras} cameras")
            terms.append(StaticPrior(share, block=TIME_OFFSET, variable=time_offsets(c.num_cameras),
                                     sigma=(sigma[:, None] if sigma.ndim else sigma) * c.fps, mean=mean,
                                     name="time offset prior"))
    elif effects.self_calibration:
        terms = [SelfCalibratingReprojection(data, points=c.points, num_cameras=c.num_cameras, loss=loss, name="reprojection")]
    else:
        terms = [Reprojection(data, points=c.points, loss=loss, name="reprojection")]
    if effects.self_calibration:
        scale, centre = effects.intrinsics_sigma
        terms.append(StaticPrior(share, block=INTRINSICS_CORRECTION, variable=intrinsics_correction(c.num_cameras),
                                 sigma=np.array([scale, centre, centre]), name="intrinsics prior"))
    if any(effects.mount_sigma):
        sigma = np.repeat(np.asarray(effects.mount_sigma, float), 3)
        terms += [MountCompliance(np.ones(c.num_frames), num_cameras=c.num_cameras, sigma=sigma, name="mount compliance"),
                  MountSmoothness(mask, num_cameras=c.num_cameras, sigma=0.5 * sigma, name="mount smoothness")]
    return terms


def paper_terms(
    correspondences: Correspondences,
    skeleton: Skeleton,
    weights: ObjectiveWeights = ObjectiveWeights(),
    *,
    first_frame_has_previous: bool = False,
    include_homography: bool | None = None,
    homography_cameras: int | None = None,
    effects: CameraEffects = CameraEffects(),
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
        effects: rolling shutter, self-calibration and mount compliance (:class:`CameraEffects`; none by default,
            as in the paper). Static priors count once over the given frames (once per window in a
            :class:`StoredProblem`).
    """
    c = correspondences
    loss = loss_from_name(weights.loss, weights.loss_scale)
    mask = np.ones(c.num_frames) if first_frame_has_previous else pair_mask(c.num_frames)
    terms = _camera_terms(c, effects, loss, mask)
    if include_homography is None:
        include_homography = bool((c.homography_weights > 0).any())
    if include_homography:
        # Matches exist only where a camera did not register: keep those cameras' slots only.
        homography = {"pixels": c.homography_pixels, "pixels_prev": c.homography_pixels_prev, "weights": c.homography_weights}
        terms.append(HomographyTransfer(
            camera_slots(homography, count=homography_cameras),
            weight=weights.homography, loss=loss, name="homography",
        ))
    if any(weights.registered_pose):
        data = registered_pose_data(c.world_from_camera, c.registered, c.weights, weights.registered_pose_below)
        terms.append(RegisteredPose(data, sigma=np.asarray(weights.registered_pose, float), loss=loss, name="registered pose"))
    if weights.root_smoothness > 0:
        terms.append(RootSmoothness(mask, weight=weights.root_smoothness, name="root smoothness"))
    if weights.joint_smoothness > 0:
        terms.append(JointSmoothness(mask, skeleton=skeleton, weight=weights.joint_smoothness, name="joint smoothness"))
    return terms


TermFactory = Callable[[TermWindow], Sequence[Term]]


@dataclasses.dataclass(frozen=True)
class UserTerms:
    """A user's term factory with its settings: ``factory(window, **settings)`` → term(s), checked.

    Attributes:
        factory: the callable; settings: keyword arguments for it; name: how errors name it (e.g. its
            import path).
    """

    factory: Callable[..., Any]
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    name: str = ""

    def __call__(self, window: TermWindow) -> tuple[Term, ...]:
        label = self.name or getattr(self.factory, "__qualname__", repr(self.factory))
        made = self.factory(window, **self.settings)
        terms = (made,) if isinstance(made, Term) else tuple(made)
        num_cameras = window.rig.num_cameras if window.rig is not None else 0
        for term in terms:
            if not isinstance(term, Term):
                raise ValueError(f"term factory {label}: returned {type(term).__name__}, not a bcmocap Term")
            try:
                term.check(window.num_frames, num_cameras)
            except ValueError as exc:
                raise ValueError(f"term factory {label} (frames [{window.start}, {window.stop})): {exc}") from None
        return terms


_IMPORT_PATH = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*$")


def import_term_factory(path: str) -> Callable[..., Any]:
    """The object named by ``"package.module:name"`` (imported from ``sys.path``, e.g. ``PYTHONPATH``).

    A :class:`~bcmocap.residuals.Term` subclass gives its ``from_window`` classmethod, so a term class can be
    its own factory.

    Raises:
        ValueError: malformed path, module not importable, no such name, or not callable.
    """
    if not isinstance(path, str) or not _IMPORT_PATH.match(path):
        raise ValueError(f"term factory {path!r}: expected 'package.module:name'")
    module_name, name = path.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"term factory {path!r}: cannot import {module_name!r} ({exc}); is it on PYTHONPATH?") from None
    target = getattr(module, name, None)
    if target is None:
        raise ValueError(f"term factory {path!r}: module {module_name!r} has no {name!r}")
    if isinstance(target, type) and issubclass(target, Term):
        target = getattr(target, "from_window", None)
        if target is None:
            raise ValueError(f"term factory {path!r}: a Term class used as a factory needs a from_window classmethod")
    if not callable(target):
        raise ValueError(f"term factory {path!r}: {name!r} is not callable")
    return target


def paper_problem(
    correspondences: Correspondences, skeleton: Skeleton, rig: Rig, weights: ObjectiveWeights = ObjectiveWeights(),
    *, extra_terms: Sequence[TermFactory] = (), trial_folder: Path | None = None, effects: CameraEffects = CameraEffects(),
) -> Problem:
    """A :class:`Problem` for Eq. (1) (with the camera ``effects`` modelled) plus the terms of ``extra_terms``
    (factories given the whole sequence as one :class:`TermWindow`), checking the correspondences against the rig."""
    if correspondences.num_cameras != rig.num_cameras:
        raise ValueError(f"correspondences have {correspondences.num_cameras} cameras, the rig has {rig.num_cameras}")
    window = TermWindow(0, correspondences.num_frames, correspondences.fps, skeleton, rig, correspondences, trial_folder)
    extra = [term for factory in extra_terms for term in factory(window)]
    return Problem(skeleton, rig, [*paper_terms(correspondences, skeleton, weights, effects=effects), *extra])


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
        extra_terms: term factories (see the module docstring) called for every window, e.g.
            :class:`UserTerms`.
        trial_folder: the capture's trial folder handed to the factories.
        effects: rolling shutter, self-calibration and mount compliance (:class:`CameraEffects`).
        homography_filter: given a window (:class:`TermWindow`), the ``(W, C, M)`` homography weights to use instead
            of the store's (e.g. with the matches a camera's gyro contradicts set to 0), or None. The window the
            ``extra_terms`` factories are given carries them too.
    """

    store: CorrespondenceStore
    skeleton: Skeleton
    rig: Rig
    weights: ObjectiveWeights = ObjectiveWeights()
    include_homography: bool | None = None
    extra_terms: Sequence[TermFactory] = ()
    trial_folder: Path | None = None
    effects: CameraEffects = CameraEffects()
    homography_filter: Callable[[TermWindow], np.ndarray] | None = None

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
        window = TermWindow(start, stop, self.store.fps, self.skeleton, self.rig, corr, self.trial_folder)
        if self.homography_filter is not None and self.include_homography:
            weights = np.asarray(self.homography_filter(window), np.float64)
            if weights.shape != corr.homography_weights.shape:
                raise ValueError(f"homography_filter: weights of shape {weights.shape} for a window's "
                                 f"{corr.homography_weights.shape}")
            corr = dataclasses.replace(corr, homography_weights=weights)
            window = dataclasses.replace(window, correspondences=corr)
        terms = paper_terms(corr, self.skeleton, self.weights, first_frame_has_previous=start > 0,
                            include_homography=self.include_homography, homography_cameras=self._homography_cameras,
                            effects=self.effects)
        terms += [term for factory in self.extra_terms for term in factory(window)]
        return tuple(t.window(0, stop - start) for t in terms)
