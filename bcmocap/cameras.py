"""Camera models for body-mounted fisheye cameras.

Every model is an equinox Module: arrays (intrinsics) are pytree leaves and the image size is
static, so a batch of ``C`` cameras of one model is the same class with a leading axis ``C`` on every
array leaf (build it with :func:`stack_cameras`, index it with :func:`camera_at`, map over it with
``jax.vmap``). The methods are written for a single camera; points and pixels may carry any leading
shape.

Conventions:
    * Camera frame as OpenCV: x right, y down, z forward (optical axis). Points in any length unit.
    * Pixels as OpenCV: the centre of the top-left pixel is (0, 0), u to the right, v down.
      COLMAP puts that centre at (0.5, 0.5); :func:`bcmocap.io.colmap.to_pycolmap` / ``from_pycolmap`` convert.
    * Angles in radians; ``theta`` is the angle between a ray and the optical axis.

The fisheye models are formulated with ``theta = atan2(r, z)`` instead of normalised ``x / z``, so
they stay correct beyond 90 degrees off-axis. Projection never returns NaN: points outside a model's
valid domain get the principal point, ``valid=False`` and finite (zero) gradients.

Nothing here imports ``cv2`` or ``pycolmap`` (the core never does): the conversions to and from
``pycolmap.Camera`` are in :mod:`bcmocap.io.colmap`, OpenCV calibration files in
:mod:`bcmocap.io.opencv_calibration`.
"""

from __future__ import annotations

import abc
import math
import numbers
from collections.abc import Sequence
from typing import Any, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = [
    "FISHEYE_ANGLE_LIMIT",
    "CameraModel",
    "FOVCamera",
    "OpenCVFisheyeCamera",
    "PinholeCamera",
    "ThinPrismFisheyeCamera",
    "TiltedThinPrismFisheyeCamera",
    "stack_cameras",
    "camera_at",
    "single_camera_intrinsics",
]

# Largest angle off the optical axis accepted by the fisheye models. They are defined up to (not
# including) pi, but the ray straight behind the camera projects to a whole circle, so stay away.
FISHEYE_ANGLE_LIMIT = math.radians(179.0)
# A pinhole camera accepts points with z >= sin(PINHOLE_MARGIN) * |p|, i.e. theta <= pi/2 - margin.
PINHOLE_MARGIN = 1e-6
# Below this |omega| a FOV camera is treated as its pinhole limit (front hemisphere only): as omega
# goes to 0 the image of the back hemisphere is pushed out to radius ~ pi / omega.
FOV_PINHOLE_OMEGA = 1e-3
# Squared norm below which a point counts as the camera centre.
_MIN_NORM2 = 1e-200
# Series expansions replace the closed forms when their small parameter squared is below this.
_SERIES_EPS = 1e-4
# Kannala-Brandt: grid and Newton steps for the valid angle; table size and Newton steps for the
# inverse of theta -> theta_d. All unrolled (no while loops): fixed cost, jit/vmap/jacfwd friendly.
_KB_GRID = 1024
_KB_ROOT_STEPS = 6
_KB_TABLE = 64
_KB_NEWTON_STEPS = 8


def _float_array(x: Any) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _int_size(x: Any) -> Any:
    # Validated (with the field name) in CameraModel.__check_init__.
    if isinstance(x, numbers.Integral) and not isinstance(x, bool):
        return int(x)
    return x


def _concrete(x: Array) -> np.ndarray | None:
    """Value of ``x`` as numpy, or None while tracing."""
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def _check_shape(cls: str, name: str, x: Array, trailing: tuple[int, ...], what: str) -> None:
    if x.ndim < len(trailing) or tuple(x.shape[x.ndim - len(trailing) :]) != trailing:
        want = "(..., " + ", ".join(map(str, trailing)) + ")" if trailing else "(...)"
        raise ValueError(f"{cls}.{name} must have shape {want} ({what}); got shape {tuple(x.shape)}")


def _check_batch(cls: str, fields: dict[str, tuple[Array, int]]) -> None:
    """All array fields must share one leading batch shape."""
    shapes = {n: tuple(a.shape[: a.ndim - k]) for n, (a, k) in fields.items()}
    if len(set(shapes.values())) > 1:
        listing = ", ".join(f"{n} {tuple(a.shape)}" for n, (a, _) in fields.items())
        raise ValueError(f"{cls}: array fields have different leading (batch) shapes: {listing}")


def _check_finite_positive(cls: str, name: str, x: Array, positive: bool) -> None:
    v = _concrete(x)
    if v is None:
        return
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{cls}.{name} must be finite; got {v.tolist()}")
    if positive and not np.all(v > 0):
        raise ValueError(f"{cls}.{name} must be positive (pixels); got {v.tolist()}")


# ---------------------------------------------------------------------------------------------
# Safe scalar helpers (double-where: the unused branch is fed harmless inputs, so neither its
# value nor its derivative can be NaN/inf).


