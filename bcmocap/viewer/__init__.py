"""``bcmocap view``: a run in the browser (viser), with the paper's interactive correction of joint centres
and camera mounts (000 §4.2); and the outputs of ``bcmocap markers`` and ``bcmocap kcs`` on the same time
slider. The only package that imports viser.

- :mod:`.inputs`: what the viewers show (plain arrays and callbacks);
- :mod:`.posing`: a motion posed on an editable model in numpy (edits redraw at once);
- :mod:`.edits`: joint-centre and camera-mount edits and their checks;
- :mod:`.overlay`: a video frame with measurements, reprojections and residual lines;
- :mod:`.video`: random access to video frames;
- :mod:`.session`: what every viewer shares (the stage, the time slider, play/pause and speed);
- :mod:`.app`: the viser app of a run;
- :mod:`.tracks`: the viser app of points and lines over time (markers, joints, kinematic chains);
- :mod:`.browser`: headless Chromium over the DevTools protocol (tests, benchmark, screenshots).

Reading a run folder and saving an edited model are the pipeline's (:mod:`bcmocap.pipeline.view_input`,
:mod:`bcmocap.pipeline.model_edit`), and so is reading a ``bcmocap markers`` or ``bcmocap kcs`` folder
(:mod:`bcmocap.pipeline.view_tracks`).
"""

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562), so that the command line does not pay for JAX where it is not used.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "EditableModel": "edits",
    "CameraFrame": "inputs",
    "GroundTruth": "inputs",
    "LineTracks": "inputs",
    "PointTracks": "inputs",
    "TrackInput": "inputs",
    "ViewerInput": "inputs",
    "Posing": "posing",
})
