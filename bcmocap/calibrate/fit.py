"""Lens calibration from board views: intrinsics and one board pose per view.

Models (``model``):

* ``"fov"`` — the paper's Devernay–Faugeras FOV model (:class:`~bcmocap.cameras.FOVCamera`: fx, fy, cx, cy, ω);
* ``"equidistant"`` — ``r = f θ`` (:class:`~bcmocap.cameras.OpenCVFisheyeCamera` with k1..k4 = 0: fx, fy, cx, cy);
* ``"opencv_fisheye"`` — Kannala–Brandt (fx, fy, cx, cy, k1..k4) through ``cv2.fisheye.calibrate``, started
  from the equidistant fit; should OpenCV fail, the same model is fitted like the others;
* ``"thin_prism_fisheye"`` — Kannala–Brandt with decentering and thin-prism terms (COLMAP's THIN_PRISM_FISHEYE,
  :class:`~bcmocap.cameras.ThinPrismFisheyeCamera`: fx, fy, cx, cy, k1..k4, p1, p2, sx1, sy1), started from the
  Kannala–Brandt fit: a lens whose elements sit off their axis or whose sensor is tilted (a manufactured unit)
  leaves the Kannala–Brandt fit a few tenths of a pixel off, which these four terms take up.

The FOV, equidistant and thin-prism models are fitted with bcmocap's own differentiable cameras and its one
Levenberg–Marquardt (:func:`bcmocap.solver.levenberg_marquardt`): the board poses are the solver's
frames (6 variables each: a rotation vector applied to the initial rotation, and the translation in m),
the intrinsics its static variables, so the normal equations are block diagonal over views bordered by
the intrinsics and each step eliminates the poses by a Schur complement, as bundle adjusters do.

Initialisation needs no guess from the user: an equidistant lens is assumed for a range of fields of
view, each view's pose comes from ``cv2.solvePnP`` (IPPE, planar) on the rays, and the field of view whose
poses reproject best is refined, first as equidistant, then as the chosen model. Views that fit far worse
than the rest (blur, a misdetected corner, a planar pose on its wrong side) are dropped and the fit repeated, for
at most three rounds.

Reported errors are in pixels: ``rms_px`` is the root mean square of the per-point 2D error norm (as
OpenCV's ``calibrateCamera`` reports it).
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel, FOVCamera, OpenCVFisheyeCamera, ThinPrismFisheyeCamera
from ..geometry import SO3
from ..precision import require_float64
from ..solver.levenberg_marquardt import NormalEquations, levenberg_marquardt, static_schur_complement
from .views import BoardViews

__all__ = ["MODELS", "Calibration", "calibrate", "camera_from_params", "params_of"]

MODELS = ("fov", "opencv_fisheye", "equidistant", "thin_prism_fisheye")
PARAM_NAMES = {
    "fov": ("fx", "fy", "cx", "cy", "omega"),
    "equidistant": ("fx", "fy", "cx", "cy"),
    "opencv_fisheye": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "thin_prism_fisheye": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2", "sx1", "sy1"),
}
MIN_VIEWS = 3
# A view fitting worse than this many times the median view (and worse than REJECT_FLOOR_PX) is dropped and the fit
# repeated, for at most REJECT_ROUNDS rounds: a refit from scratch can put another view's planar pose on its wrong side
# (cv2.fisheye.calibrate on a studio board video: one view 674 px off after the first round dropped a 4.5 px view).
REJECT_FACTOR = 3.0
REJECT_FLOOR_PX = 1.0
REJECT_ROUNDS = 3
# Degenerate views: the focal length or the principal point known only to this fraction of the focal length.
DEGENERATE_FRACTION = 0.05


def camera_from_params(model: str, params, width: int, height: int) -> CameraModel:
    """The camera of ``model`` with parameter vector ``params`` (:data:`PARAM_NAMES` order; traceable)."""
    p = jnp.asarray(params)
    if model == "fov":
        return FOVCamera(width, height, focal=p[0:2], principal_point=p[2:4], omega=jnp.abs(p[4]))
    if model == "equidistant":
        return OpenCVFisheyeCamera(width, height, focal=p[0:2], principal_point=p[2:4], distortion=jnp.zeros(4))
    if model == "opencv_fisheye":
        return OpenCVFisheyeCamera(width, height, focal=p[0:2], principal_point=p[2:4], distortion=p[4:8])
    if model == "thin_prism_fisheye":
        return ThinPrismFisheyeCamera(width, height, focal=p[0:2], principal_point=p[2:4], distortion=p[4:8],
                                      tangential=p[8:10], thin_prism=p[10:12])
    raise ValueError(f"--model must be one of {', '.join(MODELS)}, got {model!r}")


def params_of(model: str, camera: CameraModel) -> np.ndarray:
    """Inverse of :func:`camera_from_params`."""
    base = [*np.asarray(camera.focal), *np.asarray(camera.principal_point)]
    if model == "fov":
        return np.array([*base, float(camera.omega)])
    if model == "equidistant":
        return np.array(base)
    if model == "thin_prism_fisheye":
        return np.array([*base, *(float(x) for name in ("distortion", "tangential", "thin_prism")
                                   for x in np.asarray(getattr(camera, name)))])
    return np.array([*base, *np.asarray(camera.distortion)])


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A fitted lens and the board poses that go with it.

    Attributes:
        model: one of :data:`MODELS`; camera: the fitted camera; method: how it was fitted.
        views: the views used (rejected ones removed); rejected: names of views left out: no board pose in the
            initial guess (the board too oblique or too small in them), or fitting as outliers.
        rotations: ``(V, 3, 3)`` camera_from_board rotations; translations: ``(V, 3)`` (m).
        residuals: ``(V, N, 2)`` projected minus detected pixels (0 where a point was not seen).
        std: one standard deviation per parameter (:data:`PARAM_NAMES` order; px, rad, or unitless),
            from the Gauss–Newton covariance scaled by the residual variance.
        steps: Levenberg–Marquardt steps of the final fit (OpenCV's iterations are not counted).
    """

    model: str
    camera: CameraModel
    method: str
    views: BoardViews
    rejected: tuple[str, ...]
    rotations: np.ndarray
    translations: np.ndarray
    residuals: np.ndarray
    std: np.ndarray
    steps: int

    @property
    def errors(self) -> np.ndarray:
        """``(V, N)`` per-point error norms (px; 0 where not seen)."""
        return np.linalg.norm(self.residuals, axis=-1) * self.views.seen

    @property
    def rms_px(self) -> float:
        e = self.errors[self.views.seen]
        return float(np.sqrt(np.mean(e**2)))

    @property
    def view_rms_px(self) -> np.ndarray:
        """``(V,)`` RMS error of each view (px)."""
        e2 = (self.errors**2).sum(axis=1)
        return np.sqrt(e2 / np.maximum(self.views.seen.sum(axis=1), 1))

    @property
    def param_names(self) -> tuple[str, ...]:
        return PARAM_NAMES[self.model]