def _atan2_over_y(y2: Array, z: Array) -> Array:
    """``atan2(y, z) / y`` for ``y = sqrt(y2) >= 0``, smooth in ``y2`` at 0 when ``z > 0``.

    Callers guarantee ``y2 > 0`` or ``z > 0``.
    """
    series = (z > 0) & (y2 < _SERIES_EPS * z * z)
    zs = jnp.where(series, z, 1.0)
    t2 = y2 / (zs * zs)
    # atan(t) / t = 1 - t^2/3 + t^4/5 - ...; remainder < t^10/11 < 1e-21 here.
    f_series = (1.0 + t2 * (-1.0 / 3 + t2 * (1.0 / 5 + t2 * (-1.0 / 7 + t2 / 9)))) / zs
    y = jnp.sqrt(jnp.where(series | (y2 <= 0), 1.0, y2))
    f_general = jnp.arctan2(y, z) / y
    return jnp.where(series, f_series, f_general)


def _sinc_cos(x2: Array) -> tuple[Array, Array]:
    """``(sin(x) / x, cos(x))`` for ``x = sqrt(x2) >= 0``, smooth in ``x2`` at 0."""
    series = x2 < _SERIES_EPS
    sinc_s = 1.0 + x2 * (-1.0 / 6 + x2 * (1.0 / 120 + x2 * (-1.0 / 5040 + x2 / 362880)))
    cos_s = 1.0 + x2 * (-1.0 / 2 + x2 * (1.0 / 24 + x2 * (-1.0 / 720 + x2 / 40320)))
    x = jnp.sqrt(jnp.where(series, 1.0, x2))
    return jnp.where(series, sinc_s, jnp.sin(x) / x), jnp.where(series, cos_s, jnp.cos(x))


def _safe_sqrt(x: Array) -> Array:
    """sqrt with a zero (not infinite) derivative at 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _normalize(v: Array) -> Array:
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > _MIN_NORM2
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.array([0.0, 0.0, 1.0]))


# ---------------------------------------------------------------------------------------------


class CameraModel(eqx.Module):
    """Abstract camera model: intrinsics as array leaves, image size as static ints.

    Attributes:
        width: Image width in pixels (static).
        height: Image height in pixels (static).
    """

    width: int = eqx.field(static=True, converter=_int_size)
    height: int = eqx.field(static=True, converter=_int_size)

    def __check_init__(self) -> None:
        cls = type(self).__name__
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"{cls}.{name} must be a positive integer (pixels); got {v!r}")

    # -- model-specific part ------------------------------------------------------------------

    @property
    @abc.abstractmethod
    def max_angle(self) -> Array:
        """Half field of view (rad): project is valid and invertible for ``theta <= max_angle``.

        Shape ``()`` for a single camera (the batch shape for a batched one).
        """

    @abc.abstractmethod
    def _project_normalized(self, points_cam: Array) -> Array:
        """Offsets ``(pixel - principal_point) / focal``, shape (..., 2), for valid points only."""

    @abc.abstractmethod
    def _unproject_normalized(self, m: Array) -> Array:
        """Unit rays (..., 3) from ``m = (pixel - principal_point) / focal``, shape (..., 2)."""

    # -- shared -------------------------------------------------------------------------------

    focal: eqx.AbstractVar[Array]
    principal_point: eqx.AbstractVar[Array]

    def project(self, points_cam: Array) -> tuple[Array, Array]:
        """Project points in the camera frame to pixels.

        Args:
            points_cam: (..., 3) points in the camera frame (any length unit).

        Returns:
            ``(pixels, valid)``: (..., 2) pixel coordinates (OpenCV convention) and a (...) bool
            mask. A point at the camera centre, non-finite, or more than :attr:`max_angle` off the
            optical axis is invalid: its pixel is the principal point and its gradients are zero.
        """
        p = jnp.asarray(points_cam, dtype=jnp.result_type(float))
        if p.shape[-1:] != (3,):
            raise ValueError(f"project: points_cam must have shape (..., 3); got {p.shape}")
        return _project(self, p)

    def unproject(self, pixels: Array) -> Array:
        """Bearing vectors of pixels.

        Args:
            pixels: (..., 2) pixel coordinates (OpenCV convention).

        Returns:
            (..., 3) unit rays in the camera frame. Pixels beyond the image of :attr:`max_angle`
            are clamped to that boundary (their ray is at ``max_angle`` off-axis).
        """
        uv = jnp.asarray(pixels, dtype=jnp.result_type(float))
        if uv.shape[-1:] != (2,):
            raise ValueError(f"unproject: pixels must have shape (..., 2); got {uv.shape}")
        return _unproject(self, uv)

    def in_image(self, pixels: Array) -> Array:
        """(...) bool mask: pixel (..., 2) lies in [-0.5, width-0.5] x [-0.5, height-0.5]."""
        uv = jnp.asarray(pixels)
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape of the intrinsics (``()`` for a single camera)."""
        return tuple(self.focal.shape[:-1])


# Compiled once per camera class, image size and input shape, so that eager calls (outside any
# user jit) are fast; inside a user's jit/vmap/grad these simply inline.
@jax.jit
def _project(cam: CameraModel, p: Array) -> tuple[Array, Array]:
    n2 = jnp.sum(p * p, axis=-1)
    nonzero = n2 > _MIN_NORM2
    norm = jnp.sqrt(jnp.where(nonzero, n2, 1.0))
    cos_max = jnp.cos(jax.lax.stop_gradient(cam.max_angle))
    valid = nonzero & (p[..., 2] >= cos_max * norm) & jnp.all(jnp.isfinite(p), axis=-1)
    # Double-where: invalid points are replaced by the optical axis before any arithmetic, so
    # neither their values nor their derivatives can be NaN or inf.
    p_safe = jnp.where(valid[..., None], p, jnp.array([0.0, 0.0, 1.0]))
    uv = cam.focal * cam._project_normalized(p_safe) + cam.principal_point
    return jnp.where(valid[..., None], uv, cam.principal_point), valid


