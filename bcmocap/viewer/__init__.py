"""``bcmocap view``: a run in the browser (viser), with the paper's interactive correction of joint centres
and camera mounts (000 §4.2). The only package that imports viser.

- :mod:`.inputs`: what the viewer shows (plain arrays and callbacks);
- :mod:`.posing`: a motion posed on an editable model in numpy (edits redraw at once);
- :mod:`.edits`: joint-centre and camera-mount edits and their checks;
- :mod:`.overlay`: a video frame with measurements, reprojections and residual lines;
- :mod:`.video`: random access to video frames;
- :mod:`.app`: the viser app;
- :mod:`.browser`: headless Chromium over the DevTools protocol (tests, benchmark, screenshots).

Reading a run folder and saving an edited model are the pipeline's (:mod:`bcmocap.pipeline.view_input`,
:mod:`bcmocap.pipeline.model_edit`).
"""

from .edits import EditableModel
from .inputs import CameraFrame, GroundTruth, ViewerInput
from .posing import Posing

__all__ = ["CameraFrame", "EditableModel", "GroundTruth", "Posing", "ViewerInput"]
