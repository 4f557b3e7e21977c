"""Simulated optical markers: what a Vicon-style system would report for a skeleton's motion.

Markers are rigidly attached to segments a few centimetres off the bone. The simulator adds what a
passive optical system does to their trajectories: measurement noise, occasional jumps ("spikes"),
occlusion gaps, and *label breaks* — after a gap (and now and then without one) the system cannot tell the
reappearing marker from a new one and reports it under a new label. The truth (which physical marker each
label is, the clean trajectories, the skeleton and motion) is kept for evaluation.

Also here: a full-body marker set for the camera skeleton of :data:`bcmocap.sim.motions.BODY_SEGMENTS`,
a range-of-motion "calibration" sequence that exercises every joint (as the subjects of Kirk et al. did),
and the three-rod linkage with universal joints of their Table 1.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from ..geometry import SO3, quat_from_matrix
from ..kinematics.fk import forward_kinematics
from ..kinematics.skeleton import JointType, Motion, Skeleton
from .observe import body_capsules, segment_distance_squared

__all__ = [
    "MarkerNoise",
    "MarkerSpec",
    "Occlusion",
    "SimulatedMarkers",
    "calibrate_occlusion",
    "calibration_motion",
    "camera_ring",
    "full_body_markers",
    "linkage_markers",
    "linkage_motion",
    "linkage_skeleton",
    "marker_positions",
    "occlusion_margins",
    "simulate_markers",
]


@dataclasses.dataclass(frozen=True)
class MarkerSpec:
    """A marker rigidly attached to a segment.

    Attributes:
        name: marker name (unique in a set).
        segment: name of the segment it is attached to.
        offset: ``(3,)`` position in the segment frame (m): origin at the segment's joint, axes parallel
            to the world at rest.
    """

    name: str
    segment: str
    offset: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class MarkerNoise:
    """What the optical system does to the marker trajectories (defaults: a Vicon-like passive system).

    Attributes:
        sigma_m: Gaussian noise per coordinate (m).
        spike_probability: chance per marker-frame that a jump starts.
        spike_size_m: range of a jump's displacement (m); spike_frames: its length range (frames).
        gap_rate_hz: occlusions per marker per second; gap_seconds: range of their length (s).
        relabel_after_gap: probability that a marker comes back from a gap under a new label.
        label_break_rate_hz: label breaks per marker per second without a gap (tracking swaps).
    """

    sigma_m: float = 0.001
    spike_probability: float = 1e-4
    spike_size_m: tuple[float, float] = (0.02, 0.06)
    spike_frames: tuple[int, int] = (1, 3)
    gap_rate_hz: float = 0.1
    gap_seconds: tuple[float, float] = (0.05, 0.5)
    relabel_after_gap: float = 1.0
    label_break_rate_hz: float = 0.01

    @staticmethod
    def clean() -> MarkerNoise:
        """No noise, no jumps, no gaps, no label breaks."""
        return MarkerNoise(0.0, 0.0, (0.0, 0.0), (1, 1), 0.0, (0.0, 0.0), 0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class SimulatedMarkers:
    """Marker trajectories as an optical system reports them, with the truth.

    Attributes:
        positions: ``(F, L, 3)`` reported positions per label (m), NaN where the label has no data.
        labels: ``L`` labels as the system names them (``*0``, ``*1`` … when labels break, else the marker names).
        label_marker: ``(L,)`` index of the physical marker behind each label.
        true_positions: ``(F, M, 3)`` noise-free positions of the physical markers (m).
        markers: the ``M`` physical markers.
        skeleton, motion: the truth (``F`` frames).
        fps: frame rate (Hz).
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    label_marker: np.ndarray
    true_positions: np.ndarray
    markers: tuple[MarkerSpec, ...]
    skeleton: Skeleton
    motion: Motion
    fps: float

    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.markers)

    @property
    def marker_segments(self) -> np.ndarray:
        """``(M,)`` skeleton segment index of each physical marker."""
        return np.array([self.skeleton.index(m.segment) for m in self.markers])

    def identified_positions(self) -> np.ndarray:
        """``(F, M, 3)`` reported positions with the true identities (labels merged by the truth)."""
        out = np.full(self.true_positions.shape, np.nan)
        for label, marker in enumerate(self.label_marker):
            seen = np.isfinite(self.positions[:, label, 0])
            out[seen, marker] = self.positions[seen, label]
        return out


