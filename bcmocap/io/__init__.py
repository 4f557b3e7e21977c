"""Motion files: BVH and Acclaim ASF/AMC (the CMU database) to and from :class:`~bcmocap.kinematics.Skeleton`
and :class:`~bcmocap.kinematics.Motion`, converted to bcmocap's Z-up world in metres; PLY point clouds and camera
paths; C3D marker files."""

from .asf import AsfBone, AsfData, load_cmu, read_amc, read_asf
from .bvh import BvhData, read_bvh, write_bvh
from .c3d import C3dData, read_c3d  # noqa: F401  (C3D marker trajectories, via ezc3d)
from .ply import read_ply, read_ply_elements, write_camera_paths_ply, write_ply

__all__ = [
    "AsfBone",
    "AsfData",
    "BvhData",
    "load_cmu",
    "read_amc",
    "read_asf",
    "read_bvh",
    "read_ply",
    "read_ply_elements",
    "write_bvh",
    "write_camera_paths_ply",
    "write_ply",
]
