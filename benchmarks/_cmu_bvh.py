"""CMU trials from the cgspeed BVH conversion (Bruce Hahne's "MotionBuilder-friendly" BVH, 2010) as the joint
positions their ASF/AMC files would give (issue 47: subject 35's walks whose AMC files are nowhere public;
``benchmarks/data/cmu_bvh/SOURCES.md``).

The conversion keeps the ASF's bones one for one, in the same order under other names (``Hips`` for ``root``,
``LeftUpLeg`` for ``lfemur``, …), each offset the ASF bone's direction × length in the file's units (1/0.45 inch),
and adds a T-pose as frame 0. It drops two lengths: the thorax's (``Neck`` and both shoulders sit at ``Spine1``'s
origin, 0.116 m below where the ASF puts them for subject 35) and the wrists' (the hands). The thorax is put back from
the subject's ASF file: its rest vector (``lowerneck`` from ``thorax``) hangs ``Neck`` and the shoulders from
``Spine1``. At rest every joint of :data:`~bcmocap.kcs.CMU_JOINTS` then sits where the ASF puts it (the hands, which
the chain leaves out, 0.10 m off).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from bcmocap.io import read_bvh
from bcmocap.kcs import CMU_JOINTS
from bcmocap.kinematics import joint_positions

#: Metres per length unit of the CMU files and of their cgspeed conversion (1/0.45 inch).
CGSPEED_LENGTH_UNIT_M = 0.0254 / 0.45


def rest_positions(skeleton) -> np.ndarray:
    """``(J, 3)`` joint positions (m) of ``skeleton`` in its rest pose (:meth:`~bcmocap.kinematics.Skeleton.rest_motion`)."""
    return np.asarray(joint_positions(skeleton, skeleton.rest_motion()))


def cgspeed_skeleton(bvh_path: str | Path, asf):
    """The BVH file's :class:`~bcmocap.io.BvhData` with the thorax put back from ``asf`` (the subject's
    :func:`~bcmocap.io.read_asf`).

    Raises:
        ValueError: the file's joints are not the ASF's bones, or its neck is not where the conversion puts it.
    """
    bvh = read_bvh(bvh_path, length_unit_m=CGSPEED_LENGTH_UNIT_M)
    names, parents = asf.skeleton.names, np.asarray(asf.skeleton.parents)
    if len(bvh.skeleton.names) != len(names) or not np.array_equal(np.asarray(bvh.skeleton.parents), parents):
        raise ValueError(f"{bvh_path}: its {len(bvh.skeleton.names)} joints are not the {len(names)} bones of the ASF "
                         "file in order (not a cgspeed conversion of this subject)")
    thorax = names.index("thorax")
    hung = np.flatnonzero(parents == thorax)  # lowerneck and the clavicles: Neck, LeftShoulder, RightShoulder
    offsets = np.array(bvh.skeleton.offsets)
    if np.abs(offsets[hung]).max() > 1e-9:
        raise ValueError(f"{bvh_path}: '{bvh.skeleton.names[hung[0]]}' is not at its parent's origin, as the cgspeed "
                         "conversion puts it")
    rest = rest_positions(asf.skeleton)
    offsets[hung] = rest[names.index("lowerneck")] - rest[thorax]
    return dataclasses.replace(bvh, skeleton=dataclasses.replace(bvh.skeleton, offsets=offsets))


def read_cgspeed_trial(bvh_path: str | Path, asf) -> np.ndarray:
    """``(F, J, 3)`` positions (m) of :data:`~bcmocap.kcs.CMU_JOINTS` over the trial's frames (the conversion's T-pose
    frame 0 left out), as :func:`~bcmocap.io.read_amc` of the trial's AMC file would give them."""
    bvh = cgspeed_skeleton(bvh_path, asf)
    keep = [asf.skeleton.names.index(n) for n in CMU_JOINTS]
    return np.asarray(joint_positions(bvh.skeleton, bvh.motion))[1:, keep]
