"""One way to write a residual term: a decorated function of the frames (or camera poses) it spans, its data and
its declared variables.

::

    @residual_term(frames=2)
    def planted_feet(states, data, variables):
        step = states[1].world_from_segment.translation() - states[0].world_from_segment.translation()
        return step[FEET], data                    # r (n, k), valid (n,)

    term = planted_feet(flags, weight=1e4)         # data's leading axis: the frame

The function is always ``fn(x, data, variables) -> (r, valid)``:

- ``x`` is what the term spans. Without ``camera``: the :class:`~.base.FrameState` of one frame (``frames=1``), or
  of ``frames`` consecutive frames stacked on a leading axis, oldest first (``x[i]`` is frame ``t − frames + 1 + i``).
  With ``camera=True``: a :class:`~.base.CameraView` of one camera, its ``cam_from_world`` at the frame (``frames=1``) or
  at ``t − 1`` and ``t`` stacked (``frames=2``), and its intrinsics; the term's data is then per camera
  (``(T, C, ...)``, or camera slots, see :func:`~.base.camera_slots`).
- ``data`` is the term's data at that frame (and camera): ``data[t]`` or ``data[t, c]``.
- ``variables`` holds the term's declared static variables by name (``statics``; a
  :class:`~.variables.PerCamera` block reduced to this camera's value), the same argument whether or not there are
  any. Per-frame variables (``frame_variables``) are in ``x.variables``.

It returns residual blocks ``r`` ``(n, k)`` and a mask ``valid`` ``(n,)``; the solver zeroes invalid blocks, applies
the robust ``loss`` and the ``weight`` of the term object (``fn(data, weight=…, loss=…, name=…)``) and differentiates
it. The decorator makes a :class:`~.base.Term` of the right kind (frame, pair, multi-frame, camera, camera pair), so
the solver places it in its structured normal equations by its footprint.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from .base import CameraPairTerm, CameraTerm, FrameTerm, MultiFrameTerm, PairTerm, Term
from .variables import Variable

__all__ = ["residual_term"]


def residual_term(fn: Callable | None = None, *, frames: int = 1, camera: bool = False,
                  statics: Mapping[str, int | Variable] | None = None,
                  frame_variables: Mapping[str, int | Variable] | None = None,
                  rotation_only: bool = False) -> type[Term] | Callable[[Callable], type[Term]]:
    """Make a residual term class from ``fn(x, data, variables) -> (r, valid)`` (see the module's notes).

    Args:
        fn: the residual function (or None, to use the decorator with arguments).
        frames: consecutive frames one residual block spans (1, 2, … without ``camera``; 1 or 2 with it).
        camera: the data is per camera and ``fn`` sees one camera's pose(s) (:class:`~.base.CameraView`); the solver then
            differentiates w.r.t. the 6-DOF pose only and chains it through the kinematics, which is much cheaper
            for many measurements per camera.
        statics: static variable blocks the term reads (``{name: size or Variable}``: a bias, a readout, a lens
            correction), shared by every frame of a window and solved with the motion.
        frame_variables: per-frame variable blocks (not with ``camera``: camera terms see
            :data:`~.variables.CAMERA_OFFSETS` through the poses).
        rotation_only: a two-frame camera term whose residual depends on the cameras' rotations only.

    Returns:
        A :class:`~.base.Term` subclass named after ``fn``: construct it with the data
        (``term = fn_name(data, weight=1.0, loss=TrivialLoss(), name="")``).

    Raises:
        ValueError: a combination the solver has no kind for.
    """
    if fn is None:
        return lambda f: residual_term(f, frames=frames, camera=camera, statics=statics,
                                       frame_variables=frame_variables, rotation_only=rotation_only)
    statics, frame_variables = dict(statics or {}), dict(frame_variables or {})
    where = f"residual_term {getattr(fn, '__qualname__', fn)!r}"
    if not (isinstance(frames, int) and frames >= 1) or (camera and frames > 2):
        raise ValueError(f"{where}: frames must be 1, 2, … (1 or 2 for a camera term), got {frames!r}")
    if camera and frame_variables:
        raise ValueError(f"{where}: a camera term cannot declare per-frame variables")
    if rotation_only and not (camera and frames == 2):
        raise ValueError(f"{where}: rotation_only is for two-frame camera terms")
    base = {(False, 1): FrameTerm, (False, 2): PairTerm, (True, 1): CameraTerm, (True, 2): CameraPairTerm}.get(
        (camera, frames), MultiFrameTerm)
    body: dict[str, Any] = {
        "__doc__": fn.__doc__,
        "__module__": fn.__module__,
        "__qualname__": fn.__qualname__,
        "residual": lambda self, x, data, variables: fn(x, data, variables),
        "static_variables": lambda self: dict(statics),
        "frame_variables": lambda self: dict(frame_variables),
    }
    if base is MultiFrameTerm:
        body["span"] = frames
    if base is CameraPairTerm:
        body["rotation_only"] = rotation_only
    return type(fn.__name__, (base,), body)