@jax.jit
def _unproject(cam: CameraModel, uv: Array) -> Array:
    return cam._unproject_normalized((uv - cam.principal_point) / cam.focal)


def _check_common(self: CameraModel) -> None:
    cls = type(self).__name__
    _check_shape(cls, "focal", self.focal, (2,), "fx, fy in pixels")
    _check_shape(cls, "principal_point", self.principal_point, (2,), "cx, cy in pixels")
    _check_finite_positive(cls, "focal", self.focal, positive=True)
    _check_finite_positive(cls, "principal_point", self.principal_point, positive=False)


class PinholeCamera(CameraModel):
    """Undistorted perspective camera: ``pixel = focal * (x, y) / z + principal_point``.

    Valid for points with ``z >= sin(PINHOLE_MARGIN) * |p|`` (in front of the camera).

    Attributes:
        focal: (..., 2) focal lengths (fx, fy) in pixels.
        principal_point: (..., 2) principal point (cx, cy) in pixels, OpenCV convention.
    """

    focal: Array = eqx.field(converter=_float_array)
    principal_point: Array = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        _check_common(self)
        _check_batch(
            type(self).__name__, {"focal": (self.focal, 1), "principal_point": (self.principal_point, 1)}
        )

    @property
    def max_angle(self) -> Array:
        """``pi/2 - PINHOLE_MARGIN``: only points in front of the camera project."""
        return jnp.full(self.focal.shape[:-1], 0.5 * math.pi - PINHOLE_MARGIN)

    def _project_normalized(self, p: Array) -> Array:
        return p[..., :2] / p[..., 2:3]

    def _unproject_normalized(self, m: Array) -> Array:
        return _normalize(jnp.concatenate([m, jnp.ones_like(m[..., :1])], axis=-1))


class FOVCamera(CameraModel):
    """Devernay-Faugeras field-of-view fisheye model (COLMAP "FOV").

    With ``theta`` the angle off the optical axis, the normalised image radius is
    ``r_d = atan(2 tan(theta) tan(omega / 2)) / omega``, evaluated as
    ``atan2(2 tan(omega / 2) sin(theta), cos(theta)) / omega`` so that it holds for theta >= 90 deg;
    ``pixel = focal * r_d * (x, y) / r + principal_point`` with ``r = sqrt(x^2 + y^2)``.
    ``omega -> 0`` is the pinhole limit.

    Attributes:
        focal: (..., 2) focal lengths (fx, fy) in pixels.
        principal_point: (..., 2) principal point (cx, cy) in pixels, OpenCV convention.
        omega: (...) distortion parameter in radians, ``0 <= omega < pi``.
    """

    focal: Array = eqx.field(converter=_float_array)
    principal_point: Array = eqx.field(converter=_float_array)
    omega: Array = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        cls = type(self).__name__
        _check_common(self)
        _check_batch(
            cls,
            {
                "focal": (self.focal, 1),
                "principal_point": (self.principal_point, 1),
                "omega": (self.omega, 0),
            },
        )
        v = _concrete(self.omega)
        if v is not None and not (np.all(np.isfinite(v)) and np.all(v >= 0) and np.all(v < math.pi)):
            raise ValueError(f"{cls}.omega must be finite and in [0, pi) radians; got {v.tolist()}")

    @property
    def max_angle(self) -> Array:
        """``FISHEYE_ANGLE_LIMIT`` (179 deg); just under 90 deg in the pinhole limit ``omega < 1e-3``.

        The model is a bijection from directions with ``theta < pi`` onto a disc of radius
        ``pi / omega`` (normalised), so only the ray straight behind the camera is excluded.
        """
        return jnp.where(
            jnp.abs(self.omega) < FOV_PINHOLE_OMEGA, 0.5 * math.pi - PINHOLE_MARGIN, FISHEYE_ANGLE_LIMIT
        )

    def _tan_ratio(self) -> tuple[Array, Array]:
        """``(g, a^2)`` with ``a = 2 tan(omega / 2)`` and ``g = a / omega`` (-> 1 as omega -> 0)."""
        w = self.omega
        small = jnp.abs(w) < 1e-2
        x2 = 0.25 * w * w
        # tan(x) / x series; remainder ~ 0.02 x^8 < 1e-20.
        g_series = 1.0 + x2 * (1.0 / 3 + x2 * (2.0 / 15 + x2 * 17.0 / 315))
        ws = jnp.where(small, 1.0, w)
        g = jnp.where(small, g_series, 2.0 * jnp.tan(0.5 * ws) / ws)
        return g, (g * w) ** 2

    def _project_normalized(self, p: Array) -> Array:
        g, a2 = self._tan_ratio()
        r2 = p[..., 0] ** 2 + p[..., 1] ** 2
        # r_d / r = (a / omega) * atan2(a r, z) / (a r): no division by r, smooth on the axis.
        s = g * _atan2_over_y(a2 * r2, p[..., 2])
        return p[..., :2] * s[..., None]

    def _unproject_normalized(self, m: Array) -> Array:
        g, a2 = self._tan_ratio()
        # Image radius of the max_angle ray: pixels further out are clamped to it.
        th = self.max_angle
        sin_t, cos_t = jnp.sin(th), jnp.cos(th)
        rd_max = g * _atan2_over_y(a2 * sin_t**2, cos_t) * sin_t
        q = jnp.sum(m * m, axis=-1)
        clamp = q > rd_max**2
        scale = jnp.where(clamp, rd_max / jnp.sqrt(jnp.where(clamp, q, 1.0)), 1.0)
        rho2 = self.omega**2 * jnp.where(clamp, rd_max**2, q)
        # tan(theta) = tan(rho) / a, so the ray is parallel to (m sin(rho) / r_d, a cos(rho)),
        # i.e. to (m sinc(rho), (a / omega) cos(rho)); this is (m, 1) in the pinhole limit.
        sinc, cos = _sinc_cos(rho2)
        ray = jnp.concatenate([m * (scale * sinc)[..., None], (g * cos)[..., None]], axis=-1)
        return _normalize(ray)


