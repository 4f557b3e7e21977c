"""The capture folder (format ``"bcmocap-capture"``): its layout, manifest, paths and ground truth, in one place.

Writers: :mod:`bcmocap.sim.studio` (a synthetic capture with its ground truth), :mod:`bcmocap.frontend.assemble`
(``bcmocap init``: a real shoot's files arranged into a capture folder) and :mod:`bcmocap.sim.sensors` (the IMU
and contact files). Readers: :func:`bcmocap.frontend.capture.read_capture` (what the frontend needs) and
:func:`load_ground_truth` (the studio's truth; the pipeline's evaluation and the benchmarks read it). Every path of
the layout is built here (:func:`manifest_path`, :func:`trial_video_path`, :func:`imu_path`,
:func:`trial_truth_path`, …) from checked names (:func:`bcmocap.io.names.checked_name`), so it stays inside the
folder; every reader's error is a one-line ``ValueError`` naming the file and the field.

Folder layout::

    capture.json                  manifest (:func:`read_manifest`, :func:`write_manifest`): format
                                  "bcmocap-capture", version, the frame rate (field "fps", or "settings.fps"
                                  for the studio's), "audio_rate" (or "settings.audio_rate"), camera names,
                                  trials, the subject (topology, tape measurements, when the rest pose was
                                  held: :func:`subject_record`), and "complete" once everything is written;
                                  the studio's also holds its settings (and the motion files' SHA-256,
                                  "motion_files"), ``bcmocap init``'s where the videos came from ("made_by")
                                  and the claps found in each trial ("claps")
    rig.json                      which camera is strapped to which body segment ({"cameras": [{"name",
                                  "segment", "intrinsics", "lens", "video", "audio", …}], "segments"}; mounts
                                  are unknown in a real shoot: the studio's are in ground_truth/rig.json)
    intrinsics/<camera>.yml       cv2.fisheye calibration (image_width, image_height, camera_matrix,
                                  dist_coeff), as bcmocap.io.opencv_calibration.read_opencv_fisheye_calibration reads;
                                  for the studio's default FOV lens it is the Kannala-Brandt fit of that lens
    intrinsics/<camera>.json      the exact lens: {"model": "FOV" | "OPENCV_FISHEYE" | "THIN_PRISM_FISHEYE" | "PINHOLE",
                                  "width", "height", "params": [fx, fy, cx, cy, omega | k1..k4 | k1, k2, p1, p2, k3, k4,
                                  sx1, sy1]} (COLMAP's order; OpenCV pixel convention: the top-left pixel's centre is
                                  (0, 0)), and the studio's fit error in pixels
    reference/photo_NNN.jpg       reference photos of the empty room from a hand-held camera walking a
                                  loop around the capture area (JPEG quality 95; ``bcmocap init`` keeps the
                                  user's names)
    reference/camera.json, .yml   their pinhole intrinsics (same conventions; .yml with
                                  camera_matrix and 5 zero distortion_coefficients)
    trials/<trial>/<camera>.mp4   one video per body camera and trial: the studio's MPEG-4 part 2 ("mp4v", via
    trials/<trial>/<camera>.wav   OpenCV) with the camera's soundtrack (mono 16-bit PCM, same start as the
                                  video) beside it (container "mp4v-wav", the default); or H.264 video with the
                                  soundtrack as an AAC track in the same file, as a real action camera writes
                                  it (container "mp4-aac", bcmocap.io.media), and no WAV
    videos/<camera>.<ext>         (``bcmocap init``) a video holding several trials, cut by the stretches that
                                  rig.json gives
    trials/<trial>/imu.npz        the IMU in every body camera (gyro, accelerometer, their mounts) and
    trials/<trial>/contacts.npz   foot-contact flags, from the first clap to the second on the claps'
                                  clock (formats: bcmocap.io.sensors; simulation: bcmocap.sim.sensors,
                                  whose write_sensor_data adds them to a capture written before them)
    ground_truth/skeleton.json    segment names, parents, rest offsets (m), joint types, hinge axes
    ground_truth/rig.json         cameras: segment, segment_from_camera (wxyz_xyz), exact intrinsics
    ground_truth/scene.json       the textured scene's surfaces (bcmocap.sim.scene.TexturedScene)
    ground_truth/world_points.npz points (N, 3) m on the textured surfaces and their materials (N,)
    ground_truth/reference.npz    names (N,) and world_from_camera (N, 7) of the reference photos
    ground_truth/<trial>.npz      per trial frame: root_position (T, 3), rotations (T, J, 4) (Motion),
                                  joint_positions (T, J, 3), world_rotations (T, J, 4) (the bones' poses),
                                  world_from_camera (T, C, 7) (the true, rendered camera poses),
                                  world_from_mount (T, C, 7) (where each camera would be rigidly on its
                                  bone: world_from_segment · segment_from_camera), camera_offsets (T, C, 6)
                                  (translation m, rotation rad, camera frame) with world_from_camera =
                                  world_from_mount · SE3.exp(camera_offsets) (zero without mount wobble;
                                  absent from captures written before: read as zero); per camera: video_start_frame (C,),
                                  num_video_frames (C,), clap_samples (C, 2), audio_gain (C,);
                                  the clocks: video_start_time (C,), clock_rate (C,),
                                  audio_latency_s (C,), imu_clock_offset_s ();
                                  clap_frames (2,); fps, audio_rate; Vicon-style markers:
                                  marker_names (M,), marker_segments (M,), marker_offsets (M, 3) m in
                                  the segment frame, markers (T, M, 3) m with NaN in gaps
    ground_truth/<trial>.bvh      the skeleton and the trial's motion (bcmocap.io.write_bvh)
    ground_truth/passerby/<trial>.npz
                                  (room "passerby" only) the second person walking through the trial, per
                                  trial frame (NaN while out of the room): present (T,), motion (the bundled
                                  CMU trial walked), segment_names (J,), root_position (T, 3),
                                  joint_positions (T, J, 3), capsules (T, K, 2, 3) m (the end points of the
                                  body's capsules, as rendered: they occlude the cameras' views), radii (K,) m,
                                  colors (K, 3) RGB in [0, 1] (read by read_passerby_truth)

Only the studio writes ``ground_truth/``. A camera's entry in ``rig.json`` may say where its videos are instead
of ``trials/<trial>/<camera>.mp4`` (what ``bcmocap init`` writes for a shoot whose cameras recorded several
trials in one file): ``"video": {trial: "path"}`` or ``{trial: {"file": "path", "first_frame": F, "num_frames":
N}}``, a stretch of a longer file that the trial's frame 0 starts, and ``"audio": {trial: "path"}`` for its WAV
(paths relative to the capture, staying inside it).

Timing of the ground truth: video frame ``i`` of camera ``c`` shows trial time ``clip((i - video_start_time[c]) /
clock_rate[c], 0, T - 1)`` frames (``video_start_time`` is ``video_start_frame`` plus a sub-frame phase; both
are whole frames and rates are 1 unless the studio's clocks are on), and its audio covers samples
``[i, i + 1) * audio_rate / fps``; the claps are at trial frames ``clap_frames``, i.e. at sample
``(clap_frames * clock_rate[c] + video_start_time[c] + audio_latency_s[c] * clock_rate[c] * fps) * audio_rate / fps``
of camera ``c``'s track. The IMU's timestamps are the true time plus ``imu_clock_offset_s``. World frame Z up, metres; rotations as wxyz quaternions; camera frames as OpenCV.

This module imports JAX only when a ground truth is read (the paths and the manifest need none of it).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..atomic import atomic_path
from .names import checked_name

if TYPE_CHECKING:
    from ..cameras import CameraModel
    from ..kinematics.rig import Rig
    from ..kinematics.skeleton import Motion, Skeleton

__all__ = [
    "CAPTURE_FORMAT",
    "CAPTURE_VERSION",
    "MANIFEST_FILE",
    "MAX_AUDIO_RATE",
    "MAX_FPS",
    "RIG_FILE",
    "TRIALS",
    "GroundTruth",
    "Manifest",
    "TrialTruth",
    "TruthMarkers",
    "TruthPasserby",
    "changed_files",
    "contacts_path",
    "file_stamps",
    "ground_truth_dir",
    "imu_path",
    "intrinsics_dir",
    "intrinsics_path",
    "lens_path",
    "load_ground_truth",
    "manifest_path",
    "new_manifest",
    "passerby_truth_path",
    "read_json",
    "read_manifest",
    "read_npz",
    "read_passerby_truth",
    "read_trial_truth",
    "read_truth_model",
    "reference_camera_path",
    "reference_dir",
    "reference_photo_path",
    "reference_truth_path",
    "relative_name",
    "rig_path",
    "shared_video_path",
    "subject_record",
    "trial_audio_path",
    "trial_dir",
    "trial_truth_path",
    "trial_video_path",
    "truth_rig_path",
    "truth_scene_path",
    "truth_skeleton_path",
    "world_points_path",
    "write_json",
    "write_manifest",
    "video_frame_at",
]

CAPTURE_FORMAT = "bcmocap-capture"
CAPTURE_VERSION = 1
#: The trials the studio writes and ``bcmocap run`` needs: range of motion (skeleton estimation), then the capture.
TRIALS = ("rom", "capture")
MANIFEST_FILE = "capture.json"
RIG_FILE = "rig.json"
MAX_FPS = 10_000.0  # Hz; a faster video is a corrupt header, not a camera
MAX_AUDIO_RATE = 1_000_000  # samples/s

_SUFFIX = re.compile(r"(\.[A-Za-z0-9]{1,8})?")  # a file's extension (or none)


# ---------------------------------------------------------------------------------------------
# Paths: every file of the layout, from checked names (so that each stays inside the folder).


def _name(folder, value: object, what: str) -> str:
    return checked_name(value, what, folder)


def _file_name(folder, stem: object, suffix: str, what: str) -> str:
    stem = _name(folder, stem, what)
    if not isinstance(suffix, str) or not _SUFFIX.fullmatch(suffix):
        raise ValueError(f"{folder}: {what} {stem!r}: file extension {suffix!r} is not a plain one (e.g. '.mp4')")
    return stem + suffix


def file_stamps(folder: str | os.PathLike) -> dict[str, list[int]]:
    """Every file of the capture folder (hidden ones and symlinked folders left out) as relative path →
    ``[size bytes, mtime ns]``: what a run compares to tell that the capture changed under it. Empty when the
    folder does not exist."""
    folder = Path(folder)
    stamps = {}
    for root, dirs, files in os.walk(folder, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith("."):
                continue
            path = Path(root) / name
            try:
                stat = path.stat()
            except OSError:  # a dangling symlink, or removed meanwhile: counts as missing
                continue
            stamps[path.relative_to(folder).as_posix()] = [stat.st_size, stat.st_mtime_ns]
    return stamps


def changed_files(before: dict, after: dict) -> list[str]:
    """The files of two :func:`file_stamps` that were added, removed or changed, each as a short phrase."""
    out = []
    for name in sorted(set(before) | set(after)):
        if name not in after:
            out.append(f"{name} (removed)")
        elif name not in before:
            out.append(f"{name} (added)")
        elif list(before[name]) != list(after[name]):
            size = "" if before[name][0] == after[name][0] else f", {before[name][0]:,} → {after[name][0]:,} bytes"
            out.append(f"{name} (modified{size})")
    return out


def manifest_path(folder: str | os.PathLike) -> Path:
    """``capture.json``."""
    return Path(folder) / MANIFEST_FILE


def rig_path(folder: str | os.PathLike) -> Path:
    """``rig.json``: the cameras, their segments, lens files and videos."""
    return Path(folder) / RIG_FILE


def intrinsics_dir(folder: str | os.PathLike) -> Path:
    """``intrinsics/``: the cameras' calibrations."""
    return Path(folder) / "intrinsics"


