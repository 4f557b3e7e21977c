"""The residual-term API.

A term is one *batched* kind of measurement: it holds its data (arrays whose leading axis is the
frame, so a time window is a slice) and a pure function of the variables it touches. Terms differ by
their footprint, which the solver exploits to build block-tridiagonal normal equations:

=====================  ==============================================  ==========================
kind                   the residual is a function of                    data leading axes
=====================  ==============================================  ==========================
``FrameTerm``          one frame's :class:`FrameState`                  ``(T, ...)``
``PairTerm``           consecutive frames ``(t-1, t)``                  ``(T, ...)`` (indexed by t)
``MultiFrameTerm``     frames ``t-S+1 … t`` (``S = span``)              ``(T, ...)`` (indexed by t)
``CameraTerm``         one camera's ``cam_from_world`` at one frame     ``(T, C, ...)``
``CameraPairTerm``     one camera's ``cam_from_world`` at ``t-1, t``    ``(T, C, ...)`` (indexed by t)
=====================  ==============================================  ==========================

Every term's residual is one function, ``residual(x, data, variables) -> (r, valid)``: ``x`` is what the kind
spans (a :class:`FrameState`, several stacked, or a :class:`CameraView` of one camera), ``data`` the term's data
at that frame (and camera), ``variables`` the static variables it declares, by name (an empty dict when it
declares none). :func:`~.function_term.residual_term` makes a term of any kind from such a function. The
function returns residual blocks ``r`` of shape ``(n, k)`` and a boolean mask ``(n,)``. The solver zeroes invalid blocks, applies the term's robust loss per block
and multiplies by ``sqrt(weight)`` (the λ of Eq. 1), so a term's contribution to the cost is
``weight · ½ Σ ρ(‖r‖²)`` over valid blocks. Per-measurement weights or square-root information
matrices belong in the data and are applied inside the residual function (whitening).

Camera terms are differentiated with respect to the 6-DOF camera pose only (plus the static variables
they declare); the solver chains that with the Jacobian of the camera pose with respect to the frame's
root pose, joint angles and per-frame variables. That is exact and much cheaper than differentiating
every measurement with respect to every joint.

Besides the motion, a term may declare variable blocks of its own (:mod:`.variables`): static ones, one
value per window (:meth:`Term.static_variables`: a bias, a readout time, a lens correction), and
per-frame ones (:meth:`Term.frame_variables`: a camera's wobble on its mount), each with its manifold.

Camera slots: when only a few cameras per frame have data for a camera term (homography pairs exist
only where a camera could not register), its data may be a dict with the reserved key ``"camera"``:
``(T, K)`` integer camera indices; axis 1 of every other leaf then indexes those K slots instead of
all C cameras. Padded slots name any camera and carry zero weight. :func:`camera_slots` builds this
layout from per-camera data.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel
from ..geometry import SE3
from ..kinematics.skeleton import Motion
from .losses import RobustLoss, TrivialLoss
from .variables import Variable


class FrameState(eqx.Module):
    """What a frame-level residual can look at, for one frame.

    Attributes:
        motion: the frame's root position and rotations (batch shape ``()``).
        world_from_segment: SE3 with batch shape ``(J,)``.
        world_from_camera: SE3 with batch shape ``(C,)`` (empty if the problem has no rig).
        statics: the window's static variables by name (each of its block's value shape, the same at every
            frame): what terms declare in :meth:`Term.static_variables`, e.g. an accelerometer bias.
        variables: the frame's own variables by name (per-frame blocks, :meth:`Term.frame_variables`).
            ``world_from_camera`` already includes :data:`~.variables.CAMERA_OFFSETS` when a term declares it.
    """

    motion: Motion
    world_from_segment: SE3
    world_from_camera: SE3
    statics: dict = eqx.field(default_factory=dict)
    variables: dict = eqx.field(default_factory=dict)

    def __getitem__(self, i) -> FrameState:
        """The state of the ``i``-th of stacked frames (a multi-frame term's ``states[0]`` is the oldest)."""
        return jax.tree.map(lambda a: a[i], self)


class Term(eqx.Module):
    """Base class of all residual terms.

    Attributes:
        data: pytree of arrays whose leading axis is the frame (camera terms: frame, camera).
        weight: λ, multiplying this term's squared residuals in the objective.
        loss: robust loss applied per residual block.
        name: label used in reports.
    """

    data: Any
    weight: jax.Array = eqx.field(default=1.0, kw_only=True, converter=jnp.asarray)
    loss: RobustLoss = eqx.field(default_factory=TrivialLoss, kw_only=True)
    name: str = eqx.field(default="", static=True, kw_only=True)

    #: The term's footprint, which picks the solver's adapter for it (class attributes of the five kinds):
    #: ``"frame"``, ``"pair"``, ``"span"``, ``"camera"`` or ``"camera_pair"``.
    kind: ClassVar[str] = ""
    #: How many consecutive frames one residual block spans (1, 2, or a multi-frame term's ``span``).
    span: ClassVar[int] = 1
    #: Whether the data is per camera (leading axes ``(T, C)`` or camera slots) and the residual a function of one
    #: camera's pose(s) rather than of the frame state.
    per_camera: ClassVar[bool] = False

    @property
    def label(self) -> str:
        return self.name or type(self).__name__

    def num_frames(self) -> int:
        leaves = jax.tree.leaves(self.data)
        return int(np.shape(leaves[0])[0]) if leaves else 0

    def window(self, start: int, stop: int) -> Term:
        """This term restricted to frames ``[start, stop)`` with its data as JAX arrays."""
        data = jax.tree.map(lambda a: jnp.asarray(np.asarray(a[start:stop])), self.data)
        return eqx.tree_at(lambda t: t.data, self, data, is_leaf=lambda x: x is None)

    def leading_axes(self, num_frames: int, num_cameras: int) -> tuple[int, ...]:
        """The leading axes every data leaf must have: ``(T,)``, ``(T, C)`` or ``(T, K)`` camera slots.

        Raises ValueError if the term's camera slots (``data["camera"]``) are malformed.
        """
        if not self.per_camera:
            return (num_frames,)
        slots = slot_cameras(self.data)
        if slots is None:
            return (num_frames, num_cameras)
        slots = np.asarray(slots)
        if slots.ndim != 2 or slots.shape[0] != num_frames or slots.dtype.kind not in "iu":
            raise ValueError(
                f"{self.label}: data['camera'] has shape {slots.shape} and dtype {slots.dtype}; expected "
                f"integer camera indices of shape ({num_frames}, K)"
            )
        if slots.size and (slots.min() < 0 or slots.max() >= num_cameras):
            raise ValueError(f"{self.label}: data['camera'] names cameras outside [0, {num_cameras})")
        return slots.shape

    def check(self, num_frames: int, num_cameras: int) -> None:
        """Raise ValueError if the data's leading axes or values do not fit the problem."""
        expected = self.leading_axes(num_frames, num_cameras)
        for path, leaf in jax.tree_util.tree_leaves_with_path(self.data):
            shape = np.shape(leaf)
            if shape[: len(expected)] != expected:
                raise ValueError(
                    f"{self.label}: data{jax.tree_util.keystr(path)} has shape {shape}; expected leading axes "
                    f"{expected} (frames{', cameras' if len(expected) == 2 else ''})"
                )
            arr = np.asarray(leaf)
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                idx = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
                raise ValueError(f"{self.label}: data{jax.tree_util.keystr(path)} has NaN/inf at index {idx}")

    def static_variables(self) -> dict[str, int | Variable]:
        """Static variable blocks this term reads: ``{name: size or Variable}`` (a size is ``Euclidean``).

        Static variables are shared by every frame of a window — a sensor bias, a readout time, a lens
        correction (:class:`~.variables.PerCamera`), a sensor-to-camera rotation (:class:`~.variables.Rotation`)
        — and solved with the motion: the solver eliminates them by a Schur complement (``O(size)`` extra
        banded solves per step), starts them at the block's start value (0, identity) in the first window and
        carries each window's estimate into the next. Terms that name the same block share it.

        Every kind of term receives the blocks it declares as the ``variables`` argument of ``residual`` (a
        camera term: a :class:`~.variables.PerCamera` block reduced to its own camera's value).
        """
        return {}

    def frame_variables(self) -> dict[str, int | Variable]:
        """Per-frame variable blocks this term reads from ``state.variables``: ``{name: size or Variable}``.

        They join each frame's variables (the block-banded system's blocks grow by their size), start at the
        block's start value, and ``Solution.frame_variables`` holds them for every frame. Terms that name the
        same block share it; one term must give each block a prior, or nothing determines it.
        :data:`~.variables.CAMERA_OFFSETS` moves the cameras on their mounts, so camera terms see it through
        the camera poses; camera terms cannot declare per-frame blocks themselves.
        """
        return {}

    def finish(self, r: jax.Array, valid: jax.Array) -> jax.Array:
        """Mask, robustify and weight raw residual blocks ``(..., k)``: the residuals whose squares are the cost."""
        return jnp.sqrt(self.weight) * self.loss.scale_residual(self.masked(r, valid))

    @staticmethod
    def masked(r: jax.Array, valid: jax.Array) -> jax.Array:
        """Raw residual blocks ``(..., k)`` with invalid ones set to zero."""
        return jnp.where(valid[..., None], r, 0.0)

    def irls_sqrt_weights(self, masked: jax.Array) -> jax.Array:
        """``sqrt(λ ρ'(‖r‖²))`` per block ``(...)``: row scaling of the IRLS Gauss–Newton model."""
        return jnp.sqrt(self.weight * self.loss.derivative(jnp.sum(masked * masked, axis=-1)))


def slot_cameras(data: Any) -> Any:
    """The ``(T, K)`` camera index of each data slot of a camera term, or None (data per camera)."""
    return data.get("camera") if isinstance(data, dict) else None


def camera_slot_count(needed: int, num_cameras: int, multiple: int = 4) -> int:
    """Camera slots K for frames with at most ``needed`` cameras carrying weight: rounded up to
    ``multiple`` (at least ``multiple``, at most ``num_cameras``)."""
    return min(num_cameras, max(multiple, -(-needed // multiple) * multiple))


def camera_slots(data: dict, weights_key: str = "weights", multiple: int = 4, count: int | None = None) -> dict:
    """Per-camera data ``(T, C, ...)`` → camera slots ``(T, K, ...)`` keeping only cameras with weight.

    Args:
        data: dict of arrays with leading axes ``(T, C)``; ``data[weights_key]`` ``(T, C, ...)`` says
            which camera-frames carry measurements (any weight > 0).
        multiple: K is the largest number of such cameras in one frame rounded up to this multiple
            (at least ``multiple``, at most C), so windows of one sequence rarely differ in shape.
        count: K given instead (windows read one at a time agree on it exactly); must be at least
            the number of cameras with weight in any frame.

    Returns:
        The same keys with axis 1 indexing slots, plus ``"camera"`` ``(T, K)`` int32; unused slots
        repeat camera 0 with all weights 0.
    """
    if "camera" in data:
        raise ValueError("camera_slots: data already has a 'camera' key")
    weights = np.asarray(data[weights_key])
    t, c = weights.shape[:2]
    active = (weights > 0).reshape(t, c, -1).any(axis=-1)
    needed = int(active.sum(axis=1).max(initial=0))
    if count is None:
        k = camera_slot_count(needed, c, multiple)
    elif needed <= count:
        k = count
    else:
        raise ValueError(f"camera_slots: {needed} cameras carry weight in one frame, more than count={count}")
    order = np.argsort(~active, axis=1, kind="stable")[:, :k]  # active cameras first, in camera order
    used = np.take_along_axis(active, order, axis=1)
    cameras = np.where(used, order, 0).astype(np.int32)
    out = {}
    for key, value in data.items():
        value = np.asarray(value)
        index = order.reshape(t, k, *([1] * (value.ndim - 2)))
        gathered = np.take_along_axis(value, index, axis=1)
        if key == weights_key:
            gathered = np.where(used.reshape(t, k, *([1] * (value.ndim - 2))), gathered, 0)
        out[key] = gathered
    out["camera"] = cameras
    return out


class CameraView(eqx.Module):
    """What a camera term sees: one camera's pose(s) and intrinsics.

    Attributes:
        cam_from_world: SE3, batch ``()`` at the frame (:class:`CameraTerm`), or ``(2,)`` at ``t − 1`` and ``t``
            (:class:`CameraPairTerm`; ``view[0]``, ``view[1]``).
        camera: the camera's intrinsics.
    """

    cam_from_world: SE3
    camera: CameraModel

    def __getitem__(self, i) -> CameraView:
        """The view at the ``i``-th of the stacked frames (oldest first)."""
        return CameraView(SE3(self.cam_from_world.wxyz_xyz[i]), self.camera)


class FrameTerm(Term):
    """A residual on one frame's variables (priors, joint limits, contacts): ``x`` is the frame's
    :class:`FrameState`."""

    kind = "frame"

    @abc.abstractmethod
    def residual(self, x: FrameState, data: Any, variables: dict) -> tuple[jax.Array, jax.Array]:
        """Args: one frame's state, its data ``data[t]`` and the term's static variables by name. Returns
        ``(r (n, k), valid (n,))``."""


class PairTerm(Term):
    """A residual on two consecutive frames (smoothness): ``x`` is their states as :class:`StackedFrames`, ``x[0]``
    at ``t − 1`` and ``x[1]`` at ``t`` (an attribute such as ``x.motion`` is both stacked). ``data[t]`` belongs to the
    pair ``(t-1, t)``."""

    kind = "pair"
    span = 2

    @abc.abstractmethod
    def residual(self, x: FrameState, data: Any, variables: dict) -> tuple[jax.Array, jax.Array]:
        """Returns ``(r (n, k), valid (n,))`` for the pair ``(t-1, t)``."""


class MultiFrameTerm(Term):
    """A residual on ``span`` consecutive frames ``t − span + 1 … t`` (an accelerometer over three frames,
    a jerk prior): ``x`` is their :class:`FrameState` with leading axis ``span``, oldest first. ``data[t]``
    belongs to the frames ending at ``t``; blocks whose first frames fall before the sequence are dropped. The
    normal equations become block banded with bandwidth ``span − 1`` (:mod:`bcmocap.solver.block_banded`), and
    each window keeps ``span − 1`` solved frames before it fixed, so the term also connects across window seams.

    Attributes:
        span: the number of frames (class attribute, ≥ 2; a static property of the term's kind).
    """

    kind = "span"
    span = 3

    @abc.abstractmethod
    def residual(self, x: FrameState, data: Any, variables: dict) -> tuple[jax.Array, jax.Array]:
        """Args: the frames' states with leading axis ``span`` (oldest first), ``data[t]`` and the term's static
        variables. Returns ``(r (n, k), valid (n,))``."""


class CameraTerm(Term):
    """Measurements of one camera at one frame (reprojection): ``x`` is a :class:`CameraView`.

    A term whose measurement ``i`` depends on the pose only through the camera-frame position of its own
    world point ``i`` may say so by returning those points from :meth:`world_points` and implementing
    :meth:`residual_in_camera`; the solver then differentiates the lens with 3 tangents instead of 6.
    """

    kind = "camera"
    per_camera = True

    @abc.abstractmethod
    def residual(self, x: CameraView, data: Any, variables: dict) -> tuple[jax.Array, jax.Array]:
        """Args: one camera's pose (batch ``()``) and intrinsics, its data ``data[t, c]`` and the term's static
        variables (a :class:`~.variables.PerCamera` block reduced to this camera's value)."""

    def world_points(self, data: Any) -> jax.Array | None:
        """``(n, 3)`` world points whose camera-frame positions alone determine the residuals, or None."""
        return None

    def residual_in_camera(self, points_cam: jax.Array, camera: CameraModel, data: Any) -> tuple[jax.Array, jax.Array]:
        """The residual from camera-frame points ``(n, 3)``; block ``i`` may depend on point ``i`` only."""
        raise NotImplementedError(f"{self.label}: world_points() is given but residual_in_camera() is not")


class CameraPairTerm(Term):
    """Measurements linking one camera at frames ``t-1`` and ``t`` (homography transfer): ``x`` is a
    :class:`CameraView` with both poses (``x[0]``, ``x[1]``).

    Subclasses whose residual depends on the camera orientations only set ``rotation_only = True``;
    the solver then differentiates with respect to the 3 rotation tangents of each pose, not all 6.
    """

    kind = "camera_pair"
    span = 2
    per_camera = True
    rotation_only = False

    @abc.abstractmethod
    def residual(self, x: CameraView, data: Any, variables: dict) -> tuple[jax.Array, jax.Array]:
        """Args: the camera's poses at ``t-1`` and ``t`` and its intrinsics, ``data[t, c]`` and the term's static
        variables."""


def stacked(*frames):
    """Pytrees of one frame each (states, poses) stacked on a new leading axis, oldest first."""
    return jax.tree.map(lambda *a: jnp.stack(a), *frames)


class StackedFrames:
    """Consecutive frames' states read as one :class:`FrameState` with a leading axis, oldest first: ``x[i]`` is the
    ``i``-th frame's state as it is, and an attribute (``x.motion``, ``x.world_from_camera``, …) is stacked when it
    is read, so that a pair term pays only for what it reads."""

    def __init__(self, *frames: FrameState):
        self._frames = frames

    def __getitem__(self, i):
        return self._frames[i] if isinstance(i, int) else jax.tree.map(lambda a: a[i], stacked(*self._frames))

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return stacked(*(getattr(frame, name) for frame in self._frames))


def declared_statics(term: Term, statics: dict) -> dict:
    """The static variables ``term`` declares, taken from ``statics`` (the window's, by name)."""
    return {name: statics[name] for name in term.static_variables()}
