"""Virtual cameras (§4.2, Eqs. 6–7, Fig. 5): several cameras on one limb act as one robust camera.

The cameras on a segment are rigidly connected, so the relative transform ``reference_from_camera``
between a reference camera and each other camera is constant: it is estimated as a robust average
over the frames where both are registered (Eq. 6). The virtual camera ``V`` is a frame fixed to the
same rigid body; each physical camera is re-parameterised by it through ``camera_from_virtual``
(Eq. 7), so at any frame every registered camera gives an estimate of ``world_from_virtual`` and the
virtual camera's pose is their robust average — a camera that failed or drifted at that frame is
outvoted instead of corrupting the limb's pose.

Where ``V`` sits on the body is a choice. The paper lets it coincide with the reference camera; by
default here it sits at the mean of the cameras (rotation: chordal mean of their orientations,
position: the mean of their centres), which spreads each camera's rotation noise over shorter lever
arms. ``centred=False`` gives the paper's choice.

In a :class:`~bcmocap.kinematics.Rig`, a virtual camera needs no new machinery: the physical mounts
are re-expressed as ``segment_from_camera = segment_from_virtual @ virtual_from_camera``
(:func:`reparameterise_rig`), and the solver's reprojection term keeps projecting through the
physical cameras, now tied to the limb through the virtual camera.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from ..geometry import average_quaternions, compose_poses, invert_pose, quat_conjugate, quat_multiply
from .rig import Rig

#: Tukey biweight cut-off, in multiples of the median residual of the sample (for a χ-distributed
#: 3-D error norm the median is ≈ 1.54 σ, so inliers are kept out to ≈ 6 σ).
TUKEY_CUTOFF = 4.0


def _tukey_weights(normalised: np.ndarray, mask: np.ndarray) -> np.ndarray:
    w = np.where(normalised < TUKEY_CUTOFF, (1.0 - (normalised / TUKEY_CUTOFF) ** 2) ** 2, 0.0)
    return np.where(mask, w, 0.0)


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Lower median over the last axis of the entries where ``mask`` is True (1.0 where none is)."""
    count = mask.sum(axis=-1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=-1)
    mid = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, mid, 1.0)