def marker_positions(skeleton: Skeleton, motion: Motion, markers: tuple[MarkerSpec, ...]) -> np.ndarray:
    """``(F, M, 3)`` world positions of segment-fixed markers (m) for a ``(F,)`` motion."""
    poses = forward_kinematics(skeleton, motion)
    rot = np.asarray(poses.rotation().as_matrix())  # (F, J, 3, 3)
    trans = np.asarray(poses.translation())  # (F, J, 3)
    seg = np.array([skeleton.index(m.segment) for m in markers])
    off = np.array([m.offset for m in markers], dtype=np.float64)
    return np.einsum("fmij,mj->fmi", rot[:, seg], off) + trans[:, seg]


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs ``[start, stop)`` of True in a 1-D boolean array."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2], edges[1::2]))


def simulate_markers(
    skeleton: Skeleton,
    motion: Motion,
    markers: tuple[MarkerSpec, ...],
    fps: float,
    noise: MarkerNoise = MarkerNoise(),
    seed: int = 0,
    occlusion: Occlusion | None = None,
) -> SimulatedMarkers:
    """Reported marker trajectories for a motion: noise, jumps, gaps and label breaks.

    Gaps are placed at random (Poisson, ``gap_rate_hz`` per marker), never covering a marker's whole
    trajectory; without ``occlusion`` the first frame sees every marker. With ``occlusion`` the body also
    hides markers from a ring of cameras (:class:`Occlusion`): long gaps that follow the motion, where a
    marker may be lost from the first frame on. A label ends at a gap with probability
    ``relabel_after_gap`` and at a random frame at ``label_break_rate_hz``; labels are then named ``*k``
    in order of appearance (as a passive system names unidentified trajectories).

    Args:
        skeleton, motion: the truth, ``F`` frames.
        markers: the physical markers.
        fps: frame rate (Hz).
        noise: the measurement model.
        seed: random seed (the same seed gives the same data).
        occlusion: the cameras and body occlusion (None: only ``noise``'s random gaps).
    """
    rng = np.random.default_rng(seed)
    truth = marker_positions(skeleton, motion, markers)
    num_frames, num_markers, _ = truth.shape
    observed = truth + rng.normal(scale=noise.sigma_m, size=truth.shape) if noise.sigma_m > 0 else truth.copy()
    if noise.spike_probability > 0:
        starts = np.argwhere(rng.random((num_frames, num_markers)) < noise.spike_probability)
        for f, m in starts:
            length = rng.integers(noise.spike_frames[0], noise.spike_frames[1] + 1)
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            observed[f : f + length, m] += direction * rng.uniform(*noise.spike_size_m)

    visible = np.ones((num_frames, num_markers), bool)
    if occlusion is not None:
        visible = occlusion.margin_m <= occlusion_margins(skeleton, motion, markers, occlusion)
    breaks = np.zeros((num_frames, num_markers), bool)  # a new label starts at this frame
    duration = num_frames / fps
    for m in range(num_markers):
        for _ in range(rng.poisson(noise.gap_rate_hz * duration)):
            length = max(1, int(round(rng.uniform(*noise.gap_seconds) * fps)))
            start = int(rng.integers(1, max(2, num_frames - length)))
            visible[start : start + length, m] = False
        for start, stop in _spans(~visible[:, m]):
            if stop < num_frames and rng.random() < noise.relabel_after_gap:
                breaks[stop, m] = True
        for _ in range(rng.poisson(noise.label_break_rate_hz * duration)):
            f = int(rng.integers(1, num_frames))
            if visible[f, m]:
                breaks[f, m] = True

    # Cut every marker's visible frames into labelled fragments.
    fragments: list[tuple[int, int, int]] = []  # (first frame, marker, stop)
    for m in range(num_markers):
        cuts = np.flatnonzero(breaks[:, m])
        bounds = [0, *cuts.tolist(), num_frames]
        for a, b in zip(bounds[:-1], bounds[1:]):
            spans = _spans(visible[a:b, m])
            if spans:  # one label from its first to its last visible frame, gaps included
                fragments.append((a + spans[0][0], m, a + spans[-1][1]))
    fragments.sort()
    relabelled = len(fragments) > num_markers
    positions = np.full((num_frames, len(fragments), 3), np.nan)
    label_marker = np.zeros(len(fragments), int)
    labels = []
    for k, (start, m, stop) in enumerate(fragments):
        seen = visible[start:stop, m]
        positions[start:stop, k][seen] = observed[start:stop, m][seen]
        label_marker[k] = m
        labels.append(f"*{k}" if relabelled else markers[m].name)
    return SimulatedMarkers(positions, tuple(labels), label_marker, truth, tuple(markers), skeleton, motion, float(fps))


