"""Motion files: BVH and Acclaim ASF/AMC (the CMU database) to and from :class:`~bcmocap.kinematics.Skeleton`
and :class:`~bcmocap.kinematics.Motion`, converted to bcmocap's Z-up world in metres; PLY point clouds and camera
paths; C3D marker files."""

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562), so that `import bcmocap.io.<module>` (e.g. the commands' output folders) does
# not pay for JAX where it is not used.
_PUBLIC = {
    "AsfBone": "asf",
    "AsfData": "asf",
    "load_cmu": "asf",
    "read_amc": "asf",
    "read_asf": "asf",
    "BvhData": "bvh",
    "read_bvh": "bvh",
    "write_bvh": "bvh",
    "C3dData": "c3d",
    "read_c3d": "c3d",
    "read_ply": "ply",
    "read_ply_elements": "ply",
    "write_camera_paths_ply": "ply",
    "write_ply": "ply",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _PUBLIC)