def robust_average_poses(
    poses: np.ndarray, mask: np.ndarray | None = None, *, robust: bool = True, iterations: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Robust mean of rigid transforms, batched: a Tukey-reweighted chordal/Euclidean mean.

    Starts from the medoid (the sample whose median distance to the others is smallest), then
    iterates: rotation = chordal L2 mean (Markley et al.), position = weighted mean, weights = Tukey
    biweight of each sample's combined residual ``√((angle/s_R)² + (distance/s_p)²)``, where ``s_R`` and
    ``s_p`` are the sample's median angle and distance. Samples far beyond the bulk get weight 0; with
    noiseless samples the result is their common value.

    Args:
        poses: ``(..., N, 7)`` transforms (wxyz_xyz) averaged over axis ``-2``; masked rows may hold NaN.
        mask: ``(..., N)`` bool, which samples exist (default: all).
        robust: False gives the plain chordal/Euclidean mean of the masked samples.
        iterations: reweighting passes.

    Returns:
        ``(..., 7)`` means (NaN where no sample exists) and ``(..., N)`` final weights in [0, 1].
    """
    poses = np.asarray(poses, dtype=np.float64)
    mask = np.ones(poses.shape[:-1], bool) if mask is None else np.asarray(mask, bool)
    if poses.ndim < 2 or poses.shape[-1] != 7 or mask.shape != poses.shape[:-1]:
        raise ValueError(f"robust_average_poses: expected poses (..., N, 7) and mask (..., N), got {poses.shape} and {mask.shape}")
    batch, n = poses.shape[:-2], poses.shape[-2]
    m = mask.reshape(-1, n)
    flat = np.where(m[..., None], poses.reshape(-1, n, 7), np.array([1.0, 0, 0, 0, 0, 0, 0]))
    q = flat[..., :4] / np.linalg.norm(flat[..., :4], axis=-1, keepdims=True)
    p = flat[..., 4:]

    def mean_of(w):
        vecs = np.linalg.eigh(np.einsum("bn,bni,bnj->bij", w, q, q))[1][..., -1]
        mean_q = np.where(vecs[:, :1] < 0, -vecs, vecs)
        return mean_q, np.einsum("bn,bnk->bk", w, p) / np.maximum(w.sum(1), 1e-300)[:, None]

    def distances(mean_q, mean_p):
        """Angles and distances ``(B, ..., N)`` from centres ``(B, ..., 4|3)`` to every sample."""
        expand = (slice(None),) + (None,) * (mean_q.ndim - 2)
        rel = quat_multiply(quat_conjugate(mean_q)[..., None, :], q[expand])
        angle = 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))  # accurate near 0
        return angle, np.linalg.norm(p[expand] - mean_p[..., None, :], axis=-1)

    def normalised(angle, dist, scale_mask):
        # floors far below any real noise: rounding-level residuals of exact samples keep full weight
        s_rot = np.maximum(_masked_median(angle.reshape(len(m), -1), scale_mask), 1e-9)
        s_pos = np.maximum(_masked_median(dist.reshape(len(m), -1), scale_mask), 1e-9)
        extra = (None,) * (angle.ndim - 1)
        return np.sqrt((angle / s_rot[(..., *extra)]) ** 2 + (dist / s_pos[(..., *extra)]) ** 2)

    w = m.astype(float)
    if robust and n > 2:
        # medoid start: the candidate with the smallest median distance to the others (one scale for all)
        cand = np.arange(n) if n <= 128 else np.linspace(0, n - 1, 128).astype(int)
        angle, dist = distances(q[:, cand], p[:, cand])  # (B, K, N)
        pair_mask = m[:, cand, None] & m[:, None, :]
        score = _masked_median(normalised(angle, dist, pair_mask.reshape(len(m), -1)), pair_mask)
        start = cand[np.argmin(np.where(m[:, cand], score, np.inf), axis=1)]
        rows = np.arange(len(m))
        mean_q, mean_p = q[rows, start], p[rows, start]
        for _ in range(iterations):
            w = _tukey_weights(normalised(*distances(mean_q, mean_p), m), m)
            w = np.where(w.sum(1, keepdims=True) > 0, w, m.astype(float))
            mean_q, mean_p = mean_of(w)
    else:
        mean_q, mean_p = mean_of(w)
    out = np.where(m.any(1)[:, None], np.concatenate([mean_q, mean_p], axis=-1), np.nan)
    return out.reshape(*batch, 7), w.reshape(*batch, n)


@dataclasses.dataclass(frozen=True)
class VirtualCamera:
    """Physical cameras on one rigid limb, re-parameterised by one virtual camera ``V``.

    Attributes:
        name: the virtual camera's name (usually its segment's).
        cameras: names of the physical cameras, in the order of ``virtual_from_camera``.
        virtual_from_camera: ``(K, 7)`` transforms (wxyz_xyz) camera frame → virtual frame (m).
        reference: the physical camera the relative transforms were measured against.
        frames: ``(K,)`` frames each camera was registered together with the reference.
        inlier_fraction: ``(K,)`` share of those frames kept by the robust average.
    """

    name: str
    cameras: tuple[str, ...]
    virtual_from_camera: np.ndarray
    reference: str
    frames: np.ndarray
    inlier_fraction: np.ndarray

    def camera_from_virtual(self) -> np.ndarray:
        """``(K, 7)`` inverse mounts (Eq. 7: ``camera_from_virtual = reference_from_camera⁻¹`` up to where V sits)."""
        return invert_pose(self.virtual_from_camera)

    def world_from_virtual(
        self, world_from_camera: np.ndarray, registered: np.ndarray, *, robust: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """The virtual camera's pose at every frame: the (robust) average of what each registered camera says.

        Args:
            world_from_camera: ``(T, K, 7)`` poses of this virtual camera's physical cameras (in
                :attr:`cameras` order); unregistered rows are never read.
            registered: ``(T, K)`` bool.
            robust: Tukey-reweighted average (one camera disagreeing with two others is dropped);
                False gives the plain chordal/Euclidean mean.

        Returns:
            ``(T, 7)`` ``world_from_virtual`` (NaN where no camera is registered) and ``(T,)`` bool known.
        """
        world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
        registered = np.asarray(registered, bool)
        k = len(self.cameras)
        if world_from_camera.ndim != 3 or world_from_camera.shape[1:] != (k, 7) or registered.shape != world_from_camera.shape[:2]:
            raise ValueError(
                f"virtual camera '{self.name}': expected world_from_camera (T, {k}, 7) and registered (T, {k}) for "
                f"cameras {list(self.cameras)}, got {world_from_camera.shape} and {registered.shape}"
            )
        safe = np.where(registered[..., None], world_from_camera, np.array([1.0, 0, 0, 0, 0, 0, 0]))
        each = compose_poses(safe, self.camera_from_virtual()[None])
        mean, _ = robust_average_poses(each, registered, robust=robust)
        known = registered.any(axis=1)
        return np.where(known[:, None], mean, np.nan), known

    def camera_poses(self, world_from_virtual: np.ndarray) -> np.ndarray:
        """``(..., K, 7)`` physical camera poses implied by virtual poses ``(..., 7)`` (Fig. 5b)."""
        return compose_poses(np.asarray(world_from_virtual, dtype=np.float64)[..., None, :], self.virtual_from_camera)


def estimate_virtual_camera(
    cameras: Sequence[str],
    world_from_camera: np.ndarray,
    registered: np.ndarray,
    *,
    name: str | None = None,
    reference: str | None = None,
    centred: bool = True,
    min_frames: int = 20,
) -> VirtualCamera:
    """A virtual camera from the trajectories of cameras rigidly mounted on one limb (Eqs. 6–7).

    Args:
        cameras: names of the K physical cameras.
        world_from_camera: ``(T, K, 7)`` their registered poses (wxyz_xyz); unregistered rows are never read.
        registered: ``(T, K)`` bool.
        name: the virtual camera's name (default: the cameras' names joined by "+").
        reference: the camera the others are measured against (default: the one registered most often).
        centred: put ``V`` at the mean of the cameras (default) or, as in the paper, at the reference.
        min_frames: fewer co-registered frames than this for a camera gives a warning naming it.

    Raises:
        ValueError: shapes do not match, or a camera is never registered together with the reference.
    """
    cameras = tuple(str(c) for c in cameras)
    world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
    registered = np.asarray(registered, bool)
    k = len(cameras)
    name = "+".join(cameras) if name is None else name
    if k == 0:
        raise ValueError(f"virtual camera '{name}': no cameras given")
    if world_from_camera.ndim != 3 or world_from_camera.shape[1:] != (k, 7) or registered.shape != world_from_camera.shape[:2]:
        raise ValueError(
            f"virtual camera '{name}': expected world_from_camera (T, {k}, 7) and registered (T, {k}) for cameras "
            f"{list(cameras)}, got {world_from_camera.shape} and {registered.shape}"
        )
    counts = registered.sum(axis=0)
    if reference is None:
        ref = int(np.argmax(counts))
    elif reference in cameras:
        ref = cameras.index(reference)
    else:
        raise ValueError(f"virtual camera '{name}': reference camera '{reference}' is not one of {list(cameras)}")
    if counts[ref] == 0:
        raise ValueError(f"virtual camera '{name}': camera '{cameras[ref]}' is never registered")
    ref_from_cam = np.zeros((k, 7))
    frames = np.zeros(k, int)
    inliers = np.ones(k)
    for i in range(k):
        both = registered[:, ref] & registered[:, i]
        frames[i] = both.sum()
        if i == ref:
            ref_from_cam[i] = [1.0, 0, 0, 0, 0, 0, 0]
            continue
        if frames[i] == 0:
            raise ValueError(
                f"virtual camera '{name}': camera '{cameras[i]}' is never registered in the same frame as the reference "
                f"'{cameras[ref]}', so its transform to the limb is unknown"
            )
        if frames[i] < min_frames:
            warnings.warn(
                f"virtual camera '{name}': camera '{cameras[i]}' is registered with '{cameras[ref]}' in only "
                f"{frames[i]} frames (< {min_frames}); its mount is poorly determined",
                stacklevel=2,
            )
        rel = compose_poses(invert_pose(world_from_camera[both, ref]), world_from_camera[both, i])
        ref_from_cam[i], w = robust_average_poses(rel)  # Eq. (6), f_a robust
        inliers[i] = float(np.mean(w > 0))
    if centred:
        centre = np.concatenate([average_quaternions(ref_from_cam[:, :4]), ref_from_cam[:, 4:].mean(axis=0)])
    else:
        centre = ref_from_cam[ref]
    virtual_from_cam = compose_poses(invert_pose(centre), ref_from_cam)
    return VirtualCamera(name, cameras, virtual_from_cam, cameras[ref], frames, inliers)


def reparameterise_rig(rig: Rig, virtual_cameras: Sequence[VirtualCamera], virtual_mounts: Mapping[str, np.ndarray]) -> Rig:
    """The rig with each virtual camera's physical mounts re-expressed through it (Fig. 5b).

    ``segment_from_camera = segment_from_virtual @ virtual_from_camera`` for every camera of a virtual
    camera; other cameras keep their mounts. The result is an ordinary :class:`Rig`: forward
    kinematics and the solver's reprojection term use it unchanged.

    Args:
        rig: the rig (names, segments and intrinsics are kept).
        virtual_cameras: virtual cameras whose physical cameras are in ``rig``.
        virtual_mounts: virtual camera name → ``(7,)`` ``segment_from_virtual``, where ``V`` sits on its segment.

    Raises:
        ValueError: a camera is not in the rig, the cameras of one virtual camera sit on different
            segments, or a virtual camera has no entry in ``virtual_mounts``.
    """
    mounts = np.array(rig.segment_from_camera)
    for vc in virtual_cameras:
        if vc.name not in virtual_mounts:
            raise ValueError(f"reparameterise_rig: no segment_from_virtual for virtual camera '{vc.name}'")
        idx = [rig.index(c) for c in vc.cameras]
        segs = {rig.segments[i] for i in idx}
        if len(segs) != 1:
            raise ValueError(f"reparameterise_rig: the cameras of virtual camera '{vc.name}' are on different segments {sorted(segs)}")
        mounts[idx] = compose_poses(np.asarray(virtual_mounts[vc.name], dtype=np.float64), vc.virtual_from_camera)
    return Rig(rig.names, rig.segments, mounts, rig.intrinsics)


def segment_from_virtual(rig: Rig, vc: VirtualCamera) -> np.ndarray:
    """``(7,)`` where a rig's mounts put the virtual camera on its segment (robust mean over its cameras)."""
    idx = [rig.index(c) for c in vc.cameras]
    each = compose_poses(np.asarray(rig.segment_from_camera)[idx], invert_pose(vc.virtual_from_camera))
    return robust_average_poses(each)[0]