# ---------------------------------------------------------------------------------------------
# Initialisation (numpy, cv2).


def _equidistant_rays(pixels: np.ndarray, focal: float, centre: np.ndarray) -> np.ndarray:
    m = (pixels - centre) / focal
    theta = np.linalg.norm(m, axis=-1, keepdims=True)
    direction = np.divide(m, theta, out=np.zeros_like(m), where=theta > 0)
    return np.concatenate([direction * np.sin(theta), np.cos(theta)], axis=-1)


def _pose_from_rays(points: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """camera_from_board (R, t) by planar PnP on rays within 80° of the axis; None if too few, or no finite pose."""
    import cv2

    front = rays[:, 2] > math.cos(math.radians(80))
    if front.sum() < 4:
        return None
    normalised = rays[front, :2] / rays[front, 2:]
    ok, rvec, tvec = cv2.solvePnP(points[front], normalised, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):  # IPPE reports NaN poses as found
        return None  # (corners on one line: a board seen edge-on or at the frame's edge)
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3)


def _equidistant_error(points, pixels, rotation, translation, focal, centre) -> np.ndarray:
    p = points @ rotation.T + translation
    r = np.linalg.norm(p[:, :2], axis=1)
    theta = np.arctan2(r, p[:, 2])
    scale = np.divide(theta, r, out=np.ones_like(r), where=r > 0)
    return np.linalg.norm(focal * p[:, :2] * scale[:, None] + centre - pixels, axis=1)


