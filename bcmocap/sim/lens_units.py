"""Manufactured lens units: each body camera its own copy of one lens design, as a box of cameras is.

Cameras of one model share a lens design, but no two units image alike: each lens is focused and glued
onto its sensor separately, its elements sit micrometres off their nominal places, and the sensor is
slightly tilted. :func:`manufactured_lens_units` draws such units of a design as
:class:`~bcmocap.cameras.TiltedThinPrismFisheyeCamera`: a thin-prism fisheye (COLMAP's THIN_PRISM_FISHEYE) in
front of a sensor tilted as OpenCV's tilted model has it, a model outside every family the solver and
``bcmocap calibrate`` fit (FOV, Kannala-Brandt, thin-prism fisheye): the decentering and thin-prism terms are
what the first two lack, and the tilt acts on the distorted image, where the thin-prism family's terms act
before the distortion. :func:`lens_design` is the studio's design: the Kannala-Brandt fit of the paper's 170°
FOV-model lens (:func:`~bcmocap.sim.rig.fov_camera_for`) with a higher-order term added, so that the design
itself is not in the FOV family either; :func:`nominal_lens` is the design as a user would be given it in a
family the pipeline reads (its data sheet, or the FOV-model lens closest to it).

Magnitudes (:class:`UnitTolerances`) are for a 1/2.3" action-camera sensor (6.17 mm wide: 9.6 µm per pixel
at 640 px) behind a fisheye of about 2.9 mm focal length; pixel figures scale with the image width.

* Focal length, σ 0.3 % (fx and fy together): stock machine-vision lenses of one catalogue entry differ by up
  to 2-3 % in focal length (optowiki.info, "Field of view changes from lens to lens"); an action camera's lens
  is focused onto its own sensor in production, and the image scale follows the lens-to-sensor distance, so
  10 µm of focus travel on a 2.9 mm lens is 0.35 %. σ 0.3 % (a few tenths of a per cent, tails near 1 %) is a
  judgement between the two.
* Principal point, σ 0.25 % of the width per axis (1.6 px at 640 px; 2.3 px RMS offset): Parrot's ANAFI
  Thermal white paper aligns the optical centre to the sensor centre within ±22 µm (±20 px) by active
  alignment, 2.3 px of 9.6 µm here; Tetracam's multi-sensor cameras quote lens/sensor displacements up to 56 µm
  (±4 px of theirs), typically ±2 px.
* Radial profile: ``theta_d`` off the design by ``theta Σ a_i (theta / theta_edge)^(2i)`` (i = 1..4, ``theta_edge``
  the image corner's angle), each ``a_i`` with σ 5e-4: a judgement (0.05 % of the image radius per term, a few
  tenths of a pixel at the corners). A Kannala-Brandt calibration absorbs it; it only moves the unit off the
  design.
* Decentering p1, p2, σ 2e-4 (equidistant normalised units, as COLMAP's model): up to about half a pixel
  (5 µm) at the corners at 640 px. Photogrammetry treats decentering as an order below radial distortion
  (PhotoModeler's documentation: "often not modeled because its contribution is much smaller than radial lens
  distortion"; Matsuoka et al. 2006, IAPRS XXXVI/5: small, yet it changes the estimated distortion field). The
  value is a judgement of that order.
* Thin prism sx1, sy1, σ 1e-4: about a quarter of a pixel at the corners. Thin-prism distortion comes from
  lens elements' manufacturing imperfections and a sensor tilted off the optical axis (Weng, Cohen & Herniou
  1992, IEEE PAMI 14(10); DLR's CalLab documentation); the value is a judgement, half the decentering.

Every draw is clipped at 3 σ. With these, the best Kannala-Brandt lens of a unit (its own focal lengths,
centre and k1..k4) stays within a few tenths of a pixel of it over the image, while the design misses a unit
by pixels (tests/test_lens_units.py; ``benchmarks/lens_units.py`` measures what ``bcmocap calibrate`` recovers).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..cameras import FOVCamera, OpenCVFisheyeCamera, TiltedThinPrismFisheyeCamera
from ..io.opencv_calibration import fit_opencv_fisheye
from .rig import fov_camera_for

__all__ = ["DESIGN_DEPARTURE", "UnitTolerances", "edge_angle", "lens_design", "manufactured_lens_units", "nominal_lens"]

#: How far the design's image radius departs from the FOV-model lens's Kannala-Brandt fit at the image corner (a
#: share of that radius, growing as ``theta^7``): 0.4 %, 1.5 px at 640 × 360. A judgement: a real design is near,
#: not on, a one-parameter model.
DESIGN_DEPARTURE = 0.004


@dataclasses.dataclass(frozen=True)
class UnitTolerances:
    """Standard deviations of a unit's departures from its design (module docstring: sources and judgements).

    Attributes:
        focal_pct: focal length (%, fx and fy together).
        centre_fraction: principal point, per axis, as a share of the image width.
        radial: each of the four relative radial terms ``a_i`` (dimensionless).
        decentering: p1 and p2 (dimensionless).
        thin_prism: sx1 and sy1 (dimensionless).
        tilt_deg: the sensor's tilt about x and about y (degrees).
        clip_sigmas: draws are clipped at this many standard deviations.
    """

    focal_pct: float = 0.3
    centre_fraction: float = 0.0025
    radial: float = 5e-4
    decentering: float = 2e-4
    thin_prism: float = 1e-4
    tilt_deg: float = 0.1
    clip_sigmas: float = 3.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < math.inf:
                raise ValueError(f"UnitTolerances.{field.name} must be a finite number >= 0, got {value!r}")


def edge_angle(camera) -> float:
    """Angle (rad) off the optical axis of the image corner farthest from the principal point of a single camera."""
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    rays = np.asarray(camera.unproject(corners))
    return float(np.max(np.arccos(np.clip(rays[:, 2], -1.0, 1.0))))


def lens_design(width: int = 640, height: int = 360, fov_deg: float = 170.0) -> OpenCVFisheyeCamera:
    """The studio's lens design for ``width`` × ``height`` px images: the Kannala-Brandt fit
    (:func:`~bcmocap.io.opencv_calibration.fit_opencv_fisheye`) of the FOV-model lens of ``fov_deg`` horizontal
    field of view, with ``theta_d`` raised by ``DESIGN_DEPARTURE`` of its value at the image corner, as
    ``theta^7`` (``k3`` grows), centred on the image.
    """
    fov = fov_camera_for(width, height, fov_deg)
    fitted, _ = fit_opencv_fisheye(fov)
    edge = edge_angle(fov)
    k = np.asarray(fitted.distortion, np.float64).copy()
    poly_edge = 1.0 + sum(k[i] * edge ** (2 * i + 2) for i in range(4))
    k[2] += DESIGN_DEPARTURE * poly_edge / edge**6
    return OpenCVFisheyeCamera(width, height, focal=np.asarray(fitted.focal), principal_point=np.asarray(fitted.principal_point),
                               distortion=k)


def manufactured_lens_units(design: OpenCVFisheyeCamera, count: int, rng: np.random.Generator,
                            tolerances: UnitTolerances = UnitTolerances()) -> list[TiltedThinPrismFisheyeCamera]:
    """``count`` units of a lens design, each off it as manufactured lenses are (module docstring).

    Args:
        design: a single Kannala-Brandt camera (e.g. :func:`lens_design`): the nominal lens.
        count: units to draw (>= 0).
        rng: the draws' generator (units are drawn one after another, each from the same sequence of draws).
        tolerances: their standard deviations.

    Returns:
        ``count`` :class:`~bcmocap.cameras.TiltedThinPrismFisheyeCamera` of the design's image size.
    """
    if not isinstance(design, OpenCVFisheyeCamera) or design.batch_shape != ():
        raise ValueError(f"manufactured_lens_units: design must be a single OpenCVFisheyeCamera, got "
                         f"{type(design).__name__} of batch shape {getattr(design, 'batch_shape', None)}")
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"manufactured_lens_units: count must be a whole number >= 0, got {count!r}")
    t = tolerances
    focal = np.asarray(design.focal, np.float64)
    centre = np.asarray(design.principal_point, np.float64)
    k = np.asarray(design.distortion, np.float64)
    edge = edge_angle(design)

    def normal(sigma: float, size: int) -> np.ndarray:
        return np.clip(rng.standard_normal(size), -t.clip_sigmas, t.clip_sigmas) * sigma

    units = []
    for _ in range(count):
        scale = 1.0 + normal(t.focal_pct / 100.0, 1)[0]
        shift = normal(t.centre_fraction * design.width, 2)
        radial = normal(t.radial, 4) / edge ** (2.0 * np.arange(1, 5))  # theta_d / theta gains a_i (theta / edge)^(2i)
        tangential, thin_prism = normal(t.decentering, 2), normal(t.thin_prism, 2)
        units.append(TiltedThinPrismFisheyeCamera(
            design.width, design.height, focal=focal * scale, principal_point=centre + shift, distortion=k + radial,
            tangential=tangential, thin_prism=thin_prism, tilt=np.deg2rad(normal(t.tilt_deg, 2))))
    return units


def nominal_lens(design: OpenCVFisheyeCamera, family: str) -> OpenCVFisheyeCamera | FOVCamera:
    """The design as a user is given it: ``family`` "opencv_fisheye", the design itself (its data sheet); "fov", the
    FOV-model lens whose image radius is closest to the design's over the image (least squares over angles up to
    the image corner; same centre)."""
    if family == "opencv_fisheye":
        return design
    if family != "fov":
        raise ValueError(f"nominal_lens: family must be 'fov' or 'opencv_fisheye', got {family!r}")
    from scipy.optimize import minimize_scalar

    theta = np.linspace(0.0, edge_angle(design), 400)[1:]
    radius = theta * (1.0 + sum(float(design.distortion[i]) * theta ** (2 * i + 2) for i in range(4)))

    def fov_radius(omega: float) -> np.ndarray:  # r_d / focal of the FOV model (atan2 form: beyond 90 degrees)
        return np.arctan2(2.0 * math.tan(omega / 2.0) * np.sin(theta), np.cos(theta)) / omega

    def focal_and_error(omega: float) -> tuple[float, float]:
        shape = fov_radius(omega)
        scale = float(shape @ radius / (shape @ shape))
        return scale, float(np.sum((scale * shape - radius) ** 2))

    omega = float(minimize_scalar(lambda w: focal_and_error(w)[1], bounds=(0.05, 3.0), method="bounded",
                                  options={"xatol": 1e-10}).x)
    scale, _ = focal_and_error(omega)
    return FOVCamera(design.width, design.height, focal=np.asarray(design.focal) * scale,
                     principal_point=np.asarray(design.principal_point), omega=omega)
