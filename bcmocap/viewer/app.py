"""The viewer: a viser web app over a :class:`~bcmocap.viewer.inputs.ViewerInput`.

Scene (Z up, metres), by node name: ``/estimate/bones`` and ``/estimate/joints`` (the estimated skeleton,
one batched mesh of J spheres; a joint's colour is its position error when there is ground truth, green
0 cm → red :data:`ERROR_RED_CM`), ``/truth/bones`` and ``/truth/joints`` (the ground truth, orange),
``/cameras/bodies`` and ``/cameras/frusta`` (the body cameras at their poses under the model being viewed:
C boxes, C × 8 lines), ``/registered/frusta`` (the frontend's registered poses, on request),
``/scene/points``, ``/root_path`` and ``/edit/gizmo`` (the transform gizmo of the selected joint centre or
camera mount). Batched nodes keep a playback frame to a handful of messages, which the browser can follow.

Panel: playback (frame slider, play/pause, speed, motion; :mod:`.session`), what to show, the selected
camera's video frame with measurements and reprojections (:mod:`.overlay`), model editing (select, drag,
save, revert; :mod:`.edits`), ``metrics.json`` and the run's pictures. Everything the panel does is also a
method (:meth:`Viewer.show_frame`, :meth:`Viewer.select`, :meth:`Viewer.drag_to`, :meth:`Viewer.save`),
which is how the tests drive it.

The first frame needs only the model and the motions: the scene points, the ground truth and the camera
videos that :attr:`ViewerInput.later <bcmocap.viewer.inputs.ViewerInput.later>` defers are read in a
background thread, and added to the scene and panel with the pictures once a browser has that frame
(:attr:`Viewer.ready` is set then).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ..geometry import matrix_from_quat
from .edits import EditableModel
from .inputs import ViewerInput
from .posing import Posing
from .session import MAX_PLAYBACK_RATE, Session

#: Joint error (cm) drawn fully red; 0 cm is green.
ERROR_RED_CM = 5.0
#: Bones, truth, cameras, registered poses, selection, scene points, error-free joints (RGB).
BONE, TRUTH, CAMERA, REGISTERED, SELECTED, POINTS, JOINT = ((40, 110, 230), (255, 140, 0), (35, 35, 35),
                                                            (150, 150, 150), (250, 190, 0), (120, 140, 160),
                                                            (40, 110, 230))
#: ``bcmocap view`` reads the deferred scene points, ground truth, videos and pictures while the page starts
#: up, and sends them this long (s) after a browser has reported its view (it does once it is connected and
#: has the first frame's messages), or after :data:`FIRST_VIEW_WAIT_S` without a browser: sent before, a
#: megabyte or more would stand between the page and its first frame.
FIRST_VIEW_SETTLE_S, FIRST_VIEW_WAIT_S = 1.0, 10.0
_NOTHING = "(nothing)"
_NO_CAMERA = "(none)"


def error_colours(error_cm: np.ndarray) -> np.ndarray:
    """``(..., 3)`` uint8 colours of joint errors (cm): green at 0, yellow at half :data:`ERROR_RED_CM`,
    red from :data:`ERROR_RED_CM` on; NaN (no truth) is the plain joint colour."""
    e = np.asarray(error_cm, np.float64)
    u = np.clip(np.nan_to_num(e, nan=0.0) / ERROR_RED_CM, 0.0, 1.0)[..., None]
    green, yellow, red = np.array([40, 200, 60]), np.array([240, 210, 40]), np.array([220, 40, 40])
    colour = np.where(u < 0.5, green + (yellow - green) * (2 * u), yellow + (red - yellow) * (2 * u - 1))
    colour = np.where(np.isnan(e)[..., None], np.array(JOINT), colour)
    return np.round(colour).astype(np.uint8)


def frustum_lines(poses: np.ndarray, aspect: float, depth: float = 0.07, fov_deg: float = 70.0) -> np.ndarray:
    """``(C * 8, 2, 3)`` line segments drawing a frustum (apex to the 4 corners, and the image rectangle) for
    each camera pose ``(C, 7)`` world_from_camera (OpenCV axes: z forward, y down); ``depth`` in m,
    ``fov_deg`` vertical (a symbol of where a camera looks, not its real 170° field)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    h = depth * np.tan(np.deg2rad(fov_deg) / 2)
    w = h * aspect
    corners = np.array([[-w, -h, depth], [w, -h, depth], [w, h, depth], [-w, h, depth]])
    world = np.einsum("cij,kj->cki", matrix_from_quat(poses[:, :4]), corners) + poses[:, None, 4:]
    apex = np.broadcast_to(poses[:, None, 4:], world.shape)
    rays = np.stack([apex, world], axis=2)
    rim = np.stack([world, np.roll(world, -1, axis=1)], axis=2)
    return np.concatenate([rays, rim], axis=1).reshape(-1, 2, 3)


