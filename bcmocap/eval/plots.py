"""PNG figures of results, after the paper's figures (000 §5): joint angles (Fig. 7a), joint positions
(Fig. 7b), camera centres before and after optimisation (Fig. 6), the root path over the sparse scene
(Fig. 9) and skeleton poses in 3D.

Every function takes numpy arrays (SI units: metres, seconds; angles in degrees where the name says
``_deg``), writes one PNG atomically (temporary file + rename) and returns its path. Figures are drawn with
``matplotlib.figure.Figure`` on an Agg canvas, so pyplot's global state and backend are never touched.
NaN marks missing data: lines break there and points are skipped. Wrong shapes raise ``ValueError``
naming the argument. The world is bcmocap's: Z up.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_path

__all__ = [
    "plot_camera_centres",
    "plot_joint_angles",
    "plot_joint_positions",
    "plot_skeleton_poses",
    "plot_top_view",
]

_MAX_SCENE_POINTS_2D = 50_000
_MAX_SCENE_POINTS_3D = 20_000
_ESTIMATE = {"color": "tab:blue", "lw": 1.2, "label": "estimate"}
_TRUTH = {"color": "black", "lw": 1.0, "ls": "--", "label": "ground truth"}


# ---- helpers ----------------------------------------------------------------------------------------


def _array(what: str, name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as float64 with ``shape`` (ints fixed, None free, matched by position)."""
    a = np.asarray(value)
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{what}: {name} must be real numbers, got dtype {a.dtype}")
    ok = a.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, a.shape))
    if not ok:
        spec = "(" + ", ".join("·" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{what}: {name} must have shape {spec}, got {a.shape}")
    return a.astype(np.float64)


def _names(what: str, names, count: int) -> list[str]:
    if isinstance(names, str):
        raise TypeError(f"{what}: names must be a sequence of {count} strings, got a single string")
    out = [str(n) for n in names]
    if len(out) != count:
        raise ValueError(f"{what}: names must have {count} entries (one per joint), got {len(out)}")
    return out


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike, dpi: int) -> Path:
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path


def _subsample(points: np.ndarray, limit: int) -> np.ndarray:
    """Finite rows of ``points``, at most ``limit`` of them (a fixed random subset, so figures are reproducible)."""
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) > limit:
        keep = np.random.default_rng(0).choice(len(points), size=limit, replace=False)
        points = points[np.sort(keep)]
    return points


def _equal_2d(ax, fixed_limits: bool = False) -> None:
    """Equal axis scales; the data limits grow to fit the box unless the limits were set explicitly."""
    ax.set_aspect("equal", adjustable="box" if fixed_limits else "datalim")
    ax.grid(True, lw=0.3, alpha=0.5)


# ---- Fig. 7a: joint angles --------------------------------------------------------------------------


