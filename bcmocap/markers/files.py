"""The output folder of ``bcmocap markers`` (:meth:`bcmocap.markers.pipeline.MarkerSkeleton.save` writes it,
``bcmocap view`` reads it): the file names, owned here once.

``skeleton.json`` (``fps``; ``segments``: name, parent, markers; ``markers``: label → segment), ``poses.npz``
(``root_position`` ``(F, 3)`` m, ``rotations`` ``(F, J, 4)`` wxyz, ``joint_positions`` ``(F, J, 3)`` m,
``marker_positions`` ``(F, M, 3)`` m, ``marker_labels`` ``(M,)``, ``segment_names`` ``(J,)``), ``skeleton.bvh``
and ``report.txt``.
"""

SKELETON_BVH = "skeleton.bvh"
SKELETON_JSON = "skeleton.json"
POSES = "poses.npz"
REPORT = "report.txt"
#: Every file the command writes.
OUTPUT_FILES = (SKELETON_BVH, SKELETON_JSON, POSES, REPORT)