def intrinsics_path(folder: str | os.PathLike, camera: str, suffix: str = ".yml") -> Path:
    """``intrinsics/<camera><suffix>``: the camera's calibration (``.yml``: cv2.fisheye; ``.json``: :func:`lens_path`)."""
    return intrinsics_dir(folder) / _file_name(folder, camera, suffix, "camera")


def lens_path(folder: str | os.PathLike, camera: str) -> Path:
    """``intrinsics/<camera>.json``: the camera's exact lens."""
    return intrinsics_path(folder, camera, ".json")


def reference_dir(folder: str | os.PathLike) -> Path:
    """``reference/``: the reference photos and their camera."""
    return Path(folder) / "reference"


def reference_photo_path(folder: str | os.PathLike, photo: int | str) -> Path:
    """``reference/photo_NNN.jpg`` for the studio's photo number ``photo``, or ``reference/<photo>`` for a name."""
    name = f"photo_{int(photo):03d}.jpg" if isinstance(photo, (int, np.integer)) else _name(folder, photo, "photo")
    return reference_dir(folder) / name


def reference_camera_path(folder: str | os.PathLike, suffix: str = ".json") -> Path:
    """``reference/camera.json`` (or ``.yml``): the reference photos' intrinsics."""
    return reference_dir(folder) / _file_name(folder, "camera", suffix, "reference camera")