def _kb_poly(k: Array, t2: Array) -> Array:
    """``1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8``."""
    k1, k2, k3, k4 = (k[..., i] for i in range(4))
    return 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))


def _kb_dpoly(k: Array, t2: Array) -> Array:
    """d/dtheta of ``theta * poly(theta^2)``: ``1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8``."""
    k1, k2, k3, k4 = (k[..., i] for i in range(4))
    return 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))


def _kb_ddpoly(k: Array, t: Array) -> Array:
    """Second derivative of ``theta * poly(theta^2)``."""
    k1, k2, k3, k4 = (k[..., i] for i in range(4))
    t2 = t * t
    return t * (6 * k1 + t2 * (20 * k2 + t2 * (42 * k3 + t2 * 72 * k4)))


@jax.jit
def _kb_max_angle_single(k: Array) -> Array:
    """First angle in (0, FISHEYE_ANGLE_LIMIT] where ``d theta_d / d theta`` stops being positive."""
    grid = jnp.linspace(0.0, FISHEYE_ANGLE_LIMIT, _KB_GRID + 1)
    d = _kb_dpoly(k, grid * grid)
    bad = d <= 0
    i = jnp.maximum(jnp.argmax(bad), 1)  # d(0) = 1 > 0, so a sign change lies in (grid[i-1], grid[i]]
    lo, hi, d_lo, d_hi = grid[i - 1], grid[i], d[i - 1], d[i]
    # Linear interpolation, then Newton on d(theta) = 0 kept inside the bracket (unrolled: no loop).
    t = lo + (hi - lo) * d_lo / jnp.where(d_lo > d_hi, d_lo - d_hi, 1.0)
    for _ in range(_KB_ROOT_STEPS):
        dd = _kb_ddpoly(k, t)
        t = jnp.clip(t - _kb_dpoly(k, t * t) / jnp.where(dd < 0, dd, -1.0), lo, hi)
    # Step back onto the side where the derivative is still positive.
    t = jnp.where(_kb_dpoly(k, t * t) > 0, t, jnp.nextafter(t, lo))
    return jnp.where(jnp.any(bad), t, FISHEYE_ANGLE_LIMIT)