# ---- occlusion by the body, seen by a ring of cameras ------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Occlusion:
    """Which markers a ring of Vicon-like cameras sees past the body.

    The cameras stand on a horizontal ring around the capture volume, all aimed at a point above its
    centre. A marker is reported at a frame if at least ``min_cameras`` cameras (two rays triangulate a
    marker) have it in their field of view and see it past the body: the straight line from the camera to
    the marker passes no capsule around a body segment (:func:`bcmocap.sim.observe.body_capsules`, the
    same capsules the body-camera simulator uses, each grown by ``margin_m``). A marker sits on the skin,
    so no capsule is allowed to swallow it in the rest pose: for each marker and capsule the radius is
    capped ``skin_m`` below the marker's distance from that capsule's axis at rest; a marker still ends up
    inside a capsule when body parts press together (a thigh on the belly in a crouch). Gaps are then long
    and follow the motion: a marker is lost while its own limb or another part of the body turns it away
    from the cameras or stands in front of it.

    ``margin_m`` is the knob that sets how much is lost (bigger capsules, grazing rays lost to the
    silhouette); :func:`calibrate_occlusion` chooses it for a target missing fraction.

    Attributes:
        num_cameras: cameras on the ring.
        ring_radius_m, camera_height_m: the ring (m).
        aim_height_m: height of the point the cameras look at, above the ring's centre (m).
        half_fov_deg: half the (conical) field of view of each camera.
        min_cameras: cameras that must see a marker.
        margin_m: growth of every capsule (m; negative shrinks them).
        skin_m: clearance kept between a marker and each capsule at rest (m).
        centre_xy: the ring's centre on the floor (m); None: the mean root position of the motion.
    """

    num_cameras: int = 10
    ring_radius_m: float = 4.0
    camera_height_m: float = 2.5
    aim_height_m: float = 0.8
    half_fov_deg: float = 35.0
    min_cameras: int = 2
    margin_m: float = 0.0
    skin_m: float = 0.005
    centre_xy: tuple[float, float] | None = None


def camera_ring(occlusion: Occlusion, centre_xy) -> tuple[np.ndarray, np.ndarray]:
    """``(N, 3)`` camera centres and ``(N, 3)`` unit viewing directions of the ring around ``centre_xy``."""
    angle = 2.0 * np.pi * np.arange(occlusion.num_cameras) / occlusion.num_cameras
    cx, cy = (float(x) for x in centre_xy)
    centres = np.stack([cx + occlusion.ring_radius_m * np.cos(angle), cy + occlusion.ring_radius_m * np.sin(angle),
                        np.full(len(angle), occlusion.camera_height_m)], -1)
    look = np.array([cx, cy, occlusion.aim_height_m]) - centres
    return centres, look / np.linalg.norm(look, axis=-1, keepdims=True)


@jax.jit
def _ray_capsule_distance2(points, cameras, ends):
    """``(B, M, N, K)`` squared distances between the rays from ``N`` cameras to ``(B, M)`` markers and ``(B, K)`` capsule axes."""
    return segment_distance_squared(points[:, :, None, None], cameras[None, None, :, None],
                                    ends[:, None, None, :, 0], ends[:, None, None, :, 1])