def trial_dir(folder: str | os.PathLike, trial: str) -> Path:
    """``trials/<trial>/``."""
    return Path(folder) / "trials" / _name(folder, trial, "trial")


def trial_video_path(folder: str | os.PathLike, trial: str, camera: str, suffix: str = ".mp4") -> Path:
    """``trials/<trial>/<camera><suffix>``: the camera's video of one trial, where no ``rig.json`` entry says otherwise."""
    return trial_dir(folder, trial) / _file_name(folder, camera, suffix, "camera")


def trial_audio_path(folder: str | os.PathLike, trial: str, camera: str) -> Path:
    """``trials/<trial>/<camera>.wav``: the camera's soundtrack of one trial beside its video (if it has one)."""
    return trial_video_path(folder, trial, camera, ".wav")


def shared_video_path(folder: str | os.PathLike, camera: str, suffix: str = ".mp4") -> Path:
    """``videos/<camera><suffix>`` (``bcmocap init``): a camera's video holding several trials."""
    return Path(folder) / "videos" / _file_name(folder, camera, suffix, "camera")


def imu_path(folder: str | os.PathLike, trial: str) -> Path:
    """``trials/<trial>/imu.npz`` (:mod:`bcmocap.io.sensors`)."""
    from .sensors import IMU_FILE

    return trial_dir(folder, trial) / IMU_FILE