def _initial_guess(views: BoardViews) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Focal length of the equidistant lens whose planar-PnP poses reproject best, those poses, and which views
    have one ``(V,)`` bool: the candidate posing the most views wins, then the smallest median error."""
    centre = np.array([(views.width - 1) / 2, (views.height - 1) / 2])
    half_diagonal = 0.5 * math.hypot(views.width, views.height)
    points = views.board.points
    best = None
    for half_fov_deg in np.arange(25.0, 126.0, 5.0):  # half field of view across the diagonal
        focal = half_diagonal / math.radians(half_fov_deg)
        rotations, translations, posed, score = [], [], [], 0.0
        for v in range(views.num_views):
            m = views.seen[v]
            pose = _pose_from_rays(points[m], _equidistant_rays(views.pixels[v, m], focal, centre))
            posed.append(pose is not None)
            if pose is None:
                continue
            rotations.append(pose[0])
            translations.append(pose[1])
            score += float(np.median(_equidistant_error(points[m], views.pixels[v, m], *pose, focal, centre)))
        key = (-sum(posed), score)
        if rotations and (best is None or key < best[0]):
            best = (key, focal, rotations, translations, np.array(posed))
    if best is None or best[4].sum() < MIN_VIEWS:
        raise ValueError("degenerate views: no board pose could be estimated in enough views (the board must be seen "
                         "in front of the lens, less than 80° off its axis)")
    return best[1], np.stack(best[2]), np.stack(best[3]), best[4]


# ---------------------------------------------------------------------------------------------
# Levenberg–Marquardt with the project's solver.


class _Problem(eqx.Module):
    """What the residuals of one fit need: detections, board points, initial rotations."""

    pixels: jax.Array  # (V, N, 2)
    seen: jax.Array  # (V, N) float 0/1
    points: jax.Array  # (N, 3)
    rotations0: jax.Array  # (V, 3, 3)
    model: str = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)


def _view_residual(pose, params, pixels, seen, rotation0, problem: _Problem):
    """``(2N,)`` projected minus detected pixels of one view (0 where unseen)."""
    camera = camera_from_params(problem.model, params, problem.width, problem.height)
    rotation = SO3.exp(pose[:3]).as_matrix() @ rotation0
    projected, _ = camera.project(problem.points @ rotation.T + pose[3:])
    return ((projected - pixels) * seen[:, None]).reshape(-1)


def _residuals(y, problem: _Problem):
    poses, params = y
    return jax.vmap(_view_residual, in_axes=(0, None, 0, 0, 0, None))(
        poses, params, problem.pixels, problem.seen, problem.rotations0, problem)


def _system(problem: _Problem, y) -> NormalEquations:
    """Block-diagonal (one 6×6 block per view) normal equations bordered by the intrinsics."""
    poses, params = y
    jac = jax.vmap(jax.jacfwd(_view_residual, argnums=(0, 1)), in_axes=(0, None, 0, 0, 0, None))
    j_pose, j_intr = jac(poses, params, problem.pixels, problem.seen, problem.rotations0, problem)
    r = _residuals(y, problem)
    return NormalEquations(
        jnp.einsum("vri,vrj->vij", j_pose, j_pose), (), jnp.einsum("vri,vr->vi", j_pose, r),
        jnp.einsum("vri,vrs->vis", j_pose, j_intr), jnp.einsum("vrs,vru->su", j_intr, j_intr),
        jnp.einsum("vrs,vr->s", j_intr, r))


@partial(jax.jit, static_argnames=("max_steps",))
def _solve(problem: _Problem, y0, max_steps: int):
    y, report = levenberg_marquardt(_residuals, eqx.Partial(_system, problem), y0, problem,
                                    rtol=1e-10, atol=1e-10, max_steps=max_steps)
    return y, report.num_steps


@jax.jit
def _evaluate(problem: _Problem, y):
    return _residuals(y, problem), _system(problem, y)


def _lm(views: BoardViews, model: str, params: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
        max_steps: int = 200):
    """Refine intrinsics and poses (``max_steps=0``: only evaluate them); returns (params, rotations,
    translations, residuals (V, N, 2), std, steps)."""
    problem = _Problem(jnp.asarray(views.pixels), jnp.asarray(views.seen, jnp.float64),
                       jnp.asarray(views.board.points), jnp.asarray(rotations), model, views.width, views.height)
    y = (jnp.concatenate([jnp.zeros((views.num_views, 3)), jnp.asarray(translations)], axis=1), jnp.asarray(params))
    steps = 0
    if max_steps > 0:
        y, steps = _solve(problem, y, max_steps)
    poses, fitted = np.array(y[0]), np.array(y[1])
    if not np.all(np.isfinite(fitted)) or not np.all(np.isfinite(poses)):
        raise FloatingPointError(f"the {model} fit diverged (non-finite parameters)")
    residuals, system = _evaluate(problem, y)
    residuals = np.asarray(residuals).reshape(views.pixels.shape)
    new_rotations = np.asarray(jax.vmap(lambda w, r0: SO3.exp(w).as_matrix() @ r0)(jnp.asarray(poses[:, :3]),
                                                                                   jnp.asarray(rotations)))
    if model == "fov":
        fitted[4] = abs(fitted[4])
    return fitted, new_rotations, poses[:, 3:], residuals, _std(system, residuals, views), int(steps)


def _std(system: NormalEquations, residuals: np.ndarray, views: BoardViews) -> np.ndarray:
    """Standard deviations of the intrinsics: ``sqrt(diag(σ² S⁻¹))``, ``S`` the Schur complement of the poses
    (inf where ``S`` is singular)."""
    schur = np.asarray(static_schur_complement(system))
    count = 2 * int(views.seen.sum())
    unknowns = 6 * views.num_views + schur.shape[0]
    sigma2 = float((residuals**2).sum()) / max(count - unknowns, 1)
    scale = np.sqrt(np.maximum(np.diag(schur), 1e-300))
    normalised = schur / np.outer(scale, scale)
    eig = np.linalg.eigvalsh(normalised)
    if eig[0] <= 1e-14 * eig[-1]:
        return np.full(schur.shape[0], np.inf)
    cov = np.linalg.inv(normalised) / np.outer(scale, scale)
    return np.sqrt(np.maximum(np.diag(cov), 0.0) * sigma2)


def _opencv_fisheye(views: BoardViews, focal: float, rotations: np.ndarray, translations: np.ndarray):
    """``cv2.fisheye.calibrate`` from the equidistant fit; returns (params, rotations, translations) or None."""
    import cv2

    objects = [views.board.points[m].reshape(1, -1, 3) for m in views.seen]
    images = [views.pixels[v, m].reshape(1, -1, 2) for v, m in enumerate(views.seen)]
    k0 = np.array([[focal[0], 0.0, focal[2]], [0.0, focal[1], focal[3]], [0.0, 0.0, 1.0]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW  # OpenCV 5: in cv2
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        _, k, d, rvecs, tvecs = cv2.fisheye.calibrate(objects, images, (views.width, views.height), k0,
                                                      np.zeros((4, 1)), flags=flags, criteria=criteria)
    except cv2.error:
        return None
    params = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2], *np.asarray(d).reshape(4)])
    if not np.all(np.isfinite(params)) or params[0] <= 0 or params[1] <= 0:
        return None
    rot = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    return params, rot, np.stack([np.asarray(t).reshape(3) for t in tvecs])


def _fit(views: BoardViews, model: str, max_steps: int):
    """``(views fitted, params, rotations, translations, residuals, std, steps, method)``: the views without a
    board pose in the initial guess are left out."""
    focal, rotations, translations, posed = _initial_guess(views)
    views = views.subset(posed)
    return (views, *_fit_posed(views, model, max_steps, focal, rotations, translations))


def _fit_posed(views: BoardViews, model: str, max_steps: int, focal: float, rotations, translations):
    centre = [(views.width - 1) / 2, (views.height - 1) / 2]
    eq = _lm(views, "equidistant", np.array([focal, focal, *centre]), rotations, translations, max_steps)
    if model == "equidistant":
        return (*eq, "bcmocap Levenberg-Marquardt")
    if model == "fov":
        omega = 0.5  # close to equidistant over the small angles: f_fov = f_eq ω / (2 tan(ω/2))
        ratio = omega / (2 * math.tan(omega / 2))
        start = np.array([eq[0][0] * ratio, eq[0][1] * ratio, eq[0][2], eq[0][3], omega])
        return (*_lm(views, "fov", start, eq[1], eq[2], max_steps), "bcmocap Levenberg-Marquardt")
    found = _opencv_fisheye(views, eq[0], eq[1], eq[2])
    if found is not None:
        params, rot, trans = found
        # Residuals and covariance with bcmocap's camera at OpenCV's optimum (evaluated, not moved).
        fitted = _lm(views, "opencv_fisheye", params, rot, trans, max_steps=0)
        return (*fitted, "cv2.fisheye.calibrate")
    start = np.array([*eq[0], 0.0, 0.0, 0.0, 0.0])
    return (*_lm(views, "opencv_fisheye", start, eq[1], eq[2], max_steps),
            "bcmocap Levenberg-Marquardt (cv2.fisheye.calibrate failed)")


def calibrate(views: BoardViews, model: str = "fov", *, max_steps: int = 200, reject_outliers: bool = True) -> Calibration:
    """Fit ``model`` to board views (see the module docstring).

    Raises:
        ValueError: too few views, or degenerate views (intrinsics not determined); one line each.
    """
    require_float64("bcmocap calibrate")
    if model not in MODELS:
        raise ValueError(f"--model must be one of {', '.join(MODELS)}, got {model!r}")
    if views.num_views < MIN_VIEWS:
        raise ValueError(f"too few views: the board was found in {views.num_views} of {views.examined} images or "
                         f"frames; at least {MIN_VIEWS} are needed (10-40 spread over the image are better)")
    if model == "thin_prism_fisheye":  # from the Kannala-Brandt calibration, its bad views already left out
        kb = calibrate(views, "opencv_fisheye", max_steps=max_steps, reject_outliers=reject_outliers)
        views, rejected = kb.views, kb.rejected
        start = np.array([*params_of("opencv_fisheye", kb.camera), 0.0, 0.0, 0.0, 0.0])
        params, rotations, translations, residuals, std, steps = _lm(views, model, start, kb.rotations,
                                                                     kb.translations, max_steps)
        method = f"bcmocap Levenberg-Marquardt from {kb.method}"
    else:
        given = views.names
        views, params, rotations, translations, residuals, std, steps, method = _fit(views, model, max_steps)
        posed = set(views.names)
        rejected: tuple[str, ...] = tuple(n for n in given if n not in posed)  # no board pose
        for _ in range(REJECT_ROUNDS if reject_outliers else 0):
            view_rms = np.sqrt((residuals**2).sum(axis=(1, 2)) / np.maximum(views.seen.sum(axis=1), 1))
            bad = view_rms > max(REJECT_FACTOR * float(np.median(view_rms)), REJECT_FLOOR_PX)
            if not bad.any() or (~bad).sum() < MIN_VIEWS:
                break
            rejected += tuple(n for n, b in zip(views.names, bad) if b)
            views, params, rotations, translations, residuals, std, steps, method = _fit(
                views.subset(~bad), model, max_steps)
    camera = camera_from_params(model, params, views.width, views.height)
    focal_scale = float(np.mean(params[:2]))
    if not np.all(np.isfinite(std[:4])) or np.max(std[:4]) > DEGENERATE_FRACTION * focal_scale:
        worst = PARAM_NAMES[model][int(np.argmax(np.where(np.isfinite(std[:4]), std[:4], np.inf)))]
        raise ValueError(f"degenerate views: the {views.num_views} views do not determine the intrinsics ({worst} "
                         f"uncertain by {std[PARAM_NAMES[model].index(worst)]:.3g} px); show the board tilted, at "
                         "several distances and over the whole image")
    return Calibration(model, camera, method, views, rejected, rotations, translations, residuals, std, steps)
