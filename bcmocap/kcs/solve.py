"""Algorithm 1: alternate per-frame weak-perspective cameras and a nuclear-norm shape step in the KCS.

Model (Eqs. 5, 14): the bones of frame ``k`` are ``B_k = B0 + A_k S`` with ``B0 = X0 C`` the initial bone
configuration (a mean pose), ``S`` (r × b, orthonormal rows) a shape basis and ``A_k`` (3 × r); the
observation is ``Y_k = X′_k C = P_k B_k``. The shape step solves Eq. 21,

    min ‖Â‖_*  s.t.  ‖W C − P(Â S + B̂0)‖_F = 0,

in its penalty form ``½ Σ_k ‖(Y_k − P_k B_k)‖²/s̄² + τ ‖Â‖_*`` (``s̄`` the largest camera scale, so ``τ`` is
in model units, metres) by proximal gradient: a gradient step on the reprojection term, then singular
value thresholding (the proximal map of ``τ‖·‖_*``, Cai, Candès & Shen). As ``τ → 0`` its minimiser tends
to Eq. 21's.

**Why a constancy projection.** With the cameras fixed, the reprojection constraint fixes each frame's
bones in the image plane and leaves their depth free; the nuclear norm of ``Â`` (invariant to the per-frame
rotations) is then smallest when the depth rows of ``Â`` vanish, i.e. Eq. 21 alone returns every bone at
the depth of ``B0`` in the camera frame — a flat deviation from the mean pose (on CMU walking with
near-static cameras about 60–70 mm of 3-D error). Proposition 1's premise, constant bone lengths, is what
carries the depth; the paper relaxes it away. With ``constant_bone_lengths=True`` (default) each
proximal step is followed by a (relaxed) projection onto the set of bones with constant lengths
``l`` (``l`` = the current mean length of each bone over the sequence, scaled so that the lengths sum to the mean
pose's: ``prior_scale``, since weak perspective does not observe the body's scale): in the camera frame a bone keeps
its image-plane part and gets depth ``±√(l² − ‖u‖²)``. The sign of the depth — the classical
monocular ambiguity — is taken from the nuclear-norm estimate and, every ``sign_every`` steps, chosen
jointly over the sequence per bone by dynamic programming: agreement with the nuclear-norm estimate plus
``sign_smoothness`` × the squared second difference of the bone over time (a bone passes smoothly through
the image plane rather than bouncing off it). Set ``constant_bone_lengths=False`` for the paper's
relaxation as printed.

**Anatomy (beyond the paper).** Per-bone smoothness cannot tell a bone flipped over a whole stretch of
frames from the true one. For a human chain (:func:`~bcmocap.kcs.anatomy.human_anatomy`) the signs of
whole limbs (thigh–shank–foot, upper arm–forearm, the pelvis, the thorax) are then chosen jointly by a
second-order dynamic programme over the sign combinations (:func:`limb_signs`), with hinge penalties
(knees bend backwards about the pelvis's lateral axis, feet point forwards, elbows do not hyper-extend)
and the rigidity of pelvis and thorax; inside Algorithm 1 after every per-bone choice
(``anatomy_in_loop``) and once at the end. ``KCSOptions(anatomy=False)`` is the paper's method.

Everything is jitted and vmaps over independent sequences or camera paths; shapes are static and
missing joints are masked (a bone is observed when both its joints are).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..precision import require_float64
from .anatomy import Anatomy, human_anatomy
from .cameras import WeakPerspectiveCameras, fit_cameras, initial_cameras, reprojection_rms
from .chain_space import KinematicChainSpace

__all__ = ["KCSOptions", "KCSResult", "limb_signs", "padded_length", "reconstruct", "singular_value_threshold",
           "solve_bones"]


@dataclasses.dataclass(frozen=True)
class KCSOptions:
    """Settings of Algorithm 1 (hashable: a static argument of the jitted solver).

    Attributes:
        max_iterations: outer iterations (one shape step and one camera step each).
        tolerance: stop when the bones change by less than this, relative (Frobenius), in one iteration.
        shape_steps: proximal-gradient steps per shape step (a multiple of ``sign_every``).
        camera_steps: EM steps of Eq. 22 per frame per camera step.
        initial_camera_steps: EM steps per start when fitting the first cameras to ``B0``.
        nuclear_weight: ``τ``, the nuclear-norm weight (model units, metres).
        rank: rank ``3K`` of the shape basis ``S`` from the SVD of ``Ŵ C`` (Eq. 4); ``None`` = all bones.
        constant_bone_lengths: project onto constant bone lengths after each proximal step (see above).
        length_weight: relaxation of that projection (1 = exact projection).
        sign_smoothness: weight of the temporal second difference when choosing depth signs.
        sign_every: choose depth signs over the whole sequence every this many proximal steps.
        depth_smoothing: σ (frames) of a Gaussian smoothing of the squared depths ``l² − ‖u‖²`` over time
            in the constancy projection (0 = none); see :func:`_project_lengths`.
        anatomy: after Algorithm 1, choose the depth signs of whole limbs with anatomical hinges
            (:mod:`bcmocap.kcs.anatomy`, an addition beyond the paper) when the chain is a human one that
            :func:`~bcmocap.kcs.anatomy.human_anatomy` recognises (or an :class:`Anatomy` is given).
        hinge_weight: weight of a hinge's penalty (normalised, dimensionless) per frame in that choice.
            100: chosen on CMU subject 35 walking (six walks: 20.3 mm with 100, 21.7 with 10).
        rigid_weight: weight of the rigid pelvis and thorax (absolute difference of cosines) in that
            choice. Kept apart from the hinges: on noisy joints these angles are noisy, and 100 costs
            there (1 px of noise on three walks: 30.7 mm with 100, 27.7 with 10), while on exact joints
            the two settings are equal.
        limb_smoothness: weight of the squared second difference of the limb's joints (m²) over time.
        limb_agreement: weight of the squared distance to Algorithm 1's bones (m²).
        anatomy_in_loop: also choose the limb signs inside Algorithm 1, at every per-bone sign choice
            (after it), so that the shape and camera steps continue from anatomically plausible limbs.
        keypoint_smoothing: σ (frames) of a Gaussian smoothing of the observed 2-D bones over time before the solve,
            each bone over the frames where it is observed (0 = none): a detector's keypoints jitter from frame to
            frame, which the constancy projection's square root amplifies in depth.
        prior_scale: hold the estimated bone lengths' sum to the initial configuration's (the mean pose's) in the
            constancy projection: weak perspective does not observe the body's scale, and left free the lengths
            drift about 1 % long together with the cameras' scales (on CMU subject 35 walking), where 1 % costs 3 mm.
            On the 23 walks of subject 35 (6 camera paths each) it takes the mean 3-D error from 20.32 to 18.13 mm
            (better on every walk), the jumps 02_04 and 01_01 (other subjects) from 48.35 to 46.00 mm, 13_11 from
            44.53 to 44.86 mm; the tests' quadruped from 21.6 to 22.9 mm. False leaves the scale to the solve. Without
            effect where the lengths are given (``reconstruct(..., bone_lengths=)``) or not held
            (``constant_bone_lengths=False``).
    """

    max_iterations: int = 30
    tolerance: float = 1e-3
    shape_steps: int = 20
    camera_steps: int = 10
    initial_camera_steps: int = 40
    nuclear_weight: float = 0.03
    rank: int | None = None
    constant_bone_lengths: bool = True
    length_weight: float = 0.5
    sign_smoothness: float = 30.0
    sign_every: int = 5
    depth_smoothing: float = 3.0
    anatomy: bool = True
    hinge_weight: float = 100.0
    rigid_weight: float = 10.0
    limb_smoothness: float = 30.0
    limb_agreement: float = 1.0
    anatomy_in_loop: bool = True
    keypoint_smoothing: float = 0.0
    prior_scale: bool = True

    def __post_init__(self):
        for name in ("max_iterations", "shape_steps", "camera_steps", "initial_camera_steps", "sign_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"KCSOptions: {name} must be at least 1, got {getattr(self, name)}")
        if self.shape_steps % self.sign_every:
            raise ValueError(
                f"KCSOptions: shape_steps ({self.shape_steps}) must be a multiple of sign_every ({self.sign_every})"
            )
        nonneg = ("nuclear_weight", "tolerance", "sign_smoothness", "depth_smoothing", "hinge_weight", "rigid_weight",
                  "limb_smoothness", "limb_agreement", "keypoint_smoothing")
        if not min(getattr(self, n) for n in nonneg) >= 0:
            raise ValueError(f"KCSOptions: {', '.join(nonneg)} must be non-negative")
        if not 0 < self.length_weight <= 1:
            raise ValueError(f"KCSOptions: length_weight must be in (0, 1], got {self.length_weight}")
        if self.rank is not None and int(self.rank) < 1:
            raise ValueError(f"KCSOptions: rank must be positive or None, got {self.rank}")


class KCSResult(eqx.Module):
    """Output of Algorithm 1 (leading batch axes ``...`` as in the input).

    Attributes:
        joints: ``(..., F, J, 3)`` reconstructed joints in the model frame (the mean pose's), root at the
            origin, in the mean pose's units (metres).
        joints_camera: ``(..., F, J, 3)`` the same in each frame's camera frame (x, y image axes, z depth).
        bones: ``(..., F, b, 3)`` bone vectors ``(Â S + B̂0)ᵀ`` in the model frame.
        cameras: per-frame weak-perspective cameras.
        bone_lengths: ``(..., b)`` mean bone lengths over the sequence.
        reprojection_px: ``(..., 2 · max_iterations + 1)`` RMS reprojection error of the observed bones
            (pixels per coordinate): entry 0 after the first cameras (``A = 0``), then after each shape step
            (odd entries) and each camera step (even entries), as in the paper's Fig. 5; NaN after the
            last iteration.
        iterations: ``(...)`` outer iterations run.
        converged: ``(...)`` whether the tolerance was met before ``max_iterations``.
    """

    joints: jax.Array
    joints_camera: jax.Array
    bones: jax.Array
    cameras: WeakPerspectiveCameras
    bone_lengths: jax.Array
    reprojection_px: jax.Array
    iterations: jax.Array
    converged: jax.Array


def singular_value_threshold(matrix: jax.Array, threshold) -> jax.Array:
    """Proximal map of ``threshold · ‖·‖_*``: shrink the singular values of ``matrix`` (m × n) by ``threshold``.

    Computed from the eigen-decomposition of the small Gram matrix (n × n for a tall matrix, m × m for a
    wide one): ``M V diag(max(σ − t, 0)/σ) Vᵀ``. Same result as thresholding a full SVD (singular values
    below ``threshold`` vanish, so squaring the condition number costs nothing that is kept), and far
    cheaper under ``vmap`` on CPU, where batched SVDs of tall matrices are slow.
    """
    wide = matrix.shape[-2] < matrix.shape[-1]
    m = jnp.swapaxes(matrix, -1, -2) if wide else matrix
    lam, v = jnp.linalg.eigh(jnp.swapaxes(m, -1, -2) @ m)
    s = jnp.sqrt(jnp.maximum(lam, 0.0))
    factor = jnp.where(s > threshold, (s - threshold) / jnp.where(s > 0, s, 1.0), 0.0)
    out = m @ (v * factor[..., None, :]) @ jnp.swapaxes(v, -1, -2)
    return jnp.swapaxes(out, -1, -2) if wide else out


def _viterbi_signs(candidates: jax.Array, target: jax.Array, smoothness, frames=None) -> jax.Array:
    """Depth signs of one bone over time (second-order dynamic programming).

    Args:
        candidates: ``(F, 2, 3)`` the bone with positive (index 0) and negative (1) depth, camera frame.
        target: ``(F, 3)`` the unconstrained estimate to agree with.
        smoothness: weight of ``‖b_{k−1} − 2 b_k + b_{k+1}‖²``.
        frames: ``(F,)`` 1 for the sequence's frames, 0 for padding after them (None: all frames).

    Returns:
        ``(F,)`` chosen candidate index per frame.
    """
    unary = jnp.sum((candidates - target[:, None]) ** 2, axis=-1)  # (F, 2)
    return _viterbi_states(unary, candidates[:, :, None], smoothness, frames)


def _viterbi_states(unary: jax.Array, points: jax.Array, smoothness, frames=None) -> jax.Array:
    """Second-order dynamic programme over ``S`` discrete states per frame.

    Args:
        unary: ``(F, S)`` cost of each state in each frame.
        points: ``(F, S, n, 3)`` points that each state places; the pairwise cost is ``smoothness`` ×
            ``Σ ‖p_{k−1} − 2 p_k + p_{k+1}‖²`` over the ``n`` points.
        frames: ``(F,)`` 1 for the sequence's frames, 0 for padding after them: a padded frame's unary and
            every second difference ending at it cost nothing, so the sequence's states are those of the
            unpadded programme (None: all frames).

    Returns:
        ``(F,)`` the state sequence of least total cost (F ≥ 3).
    """
    s = unary.shape[1]
    if frames is not None:
        unary = unary * frames[:, None]
    live = jnp.ones(unary.shape[0]) if frames is None else frames
    cost0 = unary[0][:, None] + unary[1][None, :]  # states (s_{k-1}, s_k)

    def forward(cost, k):
        acc = points[k - 2][:, None, None] - 2 * points[k - 1][None, :, None] + points[k][None, None, :]
        total = cost[:, :, None] + live[k] * smoothness * jnp.sum(acc**2, axis=(-1, -2))  # (a, b, c)
        back = jnp.argmin(total, axis=0)  # (b, c)
        return jnp.min(total, axis=0) + unary[k][None, :], back

    cost, backs = jax.lax.scan(forward, cost0, jnp.arange(2, unary.shape[0]))
    last = jnp.argmin(cost)
    s_prev, s_last = last // s, last % s

    def backward(carry, back):
        b, c = carry
        a = back[b, c]
        return (a, b), a

    _, rest = jax.lax.scan(backward, (s_prev, s_last), backs, reverse=True)
    return jnp.concatenate([rest, jnp.stack([s_prev, s_last])])


def _unit(v):
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 0, n, 1.0)


def limb_signs(
    camera_bones: jax.Array,
    anatomy: Anatomy,
    hinge_weight=KCSOptions.hinge_weight,
    smoothness=KCSOptions.limb_smoothness,
    agreement=KCSOptions.limb_agreement,
    target=None,
    rest_bones=None,
    rigid_weight=KCSOptions.rigid_weight,
    frames=None,
):
    """Depth signs of whole limbs chosen jointly over time with anatomical hinges (beyond the paper).

    For each limb of ``anatomy`` (``n`` bones, ``2ⁿ`` sign combinations per frame) a second-order dynamic
    programme over the sequence minimises, per frame, ``hinge_weight`` × the hinge penalties
    (:mod:`bcmocap.kcs.anatomy`: wrong bending direction ``relu(−σ c)`` and, for planar hinges, the axis
    leaving the lateral axis ``|p̂ × ĉ| − σ c`` with ``c = (p̂ × ĉ)·lateral``), plus ``agreement`` × the
    squared distance to the given bones, plus ``smoothness`` × the squared second difference of the
    limb's joints (relative to its first joint) over time. The magnitudes of the depths are kept.

    Args:
        camera_bones: ``(F, b, 3)`` bones in each frame's camera frame (x, y image axes, z depth).
        anatomy: limbs, hinges and lateral axes (static).
        hinge_weight, smoothness, agreement: weights (see above).
        target: ``(F, b, 3)`` bones to agree with (default ``camera_bones``).
        rest_bones: ``(b, 3)`` the initial configuration ``B0``: the angles of ``anatomy.rigid`` pairs
            are held to theirs (``rigid_weight`` × the absolute difference of cosines); ``None`` = unused.
        rigid_weight: weight of those rigid angles.
        frames: ``(F,)`` 1 for the sequence's frames, 0 for padding after them (None: all frames).

    Returns:
        ``(F, b, 3)`` the bones with the limbs' depth signs replaced (other bones unchanged).
    """
    f = camera_bones.shape[0]
    if f < 3 or not anatomy.limbs:
        return camera_bones
    laterals = []
    for pairs in anatomy.laterals:
        v = sum(_unit(camera_bones[:, a] - camera_bones[:, b]) for a, b in pairs)
        laterals.append(_unit(v))
    target = camera_bones if target is None else target
    out = camera_bones
    for index, limb in enumerate(anatomy.limbs):
        n = len(limb)
        bits = np.array(list(itertools.product((0, 1), repeat=n)))  # (S, n), 1 = negative depth
        bones = camera_bones[:, list(limb)]  # (F, n, 3)
        z = jnp.abs(bones[..., 2])
        sign = jnp.asarray(1.0 - 2.0 * bits)  # (S, n)
        states = jnp.concatenate(
            [jnp.broadcast_to(bones[:, None, :, :2], (f, len(bits), n, 2)), (sign[None] * z[:, None])[..., None]], -1
        )  # (F, S, n, 3)
        unary = agreement * jnp.sum((states - target[:, None, list(limb)]) ** 2, axis=(-1, -2))
        lengths = jnp.linalg.norm(states, axis=-1)  # (F, S, n)
        for h in anatomy.hinges:
            if h.limb != index:
                continue
            cross = jnp.cross(states[:, :, h.parent], states[:, :, h.child])
            den = lengths[:, :, h.parent] * lengths[:, :, h.child]
            den = jnp.where(den > 0, den, 1.0)
            c = jnp.einsum("fsi,fi->fs", cross, laterals[h.lateral]) / den
            penalty = jax.nn.relu(-h.sign * c)
            if h.planar:
                penalty = penalty + jnp.linalg.norm(cross, axis=-1) / den - h.sign * c
            unary = unary + hinge_weight * penalty
        for limb_index, i, j in anatomy.rigid:
            if limb_index != index or rest_bones is None:
                continue
            a, b = rest_bones[limb[i]], rest_bones[limb[j]]
            rest_cos = jnp.dot(a, b) / jnp.maximum(jnp.linalg.norm(a) * jnp.linalg.norm(b), 1e-300)
            den = lengths[:, :, i] * lengths[:, :, j]
            cos = jnp.sum(states[:, :, i] * states[:, :, j], axis=-1) / jnp.where(den > 0, den, 1.0)
            unary = unary + rigid_weight * jnp.abs(cos - rest_cos)
        pick = _viterbi_states(unary, jnp.cumsum(states, axis=2), smoothness, frames)
        out = out.at[:, list(limb)].set(states[jnp.arange(f), pick])
    return out


def _anatomical_signs(camera_bones, anatomy: Anatomy, rest_bones, options: KCSOptions, target=None, frames=None):
    """:func:`limb_signs` with the weights of ``options``."""
    return limb_signs(
        camera_bones, anatomy, options.hinge_weight, options.limb_smoothness, options.limb_agreement, target,
        rest_bones, options.rigid_weight, frames,
    )


def _smooth_in_time(x, sigma: float, frames=None):
    """Gaussian smoothing (σ in frames) of ``(F, b)`` along frames, renormalised at the ends (and where ``frames``
    ``(F,)`` marks padding after the sequence with 0, at the sequence's end)."""
    if sigma <= 0 or x.shape[0] < 2:
        return x
    half = max(1, int(np.ceil(3 * sigma)))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    k = k / k.sum()
    f = x.shape[0]

    # A sum of shifted copies rather than jnp.convolve: the kernel is short, and batched XLA CPU
    # convolutions under vmap were the suspect of segfaults in XLA's Eigen threads on long sequences.
    def conv(v):
        padded = jnp.pad(v, ((half, half), (0, 0)))
        return sum(float(w) * padded[i : i + f] for i, w in enumerate(k))

    live = jnp.ones_like(x) if frames is None else jnp.broadcast_to(frames[:, None], x.shape)
    return conv(x * live) / jnp.maximum(conv(live), 1e-300)


def _project_lengths(
    bones, rotation, observed, lengths, weight, smoothness, choose_signs: bool, depth_sigma=0.0, limbs=None,
    frames=None,
):
    """Relaxed projection of ``(F, 3, b)`` bones onto constant ``lengths`` (b,).

    An observed bone keeps its image-plane part (pinned by the data) and gets its depth from its length;
    an unobserved one (``observed`` (F, b) false) is scaled to its length (the nearest point). The squared
    depth ``l² − ‖u‖²`` is smoothed over ``depth_sigma`` frames first: its square root amplifies image
    noise wherever a bone lies near the image plane (1 px at 200 px/m gives ~7 cm on a 40 cm bone).
    ``limbs`` = ``(anatomy, rest bones B0ᵀ, options)`` also chooses the limbs' signs (:func:`limb_signs`)
    after the per-bone choice; None = not. ``frames`` ``(F,)``: 0 for padding after the sequence (None: none).
    """
    cam = rotation @ bones  # (F, 3, b)
    norm = jnp.linalg.norm(cam, axis=1)
    radial = cam * (lengths / jnp.where(norm > 0, norm, 1.0))[:, None]
    u = jnp.where(observed[:, None], cam[:, :2], radial[:, :2])
    norm_u = jnp.linalg.norm(u, axis=1)
    shrink = jnp.minimum(1.0, lengths / jnp.where(norm_u > 0, norm_u, 1.0))
    u = u * shrink[:, None]
    depth = jnp.sqrt(jnp.maximum(_smooth_in_time(lengths**2 - jnp.sum(u * u, axis=1), depth_sigma, frames), 0.0))
    if choose_signs and bones.shape[0] >= 3:
        cand = jnp.stack([jnp.concatenate([u, depth[:, None]], 1), jnp.concatenate([u, -depth[:, None]], 1)], 1)
        pick = jax.vmap(_viterbi_signs, in_axes=(3, 2, None, None), out_axes=1)(cand, cam, smoothness, frames)  # (F, b)
        sign = 1.0 - 2.0 * pick
    else:
        sign = jnp.where(cam[:, 2] < 0, -1.0, 1.0)
    chosen = jnp.concatenate([u, (sign * depth)[:, None]], axis=1)
    if choose_signs and limbs is not None and bones.shape[0] >= 3:
        anatomy, rest, options = limbs
        chosen = _anatomical_signs(chosen.swapaxes(1, 2), anatomy, rest, options, cam.swapaxes(1, 2),
                                   frames).swapaxes(1, 2)
    projected = rotation.swapaxes(1, 2) @ chosen
    return bones + weight * (projected - bones)


def solve_bones(bones_2d, weights, initial_bones, options: KCSOptions = KCSOptions(), anatomy: Anatomy | None = None,
                frames=None, known_lengths=None):
    """Algorithm 1 on one sequence in the KCS (pure, jittable, vmappable; no input checks).

    Args:
        bones_2d: ``(F, 2, b)`` observed bones ``W C`` (pixels; anything at masked bones).
        weights: ``(F, b)`` 1 where the bone is observed, 0 where not.
        initial_bones: ``(3, b)`` ``B0 = X0 C`` (metres).
        options: settings (static).
        anatomy: limbs and hinges (static) for the final choice of limb signs (:func:`limb_signs`),
            used when ``options.anatomy``; ``None`` = none.
        frames: ``(F,)`` 1 for the sequence's frames, 0 for padding after them (their ``weights`` 0 too): the
            padded frames' shape coefficients are held at 0 and they enter no mean, smoothing or sign choice, so
            the sequence's result is the unpadded one's (None: no padding).
        known_lengths: ``(b,)`` bone lengths (metres) to project onto instead of the current mean lengths (None:
            estimated), e.g. measured on the subject.

    Returns:
        ``(bones (F, 3, b), cameras, lengths (b,), reprojection history, iterations, converged)``.
    """
    y = jnp.where(weights[:, None, :] > 0, bones_2d, 0.0)
    w = weights
    b0 = initial_bones
    f, _, nb = y.shape
    live = jnp.ones(f) if frames is None else frames
    if options.keypoint_smoothing > 0:  # each observed bone averaged over the frames it is observed in
        flat = jnp.concatenate([(y * w[:, None, :]).reshape(f, 2 * nb), w], axis=1)
        smooth = _smooth_in_time(flat * live[:, None], options.keypoint_smoothing)  # Σ k·y·w and Σ k·w, normalised alike
        total, count = smooth[:, : 2 * nb].reshape(f, 2, nb), smooth[:, 2 * nb:]
        y = jnp.where(w[:, None, :] > 0, total / jnp.where(count > 0, count, 1.0)[:, None, :], 0.0)

    prior_lengths = jnp.linalg.norm(b0, axis=0)  # (b,) the initial configuration's

    def mean_length(bones):
        return jnp.sum(jnp.linalg.norm(bones, axis=1) * live[:, None], axis=0) / jnp.maximum(jnp.sum(live), 1.0)
    cams = initial_cameras(y, w, b0, options.initial_camera_steps)
    if options.rank is None or options.rank >= nb:
        basis = jnp.eye(nb)
    else:
        residual = (y - cams.matrices() @ b0) * w[:, None, :]  # Ŵ C (Eq. 4 in the KCS)
        _, _, vt = jnp.linalg.svd(residual.reshape(2 * f, nb), full_matrices=False)
        basis = vt[: options.rank]
    r = basis.shape[0]
    tau = options.nuclear_weight
    use_anatomy = options.anatomy and anatomy is not None and options.constant_bone_lengths
    limbs = (
        (anatomy, b0.T, options)
        if use_anatomy and options.anatomy_in_loop
        else None
    )
    history = jnp.full(2 * options.max_iterations + 1, jnp.nan).at[0].set(reprojection_rms(y, w, b0, cams))

    def prox_step(a, cams, choose_signs):
        bones = b0 + a @ basis
        p = cams.matrices()
        s_max = jnp.max(cams.scale)
        res = w[:, None, :] * (y - p @ bones)
        grad = -(p.swapaxes(1, 2) @ res) / s_max**2
        a = a - grad @ basis.T
        a = singular_value_threshold((a * live[:, None, None]).reshape(3 * f, r), tau).reshape(f, 3, r)
        if options.constant_bone_lengths:
            bones = b0 + a @ basis
            lengths = mean_length(bones) if known_lengths is None else known_lengths
            if known_lengths is None and options.prior_scale:
                lengths = lengths * (jnp.sum(prior_lengths) / jnp.sum(lengths))
            bones = _project_lengths(
                bones,
                cams.rotation,
                w > 0,
                lengths,
                options.length_weight,
                options.sign_smoothness,
                choose_signs,
                options.depth_smoothing,
                limbs,
                frames,
            )
            a = (bones - b0) @ basis.T
        return a * live[:, None, None]

    def shape_step(a, cams):
        def block(_, a):
            a = jax.lax.fori_loop(0, options.sign_every - 1, lambda _, a: prox_step(a, cams, False), a)
            return prox_step(a, cams, True)

        return jax.lax.fori_loop(0, options.shape_steps // options.sign_every, block, a)

    def cond(state):
        it, _, _, _, converged = state
        return (it < options.max_iterations) & ~converged

    def body(state):
        it, a, cams, history, _ = state
        old = b0 + a @ basis
        a = shape_step(a, cams)
        bones = b0 + a @ basis
        history = history.at[2 * it + 1].set(reprojection_rms(y, w, bones, cams))
        cams = fit_cameras(y, w, bones, cams, options.camera_steps)
        history = history.at[2 * it + 2].set(reprojection_rms(y, w, bones, cams))
        size = jnp.linalg.norm(old * live[:, None, None])  # the sequence's bones (the padding's are B0's)
        change = jnp.linalg.norm(bones - old) / jnp.maximum(size, 1e-300)
        return it + 1, a, cams, history, change < options.tolerance

    a0 = jnp.zeros((f, 3, r))
    it, a, cams, history, converged = jax.lax.while_loop(cond, body, (0, a0, cams, history, jnp.array(False)))
    bones = b0 + a @ basis
    if use_anatomy:
        cam = (cams.rotation @ bones).swapaxes(1, 2)  # (F, b, 3)
        cam = _anatomical_signs(cam, anatomy, b0.T, options, frames=frames)
        bones = cams.rotation.swapaxes(1, 2) @ cam.swapaxes(1, 2)
    lengths = mean_length(bones)
    return bones, cams, lengths, history, it, converged


@functools.partial(jax.jit, static_argnames=("options", "anatomy"))
def _solve_batch(bones_2d, weights, initial_bones, d_joints, frames, known_lengths, options, anatomy=None):
    def one(y, w, b0, known):
        bones, cams, lengths, history, it, converged = solve_bones(y, w, b0, options, anatomy, frames, known)
        joints = (bones @ d_joints).swapaxes(1, 2)  # (F, J, 3)
        joints_camera = joints @ cams.rotation.swapaxes(1, 2)
        return KCSResult(joints, joints_camera, bones.swapaxes(1, 2), cams, lengths, history, it, converged)

    return jax.vmap(one, in_axes=(0, 0, 0, None if known_lengths is None else 0))(bones_2d, weights, initial_bones,
                                                                                   known_lengths)


def padded_length(frames: int) -> int:
    """The length a sequence of ``frames`` frames is padded to (:func:`reconstruct`): the least of 16, 24, 32, 48, 64,
    96, … (``2ᵏ`` and ``1.5 · 2ᵏ``) that holds it, so any length reuses one of a few compiled programs at most a
    half longer; fewer than 3 frames are not padded (no sign choice over time there)."""
    if frames < 3:
        return frames
    size = 16
    while size < frames:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def _prepare(chain: KinematicChainSpace, joints_2d, mean_pose, mask):
    """Checks and converts the inputs of :func:`reconstruct` (numpy, before tracing)."""
    j = chain.num_joints
    x = np.asarray(joints_2d, dtype=np.float64)
    if x.ndim < 3 or x.shape[-2:] != (j, 2):
        raise ValueError(
            f"reconstruct: joints_2d must have shape (..., F, {j}, 2) (frames, the {j} joints {list(chain.names)}, "
            f"image x y), got {x.shape}"
        )
    if x.shape[-3] < 1:
        raise ValueError("reconstruct: joints_2d has no frames")
    if np.isinf(x).any():
        idx = tuple(int(i) for i in np.argwhere(np.isinf(x))[0])
        raise ValueError(f"reconstruct: joints_2d holds an infinite value at index {idx}; mark missing joints with NaN or the mask")
    observed = np.all(np.isfinite(x), axis=-1)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != x.shape[:-1]:
            raise ValueError(f"reconstruct: mask must have shape {x.shape[:-1]} (..., F, J), got {m.shape}")
        observed &= m.astype(bool)
    batch = x.shape[:-3]
    x0 = np.asarray(mean_pose, dtype=np.float64)
    if x0.shape[-2:] != (j, 3):
        raise ValueError(f"reconstruct: mean_pose must have shape (..., {j}, 3), got {x0.shape}")
    try:
        x0 = np.broadcast_to(x0, (*batch, j, 3))
    except ValueError:
        raise ValueError(f"reconstruct: mean_pose {x0.shape} does not broadcast to the batch shape {batch}") from None
    if not np.all(np.isfinite(x0)):
        raise ValueError("reconstruct: mean_pose holds NaN or inf")
    c = chain.C
    start = np.array([a for a, _ in chain.links])
    end = np.array([b for _, b in chain.links])
    weights = (observed[..., start] & observed[..., end]).astype(np.float64)  # (..., F, b)
    per_frame = weights.sum(-1)
    good = (per_frame >= 2).any(-1)
    if not np.all(good):
        which = tuple(int(i) for i in np.argwhere(~np.asarray(good).reshape(batch))[0]) if batch else ()
        raise ValueError(
            f"reconstruct: sequence {which} has no frame with at least 2 observed bones (both joints of a bone must "
            "be observed); nothing to fit a camera to"
        )
    y = np.einsum("jb,...fjd->...fdb", c, np.where(observed[..., None], x, 0.0))  # (..., F, 2, b)
    b0 = np.einsum("jb,...jd->...db", c, x0)  # (..., 3, b)
    return y, weights, b0, batch


def reconstruct(
    chain: KinematicChainSpace,
    joints_2d,
    mean_pose,
    mask=None,
    options: KCSOptions = KCSOptions(),
    anatomy: Anatomy | None = None,
    pad: bool = True,
    bone_lengths=None,
) -> KCSResult:
    """3-D motion of a kinematic chain from its 2-D joints in one uncalibrated camera (Algorithm 1).

    Args:
        chain: the topology (and extra rigid links).
        joints_2d: ``(..., F, J, 2)`` image positions (pixels); NaN marks a missing joint. Leading axes are
            independent sequences or camera paths, solved in one vmapped, jitted call.
        mean_pose: ``(J, 3)`` or ``(..., J, 3)`` the initial configuration ``X0`` (metres): any reasonable
            pose of the chain, e.g. :func:`~bcmocap.kcs.mean_pose` of other sequences; it fixes the scale.
        mask: optional ``(..., F, J)`` booleans, False for missing joints.
        options: solver settings.
        anatomy: limbs and hinges for the final limb-sign choice (``options.anatomy``); default
            :func:`~bcmocap.kcs.anatomy.human_anatomy` of ``chain`` (``None`` for non-human chains).
        pad: solve the sequences padded to :func:`padded_length` frames (padding that changes no result: see
            :func:`solve_bones`), so that a new length reuses a compiled program; False solves them as they are.
        bone_lengths: ``(b,)`` or ``(..., b)`` known bone lengths in the mean pose's units (metres), in the order of
            ``chain.links``, e.g. measured on the subject: the constancy projection holds the bones to them instead of
            to their current mean lengths (None: estimated, and with ``options.prior_scale`` scaled to the mean pose's
            sum). Bone lengths carry most of the error left with estimated ones (docs/benchmarks/kcs.md).

    Returns:
        A :class:`KCSResult` with the batch shape of ``joints_2d``.

    Raises:
        ValueError: wrong shapes (naming the expected and actual ones), infinite values, a mean pose with
            NaN, a sequence where no frame observes two bones, or bone lengths that are not positive and finite
            (or given with ``constant_bone_lengths=False``).
    """
    require_float64("bcmocap.kcs.reconstruct")
    if options.rank is not None:
        frames = np.shape(joints_2d)[-3] if np.ndim(joints_2d) >= 3 else 0
        if options.rank > min(2 * frames, chain.num_bones):
            raise ValueError(
                f"reconstruct: rank {options.rank} exceeds min(2 F, b) = {min(2 * frames, chain.num_bones)} "
                f"for {frames} frames and {chain.num_bones} bones"
            )
    y, w, b0, batch = _prepare(chain, joints_2d, mean_pose, mask)
    f, b = y.shape[-3], y.shape[-1]
    known = None
    if bone_lengths is not None:
        if not options.constant_bone_lengths:
            raise ValueError("reconstruct: bone_lengths needs KCSOptions(constant_bone_lengths=True): the relaxation "
                             "as printed holds no bone to a length")
        known = np.asarray(bone_lengths, dtype=np.float64)
        if known.ndim < 1 or known.shape[-1] != b:
            raise ValueError(f"reconstruct: bone_lengths must have shape (..., {b}) (one per link of the chain), got "
                             f"{known.shape}")
        try:
            known = np.broadcast_to(known, (*batch, b)).reshape(-1, b)
        except ValueError:
            raise ValueError(f"reconstruct: bone_lengths {known.shape} does not broadcast to the batch shape {batch}") from None
        if not (np.all(np.isfinite(known)) and np.all(known > 0)):
            raise ValueError("reconstruct: bone_lengths must be positive and finite (metres)")
    size = padded_length(f) if pad else f
    y = np.concatenate([y.reshape(-1, f, 2, b), np.zeros((int(np.prod(batch, dtype=int)), size - f, 2, b))], axis=1)
    w = np.concatenate([w.reshape(-1, f, b), np.zeros((len(y), size - f, b))], axis=1)
    flat = _solve_batch(
        jnp.asarray(y),
        jnp.asarray(w),
        jnp.asarray(b0.reshape(-1, 3, b)),
        jnp.asarray(chain.D_least_squares),
        jnp.asarray(np.arange(size) < f, dtype=jnp.float64),
        None if known is None else jnp.asarray(known),
        options,
        (anatomy if anatomy is not None else human_anatomy(chain)) if options.anatomy else None,
    )
    if size > f:  # the sequence's frames of the per-frame fields
        cut = lambda a: a[:, :f]  # noqa: E731
        flat = dataclasses.replace(flat, joints=cut(flat.joints), joints_camera=cut(flat.joints_camera),
                                   bones=cut(flat.bones), cameras=jax.tree.map(cut, flat.cameras))
    return jax.tree.map(lambda a: a.reshape(*batch, *a.shape[1:]), flat)