def occlusion_margins(
    skeleton: Skeleton, motion: Motion, markers: tuple[MarkerSpec, ...], occlusion: Occlusion = Occlusion(), *, chunk: int = 32
) -> np.ndarray:
    """``(F, M)`` for each marker and frame, the capsule margin (m) above which the marker is hidden.

    With capsules grown by ``μ``, the ray from camera ``c`` to marker ``m`` is blocked by capsule ``k`` if it
    passes within ``min(r_k + μ, cap_mk)`` of the capsule's axis, i.e. for ``μ > D_mck − r_k`` when
    ``D_mck < cap_mk``; the marker is hidden once fewer than ``min_cameras`` cameras (those in whose field of
    view it lies) keep an unblocked ray. So the marker is seen at frame ``f`` exactly when
    ``occlusion.margin_m ≤ margins[f, m]`` (``-inf``: never seen, ``+inf``: nothing on the body can hide it).
    Vectorised over markers, cameras and capsules, in chunks of frames.
    """
    caps = body_capsules(skeleton)
    seg = np.array([c.segment for c in caps])
    ends = np.stack([np.array([c.a for c in caps]), np.array([c.b for c in caps])], 1)  # (K, 2, 3) in segment frames
    radius = np.array([c.radius for c in caps])
    # cap: the marker's distance from each capsule axis at rest, less the skin clearance
    # at rest every segment frame is parallel to the world (see MarkerSpec)
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    rest_marker = np.array([rest[skeleton.index(m.segment)] + np.asarray(m.offset) for m in markers])  # (M, 3)
    rest_ends = ends + rest[seg][:, None]
    rest_dist = np.sqrt(np.asarray(segment_distance_squared(rest_marker[:, None], rest_marker[:, None],
                                                            rest_ends[None, :, 0], rest_ends[None, :, 1])))
    cap = rest_dist - occlusion.skin_m  # (M, K)
    if occlusion.centre_xy is None:
        centre = np.asarray(motion.root_position)[:, :2].mean(0)
    else:
        centre = np.asarray(occlusion.centre_xy, dtype=np.float64)
    cams, look = camera_ring(occlusion, centre)
    cos_fov = np.cos(np.deg2rad(occlusion.half_fov_deg))
    poses = forward_kinematics(skeleton, motion)
    rot = np.asarray(poses.rotation().as_matrix())[:, seg]  # (F, K, 3, 3)
    trans = np.asarray(poses.translation())[:, seg]
    world_ends = np.einsum("fkij,kej->fkei", rot, ends) + trans[:, :, None]  # (F, K, 2, 3)
    points = marker_positions(skeleton, motion, markers)  # (F, M, 3)
    num_frames, num_markers, _ = points.shape
    need = occlusion.min_cameras
    pad = (-num_frames) % chunk  # every chunk has the same shape: one compilation
    points = np.concatenate([points, np.repeat(points[-1:], pad, 0)])
    world_ends = np.concatenate([world_ends, np.repeat(world_ends[-1:], pad, 0)])
    out = np.empty((num_frames + pad, num_markers))
    for a in range(0, num_frames + pad, chunk):
        p = points[a : a + chunk]  # (B, M, 3)
        e = world_ends[a : a + chunk]
        ray = p[:, :, None] - cams[None, None]  # (B, M, N, 3) camera → marker
        in_view = np.einsum("bmni,ni->bmn", ray, look) > cos_fov * np.linalg.norm(ray, axis=-1)
        d = np.sqrt(np.asarray(_ray_capsule_distance2(p, cams, e)))  # (B, M, N, K)
        block = np.where(d < cap[None, :, None, :], d - radius, np.inf).min(-1)  # (B, M, N): blocked for μ above this
        block = np.where(in_view, block, -np.inf)
        if need > block.shape[-1]:
            out[a : a + chunk] = -np.inf
        else:
            out[a : a + chunk] = -np.partition(-block, need - 1, axis=-1)[..., need - 1]  # need-th largest
    return out[:num_frames]


def calibrate_occlusion(
    skeleton: Skeleton,
    motion: Motion,
    markers: tuple[MarkerSpec, ...],
    missing_fraction: float,
    occlusion: Occlusion = Occlusion(),
    *,
    margin_range_m: tuple[float, float] = (-0.03, 0.5),
    margins: np.ndarray | None = None,
) -> tuple[Occlusion, float]:
    """The occlusion with ``margin_m`` chosen so that about ``missing_fraction`` of the marker-frames are hidden.

    The hidden share grows with the margin (:func:`occlusion_margins`), so the margin is a quantile of
    the per-sample margins, kept in ``margin_range_m``. Returns the occlusion and the share it hides
    (the target cannot be met when even the smallest capsules hide more, e.g. with too few cameras).
    ``margins``: :func:`occlusion_margins` of this motion and occlusion, if already computed.
    """
    if not 0.0 <= missing_fraction < 1.0:
        raise ValueError(f"calibrate_occlusion: missing_fraction must be in [0, 1), got {missing_fraction}")
    if margins is None:
        margins = occlusion_margins(skeleton, motion, markers, occlusion)
    h = np.sort(np.asarray(margins).ravel())
    k = min(int(round(missing_fraction * len(h))), len(h) - 1)
    margin = float(np.clip(h[k], *margin_range_m)) if np.isfinite(h[k]) else margin_range_m[h[k] > 0]
    return dataclasses.replace(occlusion, margin_m=margin), float(np.mean(h < margin))


