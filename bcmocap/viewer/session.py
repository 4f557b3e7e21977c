"""What every viewer of :mod:`bcmocap.viewer` shares: the stage (lights, ground grid, first view) and the
time slider with play/pause and speed.

A viewer (:class:`~bcmocap.viewer.app.Viewer` for a run, :class:`~bcmocap.viewer.tracks.TrackViewer` for
the points of ``bcmocap markers`` and ``bcmocap kcs``) derives from :class:`Session`, gives it ``server``,
``lock`` and ``data`` (with ``num_frames`` and ``fps``), and draws a frame in ``_draw(frame)``; moving the
slider, playing and :meth:`Session.show_frame` all end there.
"""

from __future__ import annotations

import abc
import threading
import time

import numpy as np

#: Playback sends at most this many frames per second: a browser drawing WebGL in software falls behind a
#: faster stream of updates and then draws far fewer (``benchmarks/viewer.py``).
MAX_PLAYBACK_RATE = 15.0


class Session(abc.ABC):
    """A viewer on a viser server: its stage, and a frame slider, play/pause and speed (a thread advances
    the frame while playing).

    Attributes:
        frame: the frame shown; playing: whether playback runs; speed: playback speed (× real time);
            max_rate: the most frames per second playback sends.
        frames_drawn: frames sent to the browser so far (for frame-rate measurements).
        slider, play_button, speed_slider, time_text: the panel's controls (after :meth:`_add_playback`);
            follow: the "follow the subject" box (after :meth:`_add_follow`).
    """

    server: object
    lock: threading.RLock
    data: object

    @property
    def num_frames(self) -> int:
        return self.data.num_frames

    @property
    def fps(self) -> float:
        return self.data.fps

    def _init_playback(self, max_rate: float) -> None:
        self.frame, self.playing, self.speed, self.max_rate = 0, False, 1.0, max_rate
        self.frames_drawn = 0
        self._stop = threading.Event()
        self._player: threading.Thread | None = None

    def _set_stage(self, centre, ground_z: float, distance: float = 2.5):
        """Lights without shadows (they cost a software renderer most of its time), no environment map, a
        ground grid at height ``ground_z`` (m) under ``centre`` ``(3,)``, and the first view looking at
        ``centre`` from ``distance`` (m) to the front right and a little above; returns the grid's handle."""
        scene = self.server.scene
        centre = np.asarray(centre, np.float64)
        direction = np.array([1.0, -1.0, 0.35]) / np.linalg.norm([1.0, -1.0, 0.35])
        self.server.initial_camera.position = tuple(centre + distance * direction)
        self.server.initial_camera.look_at = tuple(centre + np.array([0.0, 0.0, -0.15]))
        scene.configure_default_lights(cast_shadow=False)
        scene.configure_environment_map(None)
        return scene.add_grid("/grid", width=40.0, height=40.0, plane="xy", cell_size=0.5, section_size=2.0,
                              shadow_opacity=0.0, position=(float(centre[0]), float(centre[1]), float(ground_z)))

    def _add_playback(self, gui) -> None:
        """The controls, in the panel's current folder."""
        self.slider = gui.add_slider("frame", 0, max(self.num_frames - 1, 1), 1, 0)
        self.slider.on_update(lambda event: self.show_frame(int(self.slider.value)))
        self.time_text = gui.add_markdown("")
        self.play_button = gui.add_button("Play", icon=None)
        self.play_button.on_click(lambda event: self.set_playing(not self.playing))
        self.speed_slider = gui.add_slider("speed ×", 0.1, 4.0, 0.1, 1.0)
        self.speed_slider.on_update(lambda event: setattr(self, "speed", float(self.speed_slider.value)))

    def _add_follow(self, gui) -> None:
        """The "follow the subject" checkbox, in the panel's current folder (see :meth:`_follow`)."""
        self.follow = gui.add_checkbox("follow the subject", True,
                                       hint="move the view with the subject, so that it stays in sight")

    def _follow(self, anchor: np.ndarray) -> None:
        """Shift every browser's view by the move of ``anchor`` ``(3,)`` (the root, the markers' centre) since
        the last frame drawn, when "follow the subject" is ticked."""
        previous, self._followed = getattr(self, "_followed", None), anchor
        if previous is None or not self.follow.value:
            return
        delta = anchor - previous
        if not np.all(np.isfinite(delta)) or not np.any(delta):
            return
        for client in self.server.get_clients().values():
            camera = client.camera
            if camera.update_timestamp == 0.0:  # the browser has not reported its view yet
                continue
            with client.atomic():
                camera.look_at = camera.look_at + delta
                camera.position = camera.position + delta

    def _start_player(self) -> None:
        self._player = threading.Thread(target=self._play_loop, name="bcmocap-view-playback", daemon=True)
        self._player.start()

    @abc.abstractmethod
    def _draw(self, frame: int) -> None:
        """Send ``frame`` to the browser (under :attr:`lock`)."""

    def show_frame(self, frame: int) -> None:
        """Draw ``frame`` (clamped to the motion)."""
        with self.lock:
            frame = int(np.clip(frame, 0, self.num_frames - 1))
            self.frame = frame
            if int(self.slider.value) != frame:
                self.slider.value = frame  # calls back into show_frame (re-entrant lock), which draws
                return
            self._draw(frame)
            self.frames_drawn += 1

    def time_line(self, frame: int) -> str:
        return f"t = {frame / self.fps:.2f} s · frame {frame} of {self.num_frames - 1} · {self.fps:g} fps"

    def set_playing(self, playing: bool) -> None:
        self.playing = bool(playing)
        self.play_button.label = "Pause" if self.playing else "Play"

    def _play_loop(self) -> None:
        last, position = time.perf_counter(), None
        while not self._stop.is_set():
            time.sleep(1 / self.max_rate)
            now = time.perf_counter()
            if not self.playing:
                last, position = now, None
                continue
            if position is None:
                position = float(self.frame)
            position = (position + (now - last) * self.speed * self.fps) % self.num_frames
            last = now
            if int(position) == self.frame:
                continue
            try:
                self.show_frame(int(position))
            except Exception as exc:  # noqa: BLE001 - playback stops; the viewer stays up
                self.set_playing(False)
                self.set_status(f"**Playback stopped:** {type(exc).__name__}: {exc}")

    @abc.abstractmethod
    def set_status(self, text: str) -> None:
        """Say ``text`` in the panel (markdown)."""

    def close(self) -> None:
        """Stop playback (the server is the caller's to stop)."""
        self._stop.set()
        if self._player is not None:
            self._player.join(timeout=2)
