"""Anatomical hinge constraints for choosing the depth signs of whole limbs (an addition beyond the paper).

Under weak perspective every bone's depth is known only up to its sign. Algorithm 1 with the constancy
projection (:mod:`bcmocap.kcs.solve`) chooses the signs bone by bone from temporal smoothness; on CMU
walking it still gets the shanks wrong in about a fifth of the frames, because a flipped stretch between
two passes of a bone through the image plane is as smooth as the true one. Anatomy settles most of
these: the knee and the elbow are (nearly) hinges, so

* **knee**: the thigh × shank axis points along the pelvis's lateral axis (left hip − right hip), i.e. the
  knee bends only backwards and the shank stays in the thigh's sagittal plane;
* **ankle**: shank × foot points against the lateral axis (the foot points forwards);
* **elbow**: upper arm × forearm points against the lateral axis, i.e. the elbow does not
  hyper-extend (sign only: the humerus rotates, so the elbow axis is not tied to the trunk);
* **pelvis and thorax** are (nearly) rigid: the angles between the two hip bones and the lower spine,
  and between the two clavicle bones (thorax → shoulder) and the lower neck, keep their values in the
  initial configuration ``B0`` (the mean pose the solver starts from).

The lateral axis is the sum of the unit vectors left hip − right hip and left shoulder − right shoulder
(both from the thorax/root bones of the current estimate), normalised.

The conventions were checked on the CMU trials of subjects 35, 02 and 01 (true poses: normalised knee
term ≥ 0.1, ankle ≤ −0.65, elbow ≤ −0.03 in every frame). These are generic facts of human anatomy, not a
prior learnt from the test sequence; the method stays training-free.

:class:`Anatomy` is static (hashable) data: limbs as chains of bone indices, whose sign combinations are
chosen jointly over the sequence by :func:`bcmocap.kcs.solve.limb_signs`, the hinges within them, and
the bone pairs that define the lateral axis.
"""

from __future__ import annotations

import dataclasses

from .chain_space import KinematicChainSpace

__all__ = ["Anatomy", "Hinge", "human_anatomy"]


@dataclasses.dataclass(frozen=True)
class Hinge:
    """A hinge between two consecutive bones of one limb.

    Attributes:
        limb: index into :attr:`Anatomy.limbs`.
        parent: position of the proximal bone within the limb.
        child: position of the distal bone within the limb.
        sign: +1 if ``parent × child`` points along the lateral axis, −1 against it.
        planar: also penalise the hinge axis leaving the lateral axis (``|p × c| − sign (p × c)·lateral``,
            normalised), not only the wrong bending direction.
        lateral: index into :attr:`Anatomy.laterals`.
    """

    limb: int
    parent: int
    child: int
    sign: float
    planar: bool
    lateral: int


@dataclasses.dataclass(frozen=True)
class Anatomy:
    """Limbs (groups of bone indices whose signs are chosen jointly) with hinges, and lateral axes.

    A limb is usually a chain (each bone starting where the previous ends); its temporal smoothness
    term acts on the cumulative sums of its bones (the chain's joints). A group of bones from one
    segment (the pelvis) works the same way: the sums are a fixed linear map of its bones.
    ``laterals`` are sums of unit differences of bone pairs (e.g. left hip − right hip).
    ``rigid`` lists ``(limb, i, j)``: bones ``i`` and ``j`` of a limb on one (nearly) rigid segment,
    whose angle keeps its value in the initial configuration ``B0``.
    """

    limbs: tuple[tuple[int, ...], ...]
    hinges: tuple[Hinge, ...]
    laterals: tuple[tuple[tuple[int, int], ...], ...]
    rigid: tuple[tuple[int, int, int], ...] = ()


def human_anatomy(chain: KinematicChainSpace) -> Anatomy | None:
    """The knee, ankle and elbow hinges and the rigid pelvis and thorax of a human chain named like
    :data:`~bcmocap.kcs.CMU_JOINTS`.

    Needs the joints ``root, lfemur, ltibia, lfoot, rfemur, rtibia, rfoot, thorax, lhumerus, lradius,
    lwrist, rhumerus, rradius, rwrist`` (``ltoes``/``rtoes`` optional: the ankle hinges; ``lowerneck``
    optional: the thorax group); returns ``None`` for other chains (the solver then keeps its per-bone
    sign choice). Limbs: left leg, right leg (thigh, shank, foot), left arm, right arm (upper arm,
    forearm), pelvis (both hip bones, lower spine), thorax (both clavicle bones, lower neck).
    """
    index = {n: i for i, n in enumerate(chain.names)}
    bone_of = {link: k for k, link in enumerate(chain.links)}

    def bone(a, b):
        if a not in index or b not in index:
            return None
        return bone_of.get((index[a], index[b]))

    hips = (bone("root", "lfemur"), bone("root", "rfemur"))
    shoulders = (bone("thorax", "lhumerus"), bone("thorax", "rhumerus"))
    if None in hips or None in shoulders:
        return None
    lateral = (hips, shoulders)
    limbs, hinges = [], []
    for side in "lr":
        leg = [bone(f"{side}femur", f"{side}tibia"), bone(f"{side}tibia", f"{side}foot")]
        if None in leg:
            return None
        toes = bone(f"{side}foot", f"{side}toes")
        if toes is not None:
            leg.append(toes)
        limbs.append(tuple(leg))
        hinges.append(Hinge(len(limbs) - 1, 0, 1, 1.0, True, 0))
        if toes is not None:
            hinges.append(Hinge(len(limbs) - 1, 1, 2, -1.0, True, 0))
    for side in "lr":
        arm = (bone(f"{side}humerus", f"{side}radius"), bone(f"{side}radius", f"{side}wrist"))
        if None in arm:
            return None
        limbs.append(arm)
        hinges.append(Hinge(len(limbs) - 1, 0, 1, -1.0, False, 0))
    rigid = []
    spine = bone("root", "thorax")
    if spine is not None:
        limbs.append((*hips, spine))
        rigid += [(len(limbs) - 1, 0, 1), (len(limbs) - 1, 0, 2), (len(limbs) - 1, 1, 2)]
    neck = bone("thorax", "lowerneck")
    if neck is not None:
        limbs.append((*shoulders, neck))
        rigid += [(len(limbs) - 1, 0, 1), (len(limbs) - 1, 0, 2), (len(limbs) - 1, 1, 2)]
    return Anatomy(tuple(limbs), tuple(hinges), (lateral,), tuple(rigid))