def plot_joint_angles(
    path: str | os.PathLike,
    times,
    angles_deg,
    names: Sequence[str],
    truth_deg=None,
    max_joints: int = 12,
    *,
    dpi: int = 100,
) -> Path:
    """Joint angle curves, one small panel per joint, estimate against ground truth (Fig. 7a).

    Each column is one scalar angle per joint and frame, plotted as given. The intended quantity is the
    magnitude of the joint's local rotation (the geodesic angle of ``parent_from_child`` from rest, degrees),
    which is defined for every joint type; per-axis angles (e.g. Euler channels) can be shown by passing one
    column per axis with names such as ``"knee.x"``. The first ``max_joints`` columns are drawn.

    Args:
        path: output ``.png``.
        times: ``(T,)`` seconds.
        angles_deg: ``(T, J)`` estimated angles (degrees); NaN where missing.
        names: ``J`` joint names (panel titles).
        truth_deg: optional ``(T, J)`` ground truth (degrees).
        max_joints: at most this many panels.
        dpi: resolution.

    Returns:
        The path written.
    """
    what = "plot_joint_angles"
    t = _array(what, "times", times, (None,))
    est = _array(what, "angles_deg", angles_deg, (len(t), None))
    labels = _names(what, names, est.shape[1])
    truth = None if truth_deg is None else _array(what, "truth_deg", truth_deg, est.shape)
    if int(max_joints) < 1:
        raise ValueError(f"{what}: max_joints must be at least 1, got {max_joints}")
    count = min(est.shape[1], int(max_joints))
    cols = min(count, 4) if count else 1
    rows = max(1, -(-count // cols))
    fig = _figure(3.0 * cols, 1.9 * rows + 0.4)
    axes = fig.subplots(rows, cols, squeeze=False, sharex=True)
    for k, ax in enumerate(axes.flat):
        if k >= count:
            ax.set_axis_off()
            continue
        ax.plot(t, est[:, k], **_ESTIMATE)
        if truth is not None:
            ax.plot(t, truth[:, k], **_TRUTH)
        ax.set_title(labels[k], fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(True, lw=0.3, alpha=0.5)
        if k % cols == 0:
            ax.set_ylabel("angle (deg)", fontsize=8)
        if k >= count - cols:
            ax.set_xlabel("time (s)", fontsize=8)
    if count and truth is not None:
        axes.flat[0].legend(fontsize=7, loc="best")
    if count == 0:
        axes.flat[0].text(0.5, 0.5, "no joints", ha="center", va="center", transform=axes.flat[0].transAxes)
    fig.suptitle("Joint angles (degrees)", fontsize=10)
    return _save(fig, path, dpi)


# ---- Fig. 7b: joint positions -----------------------------------------------------------------------


def _default_joints(num_joints: int, parents) -> list[int]:
    """The root and up to three leaves spread over the tree (last joints when ``parents`` is None)."""
    if parents is None:
        rest = list(range(max(1, num_joints - 3), num_joints))
    else:
        has_child = np.zeros(num_joints, bool)
        for p in parents:
            if p >= 0:
                has_child[p] = True
        leaves = [j for j in range(1, num_joints) if not has_child[j]]
        picks = np.linspace(0, len(leaves) - 1, num=min(3, len(leaves))).round().astype(int) if leaves else []
        rest = [leaves[i] for i in picks]
    return [0] + [j for j in dict.fromkeys(rest) if j != 0]


def plot_joint_positions(
    path: str | os.PathLike,
    times,
    positions,
    names: Sequence[str],
    truth=None,
    *,
    joints: Sequence[int] | None = None,
    parents: Sequence[int] | None = None,
    dpi: int = 100,
) -> Path:
    """x, y and z trajectories (cm) of a few joints, estimate against ground truth (Fig. 7b).

    One row per chosen joint, one column per axis (world frame, Z up). By default the joints are the
    root (index 0) and three leaves spread over the tree when ``parents`` is given, else the last three.

    Args:
        path: output ``.png``.
        times: ``(T,)`` seconds.
        positions: ``(T, J, 3)`` estimated joint positions (m); NaN where missing.
        names: ``J`` joint names.
        truth: optional ``(T, J, 3)`` ground-truth positions (m).
        joints: indices of the joints to draw (1 to 8 of them).
        parents: ``(J,)`` parent indices (-1 for the root), used to find leaves.
        dpi: resolution.

    Returns:
        The path written.
    """
    what = "plot_joint_positions"
    t = _array(what, "times", times, (None,))
    est = _array(what, "positions", positions, (len(t), None, 3))
    num_joints = est.shape[1]
    labels = _names(what, names, num_joints)
    ref = None if truth is None else _array(what, "truth", truth, est.shape)
    if num_joints == 0:
        raise ValueError(f"{what}: positions must have at least one joint, got shape {est.shape}")
    if parents is not None:
        parents = _parents(what, parents, num_joints)
    if joints is None:
        chosen = _default_joints(num_joints, parents)
    else:
        chosen = [int(j) for j in joints]
        if not 1 <= len(chosen) <= 8 or any(not 0 <= j < num_joints for j in chosen):
            raise ValueError(f"{what}: joints must be 1 to 8 indices in [0, {num_joints}), got {list(joints)}")
    fig = _figure(9.0, 1.8 * len(chosen) + 0.5)
    axes = fig.subplots(len(chosen), 3, squeeze=False, sharex=True)
    for r, j in enumerate(chosen):
        for c, axis in enumerate("xyz"):
            ax = axes[r, c]
            ax.plot(t, est[:, j, c] * 100.0, **_ESTIMATE)
            if ref is not None:
                ax.plot(t, ref[:, j, c] * 100.0, **_TRUTH)
            ax.set_title(f"{labels[j]}  {axis}", fontsize=9)
            ax.tick_params(labelsize=7)
            ax.grid(True, lw=0.3, alpha=0.5)
            if c == 0:
                ax.set_ylabel("cm", fontsize=8)
            if r == len(chosen) - 1:
                ax.set_xlabel("time (s)", fontsize=8)
    if ref is not None:
        axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle("Joint positions (cm, world frame, Z up)", fontsize=10)
    return _save(fig, path, dpi)


# ---- Fig. 6: camera centres -------------------------------------------------------------------------


def plot_camera_centres(path: str | os.PathLike, before, after, truth=None, *, dpi: int = 100) -> Path:
    """Camera centre paths before and after optimisation, from above (x-y) and from the side (x-z) (Fig. 6).

    Each camera has its own colour; before is thin and faded, after solid, ground truth dashed black.
    Missing frames (NaN) break the paths.

    Args:
        path: output ``.png``.
        before: ``(T, C, 3)`` camera centres (m) before optimisation, e.g. from SfM registration.
        after: ``(T, C, 3)`` camera centres (m) after optimisation.
        truth: optional ``(T, C, 3)`` ground-truth centres (m).
        dpi: resolution.

    Returns:
        The path written.
    """
    what = "plot_camera_centres"
    b = _array(what, "before", before, (None, None, 3))
    a = _array(what, "after", after, b.shape)
    g = None if truth is None else _array(what, "truth", truth, b.shape)
    from matplotlib.lines import Line2D

    colours = [f"C{k % 10}" for k in range(b.shape[1])]
    fig = _figure(11.0, 5.0)
    axes = fig.subplots(1, 2)
    for ax, (i, j), title in zip(axes, ((0, 1), (0, 2)), ("from above (x-y)", "from the side (x-z)")):
        for c, colour in enumerate(colours):
            ax.plot(b[:, c, i], b[:, c, j], color=colour, lw=0.8, alpha=0.4)
            ax.plot(a[:, c, i], a[:, c, j], color=colour, lw=1.4)
            if g is not None:
                ax.plot(g[:, c, i], g[:, c, j], color="black", lw=0.8, ls="--")
        ax.set_xlabel(f"{'xyz'[i]} (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_title(title, fontsize=10)
        _equal_2d(ax)
    handles = [
        Line2D([], [], color="gray", lw=0.8, alpha=0.4, label="before"),
        Line2D([], [], color="gray", lw=1.4, label="after"),
    ]
    if g is not None:
        handles.append(Line2D([], [], color="black", lw=0.8, ls="--", label="ground truth"))
    axes[0].legend(handles=handles, fontsize=8, loc="best")
    fig.suptitle(f"Camera centres of {b.shape[1]} cameras (one colour each)", fontsize=10)
    return _save(fig, path, dpi)


# ---- Fig. 9: top view of the root path over the scene -----------------------------------------------


def _time_coloured_path(ax, xy: np.ndarray, cmap: str = "viridis", lw: float = 2.0):
    """Draw ``(T, 2)`` as segments coloured by frame index; segments with a NaN end are skipped."""
    from matplotlib.collections import LineCollection

    seg = np.stack([xy[:-1], xy[1:]], axis=1)  # (T-1, 2, 2)
    frame = np.arange(len(seg), dtype=float)
    ok = np.all(np.isfinite(seg), axis=(1, 2))
    lines = LineCollection(seg[ok], cmap=cmap, linewidths=lw)
    lines.set_array(frame[ok])
    lines.set_clim(0, max(len(xy) - 1, 1))
    ax.add_collection(lines)
    return lines


def plot_top_view(
    path: str | os.PathLike,
    scene_points,
    root_path,
    camera_paths=None,
    truth_root_path=None,
    *,
    margin_m: float | None = 5.0,
    dpi: int = 100,
) -> Path:
    """The root's path over the sparse scene, seen from above (Z up), coloured by time (Fig. 9).

    Scene points are small grey dots (a fixed random subset of at most 50 000 of those in view); camera
    paths, if given, are thin grey lines; the ground-truth root path is dashed black. The view is the
    paths' extent in x-y grown by ``margin_m`` (so far outliers of the sparse structure do not shrink the
    path), or everything with ``margin_m=None``.

    Args:
        path: output ``.png``.
        scene_points: ``(N, 3)`` sparse structure (m); non-finite rows are skipped.
        root_path: ``(T, 3)`` root positions (m); NaN where missing.
        camera_paths: optional ``(T, C, 3)`` camera centres (m).
        truth_root_path: optional ``(T, 3)`` ground-truth root positions (m).
        margin_m: how far beyond the paths the view extends (m); None for the whole scene.
        dpi: resolution.

    Returns:
        The path written.
    """
    what = "plot_top_view"
    scene = _array(what, "scene_points", scene_points, (None, 3))
    root = _array(what, "root_path", root_path, (None, 3))
    cams = None if camera_paths is None else _array(what, "camera_paths", camera_paths, (len(root), None, 3))
    truth = None if truth_root_path is None else _array(what, "truth_root_path", truth_root_path, root.shape)
    if margin_m is not None and not margin_m >= 0:
        raise ValueError(f"{what}: margin_m must be non-negative or None, got {margin_m}")
    paths = [root] + ([] if cams is None else [cams.reshape(-1, 3)]) + ([] if truth is None else [truth])
    path_xy = np.concatenate(paths)[:, :2]
    path_xy = path_xy[np.all(np.isfinite(path_xy), axis=1)]
    view = None
    if margin_m is not None and len(path_xy):
        view = (path_xy.min(axis=0) - margin_m, path_xy.max(axis=0) + margin_m)
        scene = scene[np.all((scene[:, :2] >= view[0]) & (scene[:, :2] <= view[1]), axis=1)]
    scene = _subsample(scene, _MAX_SCENE_POINTS_2D)
    fig = _figure(7.5, 6.5)
    ax = fig.add_subplot()
    if len(scene):
        ax.scatter(scene[:, 0], scene[:, 1], s=0.3, c="0.6", linewidths=0, rasterized=True, label="scene points")
    if cams is not None:
        for c in range(cams.shape[1]):
            ax.plot(cams[:, c, 0], cams[:, c, 1], color="0.3", lw=0.5, alpha=0.6,
                    label="camera centres" if c == 0 else None)  # fmt: skip
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], color="black", lw=1.0, ls="--", label="ground truth root")
    lines = _time_coloured_path(ax, root[:, :2])
    if view is not None:
        ax.set_xlim(view[0][0], view[1][0])
        ax.set_ylim(view[0][1], view[1][1])
    elif len(path_xy):  # collections do not update the data limits: include the paths explicitly
        ax.update_datalim(path_xy)
        ax.autoscale_view()
    fig.colorbar(lines, ax=ax, label="frame", shrink=0.8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Root path seen from above (Z up)", fontsize=10)
    _equal_2d(ax, fixed_limits=view is not None)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc="best", markerscale=10)
    return _save(fig, path, dpi)


# ---- skeleton poses in 3D ---------------------------------------------------------------------------


def _parents(what: str, parents, num_joints: int) -> list[int]:
    p = np.asarray(parents)
    if p.shape != (num_joints,) or not np.issubdtype(p.dtype, np.integer):
        raise ValueError(f"{what}: parents must be ({num_joints},) integers, got shape {p.shape} dtype {p.dtype}")
    out = [int(v) for v in p]
    for j, v in enumerate(out):
        if not (v == -1 or 0 <= v < num_joints) or v == j:
            raise ValueError(f"{what}: parents[{j}] = {v} is not -1 or another joint's index")
    return out


def plot_skeleton_poses(
    path: str | os.PathLike,
    joint_positions,
    parents: Sequence[int],
    frames: Sequence[int],
    scene_points=None,
    *,
    margin_m: float = 0.5,
    dpi: int = 100,
) -> Path:
    """A few skeleton poses as 3D line segments, one colour per frame, over the scene, equal aspect.

    Bones with a NaN end are skipped. The view is a cube around the poses, grown by ``margin_m``; scene
    points (grey dots, at most 20 000) are those inside it, so a large scene does not shrink the skeletons.

    Args:
        path: output ``.png``.
        joint_positions: ``(T, J, 3)`` joint positions (m, Z up).
        parents: ``(J,)`` parent index per joint, -1 for the root.
        frames: 1 to 6 frame indices in ``[0, T)`` (negative indices count from the end).
        scene_points: optional ``(N, 3)`` points (m).
        margin_m: how far the view extends beyond the poses (m).
        dpi: resolution.

    Returns:
        The path written.
    """
    what = "plot_skeleton_poses"
    pos = _array(what, "joint_positions", joint_positions, (None, None, 3))
    num_frames, num_joints, _ = pos.shape
    par = _parents(what, parents, num_joints)
    picked = [int(f) for f in np.asarray(frames).reshape(-1)] if np.size(frames) else []
    if not 1 <= len(picked) <= 6 or any(not -num_frames <= f < num_frames for f in picked):
        raise ValueError(f"{what}: frames must be 1 to 6 indices in [0, {num_frames}), got {list(np.ravel(frames))}")
    picked = [f % num_frames for f in picked]
    scene = None if scene_points is None else _array(what, "scene_points", scene_points, (None, 3))
    import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)

    fig = _figure(7.0, 6.5)
    ax = fig.add_subplot(projection="3d")
    shown = pos[picked].reshape(-1, 3)
    shown = shown[np.all(np.isfinite(shown), axis=1)]
    if not margin_m >= 0:
        raise ValueError(f"{what}: margin_m must be non-negative, got {margin_m}")
    if len(shown):
        lo, hi = shown.min(axis=0), shown.max(axis=0)
    else:
        lo, hi = -np.ones(3), np.ones(3)
    # Equal aspect: a cube around the poses.
    centre, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 0.1) + margin_m
    if scene is not None:
        inside = np.all(np.abs(scene - centre) <= half, axis=1)
        near = _subsample(scene[inside], _MAX_SCENE_POINTS_3D)
        if len(near):
            ax.scatter(near[:, 0], near[:, 1], near[:, 2], s=0.5, c="0.6", depthshade=False, linewidths=0)
    for k, f in enumerate(picked):
        colour = f"C{k % 10}"
        for j, p in enumerate(par):
            if p < 0:
                continue
            bone = pos[f, [p, j]]
            if np.all(np.isfinite(bone)):
                ax.plot(bone[:, 0], bone[:, 1], bone[:, 2], color=colour, lw=2.0)
        ok = np.all(np.isfinite(pos[f]), axis=1)
        ax.scatter(*pos[f, ok].T, s=6, color=colour, depthshade=False, label=f"frame {f}")
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("Skeleton poses", fontsize=10)
    return _save(fig, path, dpi)