class OpenCVFisheyeCamera(CameraModel):
    """Kannala-Brandt equidistant fisheye model (``cv2.fisheye``, COLMAP "OPENCV_FISHEYE").

    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` with
    ``theta = atan2(r, z)``; ``pixel = focal * theta_d * (x, y) / r + principal_point``. Valid up to
    the first angle where ``theta_d`` stops increasing (at most ``FISHEYE_ANGLE_LIMIT``). OpenCV's
    skew ``alpha`` (``K[0, 1] = alpha * fx``; zero when calibrated with
    ``cv2.fisheye.CALIB_FIX_SKEW``) is not supported.

    Attributes:
        focal: (..., 2) focal lengths (fx, fy) in pixels.
        principal_point: (..., 2) principal point (cx, cy) in pixels, OpenCV convention.
        distortion: (..., 4) coefficients (k1, k2, k3, k4), dimensionless.
    """

    focal: Array = eqx.field(converter=_float_array)
    principal_point: Array = eqx.field(converter=_float_array)
    distortion: Array = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        cls = type(self).__name__
        _check_common(self)
        _check_shape(cls, "distortion", self.distortion, (4,), "k1, k2, k3, k4")
        _check_batch(
            cls,
            {
                "focal": (self.focal, 1),
                "principal_point": (self.principal_point, 1),
                "distortion": (self.distortion, 1),
            },
        )
        _check_finite_positive(cls, "distortion", self.distortion, positive=False)

    @property
    def max_angle(self) -> Array:
        """First angle where ``theta_d(theta)`` stops increasing, at most ``FISHEYE_ANGLE_LIMIT``."""
        k = jax.lax.stop_gradient(self.distortion)
        return jnp.vectorize(_kb_max_angle_single, signature="(4)->()")(k)

    def _project_normalized(self, p: Array) -> Array:
        k = self.distortion
        r2 = p[..., 0] ** 2 + p[..., 1] ** 2
        theta_over_r = _atan2_over_y(r2, p[..., 2])
        theta2 = r2 * theta_over_r**2
        s = theta_over_r * _kb_poly(k, theta2)
        return p[..., :2] * s[..., None]

    def _unproject_normalized(self, m: Array) -> Array:
        k = self.distortion
        th_max = self.max_angle
        q = jnp.sum(m * m, axis=-1)
        theta_d_max = th_max * _kb_poly(k, th_max**2)
        theta_d = jnp.minimum(_safe_sqrt(q), theta_d_max)

        # Initial guess by interpolating a table of theta_d over [0, max_angle], where theta_d is
        # increasing; then Newton steps kept inside the table cell, all without gradients.
        ks, td, t_max = (jax.lax.stop_gradient(x) for x in (k, theta_d, th_max))
        grid = jnp.linspace(0.0, 1.0, _KB_TABLE + 1) * t_max
        table = grid * _kb_poly(ks, grid * grid)
        i = jnp.clip(jnp.sum(table < td[..., None], axis=-1), 1, _KB_TABLE)
        lo, hi, f_lo, f_hi = grid[i - 1], grid[i], table[i - 1], table[i]
        t = lo + (hi - lo) * (td - f_lo) / jnp.where(f_hi > f_lo, f_hi - f_lo, 1.0)
        for _ in range(_KB_NEWTON_STEPS):
            d = _kb_dpoly(ks, t * t)
            t = jnp.clip(t - (t * _kb_poly(ks, t * t) - td) / jnp.where(d > 0, d, 1.0), lo, hi)
        # Value t; derivative -(d residual) / (d residual / d theta) (implicit function theorem).
        d = _kb_dpoly(k, t * t)
        step = (t * _kb_poly(k, t * t) - theta_d) / jnp.where(d > 0, d, 1.0)
        theta = jnp.where(q > theta_d_max**2, t, t - (step - jax.lax.stop_gradient(step)))

        theta2 = theta * theta
        sinc, cos = _sinc_cos(theta2)
        # |m| sin(theta) / theta_d = |m| sinc(theta) / poly(theta^2); m / theta_d is the azimuth.
        poly = _kb_poly(k, theta2)
        clamp_scale = jnp.where(
            q > theta_d_max**2, theta_d_max / jnp.sqrt(jnp.where(q > theta_d_max**2, q, 1.0)), 1.0
        )
        xy = m * (clamp_scale * sinc / poly)[..., None]
        return _normalize(jnp.concatenate([xy, cos[..., None]], axis=-1))


def _kb_radial_inverse(k: Array, theta_d: Array, t_max: Array) -> tuple[Array, Array]:
    """``(theta, beyond)``: the angle in ``[0, t_max]`` whose ``theta * poly(theta^2)`` is ``theta_d`` (...), and where
    ``theta_d`` lies beyond the image of ``t_max`` (then ``theta = t_max``). A table over ``[0, t_max]``
    interpolated, then Newton steps kept inside its cell; no gradients (callers add them)."""
    grid = jnp.linspace(0.0, 1.0, _KB_TABLE + 1) * t_max
    table = grid * _kb_poly(k, grid * grid)
    td = jnp.minimum(theta_d, table[-1])
    i = jnp.clip(jnp.sum(table < td[..., None], axis=-1), 1, _KB_TABLE)
    lo, hi, f_lo, f_hi = grid[i - 1], grid[i], table[i - 1], table[i]
    t = lo + (hi - lo) * (td - f_lo) / jnp.where(f_hi > f_lo, f_hi - f_lo, 1.0)
    for _ in range(_KB_NEWTON_STEPS):
        d = _kb_dpoly(k, t * t)
        t = jnp.clip(t - (t * _kb_poly(k, t * t) - td) / jnp.where(d > 0, d, 1.0), lo, hi)
    return t, theta_d > table[-1]


def _prism_slope(ps: Array) -> Array:
    """``c`` with every entry of the Jacobian of the decentering and thin-prism terms at most ``c * theta``."""
    p1, p2, s1, s2 = (jnp.abs(ps[..., i]) for i in range(4))
    return 6.0 * (p1 + p2) + 2.0 * (s1 + s2)


@jax.jit
def _thin_prism_max_angle_single(k: Array, ps: Array) -> Array:
    """:attr:`ThinPrismFisheyeCamera.max_angle` of one camera: ``k`` (4,) radial, ``ps`` (4,) ``(p1, p2, sx1, sy1)``.

    The radial map ``w -> w poly(|w|^2)`` on the disc ``|w| <= t`` is the gradient of a convex function whose
    Hessian has the eigenvalues ``poly`` and ``d theta_d / d theta``; the decentering and thin-prism terms change
    by at most ``2 c t |dw|`` (Frobenius bound). Where the smallest eigenvalue over the disc exceeds ``2 c t`` the
    whole map is strongly monotone there, hence one-to-one and invertible by Newton steps.
    """
    kb = _kb_max_angle_single(k)
    c = _prism_slope(ps)
    grid = jnp.linspace(0.0, FISHEYE_ANGLE_LIMIT, _KB_GRID + 1)
    t2 = grid * grid
    smallest = jax.lax.cummin(jnp.minimum(_kb_dpoly(k, t2), _kb_poly(k, t2)))
    bad = smallest <= 2.0 * c * grid
    last_good = grid[jnp.maximum(jnp.argmax(bad), 1) - 1]
    limit = jnp.where(jnp.any(bad), last_good, FISHEYE_ANGLE_LIMIT)
    return jnp.where(c > 0, jnp.minimum(kb, limit), kb)