def contacts_path(folder: str | os.PathLike, trial: str) -> Path:
    """``trials/<trial>/contacts.npz`` (:mod:`bcmocap.io.sensors`)."""
    from .sensors import CONTACTS_FILE

    return trial_dir(folder, trial) / CONTACTS_FILE


def ground_truth_dir(folder: str | os.PathLike) -> Path:
    """``ground_truth/`` (the studio's)."""
    return Path(folder) / "ground_truth"


def truth_skeleton_path(folder: str | os.PathLike) -> Path:
    """``ground_truth/skeleton.json``."""
    return ground_truth_dir(folder) / "skeleton.json"


def truth_rig_path(folder: str | os.PathLike) -> Path:
    """``ground_truth/rig.json``: the true mounts and rendered lenses."""
    return ground_truth_dir(folder) / "rig.json"


def truth_scene_path(folder: str | os.PathLike) -> Path:
    """``ground_truth/scene.json``."""
    return ground_truth_dir(folder) / "scene.json"


def world_points_path(folder: str | os.PathLike) -> Path:
    """``ground_truth/world_points.npz``."""
    return ground_truth_dir(folder) / "world_points.npz"


def reference_truth_path(folder: str | os.PathLike) -> Path:
    """``ground_truth/reference.npz``: the reference photos' true poses."""
    return ground_truth_dir(folder) / "reference.npz"


def trial_truth_path(folder: str | os.PathLike, trial: str, suffix: str = ".npz") -> Path:
    """``ground_truth/<trial>.npz`` (or ``.bvh``): one trial's ground truth."""
    return ground_truth_dir(folder) / _file_name(folder, trial, suffix, "trial")


def passerby_truth_path(folder: str | os.PathLike, trial: str) -> Path:
    """``ground_truth/passerby/<trial>.npz``: the passer-by of one trial (the studio's room "passerby")."""
    return ground_truth_dir(folder) / "passerby" / _file_name(folder, trial, ".npz", "trial")


def relative_name(folder: str | os.PathLike, path: str | os.PathLike) -> str:
    """``path`` relative to the capture folder, with ``/`` (as ``rig.json`` names files)."""
    return Path(path).relative_to(Path(folder)).as_posix()


# ---------------------------------------------------------------------------------------------
# Small files: JSON objects and numpy archives.