def sphere_mesh(radius: float, rings: int = 8, segments: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3)`` vertices (m) and ``(F, 3)`` faces of a UV sphere."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack(np.broadcast_arrays(np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                                        np.cos(theta)[:, None]), axis=-1).reshape(-1, 3)
    vertices = radius * np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]])
    faces, top, bottom = [], 0, len(vertices) - 1

    def at(r, k):
        return 1 + r * segments + k % segments

    for k in range(segments):
        faces.append((top, at(0, k), at(0, k + 1)))
        faces.append((bottom, at(rings - 2, k + 1), at(rings - 2, k)))
        for r in range(rings - 2):
            faces += [(at(r, k), at(r + 1, k), at(r + 1, k + 1)), (at(r, k), at(r + 1, k + 1), at(r, k + 1))]
    return vertices.astype(np.float32), np.asarray(faces, np.uint32)


def box_mesh(extents) -> tuple[np.ndarray, np.ndarray]:
    """``(8, 3)`` vertices (m) and ``(12, 3)`` outward faces of a box centred at the origin."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32) * 0.5
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6),
             (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return corners * np.asarray(extents, np.float32), np.asarray(faces, np.uint32)


class Viewer(Session):
    """One viewer session on ``server`` (a ``viser.ViserServer``) showing ``data``; playback sends at most
    ``max_rate`` frames per second. What the first frame does without (:attr:`ViewerInput.later
    <bcmocap.viewer.inputs.ViewerInput.later>`) is read in the background at once, and added to the scene
    and panel (with the pictures) once a browser has the first frame, or after ``browser_wait_s`` without
    one (0: at once; ``bcmocap view`` waits up to :data:`FIRST_VIEW_WAIT_S`).

    Attributes:
        frame, playing, speed, max_rate, frames_drawn: playback (:class:`~bcmocap.viewer.session.Session`).
        model: the model being viewed (:class:`~bcmocap.viewer.edits.EditableModel`); edited: joints and
            cameras an edit touched since the last save.
        joints: ``(T, J, 3)`` joint centres under :attr:`model`; cameras ``(T, C, 7)`` world_from_camera.
        status: the last message of the editing panel.
        ready: set once what the first frame does without (deferred inputs, pictures) is in the scene and panel.
    """

    def __init__(self, data: ViewerInput, server, max_rate: float = MAX_PLAYBACK_RATE, browser_wait_s: float = 0.0):
        self.data, self.server = data, server
        self.lock = threading.RLock()
        self._init_playback(max_rate)
        self._browser_wait_s = browser_wait_s
        self.status = ""
        self.ready = threading.Event()
        self.loaded_model = EditableModel.of(data.skeleton, data.rig)
        self.model = self.loaded_model
        self.edited_joints: set[int] = set()
        self.edited_cameras: set[int] = set()
        self.selection: tuple[str, int] | None = None
        self.camera_view: int | None = None
        self._camera_drawn_at = 0.0
        self._postures = {name: Posing(data.skeleton.parents, m.root_position, m.rotations)
                          for name, m in data.motions.items()}
        self.motion = next(iter(data.motions))
        self._dragging = False
        self._colour_key = None
        self._recompute()
        self._build_scene()
        self._build_panel()
        self.show_frame(0)
        self._start_player()
        self._extras = threading.Thread(target=self._add_extras, name="bcmocap-view-extras", daemon=True)
        self._extras.start()

    # ---- model → arrays ---------------------------------------------------------------------------
    @property
    def posing(self) -> Posing:
        return self._postures[self.motion]

    def _recompute(self) -> None:
        self.joints = self.posing.joint_positions(self.model.offsets)
        self.cameras = (self.posing.camera_poses(self.joints, self.model.camera_segments, self.model.mounts)
                        if self.model.camera_names else np.zeros((self.num_frames, 0, 7)))
        truth = self.data.truth
        self.errors_cm = None
        if truth is not None:
            index = {n: k for k, n in enumerate(truth.names)}
            pairs = [(j, index[n]) for j, n in enumerate(self.model.names) if n in index]
            self.errors_cm = np.full(self.joints.shape[:2], np.nan)
            if pairs:
                est, tru = zip(*pairs)
                diff = self.joints[:, list(est)] - truth.joints[:, list(tru)]
                self.errors_cm[:, list(est)] = 100 * truth.to_truth_scale * np.linalg.norm(diff, axis=-1)

    def error_at(self, frame: int) -> np.ndarray | None:
        """``(J,)`` joint position errors (cm, in the truth's scale) at ``frame``; None without truth."""
        return None if self.errors_cm is None else self.errors_cm[frame]

    # ---- scene ------------------------------------------------------------------------------------
    def _bones(self, positions: np.ndarray, parents) -> np.ndarray:
        pairs = [(parents[k], k) for k in range(1, len(parents))]
        return np.stack([positions[[a for a, _ in pairs]], positions[[b for _, b in pairs]]], axis=1)

    def _build_scene(self) -> None:
        scene, data = self.server.scene, self.data
        self.grid = self._set_stage(self.joints[0, 0], 0.0)
        self.points_handle = self.truth_bones = self.truth_joints = None
        self._add_scene_points()
        root = self.joints[:, 0]
        path = np.stack([root[:-1], root[1:]], axis=1) if len(root) > 1 else np.zeros((0, 2, 3))
        self.root_path = scene.add_line_segments("/root_path", path, (200, 60, 200), thickness=0.006)
        parents = self.model.parents
        self.bones = scene.add_line_segments("/estimate/bones", self._bones(self.joints[0], parents), BONE,
                                             thickness=0.018)
        self.joint_meshes = scene.add_batched_meshes_simple(
            "/estimate/joints", *sphere_mesh(0.028), np.tile([1.0, 0, 0, 0], (len(parents), 1)),
            self.joints[0], batched_colors=np.tile(JOINT, (len(parents), 1)).astype(np.uint8), lod="off",
            cast_shadow=False, receive_shadow=False)
        self.joint_meshes.on_click(lambda event: self._clicked("joint", event))
        self._add_truth()
        self.camera_meshes = self.frusta = self.registered_frusta = None
        cameras = len(self.model.camera_names)
        if cameras:
            rig = data.rig
            self._aspect = float(rig.intrinsics.width) / float(rig.intrinsics.height)
            self.camera_meshes = scene.add_batched_meshes_simple(
                "/cameras/bodies", *box_mesh((0.03, 0.022, 0.018)), self.cameras[0, :, :4], self.cameras[0, :, 4:],
                batched_colors=np.tile(CAMERA, (cameras, 1)).astype(np.uint8), lod="off", cast_shadow=False,
                receive_shadow=False)
            self.camera_meshes.on_click(lambda event: self._clicked("camera", event))
            self.frusta = scene.add_line_segments("/cameras/frusta", frustum_lines(self.cameras[0], self._aspect),
                                                  self._frustum_colours(), thickness=0.003)
            if data.registered is not None:
                self.registered_frusta = scene.add_line_segments(
                    "/registered/frusta", frustum_lines(np.nan_to_num(data.registered[0]), self._aspect), REGISTERED,
                    thickness=0.0025, visible=False)
        self.gizmo = scene.add_transform_controls("/edit/gizmo", scale=0.25, visible=False, depth_test=False)
        self.gizmo.on_update(self._on_gizmo)

    def _add_scene_points(self) -> None:
        points = self.data.scene_points
        if self.points_handle is None and points is not None and len(points):
            self.points_handle = self.server.scene.add_point_cloud(
                "/scene/points", np.asarray(points, np.float32), POINTS, point_size=0.012, precision="float32")

    def _add_truth(self) -> None:
        truth = self.data.truth
        if self.truth_joints is None and truth is not None:
            t0 = np.nan_to_num(truth.joints[self.frame])
            self.truth_bones = self.server.scene.add_line_segments("/truth/bones", self._bones(t0, truth.parents),
                                                                   TRUTH, thickness=0.01)
            self.truth_joints = self.server.scene.add_point_cloud("/truth/joints", t0.astype(np.float32), TRUTH,
                                                                  point_size=0.035, point_shape="circle",
                                                                  precision="float32")

    def _wait_for_a_browser(self, timeout: float) -> None:
        """Until :data:`FIRST_VIEW_SETTLE_S` after a browser reported its view, or ``timeout`` s without one."""
        if timeout <= 0:
            return
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self._stop.is_set():
            if any(c.camera.update_timestamp > 0 for c in self.server.get_clients().values()):
                self._stop.wait(FIRST_VIEW_SETTLE_S)
                return
            self._stop.wait(0.05)

    def _add_extras(self) -> None:
        """In the background: read what :attr:`ViewerInput.later` defers, and once a browser has the first
        frame add it to the scene and the panel, then the pictures."""
        data = self.data
        try:
            try:
                data.complete()
            except (ValueError, OSError) as exc:
                data.notes.append(f"Not everything could be read: {' '.join(str(exc).split())}")
            self._wait_for_a_browser(self._browser_wait_s)
            with self.lock:
                self._add_scene_points()
                self._add_truth()
                self._recompute()
                self._show_boxes()
                self.notes_text.content = "\n\n".join(data.notes)
                self.notes_text.visible = bool(data.notes)
                if self.camera_text is not None and self.camera_view is None:
                    self.camera_text.content = self._camera_legend()
                if self.camera_view is not None:
                    self._draw_camera_view()
                self.show_frame(self.frame)
            for path in data.pictures:
                image = _read_picture(path)
                if image is not None:
                    with self.pictures_folder:
                        self.server.gui.add_image(image, label=path.stem.replace("_", " "))
        finally:
            self.ready.set()

    # ---- panel ------------------------------------------------------------------------------------
    def _build_panel(self) -> None:
        gui, data = self.server.gui, self.data
        gui.configure_theme(control_width="large")
        gui.set_panel_label(f"bcmocap view · {data.title}")
        self.notes_text = gui.add_markdown("\n\n".join(data.notes), visible=bool(data.notes))
        with gui.add_folder("Playback"):
            self._add_playback(gui)
            if len(data.motions) > 1:
                self.motion_menu = gui.add_dropdown("motion", tuple(data.motions), initial_value=self.motion)
                self.motion_menu.on_update(lambda event: self.set_motion(self.motion_menu.value))
        with gui.add_folder("Show"):
            self.show_truth = gui.add_checkbox("ground truth", False, disabled=True)
            self.show_registered = gui.add_checkbox("registered poses (frontend)", False,
                                                    disabled=data.registered is None)
            self.show_points = gui.add_checkbox("scene points", False, disabled=True)
            self._add_follow(gui)
            self.truth_legend = gui.add_markdown(f"Joint colour: position error, green 0 cm → red ≥ "
                                                 f"{ERROR_RED_CM:g} cm; orange: the ground truth.", visible=False)
            self._show_boxes()
            for box in (self.show_truth, self.show_registered, self.show_points):
                box.on_update(lambda event: self._apply_visibility())
        self.camera_text = None
        if self.model.camera_names:
            videos = data.camera_frame is not None or data.later is not None
            with gui.add_folder("Camera view", expand_by_default=videos):
                self.camera_menu = gui.add_dropdown("camera", (_NO_CAMERA, *self.model.camera_names),
                                                    initial_value=_NO_CAMERA)
                self.camera_menu.on_update(lambda event: self.set_camera_view(
                    None if self.camera_menu.value == _NO_CAMERA
                    else self.model.camera_names.index(self.camera_menu.value)))
                self.camera_text = gui.add_markdown(self._camera_legend())
                self.camera_image = gui.add_image(np.zeros((9, 16, 3), np.uint8), visible=False)
        with gui.add_folder("Edit model"):
            choices = [_NOTHING] + [f"joint: {n}" for n in self.model.names[1:]] + \
                      [f"camera: {n}" for n in self.model.camera_names]
            self._choices = choices
            self.edit_menu = gui.add_dropdown("select", tuple(choices), initial_value=_NOTHING)
            self.edit_menu.on_update(lambda event: self._select_from_menu())
            gui.add_markdown("Drag the gizmo: a joint centre moves without moving its children or cameras; a "
                             "camera mount moves and turns relative to its segment. Click a joint or camera to "
                             "select it.")
            self.status_text = gui.add_markdown("")
            self.save_button = gui.add_button("Save model as a new version", disabled=data.save_model is None)
            self.save_button.on_click(lambda event: self.save())
            self.revert_button = gui.add_button("Revert to the loaded model")
            self.revert_button.on_click(lambda event: self.revert())
        if data.metrics:
            with gui.add_folder("Metrics", expand_by_default=False):
                gui.add_markdown(metrics_markdown(data.metrics))
        self.pictures_folder = gui.add_folder("Pictures", expand_by_default=False, visible=bool(data.pictures))

    def _show_boxes(self) -> None:
        """Enable (and tick) the ground-truth and scene-point boxes once those are in the scene."""
        for box, handle in ((self.show_truth, self.truth_joints), (self.show_points, self.points_handle)):
            if handle is not None and box.disabled:
                box.disabled = False
                box.value = True
        self.truth_legend.visible = self.truth_joints is not None

    def _camera_legend(self) -> str:
        if self.data.camera_frame is not None:
            return "green: measured · red: reprojected · yellow: residual"
        if self.data.later is not None:
            return "reading the videos and measurements ..."
        return "no videos or measurements for this run (capture folder not found)"

    def _clicked(self, kind: str, event) -> None:
        index = getattr(event, "instance_index", None)
        if index is not None and not (kind == "joint" and index == 0):
            self.select((kind, int(index)))

    def _joint_colours(self, colours) -> np.ndarray:
        out = np.tile(JOINT, (len(self.model.names), 1)).astype(np.uint8) if colours is None else colours.copy()
        if self.selection is not None and self.selection[0] == "joint":
            out[self.selection[1]] = SELECTED
        return out

    def _frustum_colours(self) -> np.ndarray:
        colours = np.tile(np.asarray(CAMERA, np.uint8), (len(self.model.camera_names), 8, 2, 1))
        if self.selection is not None and self.selection[0] == "camera":
            colours[self.selection[1]] = SELECTED
        return colours.reshape(-1, 2, 3)

    def _apply_visibility(self) -> None:
        with self.lock, self.server.atomic():
            for handle in (self.truth_bones, self.truth_joints):
                if handle is not None:
                    handle.visible = bool(self.show_truth.value)
            if self.registered_frusta is not None:
                self.registered_frusta.visible = bool(self.show_registered.value)
            if self.points_handle is not None:
                self.points_handle.visible = bool(self.show_points.value)
        self.show_frame(self.frame)

    # ---- time -------------------------------------------------------------------------------------
    def _draw(self, frame: int) -> None:
        joints, errors = self.joints[frame], self.error_at(frame)
        colours = error_colours(errors) if errors is not None else None
        with self.server.atomic():
            self.bones.points = self._bones(joints, self.model.parents)
            self.joint_meshes.batched_positions = joints
            key = (colours.tobytes() if colours is not None else None, self.selection)
            if key != self._colour_key:
                self.joint_meshes.batched_colors = self._joint_colours(colours)
                self._colour_key = key
            if self.camera_meshes is not None:
                self.camera_meshes.batched_wxyzs = self.cameras[frame, :, :4]
                self.camera_meshes.batched_positions = self.cameras[frame, :, 4:]
                self.frusta.points = frustum_lines(self.cameras[frame], self._aspect)
            if self.truth_joints is not None and self.show_truth.value:
                t = self.data.truth.joints[frame]
                ok = bool(np.isfinite(t).all())
                self.truth_bones.visible = self.truth_joints.visible = ok
                if ok:
                    self.truth_bones.points = self._bones(t, self.data.truth.parents)
                    self.truth_joints.points = t.astype(np.float32)
            if self.registered_frusta is not None and self.show_registered.value:
                pose = self.data.registered[frame]
                missing = ~np.isfinite(pose).all(axis=-1)  # unregistered: drawn as nothing (a point at the
                pose = np.where(missing[:, None], self.cameras[frame], pose)  # solved camera centre)
                lines = frustum_lines(pose, self._aspect).reshape(-1, 8, 2, 3)
                lines[missing] = pose[missing, None, None, 4:]
                self.registered_frusta.points = lines.reshape(-1, 2, 3)
            if self.selection is not None and not self._dragging:
                self._place_gizmo()
        self._follow(joints[0])
        self.time_text.content = self._time_line(frame, errors)
        if self.camera_view is not None and (not self.playing or time.perf_counter() - self._camera_drawn_at > 0.5):
            self._draw_camera_view()  # while playing, twice a second: a video frame is a large message

    def _time_line(self, frame: int, errors) -> str:
        line = self.time_line(frame)
        if errors is not None and np.isfinite(errors).any():
            line += f" · joint error mean {np.nanmean(errors):.2f} cm, max {np.nanmax(errors):.2f} cm"
        return line

    def set_motion(self, name: str) -> None:
        with self.lock:
            self.motion = name
            self._recompute()
            self.show_frame(self.frame)

    # ---- camera view ------------------------------------------------------------------------------
    def set_camera_view(self, camera: int | None) -> None:
        """Show camera ``camera``'s video frame, measurements and reprojections (None: hide)."""
        with self.lock:
            self.camera_view = camera
            if camera is None:
                self.camera_image.visible = False
                return
            if self.camera_menu.value != self.model.camera_names[camera]:
                self.camera_menu.value = self.model.camera_names[camera]
            self._draw_camera_view()

    def _draw_camera_view(self) -> None:
        from ..cameras import camera_at
        from .overlay import residual_image

        c, frame = self.camera_view, self.frame
        if self.data.camera_frame is None:
            self.camera_text.content = self._camera_legend()
            return
        try:
            shot = self.data.camera_frame(c, frame)
        except ValueError as exc:
            self.camera_text.content = f"**{exc}**"
            return
        if shot is None:
            self.camera_text.content = f"{self.model.camera_names[c]}: no video frame at frame {frame}"
            self.camera_image.visible = False
            return
        self._camera_drawn_at = time.perf_counter()
        image, stats = residual_image(shot, camera_at(self.data.rig.intrinsics, c), self.cameras[frame, c], width=480)
        self.camera_image.image = image
        self.camera_image.visible = True
        residual = (f"median residual {stats['median_px']:.2f} px, max {stats['max_px']:.1f} px"
                    if stats["reprojected"] else "nothing reprojects")
        self.camera_text.content = (f"{self.model.camera_names[c]}, video frame {shot.video_frame}: "
                                    f"{stats['measurements']} measurements, {stats['reprojected']} reprojected; "
                                    f"{residual} (green measured, red reprojected)")

    # ---- editing ----------------------------------------------------------------------------------
    def _select_from_menu(self) -> None:
        value = self.edit_menu.value
        if value == _NOTHING:
            self.select(None)
        elif value.startswith("joint: "):
            self.select(("joint", self.model.names.index(value[len("joint: "):])))
        else:
            self.select(("camera", self.model.camera_names.index(value[len("camera: "):])))

    def select(self, selection: tuple[str, int] | None) -> None:
        """Select ``("joint", j)`` or ``("camera", c)`` for editing (None: nothing); puts the gizmo on it."""
        with self.lock:
            if selection == ("joint", 0):
                self.set_status(f"'{self.model.names[0]}' is the root: its position is part of the motion, not "
                                "of the model")
                selection = None
            self.selection = selection
            label = _NOTHING if selection is None else (
                f"joint: {self.model.names[selection[1]]}" if selection[0] == "joint"
                else f"camera: {self.model.camera_names[selection[1]]}")
            if self.edit_menu.value != label:
                self.edit_menu.value = label  # calls back into select
                return
            if self.camera_meshes is not None:
                colours = np.tile(CAMERA, (len(self.model.camera_names), 1)).astype(np.uint8)
                if selection is not None and selection[0] == "camera":
                    colours[selection[1]] = SELECTED
                self.camera_meshes.batched_colors = colours
                self.frusta.colors = self._frustum_colours()
            if selection is None:
                self.gizmo.visible = False
            else:
                self.gizmo.disable_rotations = selection[0] == "joint"
                self._place_gizmo()
                self.gizmo.visible = True
                if selection[0] == "camera" and self.data.camera_frame is not None:
                    self.set_camera_view(selection[1])
            self.show_frame(self.frame)

    def _place_gizmo(self) -> None:
        kind, i = self.selection
        if kind == "joint":
            self.gizmo.wxyz, self.gizmo.position = (1.0, 0.0, 0.0, 0.0), self.joints[self.frame, i]
        else:
            self.gizmo.wxyz, self.gizmo.position = self.cameras[self.frame, i, :4], self.cameras[self.frame, i, 4:]

    def _on_gizmo(self, event) -> None:
        phase = getattr(event, "phase", "update")
        if phase == "start":
            self._dragging = True
            return
        self.drag_to(np.asarray(self.gizmo.position), np.asarray(self.gizmo.wxyz), final=phase == "end")

    def drag_to(self, position, wxyz=(1.0, 0.0, 0.0, 0.0), final: bool = True) -> bool:
        """Move the selection's gizmo to ``position`` (m) and ``wxyz`` (world; ignored for a joint) at the
        current frame and apply the edit; an edit the checks refuse leaves the model as it was (the gizmo
        goes back when ``final``) and says why in the panel. Returns whether the edit was applied."""
        with self.lock:
            if self.selection is None:
                return False
            self._dragging = not final
            kind, i = self.selection
            t = self.frame
            position = np.asarray(position, np.float64)
            if kind == "joint":
                p = self.model.parents[i]
                candidate = self.model.with_joint_moved(i, position - self.joints[t, i],
                                                        self.posing.world_matrices[t, p],
                                                        self.posing.world_matrices[t, i])
                problems = candidate.problems_after_editing(joint=i, before=self.model)
            else:
                s = self.model.camera_segments[i]
                segment = np.concatenate([self.posing.world_rotations[t, s], self.joints[t, s]])
                camera = np.concatenate([np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz), position])
                candidate = self.model.with_camera_moved(i, camera, segment)
                problems = candidate.problems_after_editing(camera=i)
            if problems:
                self.set_status("**Refused:** " + "; ".join(problems))
                if final:
                    self._place_gizmo()
                return False
            self.model = candidate
            (self.edited_joints if kind == "joint" else self.edited_cameras).add(i)
            self._recompute()
            self.show_frame(t)
            if final:
                self._place_gizmo()
            self.set_status(self._edit_summary())
            return True

    def _edit_summary(self) -> str:
        names = [self.model.names[j] for j in sorted(self.edited_joints)]
        names += [self.model.camera_names[c] for c in sorted(self.edited_cameras)]
        if not names:
            return "No unsaved edits."
        return "Unsaved edits: " + ", ".join(names) + "."

    def set_status(self, text: str) -> None:
        self.status = text
        self.status_text.content = text

    def revert(self) -> None:
        """Back to the model the viewer loaded (or last saved)."""
        with self.lock:
            self.model = self.loaded_model
            self.edited_joints.clear()
            self.edited_cameras.clear()
            self._recompute()
            self.set_status("Reverted to the loaded model.")
            self.show_frame(self.frame)

    def save(self) -> bool:
        """Check the edited joints and cameras and hand the model to ``data.save_model``; the outcome is
        the panel's status. Returns whether it was saved."""
        with self.lock:
            if self.data.save_model is None:
                self.set_status("This folder cannot be edited.")
                return False
            if not (self.edited_joints or self.edited_cameras):
                self.set_status("Nothing to save: no edits since the model was loaded.")
                return False
            problems = []
            for j in sorted(self.edited_joints):
                problems += self.model.problems_after_editing(joint=j, before=self.loaded_model)
            for c in sorted(self.edited_cameras):
                problems += self.model.problems_after_editing(camera=c)
            if problems:
                self.set_status("**Not saved:** " + "; ".join(dict.fromkeys(problems)))
                return False
            try:
                message = self.data.save_model(*self.model.applied_to(self.data.skeleton, self.data.rig))
            except (ValueError, OSError) as exc:
                self.set_status(f"**Not saved:** {exc}")
                return False
            self.loaded_model = self.model
            self.edited_joints.clear()
            self.edited_cameras.clear()
            self.set_status(message)
            return True

    def close(self) -> None:
        """Stop playback and wait briefly for the background reading (the server is the caller's to stop)."""
        super().close()
        self._extras.join(timeout=10)


def metrics_markdown(metrics: dict) -> str:
    """``metrics.json`` as markdown tables: per motion, mean / median / max of each error."""
    rows, motions = [], [k for k, v in metrics.items() if isinstance(v, dict) and any(
        isinstance(s, dict) and "mean" in s for s in v.values())]
    for motion in motions:
        for name, stats in metrics[motion].items():
            if isinstance(stats, dict) and {"mean", "median", "max"} <= set(stats):
                rows.append(f"| {motion} | {name.replace('_', ' ')} | {stats['mean']:.2f} | {stats['median']:.2f} | "
                            f"{stats['max']:.2f} |")
    scalars = [f"{k.replace('_', ' ')}: {v}" for k, v in metrics.items() if isinstance(v, (int, float, str))]
    table = "| | error | mean | median | max |\n|---|---|---|---|---|\n" + "\n".join(rows) if rows else ""
    return "\n\n".join(x for x in ("; ".join(scalars), table) if x) or "(no numbers)"


def _read_picture(path, width: int = 560) -> np.ndarray | None:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        return None
    if image.shape[1] > width:
        image = cv2.resize(image, (width, round(image.shape[0] * width / image.shape[1])), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