#: The thin-prism fisheye's distortion fields: name -> (length, what it holds).
_THIN_PRISM_FIELDS = {"distortion": (4, "k1, k2, k3, k4"), "tangential": (2, "p1, p2"), "thin_prism": (2, "sx1, sy1")}


def _check_thin_prism_fields(camera: CameraModel, fields: dict[str, tuple[int, str]]) -> None:
    """Focal length and principal point, then each of ``fields`` (name -> (length, what)): shape, finite, one batch."""
    cls = type(camera).__name__
    _check_common(camera)
    for name, (length, what) in fields.items():
        _check_shape(cls, name, getattr(camera, name), (length,), what)
    _check_batch(cls, {name: (getattr(camera, name), 1) for name in ("focal", "principal_point", *fields)})
    for name in fields:
        _check_finite_positive(cls, name, getattr(camera, name), positive=False)


class ThinPrismFisheyeCamera(CameraModel):
    """Kannala-Brandt fisheye with decentering and thin-prism distortion (COLMAP "THIN_PRISM_FISHEYE").

    With ``theta = atan2(r, z)`` and the equidistant coordinates ``(u, v) = theta (x, y) / r`` (so
    ``u^2 + v^2 = theta^2``), the normalised image point is

        ``(u, v) (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``                    (radial)
        ``+ (2 p1 u v + p2 (theta^2 + 2 u^2), p1 (theta^2 + 2 v^2) + 2 p2 u v)``                (decentering)
        ``+ (sx1, sy1) theta^2``                                                          (thin prism)

    and ``pixel = focal * that + principal_point``. As in COLMAP's ``ThinPrismFisheyeCameraModel``, the
    decentering and thin-prism terms act on the equidistant coordinates, not on the radially distorted ones;
    COLMAP's ``theta = atan(r / z)`` holds in front of the camera only, ``atan2`` here also beyond 90 degrees.
    With ``p = s = 0`` this is :class:`OpenCVFisheyeCamera` (the same formula and max angle).

    Unprojection is a Newton solve in the equidistant plane (fixed steps, jit/vmap/grad friendly; derivatives
    by the implicit function theorem), started from the radial inverse.

    Attributes:
        focal: (..., 2) focal lengths (fx, fy) in pixels.
        principal_point: (..., 2) principal point (cx, cy) in pixels, OpenCV convention.
        distortion: (..., 4) radial coefficients (k1, k2, k3, k4), dimensionless.
        tangential: (..., 2) decentering coefficients (p1, p2), dimensionless.
        thin_prism: (..., 2) thin-prism coefficients (sx1, sy1), dimensionless.
    """

    focal: Array = eqx.field(converter=_float_array)
    principal_point: Array = eqx.field(converter=_float_array)
    distortion: Array = eqx.field(converter=_float_array)
    tangential: Array = eqx.field(converter=_float_array)
    thin_prism: Array = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        _check_thin_prism_fields(self, _THIN_PRISM_FIELDS)

    @property
    def max_angle(self) -> Array:
        """Largest angle (rad, at most ``FISHEYE_ANGLE_LIMIT``) up to which projection is one-to-one.

        The Kannala-Brandt limit (where ``theta_d`` stops increasing) with ``p = s = 0``; otherwise the largest
        angle (on a 0.17 degree grid) where the radial map's smallest stretch still exceeds twice a bound of how
        much the decentering and thin-prism terms can stretch (a sufficient condition; just below the radial
        limit for the small terms of real lenses).
        """
        k, ps = (jax.lax.stop_gradient(x) for x in (self.distortion, self._prism_coefficients()))
        return jnp.vectorize(_thin_prism_max_angle_single, signature="(4),(4)->()")(k, ps)

    def _prism_coefficients(self) -> Array:
        """(..., 4) ``(p1, p2, sx1, sy1)``."""
        return jnp.concatenate([self.tangential, self.thin_prism], axis=-1)

    def _decentering(self, w: Array, theta2: Array, ps: Array) -> Array:
        """(..., 2) decentering plus thin-prism terms at equidistant coordinates ``w`` (..., 2), ``theta2 = |w|^2``."""
        p1, p2, sx, sy = (ps[..., i] for i in range(4))
        u, v = w[..., 0], w[..., 1]
        du = 2.0 * p1 * u * v + p2 * (theta2 + 2.0 * u * u) + sx * theta2
        dv = 2.0 * p2 * u * v + p1 * (theta2 + 2.0 * v * v) + sy * theta2
        return jnp.stack([du, dv], axis=-1)

    def _distort(self, w: Array, k: Array, ps: Array) -> tuple[Array, Array]:
        """Normalised image points (..., 2) of equidistant coordinates ``w`` (..., 2) and their (..., 2, 2) Jacobian."""
        u, v = w[..., 0], w[..., 1]
        t2 = u * u + v * v
        poly = _kb_poly(k, t2)
        k1, k2, k3, k4 = (k[..., i] for i in range(4))
        dpoly_dt2 = k1 + t2 * (2.0 * k2 + t2 * (3.0 * k3 + t2 * 4.0 * k4))
        p1, p2, sx, sy = (ps[..., i] for i in range(4))
        # Radial part: poly I + 2 poly'(t2) w w^T; decentering and thin prism: the derivatives of _decentering.
        j00 = poly + 2.0 * dpoly_dt2 * u * u + 2.0 * p1 * v + 6.0 * p2 * u + 2.0 * sx * u
        j01 = 2.0 * dpoly_dt2 * u * v + 2.0 * p1 * u + 2.0 * p2 * v + 2.0 * sx * v
        j10 = 2.0 * dpoly_dt2 * u * v + 2.0 * p2 * v + 2.0 * p1 * u + 2.0 * sy * u
        j11 = poly + 2.0 * dpoly_dt2 * v * v + 2.0 * p2 * u + 6.0 * p1 * v + 2.0 * sy * v
        jac = jnp.stack([jnp.stack([j00, j01], axis=-1), jnp.stack([j10, j11], axis=-1)], axis=-2)
        return w * poly[..., None] + self._decentering(w, t2, ps), jac

    def _project_normalized(self, p: Array) -> Array:
        k = self.distortion
        r2 = p[..., 0] ** 2 + p[..., 1] ** 2
        theta_over_r = _atan2_over_y(r2, p[..., 2])
        theta2 = r2 * theta_over_r**2
        s = theta_over_r * _kb_poly(k, theta2)
        w = p[..., :2] * theta_over_r[..., None]
        return p[..., :2] * s[..., None] + self._decentering(w, theta2, self._prism_coefficients())

    def _unproject_normalized(self, m: Array) -> Array:
        th_max = self.max_angle
        k, ps = self.distortion, self._prism_coefficients()
        ks, pss, ms = (jax.lax.stop_gradient(x) for x in (k, ps, m))

        # Start: the radial inverse of |m| along m (as OpenCVFisheyeCamera's, exact without decentering).
        rho = _safe_sqrt(jnp.sum(ms * ms, axis=-1))
        theta, outside = _kb_radial_inverse(ks, rho, th_max)
        w = ms * (theta / jnp.where(rho > 0, rho, 1.0))[..., None]
        # Newton steps on distort(w) = m (all without gradients), each kept inside the disc |w| <= max_angle, so
        # that pixels beyond the image of the disc end on its rim (their ray at max_angle off-axis). A step that
        # does not lower the residual is not taken and the next try is half as long (near a fold of the radial
        # profile, where the Jacobian is nearly singular).
        def inside_disc(v):
            norm = _safe_sqrt(jnp.sum(v * v, axis=-1))
            beyond = norm > th_max
            return v * jnp.where(beyond, th_max / jnp.where(beyond, norm, 1.0), 1.0)[..., None], beyond

        value, jac = self._distort(w, ks, pss)
        residual = value - ms
        length = jnp.ones(ms.shape[:-1])
        for _ in range(_KB_NEWTON_STEPS):
            trial, beyond = inside_disc(w - length[..., None] * _solve_2x2(jac, residual))
            trial_value, trial_jac = self._distort(trial, ks, pss)
            trial_residual = trial_value - ms
            better = jnp.sum(trial_residual**2, axis=-1) < jnp.sum(residual**2, axis=-1)
            w = jnp.where(better[..., None], trial, w)
            residual = jnp.where(better[..., None], trial_residual, residual)
            jac = jnp.where(better[..., None, None], trial_jac, jac)
            outside = jnp.where(better, beyond, outside)
            length = jnp.where(better, 1.0, 0.5 * length)
        # Value w; derivative by the implicit function theorem (the rim's rays keep none).
        value, _ = self._distort(w, k, ps)
        step = _solve_2x2(jac, value - m)
        w = jnp.where(outside[..., None], w, w - (step - jax.lax.stop_gradient(step)))

        sinc, cos = _sinc_cos(jnp.sum(w * w, axis=-1))
        return _normalize(jnp.concatenate([w * sinc[..., None], cos[..., None]], axis=-1))


