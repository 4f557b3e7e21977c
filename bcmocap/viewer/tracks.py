"""The viewer of a ``bcmocap markers`` or ``bcmocap kcs`` folder: points and lines on a time slider.

Scene (Z up, metres): one node per layer of the :class:`~bcmocap.viewer.inputs.TrackInput`, named by its
key: a point cloud for :class:`~bcmocap.viewer.inputs.PointTracks` (``/markers``, ``/joints``), line
segments for :class:`~bcmocap.viewer.inputs.LineTracks` (``/skeleton``, ``/segments``, ``/bones``,
``/links``). Points or lines not known at a frame are left out of it. Panel: playback, "follow the
subject" (the view moves with the centre of the points), a checkbox per layer, the colour legend, and the
command's report. There is no model to edit.
"""

from __future__ import annotations

import html
import threading

import numpy as np

from .inputs import PointTracks, TrackInput
from .session import MAX_PLAYBACK_RATE, Session


class TrackViewer(Session):
    """One session on ``server`` (a ``viser.ViserServer``) showing ``data``.

    Attributes:
        handles: layer name → its scene node.
        boxes: layer name → its checkbox.
        frame, playing, speed, max_rate, frames_drawn: playback (:class:`~bcmocap.viewer.session.Session`).
        status: the last message shown in the panel.
    """

    def __init__(self, data: TrackInput, server, max_rate: float = MAX_PLAYBACK_RATE):
        if not data.layers:
            raise ValueError(f"{data.title}: nothing to show")
        self.data, self.server = data, server
        self.lock = threading.RLock()
        self._init_playback(max_rate)
        self.status = ""
        self.handles: dict = {}
        self.boxes: dict = {}
        self._build_scene()
        self._build_panel()
        self.show_frame(0)
        self._start_player()

    def _build_scene(self) -> None:
        first = self._seen(0)
        heights = [layer.positions[..., 2] for layer in self.data.layers.values() if isinstance(layer, PointTracks)]
        low = min((np.nanmin(h) for h in heights if np.isfinite(h).any()), default=0.0)  # the ground, roughly
        centre = first.mean(axis=0) if len(first) else np.zeros(3)
        extent = float(np.ptp(first, axis=0).max()) if len(first) > 1 else 1.0
        self.grid = self._set_stage(centre, float(low), distance=max(1.0, 1.5 * extent))
        scene = self.server.scene
        for name, layer in self.data.layers.items():
            if isinstance(layer, PointTracks):
                xyz, colours = layer.at(0)
                self.handles[name] = scene.add_point_cloud(f"/{name}", xyz, colours, point_size=layer.size_m,
                                                           point_shape="circle", precision="float32")
            else:
                ends, colours = layer.at(0)
                self.handles[name] = scene.add_line_segments(f"/{name}", ends, colours, thickness=layer.thickness_m)

    def _build_panel(self) -> None:
        gui, data = self.server.gui, self.data
        gui.configure_theme(control_width="large")
        gui.set_panel_label(f"bcmocap view · {data.title}")
        gui.add_markdown("\n\n".join(data.notes), visible=bool(data.notes))
        with gui.add_folder("Playback"):
            self._add_playback(gui)
        with gui.add_folder("Show"):
            self._add_follow(gui)
            for name, layer in data.layers.items():
                box = gui.add_checkbox(layer.label, True)
                box.on_update(lambda event, name=name: self._set_visible(name, bool(self.boxes[name].value)))
                self.boxes[name] = box
            if data.legend:
                gui.add_html(legend_html(data.legend))
        self.status_text = gui.add_markdown("")
        if data.report:
            with gui.add_folder("Report", expand_by_default=False):
                gui.add_markdown(data.report)

    def _set_visible(self, name: str, visible: bool) -> None:
        with self.lock:
            self.handles[name].visible = visible
            self.show_frame(self.frame)

    def _draw(self, frame: int) -> None:
        with self.server.atomic():
            for name, layer in self.data.layers.items():
                handle = self.handles[name]
                if not self.boxes[name].value:
                    continue
                shown, colours = layer.at(frame)
                handle.visible = len(shown) > 0
                handle.points, handle.colors = shown, colours
        seen = self._seen(frame)
        self._follow(seen.mean(axis=0) if len(seen) else np.full(3, np.nan))
        self.time_text.content = self.time_line(frame)

    def _seen(self, frame: int) -> np.ndarray:
        """``(n, 3)`` the points of every point layer seen at ``frame``."""
        points = [layer.positions[frame] for layer in self.data.layers.values() if isinstance(layer, PointTracks)]
        points = np.concatenate(points) if points else np.zeros((0, 3))
        return points[np.isfinite(points).all(axis=-1)]

    def set_status(self, text: str) -> None:
        self.status = text
        self.status_text.content = text


def legend_html(rows: list[tuple[str, tuple[int, int, int]]]) -> str:
    """An HTML list of ``(text, RGB)`` rows, each behind a square of its colour."""
    items = "".join(f'<div><span style="color: rgb({r}, {g}, {b}); font-size: 1.2em">&#9632;</span> '
                    f"{html.escape(text)}</div>" for text, (r, g, b) in rows)
    return f'<div style="font-size: 0.85em; line-height: 1.5">{items}</div>'
