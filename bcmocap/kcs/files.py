"""The output folder of ``bcmocap kcs`` (:func:`bcmocap.kcs.command.run_kcs` writes it, ``bcmocap view`` reads
it): the file names, owned here once.

``joints_3d.csv`` (frame, joint, x, y, z in m), ``result.npz`` (``joints`` ``(F, J, 3)`` m in the model frame,
``names``, ``parents``, ``bone_names`` ``"a->b"``, the camera path and the reprojection history),
``motion.bvh`` and ``report.json`` (``fps``, iterations, reprojection error, bone lengths).
"""

JOINTS_CSV = "joints_3d.csv"
RESULT = "result.npz"
MOTION_BVH = "motion.bvh"
REPORT = "report.json"
#: Every file the command writes.
OUTPUT_FILES = (JOINTS_CSV, RESULT, MOTION_BVH, REPORT)