def _tilt_matrix(tilt: Array) -> Array:
    """(..., 3, 3) OpenCV's ``computeTiltProjectionMatrix(tau_x, tau_y)`` for ``tilt`` (..., 2) rad: the sensor turned
    by ``tau_x`` about x, then ``tau_y`` about y, and the image projected onto it along the optical axis."""
    cx, sx = jnp.cos(tilt[..., 0]), jnp.sin(tilt[..., 0])
    cy, sy = jnp.cos(tilt[..., 1]), jnp.sin(tilt[..., 1])
    zero, one = jnp.zeros_like(cx), jnp.ones_like(cx)
    rot_x = jnp.stack([jnp.stack([one, zero, zero], -1), jnp.stack([zero, cx, sx], -1),
                       jnp.stack([zero, -sx, cx], -1)], -2)
    rot_y = jnp.stack([jnp.stack([cy, zero, -sy], -1), jnp.stack([zero, one, zero], -1),
                       jnp.stack([sy, zero, cy], -1)], -2)
    rot = rot_y @ rot_x
    project_z = jnp.stack([jnp.stack([rot[..., 2, 2], zero, -rot[..., 0, 2]], -1),
                           jnp.stack([zero, rot[..., 2, 2], -rot[..., 1, 2]], -1),
                           jnp.stack([zero, zero, one], -1)], -2)
    return project_z @ rot


def _apply_homography(h: Array, m: Array) -> Array:
    """(..., 2) the points ``m`` (..., 2) mapped by the (..., 3, 3) homographies ``h``."""
    v = jnp.einsum("...ij,...j->...i", h, jnp.concatenate([m, jnp.ones_like(m[..., :1])], axis=-1))
    return v[..., :2] / v[..., 2:]