# ---- the full-body marker set --------------------------------------------------------------------------


def _around(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Unit vector perpendicular to ``axis`` at ``angle_deg`` around it (0° towards the world's -y, i.e. forward)."""
    axis = axis / np.linalg.norm(axis)
    ref = np.array([0.0, -1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = ref - axis * (ref @ axis)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    a = np.deg2rad(angle_deg)
    return np.cos(a) * e1 + np.sin(a) * e2


def full_body_markers(skeleton: Skeleton, *, jitter_m: float = 0.0, seed: int = 0, count: int = 45) -> tuple[MarkerSpec, ...]:
    """A 45- or 68-marker full-body set for the camera skeleton (segment names of ``BODY_SEGMENTS``).

    Like a clinical "cluster" set: four on the pelvis (ASIS, PSIS), four on the trunk (C7, T10, clavicle,
    sternum), three on the head, three around each upper arm, forearm, thigh and shank, two on each hand
    and three on each foot (heel, toe, fifth metatarsal), 3–8 cm off the bone. ``count=68`` is a denser
    set like the ones labs use for floor work: five around each limb segment, three on each hand, four on
    each foot (first metatarsal too), six on the trunk (two on the upper back) and four on the head.
    ``jitter_m`` moves each marker by a random offset of that size (a different subject or placement per seed).
    """
    if count not in (45, 68):
        raise ValueError(f"full_body_markers: count must be 45 or 68, got {count}")
    dense = count == 68
    names = set(skeleton.names)
    needed = {"pelvis", "torso", "head"} | {f"{s}_{p}" for s in ("left", "right")
                                             for p in ("upper_arm", "forearm", "hand", "thigh", "shin", "foot")}
    if not needed <= names:
        raise ValueError(f"full_body_markers: the skeleton lacks segments {sorted(needed - names)}")
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    joint = {n: rest[skeleton.index(n)] for n in skeleton.names}
    specs: list[tuple[str, str, np.ndarray]] = []  # (name, segment, rest world position)

    def add(name, segment, relative):
        specs.append((name, segment, joint[segment] + np.asarray(relative, float)))

    add("LASI", "pelvis", (0.12, -0.10, -0.03))
    add("RASI", "pelvis", (-0.12, -0.10, -0.03))
    add("LPSI", "pelvis", (0.05, 0.10, 0.0))
    add("RPSI", "pelvis", (-0.05, 0.10, 0.0))
    add("C7", "torso", (0.0, 0.07, 0.33))
    add("T10", "torso", (0.0, 0.12, 0.15))
    add("CLAV", "torso", (0.0, -0.08, 0.30))
    add("STRN", "torso", (-0.02, -0.12, 0.17))
    if dense:
        add("LBAK", "torso", (0.09, 0.11, 0.26))
        add("RBAK", "torso", (-0.09, 0.11, 0.26))
    add("LFHD", "head", (0.06, -0.08, 0.14))
    add("RFHD", "head", (-0.06, -0.08, 0.14))
    if dense:
        add("LBHD", "head", (0.06, 0.09, 0.15))
        add("RBHD", "head", (-0.06, 0.09, 0.15))
    else:
        add("BHD", "head", (0.0, 0.10, 0.16))
    per_limb = (((0.2, 0.35, 0.5, 0.65, 0.8), (20.0, 92.0, 164.0, 236.0, 308.0)) if dense else None)
    for side, s in (("left", "L"), ("right", "R")):
        for part, code, child, radius, fractions in (
            ("upper_arm", "UA", "forearm", 0.05, (0.3, 0.55, 0.8)),
            ("forearm", "FA", "hand", 0.04, (0.25, 0.5, 0.8)),
            ("thigh", "TH", "shin", 0.075, (0.3, 0.55, 0.8)),
            ("shin", "SH", "foot", 0.055, (0.25, 0.5, 0.8)),
        ):
            a, b = joint[f"{side}_{part}"], joint[f"{side}_{child}"]
            places = zip(*per_limb) if dense else zip(fractions, (20.0, 140.0, 260.0))
            for k, (t, angle) in enumerate(places):
                pos = a + t * (b - a) + radius * _around(b - a, angle)
                specs.append((f"{s}{code}{k + 1}", f"{side}_{part}", pos))
        wrist, elbow = joint[f"{side}_hand"], joint[f"{side}_forearm"]
        along = (wrist - elbow) / np.linalg.norm(wrist - elbow)
        hand = ((0.05, 90.0), (0.08, 270.0)) + (((0.10, 0.0),) if dense else ())
        for k, (t, angle) in enumerate(hand):
            specs.append((f"{s}HA{k + 1}", f"{side}_hand", wrist + t * along + 0.03 * _around(along, angle)))
        lateral = 1.0 if side == "left" else -1.0
        add(f"{s}HEE", f"{side}_foot", (0.0, 0.06, -0.05))
        add(f"{s}TOE", f"{side}_foot", (0.0, -0.14, -0.06))
        add(f"{s}MT5", f"{side}_foot", (0.045 * lateral, -0.08, -0.05))
        if dense:
            add(f"{s}MT1", f"{side}_foot", (-0.035 * lateral, -0.09, -0.05))
    rng = np.random.default_rng(seed)
    out = []
    for name, segment, pos in specs:
        pos = pos + (rng.uniform(-jitter_m, jitter_m, size=3) if jitter_m > 0 else 0.0)
        out.append(MarkerSpec(name, segment, tuple(float(x) for x in pos - joint[segment])))
    return tuple(out)


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, count: int, freq_hz: tuple[float, float]) -> np.ndarray:
    """``(len(t), count)`` sums of two sinusoids of random frequency and phase, amplitude ≈ 1."""
    out = np.zeros((len(t), count))
    for _ in range(2):
        f = rng.uniform(*freq_hz, size=count)
        phase = rng.uniform(0, 2 * np.pi, size=count)
        out += np.sin(2 * np.pi * f * t[:, None] + phase) / np.sqrt(2)
    return out


def calibration_motion(
    skeleton: Skeleton,
    start: Motion,
    seconds: float,
    fps: float,
    *,
    amplitude_deg: float = 30.0,
    hinge_amplitude_deg: float = 60.0,
    seed: int = 0,
) -> Motion:
    """A range-of-motion sequence from a pose: every joint exercised at once, smoothly.

    Each ball joint adds a rotation about all three axes (random smooth signals, about ``amplitude_deg``
    each) to the start pose; each hinge bends about its axis between 0 and ``hinge_amplitude_deg``; the
    root stays in place, turning slowly about the vertical. The excursion fades in over the first half
    second so the sequence continues the start pose without a jump.

    Args:
        skeleton: the tree. start: a single-frame motion (root ``(3,)``, rotations ``(J, 4)``).
        seconds: length; fps: frame rate (Hz).

    Returns:
        A ``(F,)`` motion, ``F = round(seconds · fps)``.
    """
    rng = np.random.default_rng(seed)
    n = int(round(seconds * fps))
    t = np.arange(n) / fps
    ramp = np.clip(t / 0.5, 0.0, 1.0)
    ramp = (0.5 - 0.5 * np.cos(np.pi * ramp))[:, None]
    base = np.asarray(start.rotations, dtype=np.float64)
    rotvec = np.zeros((n, skeleton.num_segments, 3))
    for j in range(1, skeleton.num_segments):
        kind = skeleton.joint_types[j]
        if kind == JointType.BALL:
            rotvec[:, j] = np.deg2rad(amplitude_deg) * _smooth_signal(rng, t, 3, (0.15, 0.6)) * ramp
        elif kind == JointType.HINGE:
            phase = rng.uniform(0, 2 * np.pi)
            bend = 0.5 * (1 - np.cos(2 * np.pi * rng.uniform(0.2, 0.5) * t + phase)) - 0.5 * (1 - np.cos(phase))
            rotvec[:, j] = np.deg2rad(hinge_amplitude_deg) * np.abs(bend)[:, None] * ramp * np.asarray(skeleton.hinge_axes[j])
    yaw = np.deg2rad(20.0) * np.sin(2 * np.pi * 0.1 * t) * ramp[:, 0]
    rotvec[:, 0] = np.stack([np.zeros(n), np.zeros(n), yaw], -1)
    rot = np.array((SO3(np.broadcast_to(base, (n, *base.shape))) @ SO3.exp(rotvec)).wxyz)
    rot[:, 0] = np.asarray((SO3.exp(rotvec[:, 0]) @ SO3(np.broadcast_to(base[0], (n, 4)))).wxyz)
    root = np.broadcast_to(np.asarray(start.root_position, dtype=np.float64), (n, 3)).copy()
    return Motion(root, np.asarray(skeleton.project_rotations(rot)))


# ---- the three-rod linkage of Kirk et al. (Table 1) -------------------------------------------------------


def linkage_skeleton(lengths_m: tuple[float, float, float] = (0.30, 0.341, 0.30)) -> Skeleton:
    """Three rods in a chain along x at rest: ``rod1`` (free, hand-held) — ``rod2`` — ``rod3``.

    Joints are universal joints (two rotation axes, y and z of the parent frame, crossing at the joint),
    represented as BALL joints whose motion never twists about the rod (see :func:`linkage_motion`).
    """
    l1, l2, _ = lengths_m
    offsets = np.array([[0.0, 0.0, 0.0], [l1, 0.0, 0.0], [l2, 0.0, 0.0]])
    return Skeleton(("rod1", "rod2", "rod3"), (-1, 0, 1), offsets)


def linkage_markers(
    lengths_m: tuple[float, float, float] = (0.30, 0.341, 0.30), *, seed: int = 0
) -> tuple[MarkerSpec, ...]:
    """Nine markers, three per rod, 1.5–2.5 cm off the rod axis at different places along it."""
    rng = np.random.default_rng(seed)
    out = []
    for k, (name, length) in enumerate(zip(("rod1", "rod2", "rod3"), lengths_m)):
        for i, t in enumerate((0.2, 0.5, 0.8)):
            angle = rng.uniform(0, 2 * np.pi)
            r = rng.uniform(0.015, 0.025)
            x = (t + rng.uniform(-0.05, 0.05)) * length
            out.append(MarkerSpec(f"R{k + 1}M{i + 1}", name, (x, r * np.cos(angle), r * np.sin(angle))))
    return tuple(out)


def linkage_motion(seconds: float, fps: float, *, seed: int = 0, amplitude_deg: float = 50.0) -> Motion:
    """A motion of :func:`linkage_skeleton` as if waved about by hand: a smooth free motion of ``rod1`` and universal-joint bends.

    Each joint's rotation is ``Rz(a) Ry(b)`` (two axes of a universal joint, no twist about the rod) with
    smooth random ``a, b`` of about ``amplitude_deg``.
    """
    rng = np.random.default_rng(seed)
    n = int(round(seconds * fps))
    t = np.arange(n) / fps
    position = np.array([0.0, 0.0, 1.2]) + 0.25 * _smooth_signal(rng, t, 3, (0.05, 0.3))
    root_rv = np.deg2rad(45.0) * _smooth_signal(rng, t, 3, (0.05, 0.25))
    rot = np.zeros((n, 3, 4))
    rot[:, 0] = np.asarray(SO3.exp(root_rv).wxyz)
    for j in (1, 2):
        a, b = (np.deg2rad(amplitude_deg) * _smooth_signal(rng, t, 2, (0.1, 0.4))).T
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        rz = np.stack([np.stack([ca, -sa, 0 * a], -1), np.stack([sa, ca, 0 * a], -1), np.stack([0 * a, 0 * a, 1 + 0 * a], -1)], -2)
        ry = np.stack([np.stack([cb, 0 * b, sb], -1), np.stack([0 * b, 1 + 0 * b, 0 * b], -1), np.stack([-sb, 0 * b, cb], -1)], -2)
        rot[:, j] = quat_from_matrix(rz @ ry)
    return Motion(position, rot)