def read_json(path: str | os.PathLike) -> dict:
    """A JSON object of the capture folder, or ``ValueError`` naming the file (missing, not JSON, not an object)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: missing (expected by the capture folder layout)")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def write_json(path: str | os.PathLike, payload: Mapping) -> None:
    """``payload`` as JSON (indent 1, a newline at the end: the same payload gives the same bytes), written
    through a temporary file in the same folder."""
    with atomic_path(path) as tmp:
        tmp.write_bytes((json.dumps(payload, indent=1) + "\n").encode())


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of a ``.npz`` file (no pickles), or ``ValueError`` naming the file."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise ValueError(f"{path}: missing (expected by the capture folder layout)") from None
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path}: not a readable .npz file ({err})") from None


# ---------------------------------------------------------------------------------------------
# The manifest.


@dataclasses.dataclass(frozen=True)
class Manifest:
    """``capture.json``, checked by :func:`read_manifest`.

    Attributes:
        path: the file; data: its JSON object as read (every field, also those not checked here).
        version: the format version (None if the manifest gives none).
        trials: trial names (plain names, at least one, none twice).
        fps: the video frame rate (Hz; field ``fps``, else ``settings.fps``), None if neither gives it.
        audio_rate: the soundtracks' sample rate (Hz; ``audio_rate``, else ``settings.audio_rate``), or None.
        settings: ``settings`` (the studio's; ``{}`` without).
        complete: False while the capture is being written, True once it is, None if the manifest does not say.
    """

    path: Path
    data: dict
    version: int | None
    trials: tuple[str, ...]
    fps: float | None
    audio_rate: int | None
    settings: dict
    complete: bool | None

    @property
    def folder(self) -> Path:
        return self.path.parent


def read_manifest(folder: str | os.PathLike, *, require_complete: bool = False, require_fps: bool = False) -> Manifest:
    """Read and check ``capture.json`` of a capture folder.

    Args:
        folder: the capture folder.
        require_complete: refuse a capture marked incomplete (``"complete": false``: still being written).
        require_fps: refuse a manifest that gives no frame rate.

    Raises:
        ValueError: one line naming the folder or ``capture.json`` and the field at fault.
    """
    folder = Path(folder)
    path = manifest_path(folder)
    if not folder.is_dir():
        raise ValueError(f"{path}: missing (the capture folder {folder} does not exist)")
    data = read_json(path)
    if data.get("format") != CAPTURE_FORMAT:
        raise ValueError(f"{path}: format is {data.get('format')!r}, expected {CAPTURE_FORMAT!r}")
    version = data.get("version")
    if version is not None and (isinstance(version, bool) or not isinstance(version, int) or version < 1):
        raise ValueError(f"{path}: field 'version' must be a whole number >= 1, got {version!r}")
    complete = data.get("complete")
    if complete is not None and not isinstance(complete, bool):
        raise ValueError(f"{path}: field 'complete' must be true or false, got {complete!r}")
    if require_complete and complete is False:
        raise ValueError(f"{path}: the capture is marked incomplete (still being written?)")
    settings = data.get("settings", {})
    if not isinstance(settings, dict):
        raise ValueError(f"{path}: field 'settings' must be an object, got {type(settings).__name__}")
    fps = data.get("fps", settings.get("fps"))
    if (fps is not None or require_fps) and (isinstance(fps, bool) or not isinstance(fps, (int, float))
                                             or not 0 < fps <= MAX_FPS):
        raise ValueError(f"{path}: missing or invalid frame rate (field 'fps' or 'settings.fps'), got {fps!r}; "
                         f"expected a number in (0, {MAX_FPS}] Hz")
    audio_rate = data.get("audio_rate", settings.get("audio_rate"))
    if audio_rate is not None:
        if (isinstance(audio_rate, bool) or not isinstance(audio_rate, (int, float))
                or not 0 < audio_rate <= MAX_AUDIO_RATE or audio_rate != int(audio_rate)):
            raise ValueError(f"{path}: field 'audio_rate' must be a whole number of samples/s in "
                             f"(0, {MAX_AUDIO_RATE}], got {audio_rate!r}")
        audio_rate = int(audio_rate)
    trials = data.get("trials")
    if not isinstance(trials, list) or not trials:
        raise ValueError(f"{path}: field 'trials' must be a non-empty list of names, got {trials!r}")
    trials = tuple(checked_name(t, f"trials[{i}]", path) for i, t in enumerate(trials))
    if len(set(trials)) != len(trials):
        raise ValueError(f"{path}: field 'trials' names a trial twice: {list(trials)}")
    return Manifest(path, data, version, trials, None if fps is None else float(fps), audio_rate, settings, complete)


def new_manifest(**fields) -> dict:
    """A manifest: the format and version, then ``fields`` in the order given (their order is the file's)."""
    return {"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, **fields}


def write_manifest(folder: str | os.PathLike, manifest: Mapping) -> Path:
    """Write ``capture.json`` (:func:`write_json`); returns its path.

    Raises:
        ValueError: ``manifest`` is not one (:func:`new_manifest` makes one).
    """
    if manifest.get("format") != CAPTURE_FORMAT or not isinstance(manifest.get("trials"), (list, tuple)):
        raise ValueError(f"write_manifest: not a {CAPTURE_FORMAT!r} manifest with a list of trials: {dict(manifest)!r}")
    path = manifest_path(folder)
    write_json(path, manifest)
    return path


def subject_record(topology: Iterable, measurements: Iterable[Mapping] = (), rest: Mapping | None = None) -> dict:
    """The ``"subject"`` entry of ``capture.json``: what a shoot's log holds besides the videos.

    Args:
        topology: ``(name, parent or None, joint)`` per segment, parents first (joint ``"free"`` for the root,
            ``"ball"``, ``"hinge"`` or ``"fixed"``): the predefined kinematic structure.
        measurements: ``{"from", "to", "metres"}`` distances between the joint centres of two segments in the
            rest pose (what a tape measure gives: hip to ankle, shoulder to wrist), which fix the reconstruction's
            scale.
        rest: ``{"trial", "after_first_clap_s": [from, to]}``: the trial and the stretch after its first clap (s)
            in which the subject held the rest pose; None: not known.
    """
    record = {"topology": [list(s) for s in topology], "measurements": [dict(m) for m in measurements]}
    for i, entry in enumerate(record["topology"]):
        if len(entry) != 3:
            raise ValueError(f"subject_record: topology[{i}] must be (name, parent, joint), got {entry!r}")
    if rest is not None:
        record["rest"] = {k: list(v) if isinstance(v, tuple) else v for k, v in rest.items()}
    return record


# ---------------------------------------------------------------------------------------------
# The studio's ground truth.


@dataclasses.dataclass(frozen=True)
class TruthMarkers:
    """The studio's Vicon-style optical markers of a trial (ground truth): a few per segment, offset from the bone
    onto the body's surface. (The marker pipeline's input is :class:`bcmocap.markers.MarkerTrajectories`.)

    Attributes:
        names: ``(M,)`` marker names; segments ``(M,)`` segment index of each marker.
        offsets: ``(M, 3)`` marker positions in their segment's frame (m).
        positions: ``(T, M, 3)`` measured world positions (m): noisy, NaN where the marker was occluded.
    """

    names: tuple[str, ...]
    segments: np.ndarray
    offsets: np.ndarray
    positions: np.ndarray


@dataclasses.dataclass(frozen=True)
class TruthPasserby:
    """A second person walking through a trial (the studio's room "passerby"), over trial frames ``T``: NaN where
    ``present`` is False (out of the room, not rendered).

    Attributes:
        motion: the bundled CMU trial the passer-by walks ("walk" or "run").
        present: ``(T,)`` bool, in the room.
        segment_names: ``(J,)`` the passer-by's segments; root_position ``(T, 3)`` m; joint_positions ``(T, J, 3)`` m.
        capsules: ``(T, K, 2, 3)`` end points of the body's capsules (m, as rendered); radii ``(K,)`` m; colors
            ``(K, 3)`` RGB in [0, 1].
    """

    motion: str
    present: np.ndarray
    segment_names: tuple[str, ...]
    root_position: np.ndarray
    joint_positions: np.ndarray
    capsules: np.ndarray
    radii: np.ndarray
    colors: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``ground_truth/passerby/<trial>.npz`` (module docstring)."""
        return {"motion": np.array(self.motion), "present": np.asarray(self.present, bool),
                "segment_names": np.array(self.segment_names), "root_position": self.root_position,
                "joint_positions": self.joint_positions, "capsules": self.capsules, "radii": self.radii,
                "colors": self.colors}


@dataclasses.dataclass(frozen=True)
class TrialTruth:
    """Ground truth of one trial (arrays over trial frames ``T`` and cameras ``C``).

    Attributes:
        motion: the true motion (root position and joint rotations).
        joint_positions: ``(T, J, 3)`` m; world_rotations ``(T, J, 4)`` segment orientations (wxyz): the
            bones' poses.
        world_from_camera: ``(T, C, 7)`` the true camera poses (what was rendered).
        world_from_mount: ``(T, C, 7)`` where each camera would be if rigidly fixed to its bone
            (``world_from_segment · segment_from_camera``, the rig's mounts).
        camera_offsets: ``(T, C, 6)`` (translation m, rotation rad) of each camera on its mount, in its own
            frame: ``world_from_camera = world_from_mount · SE3.exp(camera_offsets)`` (the convention of
            :data:`bcmocap.residuals.variables.CAMERA_OFFSETS`); zero with rigid mounts.
        video_start_frame, num_video_frames: ``(C,)`` video frame showing trial frame 0; video length.
        clap_frames: ``(2,)`` trial frames of the claps; clap_samples ``(C, 2)`` their first audio sample
            in each camera's track; audio_gain ``(C,)``.
        markers: Vicon-style marker trajectories.
        fps, audio_rate: Hz.
        video_start_time: ``(C,)`` video frame (fractional) in which trial frame 0 happens; clock_rate ``(C,)``
            camera seconds per true second: video frame ``i`` of camera ``c`` shows trial time
            ``(i - video_start_time[c]) / clock_rate[c]`` frames. audio_latency_s ``(C,)``: how much each
            soundtrack lags its video; imu_clock_offset_s: added to the IMU's timestamps. A capture written
            before these existed had whole-frame starts, perfect clocks, no latency and no offset.
    """

    name: str
    motion: Motion
    joint_positions: np.ndarray
    world_rotations: np.ndarray
    world_from_camera: np.ndarray
    video_start_frame: np.ndarray
    num_video_frames: np.ndarray
    clap_frames: np.ndarray
    clap_samples: np.ndarray
    audio_gain: np.ndarray
    markers: TruthMarkers
    fps: float
    audio_rate: int
    world_from_mount: np.ndarray
    camera_offsets: np.ndarray
    video_start_time: np.ndarray = None
    clock_rate: np.ndarray = None
    audio_latency_s: np.ndarray = None
    imu_clock_offset_s: float = 0.0

    def __post_init__(self):
        cameras = len(self.video_start_frame)
        defaults = {"video_start_time": np.asarray(self.video_start_frame, np.float64),
                    "clock_rate": np.ones(cameras), "audio_latency_s": np.zeros(cameras)}
        for name, value in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def video_frame_of(self, camera, trial_frame) -> np.ndarray:
        """Video frame (fractional) of ``camera`` in which trial time ``trial_frame`` (frames) happens."""
        return video_frame_at(self.video_start_time[camera], self.clock_rate[camera], trial_frame)


def video_frame_at(video_start_time, clock_rate, trial_frame) -> np.ndarray:
    """Video frame (fractional) in which trial time ``trial_frame`` (frames) happens for a camera whose frame
    ``video_start_time`` shows trial frame 0 and whose clock runs ``clock_rate`` times true time (broadcasting)."""
    return np.asarray(video_start_time) + np.asarray(clock_rate) * np.asarray(trial_frame, np.float64)


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """Everything the studio (:func:`bcmocap.sim.studio.write_capture`) knows about a capture.

    Attributes:
        path: the capture folder.
        settings: the settings it was written with: the manifest's ``settings`` object, or what
            :func:`load_ground_truth`'s ``parse_settings`` made of it (:func:`bcmocap.sim.studio.load_ground_truth`:
            a :class:`~bcmocap.sim.studio.StudioSettings`).
        skeleton, rig: the true skeleton and camera mounts (exact intrinsics).
        scene: the textured scene (``ground_truth/scene.json`` as read, or what ``parse_scene`` made of it:
            :class:`~bcmocap.sim.scene.TexturedScene` from :func:`bcmocap.sim.studio.load_ground_truth`);
            world_points ``(N, 3)`` m on its surfaces and their ``materials``.
        reference_camera, reference_names, reference_poses: the photos' intrinsics, file names and
            ``world_from_camera`` ``(N, 7)``.
        trials: ``{"rom": TrialTruth, "capture": TrialTruth}``.
    """

    path: Path
    settings: Any
    skeleton: Skeleton
    rig: Rig
    scene: Any
    world_points: np.ndarray
    world_point_materials: np.ndarray
    reference_camera: CameraModel
    reference_names: tuple[str, ...]
    reference_poses: np.ndarray
    trials: dict[str, TrialTruth]


def read_truth_model(folder: str | os.PathLike) -> tuple[Manifest, Skeleton, Rig]:
    """``(manifest, skeleton, rig)`` of a studio capture: ``capture.json`` and the true model of ``ground_truth/``
    (the rendered lenses and mounts).

    Raises:
        ValueError: not a capture, or a missing or malformed file (naming it).
    """
    from .model_json import rig_from_dict, skeleton_from_dict

    manifest = read_manifest(folder)
    skeleton_file, rig_file = truth_skeleton_path(folder), truth_rig_path(folder)
    skeleton = skeleton_from_dict(read_json(skeleton_file), str(skeleton_file))
    rig = rig_from_dict(read_json(rig_file), skeleton, str(rig_file))
    return manifest, skeleton, rig


def read_trial_truth(folder: str | os.PathLike, trial: str) -> TrialTruth:
    """``ground_truth/<trial>.npz`` (module docstring); a capture written before mount wobble has rigid mounts.

    Raises:
        ValueError: naming the file, missing, unreadable or without an array it needs.
    """
    from ..kinematics.skeleton import Motion

    path = trial_truth_path(folder, trial)
    d = read_npz(path)
    try:
        return TrialTruth(
            name=trial,
            motion=Motion(d["root_position"], d["rotations"]),
            joint_positions=d["joint_positions"],
            world_rotations=d["world_rotations"],
            world_from_camera=d["world_from_camera"],
            video_start_frame=d["video_start_frame"],
            num_video_frames=d["num_video_frames"],
            clap_frames=d["clap_frames"],
            clap_samples=d["clap_samples"],
            audio_gain=d["audio_gain"],
            markers=TruthMarkers(tuple(str(x) for x in d["marker_names"]), d["marker_segments"],
                                 d["marker_offsets"], d["markers"]),
            fps=float(d["fps"]),
            audio_rate=int(d["audio_rate"]),
            # a capture written before mount wobble existed has rigid mounts
            world_from_mount=d.get("world_from_mount", d["world_from_camera"]),
            camera_offsets=d.get("camera_offsets", np.zeros(d["world_from_camera"].shape[:2] + (6,))),
            # a capture written before the studio's clocks: whole-frame starts, perfect clocks
            video_start_time=d.get("video_start_time"), clock_rate=d.get("clock_rate"),
            audio_latency_s=d.get("audio_latency_s"), imu_clock_offset_s=float(d.get("imu_clock_offset_s", 0.0)),
        )
    except KeyError as err:
        raise ValueError(f"{path}: missing array {err}") from None


def read_passerby_truth(folder: str | os.PathLike, trial: str) -> TruthPasserby | None:
    """``ground_truth/passerby/<trial>.npz`` (module docstring), or None for a capture without a passer-by.

    Raises:
        ValueError: naming the file, unreadable or without an array it needs.
    """
    path = passerby_truth_path(folder, trial)
    if not path.exists():
        return None
    d = read_npz(path)
    try:
        return TruthPasserby(str(d["motion"]), d["present"].astype(bool), tuple(str(x) for x in d["segment_names"]),
                             d["root_position"], d["joint_positions"], d["capsules"], d["radii"], d["colors"])
    except KeyError as err:
        raise ValueError(f"{path}: missing array {err}") from None


def load_ground_truth(path: str | os.PathLike, *, parse_settings: Callable[[dict, str], Any] | None = None,
                      parse_scene: Callable[[dict, str], Any] | None = None) -> GroundTruth:
    """Read the ground truth of a capture folder written by the studio (layout in the module docstring).

    Args:
        path: the capture folder.
        parse_settings: ``(settings object, where) -> settings`` (e.g. ``StudioSettings.from_dict``); None: the
            manifest's ``settings`` object as it is.
        parse_scene: ``(scene.json object, where) -> scene`` (e.g. ``TexturedScene.from_dict``); None: as it is.

    Raises:
        ValueError: naming the file that is missing or malformed.
    """
    from .model_json import camera_from_dict

    folder = Path(path)
    manifest, skeleton, rig = read_truth_model(folder)
    settings = manifest.settings if parse_settings is None else parse_settings(manifest.settings, str(manifest.path))
    scene_file = truth_scene_path(folder)
    scene = read_json(scene_file)
    if parse_scene is not None:
        scene = parse_scene(scene, str(scene_file))
    points = _arrays(world_points_path(folder), ("points", "materials"))
    reference = _arrays(reference_truth_path(folder), ("names", "world_from_camera"))
    camera_file = reference_camera_path(folder)
    ref_camera = camera_from_dict(read_json(camera_file), str(camera_file))
    trials = {name: read_trial_truth(folder, name) for name in manifest.trials}
    return GroundTruth(folder, settings, skeleton, rig, scene, points["points"], points["materials"], ref_camera,
                       tuple(str(x) for x in reference["names"]), reference["world_from_camera"], trials)


def _arrays(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    data = read_npz(path)
    for name in names:
        if name not in data:
            raise ValueError(f"{path}: missing array {name!r}")
    return data