class TiltedThinPrismFisheyeCamera(CameraModel):
    """A :class:`ThinPrismFisheyeCamera` lens in front of a slightly tilted sensor: the studio's manufactured lens
    units (:mod:`bcmocap.sim.lens_units`), a model that no calibration family here contains.

    The lens maps a ray to the normalised image point ``m`` as :class:`ThinPrismFisheyeCamera` does; the sensor,
    turned by ``tau_x`` about x and then ``tau_y`` about y, records it at ``H(tau) (m, 1)`` (dehomogenised), ``H`` as
    OpenCV's tilted sensor model builds it (``cv::computeTiltProjectionMatrix``, ``CALIB_TILTED_MODEL``, applied as
    there after the distortion); ``pixel = focal * that + principal_point``. With ``tau = 0`` this is the thin-prism
    fisheye. Its first-order effect is of the thin-prism and decentering form, but it acts on the distorted point
    where those act on the equidistant one, so a thin-prism calibration absorbs most of it, not all. Unprojection
    inverts ``H`` exactly, then the lens; the largest valid angle is the lens's.

    Attributes:
        focal, principal_point, distortion, tangential, thin_prism: as :class:`ThinPrismFisheyeCamera`.
        tilt: (..., 2) the sensor's tilt ``(tau_x, tau_y)`` (rad).
    """

    focal: Array = eqx.field(converter=_float_array)
    principal_point: Array = eqx.field(converter=_float_array)
    distortion: Array = eqx.field(converter=_float_array)
    tangential: Array = eqx.field(converter=_float_array)
    thin_prism: Array = eqx.field(converter=_float_array)
    tilt: Array = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        _check_thin_prism_fields(self, {**_THIN_PRISM_FIELDS, "tilt": (2, "tau_x, tau_y in rad")})

    @property
    def lens(self) -> ThinPrismFisheyeCamera:
        """The lens alone (the sensor untilted)."""
        return ThinPrismFisheyeCamera(self.width, self.height, focal=self.focal, principal_point=self.principal_point,
                                      distortion=self.distortion, tangential=self.tangential,
                                      thin_prism=self.thin_prism)

    @property
    def max_angle(self) -> Array:
        """The lens's largest valid angle (rad)."""
        return self.lens.max_angle

    def _project_normalized(self, p: Array) -> Array:
        return _apply_homography(_tilt_matrix(self.tilt), self.lens._project_normalized(p))

    def _unproject_normalized(self, m: Array) -> Array:
        return self.lens._unproject_normalized(_apply_homography(jnp.linalg.inv(_tilt_matrix(self.tilt)), m))


def _solve_2x2(a: Array, b: Array) -> Array:
    """``a^-1 b`` for (..., 2, 2) ``a`` and (..., 2) ``b``; zero where ``a`` is singular."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    ok = jnp.abs(det) > 1e-300
    inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
    x = a[..., 1, 1] * b[..., 0] - a[..., 0, 1] * b[..., 1]
    y = a[..., 0, 0] * b[..., 1] - a[..., 1, 0] * b[..., 0]
    return jnp.stack([x, y], axis=-1) * inv_det[..., None]


# ---------------------------------------------------------------------------------------------
# Batching

_C = TypeVar("_C", bound=CameraModel)


def stack_cameras(cameras: Sequence[_C]) -> _C:
    """Stack single cameras of one class and image size into a batched camera.

    Args:
        cameras: Non-empty sequence of cameras of the same class and width/height.

    Returns:
        A camera of the same class whose array leaves have a leading axis ``len(cameras)``.

    Raises:
        ValueError: If the sequence is empty or the classes, image sizes or leaf shapes differ.
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("stack_cameras: need at least one camera")
    first = cameras[0]
    for i, cam in enumerate(cameras[1:], start=1):
        if type(cam) is not type(first):
            raise ValueError(
                f"stack_cameras: camera {i} is a {type(cam).__name__}, camera 0 a {type(first).__name__}"
            )
        if (cam.width, cam.height) != (first.width, first.height):
            raise ValueError(
                f"stack_cameras: camera {i} has image size {cam.width}x{cam.height}, "
                f"camera 0 {first.width}x{first.height}"
            )
        s0 = [jnp.shape(x) for x in jax.tree.leaves(first)]
        si = [jnp.shape(x) for x in jax.tree.leaves(cam)]
        if s0 != si:
            raise ValueError(f"stack_cameras: camera {i} has array shapes {si}, camera 0 {s0}")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *cameras)


def camera_at(batched: _C, i: int | Array) -> _C:
    """Camera ``i`` of a batched camera (indexes the leading axis of every array leaf)."""
    return jax.tree.map(lambda x: x[i], batched)


def single_camera_intrinsics(camera: CameraModel, caller: str) -> tuple[np.ndarray, np.ndarray]:
    """``(focal, principal_point)`` of a single camera as float64 arrays; ValueError naming ``caller`` for a batch."""
    if camera.batch_shape != ():
        raise ValueError(f"{caller}: expected a single camera, got batch shape {camera.batch_shape}")
    return np.asarray(camera.focal, dtype=np.float64), np.asarray(camera.principal_point, dtype=np.float64)
