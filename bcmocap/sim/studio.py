"""Synthetic capture studio: the folder a user brings back from a body-mounted-camera shoot, and its truth.

:func:`write_capture` renders a real CMU motion (and a generated range-of-motion trial) through the
paper-like 18-camera rig in a textured room (:mod:`bcmocap.sim.scene`, :mod:`bcmocap.sim.render`),
with one video and one soundtrack per camera, reference photos of the room taken from a hand-held path
(§4.1), the intrinsics and the rig; and beside it the Vicon-style ground truth, which
:func:`load_ground_truth` reads back in one call (:func:`bcmocap.io.capture_folder.load_ground_truth` without
:mod:`bcmocap.sim`). The same settings and seed write the same bytes.

The folder's layout (``capture.json``, ``rig.json``, ``intrinsics/``, ``reference/``, ``trials/<trial>/`` with
the videos, soundtracks and sensor files, and ``ground_truth/``) is specified, and its paths built, in
:mod:`bcmocap.io.capture_folder`, which also reads the ground truth back.

Trials are ``rom`` (range of motion, for skeleton estimation: every joint swung about all its axes at
once by incommensurate sinusoids around the first pose of the capture, while the body turns in place)
and ``capture`` (the CMU motion). Timing: video frame ``i`` of camera ``c``
shows trial frame ``clip(i - video_start_frame[c], 0, T - 1)`` (the subject stands still before and
after the trial), and its audio covers samples ``[i, i + 1) * audio_rate / fps``. The clapper board
claps at trial frames ``clap_frames = (-lead, T - 1 + lead)``, i.e. at sample
``(clap_frames + video_start_frame[c]) * audio_rate / fps`` of camera ``c``'s track. Cameras start
recording at random whole frames apart (up to 0.5 s), so synchronising by the claps recovers frame
offsets exactly. Time as a shoot has it (settings ``start_subframe``, ``clock_ppm``, ``audio_latency_ms``,
``imu_offset_ms``): each camera starts at a sub-frame time, counts time with its own clock (video and audio),
its audio lags its video, and the IMU's timestamps are offset; frame ``i`` then shows trial time
``(i - video_start_time[c]) / clock_rate[c]`` (rendered at that time, the motion interpolated between frames)
and the claps move with the clocks and latencies (:func:`bcmocap.io.capture_folder` documents the arrays). World frame Z up, metres; rotations as wxyz quaternions; camera frames as OpenCV.

Containers: OpenCV's VideoWriter writes video streams only, so the default ("mp4v-wav") keeps a WAV beside
each mp4v video; every figure in the README was measured on such captures. "mp4-aac" writes what a camera
writes, H.264 + AAC in one file, through PyAV (FFmpeg's libraries in its wheels), so that a studio folder
and a real shoot assembled by ``bcmocap init`` look alike; the frontend reads both (the soundtrack is the
WAV beside the video when there is one, else the video's own audio track). It is not the default because
it changes every rendered pixel the frontend sees (H.264 at CRF 16 instead of mp4v) and so every figure
measured on a default capture, and it encodes more slowly than mp4v (x264 on one thread, so that the
same settings still write the same bytes).

Degradations of a real shoot (all off by default, so the defaults write the same bytes as before them; the
``realistic`` preset of :func:`preset_settings` turns them on, :data:`REALISTIC` says where each value comes
from): mount wobble (:mod:`bcmocap.sim.wobble`; the true camera poses are rendered and the IMU follows them),
rolling shutter and motion blur at given readout and exposure times, auto exposure and white balance
(:mod:`bcmocap.sim.exposure`), vignetting and photon shot noise (:mod:`bcmocap.sim.render`), H.264 at a bit rate
(container "mp4-aac"), and calibration error: ``intrinsics/`` then holds each camera's lens with its focal
length and centre off (seeded), while ``ground_truth/rig.json`` keeps the rendered lens. ``motion`` may also be a
BVH file or an ASF/AMC pair (:func:`~bcmocap.sim.motions.load_motion_file`); the manifest then lists the files
and their SHA-256 (``motion_files``).

Resuming: videos and tracks are written under temporary names and renamed when complete; running again
with the same settings skips every complete camera. A non-empty folder that is not a capture, or a
capture written with other settings, is refused (nothing in it is touched). A capture written before a
setting existed was written with its default, and resumes as such.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import hashlib
import json
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from ..atomic import atomic_path, disk_full, full_disk_named, write_npz_atomic
from ..cameras import CameraModel, OpenCVFisheyeCamera, PinholeCamera, camera_at, stack_cameras
from ..geometry import SE3, SO3, matrix_from_quat, quat_from_matrix
from ..io import capture_folder
from ..io.capture_folder import (
    CAPTURE_FORMAT,
    CAPTURE_VERSION,
    TRIALS,
    GroundTruth,
    TruthMarkers,
    TruthPasserby,
    ground_truth_dir,
    intrinsics_dir,
    intrinsics_path,
    lens_path,
    manifest_path,
    new_manifest,
    passerby_truth_path,
    reference_camera_path,
    reference_dir,
    reference_photo_path,
    reference_truth_path,
    relative_name,
    rig_path,
    subject_record,
    trial_audio_path,
    trial_dir,
    trial_truth_path,
    trial_video_path,
    truth_rig_path,
    truth_scene_path,
    truth_skeleton_path,
    video_frame_at,
    world_points_path,
    write_json,
    write_manifest,
)
from ..io.model_json import camera_to_dict, rig_to_dict, skeleton_to_dict
from ..io.opencv_calibration import fit_opencv_fisheye
from ..io.wav import write_wav
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import JointType, Motion, Skeleton
from .audio import soundtrack
from .exposure import ExposureControl
from .lens_units import lens_design, manufactured_lens_units, nominal_lens
from .motions import CMU_TRIALS, load_body_motion, load_motion_file
from .observe import body_capsules
from .passerby import PASSERBY_PALETTE, passerby_motion
from .render import Renderer, RenderOptions, capsule_colors
from .rig import standard_rig
from .scene import ROOM_STYLES, TexturedScene, make_room
from .sensors import write_trial_sensors
from .wobble import mount_wobble

__all__ = [  # the format's names (CAPTURE_FORMAT, GroundTruth, TrialTruth, ...) are bcmocap.io.capture_folder's
    "PRESETS",
    "READOUT_RANGE_MS",
    "REALISTIC",
    "StudioSettings",
    "camera_soundtrack",
    "capsule_ends",
    "clap_samples",
    "load_ground_truth",
    "preset_settings",
    "read_studio_model",
    "studio_subject",
    "trial_timelines",
    "write_capture",
]

CONTAINERS = ("mp4v-wav", "mp4-aac")
ROOMS = (*ROOM_STYLES, "passerby")  # StudioSettings.room
_BATCH = 4  # frames rendered per call (one compilation per camera size)
_LEAD_S = 0.25  # clap before the first / after the last trial frame
_ROLL_S = 0.1  # recording before the first clap / after the last one, plus the random offsets
_MAX_OFFSET_S = 0.5  # spread of camera start (and stop) times
MAX_SECONDS = 600.0  # longest trial (s): the soundtracks and ground truth are made whole in memory
MAX_FPS = 240.0  # highest frame rate (Hz)
_TIME_LIMITS = {"clock_ppm": 1000.0, "audio_latency_ms": 100.0, "imu_offset_ms": 1000.0}  # largest time errors


@dataclasses.dataclass(frozen=True)
class StudioSettings:
    """What :func:`write_capture` renders (all of it goes into ``capture.json``).

    Every degradation of a real shoot is off by default (the clean studio every README figure was measured
    in); :func:`preset_settings` ``("realistic", ...)`` turns them all on (:data:`REALISTIC` says where each
    value comes from).

    Attributes:
        motion: the capture's motion: a bundled CMU trial ("walk", "run", "jump", "scoop", "hop":
            :data:`~bcmocap.sim.motions.CMU_TRIALS`), a ``.bvh`` file, or an
            ``(.asf, .amc)`` pair of paths (:func:`~bcmocap.sim.motions.load_motion_file`; paths are
            stored as given, so give absolute ones to resume from elsewhere).
        motion_fps: frame rate of a motion file (Hz); 0: a BVH file's own ``Frame Time``, 120 Hz for AMC.
        motion_unit_m: metres per length unit of a motion file; 0: guessed for BVH, the ASF's ``:units``.
        seconds: length of the capture trial (s, at most ``MAX_SECONDS``); longer than the motion plays it
            back and forth.
        rom_seconds: length of the range-of-motion trial (s, at most ``MAX_SECONDS``).
        rom_tempo: speed of the range-of-motion trial's sweeps (1: each joint at 0.6–1.4 Hz; 0.5: the same
            sweeps at half that speed, as a subject moving deliberately does, in (0, 4]).
        rom_protocol: what the subject does in the range-of-motion trial (:data:`ROM_PROTOCOLS`): "together",
            every joint at once; "feet_after", the ankles turned on still legs after the rest has swung
            (:func:`studio_range_of_motion`).
        seed: random seed (scene, camera offsets, audio, markers, sensor noise).
        fps: frame rate of videos and ground truth (Hz, at most ``MAX_FPS``).
        width, height: body-camera image size (px).
        lens: "fov" (the paper's FOV model, 170°) or "opencv_fisheye" (its Kannala-Brandt fit, so the
            .yml calibration is exact).
        room: where the capture takes place (:func:`~bcmocap.sim.scene.make_room`): "textured" (rich
            non-repeating texture everywhere), "sparse" (weak texture, a blank wall, less clutter), "repeated"
            (tiles of 8 faces on the floor; identical ceiling panels, bricks and windows) or "passerby" (the
            textured room, and a second person pacing across it ahead of the subject, in every camera's frames
            but not in the reference photos: :mod:`bcmocap.sim.passerby`, ``ground_truth/passerby/<trial>.npz``).
        reference_photos: number of reference photos; reference_width, reference_height their size (px);
            reference_fov_deg their horizontal field of view (pinhole).
        motion_blur, rolling_shutter: rendering effects (:class:`~bcmocap.sim.render.RenderOptions`).
        exposure_ms: shutter time with ``motion_blur`` (ms, at most a frame period); 0: half a frame period.
        blur_samples: sub-exposures averaged per frame with ``motion_blur``.
        readout_ms: rolling-shutter readout from the first row to the last (ms, at most a frame period);
            0: 0.8 frame periods.
        audio_rate: sample rate of the soundtracks (Hz).
        markers_per_segment: Vicon-style markers on each body capsule.
        container: "mp4v-wav" (mp4v video and a WAV beside it) or "mp4-aac" (H.264 video with the
            soundtrack as an AAC track in the same MP4; width and height even).
        mount_wobble_mm, mount_wobble_deg: RMS over the capture trial of each camera's translation and
            rotation on its strap relative to its mount (:mod:`bcmocap.sim.wobble`; times a per-camera factor
            in [0.5, 1.5]); 0: rigid mounts.
        auto_exposure, white_balance: the cameras' exposure and grey-world white balance follow what they
            see (:mod:`bcmocap.sim.exposure`); off: fixed.
        vignetting: share of light lost at the most oblique ray of the image (quadratic in the ray's angle).
        read_noise_dn: σ of the read noise (8-bit levels; 1 as the clean studio has always had).
        full_scale_electrons: electrons collected at level 255 per rendered pixel; > 0 adds photon shot noise.
        video_bitrate_mbps: H.264 bit rate (Mbit/s, container "mp4-aac" only); 0: constant quality (CRF 16).
        focal_error_pct, centre_error_px: calibration error of the intrinsics given to the user
            (``intrinsics/``): each camera's focal length off by a relative amount of magnitude uniform in
            [0.3, 1] × ``focal_error_pct`` % (random sign), its centre by [0.3, 1] × ``centre_error_px`` px
            (random direction); the ground truth keeps the rendered lens.
        start_subframe: each camera starts recording at a random sub-frame time (uniform in a frame period),
            so its frames are not on the trial's frame grid and clap sync cannot be exact in whole frames;
            off: every camera starts on a whole frame.
        clock_ppm: each camera's clock runs fast or slow by up to this much (parts per million, uniform per
            camera, the same in every trial): its video and audio both count camera time; 0: perfect clocks.
        audio_latency_ms: each camera's soundtrack lags its video by a camera-specific latency, uniform in
            ``[0, audio_latency_ms]`` (the same in every trial); 0: in step.
        imu_offset_ms: the IMU recording's timestamps are off from the video's clock by an offset uniform in
            ``±imu_offset_ms`` per trial; 0: the IMU clock is the video clock.
        lens_units: each body camera is its own unit of one lens design (:mod:`bcmocap.sim.lens_units`: focal
            length, centre and radial profile off the design, plus decentering and thin-prism terms and a tilted
            sensor; seeded), rendered as a :class:`~bcmocap.cameras.TiltedThinPrismFisheyeCamera`, outside the
            solver's and the calibration's lens families,
            and kept in ``ground_truth/rig.json``; ``intrinsics/`` then holds the design's nominal lens in the
            ``lens`` family (:func:`~bcmocap.sim.lens_units.nominal_lens`; ``focal_error_pct`` and
            ``centre_error_px`` move it further); off: every camera renders the one ``lens``.
    """

    motion: str | tuple[str, str] = "walk"
    motion_fps: float = 0.0
    motion_unit_m: float = 0.0
    seconds: float = 2.0
    rom_seconds: float = 2.0
    rom_tempo: float = 1.0
    rom_protocol: str = "together"
    seed: int = 0
    fps: float = 60.0
    width: int = 640
    height: int = 360
    lens: str = "fov"
    room: str = "textured"
    reference_photos: int = 24
    reference_width: int = 1024
    reference_height: int = 768
    reference_fov_deg: float = 80.0
    motion_blur: bool = False
    rolling_shutter: bool = False
    audio_rate: int = 48000
    markers_per_segment: int = 3
    container: str = "mp4v-wav"
    exposure_ms: float = 0.0
    blur_samples: int = 4
    readout_ms: float = 0.0
    mount_wobble_mm: float = 0.0
    mount_wobble_deg: float = 0.0
    auto_exposure: bool = False
    white_balance: bool = False
    vignetting: float = 0.0
    read_noise_dn: float = 1.0
    full_scale_electrons: float = 0.0
    video_bitrate_mbps: float = 0.0
    focal_error_pct: float = 0.0
    centre_error_px: float = 0.0
    start_subframe: bool = False
    clock_ppm: float = 0.0
    audio_latency_ms: float = 0.0
    imu_offset_ms: float = 0.0
    lens_units: bool = False

    def __post_init__(self):
        if isinstance(self.motion, list):  # from JSON
            object.__setattr__(self, "motion", tuple(self.motion))
        motion = self.motion
        if isinstance(motion, tuple):
            if (len(motion) != 2 or not all(isinstance(m, str) for m in motion)
                    or not motion[0].lower().endswith(".asf") or not motion[1].lower().endswith(".amc")):
                raise ValueError(f"StudioSettings.motion: a motion given by two files must be an (.asf, .amc) pair, "
                                 f"got {motion!r}")
        elif not isinstance(motion, str) or (motion not in CMU_TRIALS and not motion.lower().endswith(".bvh")):
            raise ValueError(f"StudioSettings.motion must be one of {sorted(CMU_TRIALS)}, a .bvh file or an (.asf, .amc) "
                             f"pair, got {motion!r}")
        if self.lens not in ("fov", "opencv_fisheye"):
            raise ValueError(f"StudioSettings.lens must be 'fov' or 'opencv_fisheye', got {self.lens!r}")
        if self.room not in ROOMS:
            raise ValueError(f"StudioSettings.room must be one of {list(ROOMS)}, got {self.room!r}")
        if self.container not in CONTAINERS:
            raise ValueError(f"StudioSettings.container must be one of {CONTAINERS}, got {self.container!r}")
        if self.container == "mp4-aac" and (int(self.width) % 2 or int(self.height) % 2):
            raise ValueError(f"StudioSettings: H.264 (container 'mp4-aac') needs an even width and height, got "
                             f"{self.width} x {self.height}")
        for name, most in (("seconds", MAX_SECONDS), ("rom_seconds", MAX_SECONDS), ("fps", MAX_FPS)):
            if not 0 < getattr(self, name) <= most:  # also refuses NaN
                raise ValueError(f"StudioSettings.{name} must be in (0, {most:g}], got {getattr(self, name)}")
        for name in ("width", "height", "reference_width", "reference_height", "audio_rate"):
            if int(getattr(self, name)) < 8:
                raise ValueError(f"StudioSettings.{name} must be at least 8, got {getattr(self, name)}")
        if self.reference_photos < 0 or self.markers_per_segment < 0:
            raise ValueError("StudioSettings.reference_photos and markers_per_segment must be >= 0")
        if self.rom_protocol not in ROM_PROTOCOLS:
            raise ValueError(f"StudioSettings.rom_protocol must be one of {ROM_PROTOCOLS}, got {self.rom_protocol!r}")
        if not 0.0 < self.rom_tempo <= 4.0:  # also refuses NaN
            raise ValueError(f"StudioSettings.rom_tempo must be in (0, 4], got {self.rom_tempo}")
        if round(self.seconds * self.fps) < 2 or round(self.rom_seconds * self.fps) < 2:
            raise ValueError("StudioSettings: each trial needs at least 2 frames (seconds * fps >= 2)")
        frame_ms = 1000.0 / self.fps
        for name in ("exposure_ms", "readout_ms"):
            if not 0.0 <= getattr(self, name) <= frame_ms * (1 + 1e-9):
                raise ValueError(f"StudioSettings.{name} must be in [0, {frame_ms:.4g}] ms (one frame period at "
                                 f"{self.fps:g} fps), got {getattr(self, name)}")
        for name in ("motion_fps", "motion_unit_m", "mount_wobble_mm", "mount_wobble_deg", "read_noise_dn",
                     "full_scale_electrons", "video_bitrate_mbps", "focal_error_pct", "centre_error_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < math.inf:
                raise ValueError(f"StudioSettings.{name} must be a finite number >= 0, got {value!r}")
        if self.mount_wobble_mm > 50.0 or self.mount_wobble_deg > 20.0:
            raise ValueError(f"StudioSettings.mount_wobble_mm and mount_wobble_deg must be at most 50 mm and 20 deg "
                             f"(RMS), got {self.mount_wobble_mm} and {self.mount_wobble_deg}")
        if self.focal_error_pct > 20.0:
            raise ValueError(f"StudioSettings.focal_error_pct must be at most 20 (%), got {self.focal_error_pct}")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"StudioSettings.vignetting must be in [0, 1), got {self.vignetting!r}")
        if isinstance(self.blur_samples, bool) or not isinstance(self.blur_samples, int) or not 1 <= self.blur_samples <= 64:
            raise ValueError(f"StudioSettings.blur_samples must be a whole number in [1, 64], got {self.blur_samples!r}")
        for name in ("clock_ppm", "audio_latency_ms", "imu_offset_ms"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= _TIME_LIMITS[name]:
                raise ValueError(f"StudioSettings.{name} must be a number in [0, {_TIME_LIMITS[name]:g}], got {value!r}")
        for name in ("auto_exposure", "white_balance", "motion_blur", "rolling_shutter", "start_subframe"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"StudioSettings.{name} must be true or false, got {getattr(self, name)!r}")
        if self.video_bitrate_mbps > 0 and self.container != "mp4-aac":
            raise ValueError(f"StudioSettings.video_bitrate_mbps needs container 'mp4-aac' (H.264), got container "
                             f"{self.container!r}")
        if not isinstance(self.lens_units, bool):
            raise ValueError(f"StudioSettings.lens_units must be true or false, got {self.lens_units!r}")

    @property
    def motion_paths(self) -> tuple[str, ...]:
        """The motion file(s), or ``()`` for a bundled trial."""
        if isinstance(self.motion, tuple):
            return self.motion
        return () if self.motion in CMU_TRIALS else (self.motion,)

    def render_options(self) -> RenderOptions:
        """How the body cameras' frames are rendered."""
        return RenderOptions(
            motion_blur=self.motion_blur, rolling_shutter=self.rolling_shutter, blur_samples=self.blur_samples,
            exposure_frames=self.exposure_ms * self.fps / 1000.0 if self.exposure_ms > 0 else 0.5,
            readout_frames=min(self.readout_ms * self.fps / 1000.0, 1.0) if self.readout_ms > 0 else 0.8,
            noise_dn=self.read_noise_dn, full_scale_electrons=self.full_scale_electrons, vignetting=self.vignetting)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "capture.json") -> StudioSettings:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"{where}: unknown settings {unknown}")
        return cls(**data)


#: The settings :func:`preset_settings` ``("realistic")`` changes, and where each value comes from. Values
#: that depend on the frame rate or the image size are scaled to the capture's (``fps``, ``width``,
#: ``height``); the sources' figures are for 1920×1080 at 60 fps.
REALISTIC = {
    # A GoPro indoors exposes for about 1/100 s (GoPro Labs' "maxshut" notes: indoors 1/96 s at ISO 1600),
    # bounded by the frame period: 8 ms at 60 fps, at most half a frame period.
    "motion_blur": "on",
    "exposure_ms": "8 ms (at most half a frame period)",
    # Rolling-shutter readout, drawn per capture from READOUT_RANGE_MS: a user does not know it (their config would
    # take a data sheet's figure). Published figures: 14.8 ms (wide) and 14.3 ms (narrow field of view) for a GoPro
    # Hero3+ Black at 1080p60, measured by panning (G. Thalin's Deshaker rolling-shutter list, reproduced in the
    # rolling-shutter table of J. Huai's Kalibr fork): the only action-camera video figures found. Stills read the
    # whole 4:3 sensor and are slower: 30 ms for a GoPro Hero4 Black (Vautherin et al. 2016, ISPRS Annals III-3),
    # 17 ms for a Hero 8 Black, 16 ms in 16:9 and 21 ms in 4:3 for the DJI Mini 4 Pro's 1/1.3" sensor
    # (OpenDroneMap's rolling-shutter database). GoPros since the HERO7 write the readout into each file (GPMF's
    # SROT), so it differs by model and mode. Top of the range: the studio's cap, 0.95 of a 60 fps frame period (a
    # readout cannot outlast its frame). Bottom, 10 ms: a judgement. At the Hero 8's still line time, 1080p's 16:9
    # rows would take ~13 ms, and cameras that film 1080p at 240 fps read a frame in under 4.2 ms.
    "rolling_shutter": "on",
    "readout_ms": "drawn per capture, uniform in 10-15.8 ms (at most 0.95 frame periods)",
    # Soft-tissue artefact of skin-mounted marker clusters: peaks of ~10-18 mm and 5-10 deg on the thigh, less
    # on the shank (Leardini et al. 2005; Peters et al. 2010; bcmocap.sim.wobble): RMS 3 mm and 1.5 deg,
    # times 0.5-1.5 per camera.
    "mount_wobble_mm": "3 mm RMS",
    "mount_wobble_deg": "1.5 deg RMS",
    "auto_exposure": "on (bcmocap.sim.exposure: 0.3 s loop)",
    "white_balance": "on (grey world, 1 s loop, starting off by up to 5 %)",
    # Fisheye designs lose from a few tens of per cent to most of the light at the edge of a hemispherical
    # field (Kumler & Bauer 2000, "Fisheye lens designs and their relative performance", SPIE 4093): 40 %.
    "vignetting": "0.4",
    # A 1/2.3" action-camera sensor: 1.55 um pixels, full well ~1,900 e-/um^2 x 2.4 um^2 ~ 4,500 e- (R. N. Clark's
    # sensor performance summary: full well scales with pixel area), at ISO ~400 indoors (4x gain) 1,100 e- at
    # full scale per 1080p pixel; a rendered pixel bins (1920 x 1080) / (W x H) of them.
    "full_scale_electrons": "1,100 e- per 1080p pixel, times (1920 x 1080) / (W x H)",
    "read_noise_dn": "1 (read noise of ~2.5 e- is far below 1 level at that gain: quantisation and the camera's "
                     "processing keep the studio's 1 level)",
    # Consumer action cameras record 1080p at roughly 45-60 Mbit/s (the figure; GoPro's standard bit rates
    # are of this order); x264 is a better encoder than a camera's hardware one, so the lower figure, scaled by
    # pixels per second.
    "container": "mp4-aac (H.264)",
    "video_bitrate_mbps": "45 Mbit/s x (W x H x fps) / (1920 x 1080 x 60)",
    # The band for a field calibration: 0.3-1 % in focal length, a few px in the centre; 0.5 % of the
    # width is 3.2 px at 640 px.
    "focal_error_pct": "1 (errors of 0.3-1 %)",
    "centre_error_px": "0.5 % of the width (errors of 0.15-0.5 %)",
    # Time. Cameras started by hand (or by a remote's radio command) start at arbitrary moments, not on a common
    # frame grid: a uniform sub-frame phase.
    "start_subframe": "on",
    # Each camera's clock is its own quartz crystal: general-purpose crystals are specified at +-10 to +-50 ppm
    # frequency tolerance at 25 C plus a similar temperature stability (e.g. the frequency tolerance classes of
    # Epson's and Abracon's SMD crystal data sheets); issue 43 quotes tens of ppm between action cameras. The
    # studio takes +-20 ppm per camera (so two cameras differ by up to 40 ppm: 24 ms, 1.4 frames at 60 fps, over
    # a 10-minute take).
    "clock_ppm": "20 ppm",
    # Audio-video latency inside a camera (the audio path's buffering and the encoder's priming) is a property of
    # the model and firmware, mostly common to cameras of one model, which only shifts the common time; what
    # differs between units is a judgement here: up to 5 ms (0.3 frame periods at 60 fps), below the +-(15-45) ms
    # audio/video tolerance of broadcast practice (ITU-R BT.1359), so nobody would notice it in a video.
    "audio_latency_ms": "0-5 ms per camera (a judgement)",
    # GoPro's GPMF gyro timestamps are known to be off from the video by tens of ms (why Gyroflow estimates a
    # gyro-video offset per clip): +-30 ms per trial, a judgement of that order.
    "imu_offset_ms": "+-30 ms per trial (a judgement)",
    # Lenses: cameras of one model differ as manufactured units (bcmocap.sim.lens_units gives the sources): focal
    # length sigma 0.3 % (a judgement below the 2-3 % of stock machine-vision lenses, optowiki.info), centre sigma
    # 0.25 % of the width per axis (Parrot's ANAFI Thermal white paper: +-22 um after active alignment, 2.3 px
    # here), the radial profile off the design, decentering and thin-prism terms (Weng et al. 1992) of a few tenths
    # of a pixel at the corners (judgements); the user is given the design's nominal lens.
    "lens_units": "on (bcmocap.sim.lens_units.UnitTolerances)",
}
PRESETS = ("realistic",)
#: The rolling-shutter readouts (ms) the realistic preset draws from, uniformly, once per capture (seeded):
#: action cameras at 1080p60 (:data:`REALISTIC` gives the sources).
READOUT_RANGE_MS = (10.0, 15.8)


def preset_settings(name: str, **fields) -> StudioSettings:
    """Settings of a named preset (``"realistic"``: every degradation of a real shoot on, :data:`REALISTIC`).

    The readout (``readout_ms``) is drawn uniformly from :data:`READOUT_RANGE_MS` by the ``seed`` (one draw per
    capture, at most 0.95 frame periods): the same seed gives the same readout.

    Args:
        name: the preset.
        fields: other settings (motion, length, seed, size, frame rate…); a degradation setting given here
            replaces the preset's value.

    Raises:
        ValueError: an unknown preset or a bad setting.
    """
    if name not in PRESETS:
        raise ValueError(f"unknown studio preset {name!r}; presets: {list(PRESETS)}")
    base = StudioSettings(**{k: v for k, v in fields.items() if k not in REALISTIC})
    frame_ms = 1000.0 / base.fps
    pixels = base.width * base.height
    values = {
        "motion_blur": True,
        "exposure_ms": round(min(8.0, 0.5 * frame_ms), 4),
        "rolling_shutter": True,
        "readout_ms": round(min(_rng(base.seed, 12).uniform(*READOUT_RANGE_MS), 0.95 * frame_ms), 4),
        "mount_wobble_mm": 3.0,
        "mount_wobble_deg": 1.5,
        "auto_exposure": True,
        "white_balance": True,
        "vignetting": 0.4,
        "full_scale_electrons": round(1100.0 * 1920 * 1080 / pixels, 1),
        "read_noise_dn": 1.0,
        "container": "mp4-aac",
        "video_bitrate_mbps": round(45.0 * pixels * base.fps / (1920 * 1080 * 60), 4),
        "focal_error_pct": 1.0,
        "centre_error_px": round(0.005 * base.width, 3),
        "start_subframe": True,
        "clock_ppm": 20.0,
        "audio_latency_ms": 5.0,
        "imu_offset_ms": 30.0,
        "lens_units": True,
    }
    values.update({k: v for k, v in fields.items() if k in REALISTIC})
    return dataclasses.replace(base, **values)


# ---------------------------------------------------------------------------------------------
# Small deterministic writers (temporary file + rename; fixed zip timestamps so bytes repeat).


def _atomic_bytes(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---------------------------------------------------------------------------------------------
# Cameras and skeletons as JSON.


def _write_opencv_yaml(path: Path, camera: CameraModel) -> None:
    """cv2.FileStorage calibration: fisheye via bcmocap.cameras' writer, pinhole with 5 zero coefficients."""
    from ..io.opencv_calibration import write_opencv_fisheye_calibration, write_opencv_storage

    with atomic_path(path, suffix=path.suffix) as tmp:  # OpenCV picks the format from the suffix
        if isinstance(camera, OpenCVFisheyeCamera):
            write_opencv_fisheye_calibration(tmp, camera)
        else:
            (fx, fy), (cx, cy) = np.asarray(camera.focal), np.asarray(camera.principal_point)
            write_opencv_storage(tmp, {"image_width": int(camera.width), "image_height": int(camera.height),
                                       "camera_matrix": np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
                                       "distortion_coefficients": np.zeros((5, 1))})


# ---------------------------------------------------------------------------------------------
# Motions, markers and timing.


def _hinge_angle(q: np.ndarray, axis: np.ndarray) -> np.ndarray:
    return 2.0 * np.arctan2(q[..., 1:] @ axis, q[..., 0])


#: Swing per kind of segment in the studio's range-of-motion trial, as a share of
#: :data:`bcmocap.sim.rom.ROM_AMPLITUDE_DEG` (every joint moves at once here, so less than one at a time).
_ROM_SHARE = 0.6


def rom_rest_frames(num_frames: int, fps: float) -> np.ndarray:
    """Indices of the rest-pose hold that starts the studio's range-of-motion trial (1/5 of it, at most 0.5 s)."""
    return np.arange(_rest_hold(num_frames, fps))


def _rest_hold(num_frames: int, fps: float) -> int:
    return max(1, min(int(round(0.5 * fps)), num_frames // 5))


#: Tape-measured distances the studio records for the subject: joint centre to joint centre, rest pose.
MEASURED_JOINTS = (("left_thigh", "left_foot"), ("right_thigh", "right_foot"),
                   ("left_upper_arm", "left_hand"), ("right_upper_arm", "right_hand"))


def studio_subject(skeleton: Skeleton, rom_frames: int, fps: float) -> dict:
    """The ``"subject"`` entry of the studio's ``capture.json`` (:func:`bcmocap.io.capture_folder.subject_record`):
    the skeleton's topology, the tape measurements of :data:`MEASURED_JOINTS` it has (rest pose, to 0.1 mm),
    and the rest-pose hold that starts the range-of-motion trial of ``rom_frames`` frames at ``fps``.
    """
    rest_joints = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    measurements = []
    for a, b in MEASURED_JOINTS:
        if a in skeleton.names and b in skeleton.names:
            d = float(np.linalg.norm(rest_joints[skeleton.index(a)] - rest_joints[skeleton.index(b)]))
            measurements.append({"from": a, "to": b, "metres": round(d, 4)})
    hold = _rest_hold(rom_frames, fps)
    topology = [(n, None if p < 0 else skeleton.names[p], JointType(t).name.lower())
                for n, p, t in zip(skeleton.names, skeleton.parents, skeleton.joint_types)]
    rest = {"trial": "rom", "after_first_clap_s": [0.0, round((int(round(_LEAD_S * fps)) + hold) / fps, 4)]}
    return subject_record(topology, measurements, rest)


#: Range-of-motion protocols of the studio (:func:`studio_range_of_motion`).
ROM_PROTOCOLS = ("together", "feet_after")

#: Share of the moving stretch of the ``feet_after`` protocol in which the legs, trunk and arms swing; the ankles
#: turn in the rest of it.
_FEET_AFTER_SHARE = 0.55


def _swell(n: int, start: int, length: int) -> np.ndarray:
    """``(n,)`` a smooth envelope: sin² over ``[start, start + length)``, zero elsewhere."""
    envelope = np.zeros(n)
    length = max(length, 1)
    envelope[start:start + length] = np.sin(np.pi * (np.arange(length) + 0.5) / length) ** 2
    return envelope


def studio_range_of_motion(skeleton: Skeleton, reference: Motion, seconds: float, fps: float,
                           rng: np.random.Generator, tempo: float = 1.0, protocol: str = "together") -> Motion:
    """A generated range-of-motion trial at the first position of ``reference``: the subject holds the
    rest pose (every joint at zero, the convention of :mod:`bcmocap.kinematics.rom`;
    :func:`rom_rest_frames`), then the joints swing about all their axes (incommensurate sinusoids of
    0.6–1.4 Hz times ``tempo`` under smooth envelopes) while the body slowly turns, then holds the rest
    pose again; hinges flex to the side ``reference`` flexes them.

    ``protocol`` (:data:`ROM_PROTOCOLS`): ``"together"``, every joint at once; ``"feet_after"``, every joint but
    the ankles in the first 55 % of the moving stretch, then ankle circles on still legs in the rest. A foot
    camera sees the floor from 10–50 cm, and while its leg swings it turns at up to 300°/s; on the studio's
    realistic walk it registered in none of those frames, which left the ankle's centre undetermined
    (``docs/benchmarks/suite.md``). Turned on its own, the ankle moves the camera at a walking pace.
    """
    from .rom import DEFAULT_AMPLITUDE_DEG, ROM_AMPLITUDE_DEG

    if protocol not in ROM_PROTOCOLS:
        raise ValueError(f"range-of-motion protocol must be one of {ROM_PROTOCOLS}, got {protocol!r}")
    n = int(round(seconds * fps))
    hold = _rest_hold(n, fps)
    moving = max(n - 2 * hold, 1)
    t = np.arange(moving) / fps
    envelope = limbs_envelope = feet_envelope = _swell(n, hold, moving)
    if protocol == "feet_after":
        first = int(round(_FEET_AFTER_SHARE * moving))
        limbs_envelope, feet_envelope = _swell(n, hold, first), _swell(n, hold + first, moving - first)
    tt = np.zeros(n)
    tt[hold:hold + moving] = t
    rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, skeleton.num_segments, 1))
    ref_rot = np.asarray(reference.rotations)
    for j in range(1, skeleton.num_segments):
        name = skeleton.names[j]
        kind = name.split("_", 1)[1] if name.startswith(("left_", "right_")) else name
        amp = _ROM_SHARE * np.deg2rad(ROM_AMPLITUDE_DEG.get(kind, DEFAULT_AMPLITUDE_DEG))
        freq = tempo * rng.uniform(0.6, 1.4, 3)
        phase = rng.uniform(0, 2 * np.pi, 3)
        jt = skeleton.joint_types[j]
        swell = feet_envelope if kind == "foot" else limbs_envelope
        if jt == JointType.BALL:
            rotvec = amp * swell[:, None] * np.sin(2 * np.pi * freq * tt[:, None] + phase)
        elif jt == JointType.HINGE:
            axis = np.asarray(skeleton.hinge_axes[j])
            side = np.sign(np.mean(_hinge_angle(ref_rot[:, j], axis))) or 1.0
            angle = side * amp * swell * 0.5 * (1 - np.cos(2 * np.pi * freq[0] * tt))
            rotvec = angle[:, None] * axis
        else:
            continue
        rot[:, j] = np.asarray(SO3.exp(rotvec).wxyz)
    yaw = np.deg2rad(60.0) * envelope * np.sin(2 * np.pi * 0.2 * tempo * tt)
    rot[:, 0] = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=1)
    rot = np.asarray(skeleton.project_rotations(rot))
    position = np.broadcast_to(np.asarray(reference.root_position[0]), (n, 3))
    return Motion(np.array(position), rot)


def _marker_layout(skeleton: Skeleton, per_segment: int, rng: np.random.Generator):
    names, segments, offsets = [], [], []
    for cap in body_capsules(skeleton):
        a, b = np.asarray(cap.a, float), np.asarray(cap.b, float)
        axis = b - a
        length = np.linalg.norm(axis)
        axis = axis / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
        helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        for i in range(per_segment):
            ang = 2 * np.pi * i / max(per_segment, 1) + rng.uniform(-0.3, 0.3)
            s = rng.uniform(0.2, 0.9)
            offsets.append(a + s * (b - a) + (cap.radius + 0.012) * (np.cos(ang) * e1 + np.sin(ang) * e2))
            segments.append(cap.segment)
            names.append(f"{skeleton.names[cap.segment]}_{i + 1}")
    return tuple(names), np.asarray(segments, np.int64), np.asarray(offsets, np.float64).reshape(-1, 3)


def _simulate_markers(skeleton: Skeleton, motion: Motion, fps: float, per_segment: int, rng: np.random.Generator,
                      noise_m: float = 0.001, gaps_per_second: float = 0.3,
                      gap_frames: tuple[int, int] = (3, 30)) -> TruthMarkers:
    names, segments, offsets = _marker_layout(skeleton, per_segment, rng)
    world = SE3(np.asarray(forward_kinematics(skeleton, motion).wxyz_xyz)[:, segments])
    positions = np.asarray(world @ offsets[None]) + rng.normal(scale=noise_m, size=(motion.num_frames, len(names), 3))
    num_frames = motion.num_frames
    for m in range(len(names)):
        for _ in range(rng.poisson(gaps_per_second * num_frames / fps)):
            length = rng.integers(gap_frames[0], gap_frames[1] + 1)
            start = rng.integers(0, num_frames)
            positions[start: start + length, m] = np.nan
    return TruthMarkers(names, segments, offsets, positions)


def _timeline(num_frames: int, num_cameras: int, fps: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    lead = int(round(_LEAD_S * fps))
    roll = int(round(_ROLL_S * fps))
    spread = int(round(_MAX_OFFSET_S * fps))
    start = lead + roll + rng.integers(0, spread + 1, num_cameras)
    tail = lead + roll + rng.integers(0, spread + 1, num_cameras)
    return {
        "video_start_frame": start.astype(np.int64),
        "num_video_frames": (start + num_frames + tail).astype(np.int64),
        "clap_frames": np.array([-lead, num_frames - 1 + lead], np.int64),
        "audio_gain": rng.uniform(0.45, 1.0, num_cameras),
        # the clocks (:func:`_clocks`): whole-frame starts, perfect clocks, no latency, no IMU offset
        "video_start_time": start.astype(np.float64),
        "clock_rate": np.ones(num_cameras),
        "audio_latency_s": np.zeros(num_cameras),
        "imu_clock_offset_s": np.float64(0.0),
    }


def _clocks(settings: StudioSettings, timelines: dict[str, dict[str, np.ndarray]], num_cameras: int) -> None:
    """Add each trial's clocks to its timeline (in place): ``video_start_time`` ``(C,)``, the video frame (fractional)
    in which trial frame 0 happens; ``clock_rate`` ``(C,)``, camera seconds per true second; ``audio_latency_s``
    ``(C,)``; ``imu_clock_offset_s`` ``()``, added to the IMU's timestamps. Video frame ``i`` of camera ``c`` shows
    trial time ``(i - video_start_time[c]) / clock_rate[c]`` frames. Without time errors: whole-frame starts,
    rates of 1, no latency and no offset."""
    s = settings
    camera_rng = _rng(s.seed, 13)  # a camera's crystal and audio path: the same in every trial
    rate = 1.0 + camera_rng.uniform(-1.0, 1.0, num_cameras) * s.clock_ppm * 1e-6
    latency = camera_rng.uniform(0.0, 1.0, num_cameras) * s.audio_latency_ms / 1000.0
    for ti, timeline in enumerate(timelines.values()):
        trial_rng = _rng(s.seed, 13, ti + 1)  # a new recording: its own sub-frame start and IMU clock offset
        phase = trial_rng.uniform(0.0, 1.0, num_cameras) if s.start_subframe else np.zeros(num_cameras)
        timeline["video_start_time"] = timeline["video_start_frame"] + phase
        timeline["clock_rate"] = rate.copy()
        timeline["audio_latency_s"] = latency.copy()
        timeline["imu_clock_offset_s"] = np.float64(trial_rng.uniform(-1.0, 1.0) * s.imu_offset_ms / 1000.0)


def trial_timelines(settings: StudioSettings, num_frames: dict[str, int], num_cameras: int) -> dict[str, dict]:
    """Each trial's timeline, as :func:`write_capture` records it for trials of ``num_frames`` frames (in trial
    order, ``{"rom": ..., "capture": ...}``): the cameras' start and stop frames, the claps' trial frames, the
    audio gains and the clocks (:func:`_clocks`). Deterministic in the settings' seed and time errors; nothing is
    rendered."""
    timelines = {name: _timeline(int(n), num_cameras, settings.fps, _rng(settings.seed, 1, i))
                 for i, (name, n) in enumerate(num_frames.items())}
    _clocks(settings, timelines, num_cameras)
    return timelines


def video_frame_times(timeline: dict[str, np.ndarray], camera: int, num_frames: int) -> np.ndarray:
    """``(N,)`` trial time (frames, clipped to ``[0, num_frames - 1]``: the subject holds still before and after)
    shown in each video frame of ``camera`` (``N = num_video_frames[camera]``; module docstring)."""
    index = np.arange(int(timeline["num_video_frames"][camera]), dtype=np.float64)
    start, rate = float(timeline["video_start_time"][camera]), float(timeline["clock_rate"][camera])
    return np.clip((index - start) / rate, 0.0, num_frames - 1.0)


def _reference_poses(scene: TexturedScene, path_xy: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``(N, 7)`` world_from_camera of hand-held photos along a loop around the capture area.

    The first half of the loop looks outwards (towards the walls), the second inwards across the room;
    the camera is held at 1.5-1.7 m, pitched 5-25° down, with a little roll.
    """
    lo, hi = path_xy.min(axis=0), path_xy.max(axis=0)
    centre = 0.5 * (lo + hi)
    semi = np.maximum(0.5 * (hi - lo) + 1.2, 1.5)
    poses = []
    for i in range(count):
        outward = i < (count + 1) // 2
        k = i if outward else i - (count + 1) // 2
        per_lap = (count + 1) // 2 if outward else max(count - (count + 1) // 2, 1)
        angle = 2 * np.pi * (k + 0.5 * (not outward)) / per_lap + rng.uniform(-0.1, 0.1)
        for shrink in np.linspace(1.0, 0.3, 15):
            xy = centre + shrink * semi * np.array([np.cos(angle), np.sin(angle)])
            p = np.array([xy[0], xy[1], rng.uniform(1.5, 1.7)])
            if not scene.inside_clutter(p[None], margin_m=-1.0)[0]:
                break
        yaw = angle + (0.0 if outward else np.pi) + rng.uniform(-0.5, 0.5)
        pitch = -np.deg2rad(rng.uniform(5.0, 25.0))
        forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        roll = np.deg2rad(rng.uniform(-3.0, 3.0))
        x = np.cos(roll) * right + np.sin(roll) * down
        y = np.cross(forward, x)
        rotation = np.stack([x, y, forward], axis=1)
        poses.append(np.concatenate([quat_from_matrix(rotation), p]))
    return np.asarray(poses, np.float64).reshape(-1, 7)


# ---------------------------------------------------------------------------------------------
# The capture.


@dataclasses.dataclass
class _Plan:
    settings: StudioSettings
    skeleton: Skeleton
    rig: Rig
    scene: TexturedScene
    trials: dict[str, Motion]
    timelines: dict[str, dict[str, np.ndarray]]
    reference_camera: PinholeCamera
    reference_poses: np.ndarray
    fit_error_px: float
    mount_poses: dict[str, np.ndarray]  # per trial (T, C, 7) world_from_mount: the rigid camera poses
    camera_offsets: dict[str, np.ndarray]  # per trial (T, C, 6) (translation m, rotation rad) on the mount
    camera_poses: dict[str, np.ndarray]  # per trial (T, C, 7) world_from_camera: mount · exp(offset), rendered
    nominal_lens: CameraModel | None = None  # with lens units: the design's lens the user is given for every camera
    passerby: dict[str, TruthPasserby] = dataclasses.field(default_factory=dict)  # per trial, room "passerby"


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, *stream]))


@functools.lru_cache(maxsize=4)
def _body_motion(motion: str | tuple[str, str], fps: float, seconds: float, source_fps: float = 0.0,
                 unit_m: float = 0.0) -> tuple[Skeleton, Motion]:
    # Parsing and reducing a CMU trial takes seconds; a resumed or repeated capture in one process reuses it.
    if isinstance(motion, str) and motion in CMU_TRIALS:
        return load_body_motion(motion, fps=fps, seconds=seconds, repeat=True)
    return load_motion_file(motion, fps=fps, seconds=seconds, repeat=True, source_fps=source_fps, unit_m=unit_m)


def _given_intrinsics(camera: CameraModel, settings: StudioSettings, rng: np.random.Generator) -> CameraModel:
    """The calibration a user is given for a camera: focal length and centre off by the settings' errors."""
    if settings.focal_error_pct <= 0 and settings.centre_error_px <= 0:
        return camera
    relative = rng.uniform(0.3, 1.0) * settings.focal_error_pct / 100.0 * rng.choice([-1.0, 1.0])
    angle = rng.uniform(0.0, 2 * np.pi)
    shift = rng.uniform(0.3, 1.0) * settings.centre_error_px * np.array([np.cos(angle), np.sin(angle)])
    return eqx.tree_at(lambda c: (c.focal, c.principal_point), camera,
                       (np.asarray(camera.focal) * (1.0 + relative), np.asarray(camera.principal_point) + shift))


def _camera_truth(settings: StudioSettings, skeleton: Skeleton, rig: Rig, trials: dict[str, Motion]):
    """Per trial: rigid mount poses, offsets on the mounts (zero without wobble) and the true camera poses."""
    s = settings
    mounts = {t: np.asarray(rig.world_from_camera(forward_kinematics(skeleton, m)).wxyz_xyz) for t, m in trials.items()}
    if s.mount_wobble_mm <= 0 and s.mount_wobble_deg <= 0:
        offsets = {t: np.zeros(p.shape[:2] + (6,)) for t, p in mounts.items()}
        return mounts, offsets, dict(mounts)
    straps, first = mount_wobble(mounts["capture"], s.fps, s.mount_wobble_mm / 1000.0, math.radians(s.mount_wobble_deg),
                                 _rng(s.seed, 7))
    offsets = {t: first if t == "capture" else straps.offsets(mounts[t], s.fps, _rng(s.seed, 7, i))
               for i, t in enumerate(trials)}
    poses = {t: np.asarray((SE3(mounts[t]) @ SE3.exp(offsets[t])).wxyz_xyz) for t in trials}
    return mounts, offsets, poses


def _plan(settings: StudioSettings) -> _Plan:
    s = settings
    skeleton, motion = _body_motion(s.motion, s.fps, s.seconds, s.motion_fps, s.motion_unit_m)
    rig = standard_rig(skeleton, s.width, s.height)
    fitted, fit_error = fit_opencv_fisheye(camera_at(rig.intrinsics, 0))
    if s.lens == "opencv_fisheye":
        rig = Rig(rig.names, rig.segments, rig.segment_from_camera, stack_cameras([fitted] * rig.num_cameras))
        fit_error = 0.0
    nominal = None
    if s.lens_units:
        rig, nominal = _lens_units(s, rig)
    rom = studio_range_of_motion(skeleton, motion, s.rom_seconds, s.fps, _rng(s.seed, 5), s.rom_tempo, s.rom_protocol)
    path_xy = np.asarray(motion.root_position)[:, :2]
    scene = make_room(s.room if s.room in ROOM_STYLES else "textured", path_xy, seed=s.seed)
    trials = {"rom": rom, "capture": motion}
    timelines = trial_timelines(s, {name: m.num_frames for name, m in trials.items()}, rig.num_cameras)
    focal = 0.5 * s.reference_width / math.tan(math.radians(s.reference_fov_deg) / 2)
    reference_camera = PinholeCamera(
        width=s.reference_width, height=s.reference_height, focal=[focal, focal],
        principal_point=[(s.reference_width - 1) / 2, (s.reference_height - 1) / 2],
    )
    reference_poses = _reference_poses(scene, path_xy, s.reference_photos, _rng(s.seed, 4))
    mounts, offsets, poses = _camera_truth(s, skeleton, rig, trials)
    return _Plan(s, skeleton, rig, scene, trials, timelines, reference_camera, reference_poses, fit_error, mounts,
                 offsets, poses, nominal, passerby=_passersby(s, skeleton, trials, scene))


def _lens_units(settings: StudioSettings, rig: Rig) -> tuple[Rig, CameraModel]:
    """``rig`` with every camera its own unit of the studio's lens design (:mod:`bcmocap.sim.lens_units`, seeded),
    and the design's nominal lens in the settings' ``lens`` family (what the user is given)."""
    design = lens_design(settings.width, settings.height)
    units = manufactured_lens_units(design, rig.num_cameras, _rng(settings.seed, 11))
    return (Rig(rig.names, rig.segments, rig.segment_from_camera, stack_cameras(units)),
            nominal_lens(design, settings.lens))


def _check_folder(path: Path, settings: StudioSettings) -> bool:
    """Raise if ``path`` must not be written; True when it holds a capture to resume."""
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"{path} exists and is not a folder")
    if not path.exists() or not any(path.iterdir()):
        return False
    try:
        data = json.loads(manifest_path(path).read_text())
    except (OSError, json.JSONDecodeError):
        data = None
    if not isinstance(data, dict) or data.get("format") != CAPTURE_FORMAT:
        raise FileExistsError(
            f"{path} is not empty and is not a bcmocap capture (no valid capture.json): refusing to write into it; "
            "choose an empty or new folder"
        )
    stored = data.get("settings")
    if isinstance(stored, dict):  # a capture written before a setting existed was written with its default
        defaults = {f.name: f.default for f in dataclasses.fields(StudioSettings)}
        stored = {**json.loads(json.dumps(defaults)), **stored}
    if data.get("version") != CAPTURE_VERSION or stored != json.loads(json.dumps(settings.to_dict())):
        raise FileExistsError(
            f"{path} holds a capture written with other settings ({data.get('settings')}); refusing to mix "
            "captures: choose another folder or repeat the same settings to resume"
        )
    return True


def _frame_key(seed: int, trial: int, camera: int, frame: np.ndarray) -> np.ndarray:
    """Seeds of the sensor noise of frames (uint32), distinct per seed, trial, camera and frame."""
    base = ((int(seed) * 1_000_003 + trial * 7_919 + camera * 104_729) * 65_537) & 0xFFFFFFFF
    return ((base + np.asarray(frame, np.int64)) & 0xFFFFFFFF).astype(np.uint32)


def capsule_ends(skeleton: Skeleton, motion: Motion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body's capsules over a motion: end points ``(T, K, 2, 3)`` (world, m), radii ``(K,)``, colours ``(K, 3)``."""
    caps = body_capsules(skeleton)
    segs = np.array([c.segment for c in caps])
    local = np.array([[c.a, c.b] for c in caps], np.float64)
    world = np.asarray(forward_kinematics(skeleton, motion).wxyz_xyz)[:, segs]  # (T, K, 7)
    ends = np.asarray(SE3(world[:, :, None]) @ local[None])  # (T, K, 2, 3)
    return ends, np.array([c.radius for c in caps]), capsule_colors(caps, skeleton.names)


def _passersby(settings: StudioSettings, skeleton: Skeleton, trials: dict[str, Motion],
               scene: TexturedScene) -> dict[str, TruthPasserby]:
    """The passer-by of each trial (room "passerby": :mod:`bcmocap.sim.passerby`, NaN while out of the room), or none.

    A walking subject meets a runner, any other subject a walker (CMU's walk and run are two people).
    """
    if settings.room != "passerby":
        return {}
    gait = "run" if settings.motion == "walk" else "walk"
    out = {}
    for trial, motion in trials.items():
        walker, walk, present, _ = passerby_motion(scene, skeleton, motion, settings.fps, motion=gait)
        ends, radii, _ = capsule_ends(walker, walk)
        ends, absent = np.array(ends), ~present
        root, joints = np.array(walk.root_position), np.array(forward_kinematics(walker, walk).translation())
        for a in (ends, root, joints):
            a[absent] = np.nan
        colors = capsule_colors(body_capsules(walker), walker.names, PASSERBY_PALETTE)
        out[trial] = TruthPasserby(gait, present, tuple(walker.names), root, joints, ends, radii, colors)
    return out


_AWAY = np.array([0.0, 0.0, -1000.0])  # where an absent passer-by's capsules are rendered: under the floor, unseen


def _trial_capsules(plan: _Plan, trial: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The capsules rendered in a trial: the subject's, then the passer-by's (as :func:`capsule_ends`)."""
    ends, radii, colors = capsule_ends(plan.skeleton, plan.trials[trial])
    walker = plan.passerby.get(trial)
    if walker is None:
        return ends, radii, colors
    away = np.where(np.isnan(walker.capsules), _AWAY, walker.capsules)
    return (np.concatenate([ends, away], axis=1), np.concatenate([radii, walker.radii]),
            np.concatenate([colors, walker.colors]))


class _VideoSink:
    """A video written under a temporary name and renamed when closed (calls run on one writer thread): mp4v
    through OpenCV, or with a soundtrack H.264 + AAC in one file through PyAV."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int], audio: tuple[np.ndarray, int] | None = None,
                 bitrate_mbps: float = 0.0):
        self.path = path
        self.tmp = path.with_name(f".{path.stem}.partial.mp4")
        if audio is not None:
            from ..io.media import MediaWriter

            samples, rate = audio
            bitrate = int(round(bitrate_mbps * 1e6)) if bitrate_mbps > 0 else None
            self.media = MediaWriter(self.tmp, fps, size, rate, bitrate=bitrate)
            self.media.write_audio(samples)
            return
        import cv2

        self.media = None
        self.frames = 0
        self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size)
        if not self.writer.isOpened():
            raise RuntimeError(f"{self.tmp}: OpenCV cannot open an mp4v video writer")

    def write(self, frames_rgb: list[np.ndarray]) -> None:
        with full_disk_named(self.path.parent, self.path.name, self.tmp):
            if self.media is not None:
                self.media.write(frames_rgb)
                return
            for frame in frames_rgb:
                self.writer.write(np.ascontiguousarray(frame[..., ::-1]))
                self.frames += 1

    def close(self) -> None:
        with full_disk_named(self.path.parent, self.path.name, self.tmp):
            if self.media is not None:
                self.media.close()
            else:
                self.writer.release()
                self._check_opencv_video()
            os.replace(self.tmp, self.path)

    def _check_opencv_video(self) -> None:
        """OpenCV's writer only logs a failed write (a full disk): read the frame count back before the rename."""
        import cv2

        video = cv2.VideoCapture(str(self.tmp))
        count = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video.isOpened() else -1
        video.release()
        if count == self.frames:
            return
        free = shutil.disk_usage(self.tmp.parent).free
        if free < max(1 << 20, self.tmp.stat().st_size // 10):  # the disk is (nearly) full: say so
            raise disk_full(self.path.parent, self.path.name, written=self.tmp.stat().st_size)
        raise OSError(f"{self.tmp}: OpenCV wrote {count} of {self.frames} frames")


def _render_camera_trial(plan: _Plan, renderer: Renderer, trial_index: int, trial: str, camera: int,
                         poses: np.ndarray, capsules: tuple, video: Path, pool: concurrent.futures.Executor,
                         advance: Callable[[int], None],
                         audio: tuple[np.ndarray, int] | None = None) -> concurrent.futures.Future:
    """Render one camera's trial into ``video`` batch by batch while a writer thread encodes the previous batches.

    ``audio`` ``(samples, rate)``: the soundtrack, written into the video file as its audio track (container "mp4-aac").
    Returns the future of the video's completion (rename to its final name).
    """
    s = plan.settings
    n = plan.trials[trial].num_frames
    # The trial times the video shows, each rendered once and repeated while it holds (the subject stands still
    # before and after the trial): with whole-frame starts and perfect clocks, frames 0..n-1 with copies of the
    # first and the last.
    times, repeats = np.unique(video_frame_times(plan.timelines[trial], camera, n), return_counts=True)
    count = len(times)
    ends, radii, colors = capsules
    sink = pool.submit(_VideoSink, video, s.fps, (s.width, s.height),
                       audio, s.video_bitrate_mbps).result()
    control = None
    if s.auto_exposure or s.white_balance:
        control = ExposureControl(s.fps, s.auto_exposure, s.white_balance, _rng(s.seed, 8, trial_index, camera),
                                  renderer.rays.valid)
    writes: list[concurrent.futures.Future] = []
    for first in range(0, count, _BATCH):
        rendered = np.minimum(np.arange(first, first + _BATCH), count - 1)  # positions in `times`: noise keys
        frames = times[rendered]
        rot, org = renderer.poses_at(poses, frames)
        gains = None
        real = min(_BATCH, count - first)
        if control is not None:
            gains = control.gains(real)
            gains = np.concatenate([gains, np.repeat(gains[-1:], _BATCH - real, axis=0)])
        images = renderer.render(rot, org, renderer.capsules_at(ends, frames), radii, colors,
                                 _frame_key(s.seed, trial_index, camera, rendered), gains)
        if control is not None:
            control.meter(images[real - 1], gains[real - 1])
        video = []
        for k, image in zip(range(first, first + real), images):
            video.extend([image] * int(repeats[k]))
        writes.append(pool.submit(sink.write, video))
        if len(writes) > 2:  # back-pressure: at most a few batches wait for the encoder
            writes.pop(0).result()
        advance(real)
    for w in writes:
        w.result()
    return pool.submit(sink.close)


def write_capture(path: str | os.PathLike, settings: StudioSettings = StudioSettings(), *, progress: bool = True,
                  timings: dict | None = None) -> Path:
    """Render a synthetic capture folder and its ground truth (layout in the module docstring).

    Args:
        path: the capture folder: new, empty, or a capture with the same settings to resume.
        settings: what to render.
        progress: show a tqdm progress bar over rendered frames.
        timings: if given, filled with wall-clock seconds per phase (``setup`` — motions, scene, static
            files —, ``reference_photos``, ``trial:<name>`` rendering and encoding, compilations
            included) and the frames rendered per trial (``frames:<name>``).

    Returns:
        The folder.

    Raises:
        FileExistsError: ``path`` is a file, a non-empty folder that is not a capture, or a capture made
            with other settings (nothing is written).
    """
    import time

    from tqdm import tqdm

    clock = time.perf_counter()
    timings = {} if timings is None else timings
    folder = Path(path)
    resume = _check_folder(folder, settings)
    plan = _plan(settings)
    s, rig, skeleton = settings, plan.rig, plan.skeleton
    manifest = new_manifest(settings=s.to_dict(), cameras=list(rig.names), trials=list(TRIALS),
                            subject=studio_subject(skeleton, plan.trials["rom"].num_frames, s.fps), complete=False)
    if s.motion_paths:  # where a motion file came from (its bytes may change after the capture)
        manifest["motion_files"] = [{"path": str(f), "sha256": _sha256(Path(f))} for f in s.motion_paths]
    folder.mkdir(parents=True, exist_ok=True)
    if not resume:  # the manifest first: an interrupted capture is always recognised as one
        write_manifest(folder, manifest)
    for sub in (intrinsics_dir(folder), reference_dir(folder), ground_truth_dir(folder),
                *(trial_dir(folder, t) for t in TRIALS)):
        sub.mkdir(parents=True, exist_ok=True)
    _write_static_files(folder, plan)

    embedded = s.container == "mp4-aac"

    def written(trial: str, camera: int) -> bool:
        name = rig.names[camera]
        return (trial_video_path(folder, trial, name).exists()
                and (embedded or trial_audio_path(folder, trial, name).exists()))

    todo = [(ti, t, c) for ti, t in enumerate(TRIALS) for c in range(rig.num_cameras) if not written(t, c)]
    photos = [i for i in range(len(plan.reference_poses)) if not reference_photo_path(folder, i).exists()]
    total = sum(plan.trials[t].num_frames for _, t, _ in todo) + len(photos)
    options = s.render_options()
    with tqdm(total=total, unit="frame", desc="bcmocap simulate", disable=not progress, smoothing=0.1) as bar, \
            concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        timings["setup"] = time.perf_counter() - clock
        clock = time.perf_counter()
        _write_reference_photos(folder, plan, photos, bar.update)
        timings["reference_photos"] = time.perf_counter() - clock
        renderers: dict[bytes, Renderer] = {}
        trial_data = {}
        closing: list[concurrent.futures.Future] = []
        for trial_index, trial, camera in todo:
            if trial not in trial_data:
                for done in closing:  # the previous trial's videos are finished: its time is complete
                    done.result()
                if trial_data:
                    timings[f"trial:{list(trial_data)[-1]}"] = time.perf_counter() - clock
                timings[f"frames:{trial}"] = 0
                clock = time.perf_counter()
                trial_data[trial] = (plan.camera_poses[trial], _trial_capsules(plan, trial))
            poses, capsules = trial_data[trial]
            cam = camera_at(rig.intrinsics, camera)
            key = np.concatenate([np.ravel(np.asarray(leaf)) for leaf in jax.tree.leaves(cam)]).tobytes()
            if key not in renderers:
                renderers[key] = Renderer(plan.scene, cam, options)
            video = trial_video_path(folder, trial, rig.names[camera])
            track = camera_soundtrack(s, plan.timelines[trial], trial_index, camera)
            if not embedded:
                write_wav(trial_audio_path(folder, trial, rig.names[camera]), track, s.audio_rate)
            closing.append(_render_camera_trial(plan, renderers[key], trial_index, trial, camera, poses[:, camera],
                                                capsules, video, pool, bar.update,
                                                (track, s.audio_rate) if embedded else None))
            timings[f"frames:{trial}"] += plan.trials[trial].num_frames
        for done in closing:
            done.result()
        if todo:
            timings[f"trial:{todo[-1][1]}"] = time.perf_counter() - clock
    write_manifest(folder, {**manifest, "complete": True})
    return folder


def clap_samples(timeline: dict[str, np.ndarray], settings: StudioSettings) -> np.ndarray:
    """``(C, 2)`` first sample of each clap in each camera's track: the clap's video time on the camera's clock
    (:func:`video_frame_times` inverted), plus its audio latency."""
    frames = video_frame_at(timeline["video_start_time"][:, None], timeline["clock_rate"][:, None],
                            timeline["clap_frames"][None, :])
    latency = timeline["audio_latency_s"][:, None] * timeline["clock_rate"][:, None] * settings.fps
    return np.round((frames + latency) * settings.audio_rate / settings.fps).astype(np.int64)


def camera_soundtrack(settings: StudioSettings, timeline: dict[str, np.ndarray], trial_index: int,
                      camera: int) -> np.ndarray:
    """One camera's soundtrack of a trial (the ``trial_index``-th of :func:`trial_timelines`, whose ``timeline`` it
    is): samples in [-1, 1] at ``audio_rate``, sample 0 at video frame 0, the claps at :func:`clap_samples`."""
    s, tl = settings, timeline
    per_frame = s.audio_rate / s.fps
    num_samples = int(round(int(tl["num_video_frames"][camera]) * per_frame))
    claps = clap_samples(tl, s)[camera].tolist()
    return soundtrack(num_samples, claps, s.audio_rate, _rng(s.seed, 2, trial_index, camera),
                      gain=float(tl["audio_gain"][camera]))


def _write_reference_photos(folder: Path, plan: _Plan, todo: list[int], advance: Callable[[int], None]) -> None:
    import cv2

    if not todo:
        return
    renderer = Renderer(plan.scene, plan.reference_camera, RenderOptions())
    for first in range(0, len(todo), _BATCH):
        idx = np.array([todo[min(i, len(todo) - 1)] for i in range(first, first + _BATCH)])
        poses = plan.reference_poses[idx]
        rot = np.asarray(matrix_from_quat(poses[:, :4]))[:, None, None]
        org = poses[:, None, None, 4:]
        images = renderer.render(rot, org, keys=_frame_key(plan.settings.seed, 9, 0, idx))
        for i, image in zip(idx[: min(_BATCH, len(todo) - first)], images):
            ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
            if not ok:
                raise RuntimeError("OpenCV could not encode a reference photo as JPEG")
            _atomic_bytes(reference_photo_path(folder, int(i)), data.tobytes())
        advance(min(_BATCH, len(todo) - first))


def _write_static_files(folder: Path, plan: _Plan) -> None:
    """Intrinsics, rig, ground truth and the trials' sensor files (cheap and deterministic: rewritten on every
    run, so resuming a capture written before the sensor files adds them)."""
    from ..io.bvh import write_bvh

    s, rig, skeleton = plan.settings, plan.rig, plan.skeleton
    cameras = []
    calibration_rng = _rng(s.seed, 6)
    for c, name in enumerate(rig.names):
        given = camera_at(rig.intrinsics, c) if plan.nominal_lens is None else plan.nominal_lens
        cam = _given_intrinsics(given, s, calibration_rng)  # the rendered lens by default
        fitted, err = fit_opencv_fisheye(cam)
        _write_opencv_yaml(intrinsics_path(folder, name), fitted)
        write_json(lens_path(folder, name), {**camera_to_dict(cam), "opencv_fisheye_fit_max_error_px": err})
        entry = {"name": name, "segment": skeleton.names[rig.segments[c]],
                 "intrinsics": relative_name(folder, intrinsics_path(folder, name)),
                 "lens": relative_name(folder, lens_path(folder, name)),
                 "video": {t: relative_name(folder, trial_video_path(folder, t, name)) for t in TRIALS}}
        if s.container == "mp4v-wav":  # with "mp4-aac" the soundtrack is the video's own audio track
            entry["audio"] = {t: relative_name(folder, trial_audio_path(folder, t, name)) for t in TRIALS}
        cameras.append(entry)
    write_json(rig_path(folder), {"cameras": cameras, "segments": list(skeleton.names)})
    write_json(reference_camera_path(folder), camera_to_dict(plan.reference_camera))
    _write_opencv_yaml(reference_camera_path(folder, ".yml"), plan.reference_camera)

    write_json(truth_skeleton_path(folder), skeleton_to_dict(skeleton))
    write_json(truth_rig_path(folder), rig_to_dict(rig, skeleton))
    write_json(truth_scene_path(folder), plan.scene.to_dict())
    points, materials = plan.scene.sample_points(seed=s.seed)
    write_npz_atomic(world_points_path(folder), {"points": points, "materials": materials})
    names = [reference_photo_path(folder, i).name for i in range(len(plan.reference_poses))]
    write_npz_atomic(reference_truth_path(folder), {"names": np.array(names), "world_from_camera": plan.reference_poses})
    wobble = s.mount_wobble_mm > 0 or s.mount_wobble_deg > 0
    for ti, (trial, motion) in enumerate(plan.trials.items()):
        fk = forward_kinematics(skeleton, motion)
        markers = _simulate_markers(skeleton, motion, s.fps, s.markers_per_segment, _rng(s.seed, 3, ti))
        write_npz_atomic(trial_truth_path(folder, trial), {
            "root_position": np.asarray(motion.root_position),
            "rotations": np.asarray(motion.rotations),
            "joint_positions": np.asarray(fk.translation()),
            "world_rotations": np.asarray(fk.rotation().wxyz),
            "world_from_camera": plan.camera_poses[trial],
            "world_from_mount": plan.mount_poses[trial],
            "camera_offsets": plan.camera_offsets[trial],
            **plan.timelines[trial],
            "clap_samples": clap_samples(plan.timelines[trial], s),
            "fps": np.float64(s.fps),
            "audio_rate": np.int64(s.audio_rate),
            "marker_names": np.array(markers.names),
            "marker_segments": markers.segments,
            "marker_offsets": markers.offsets,
            "markers": markers.positions,
        })
        write_bvh(trial_truth_path(folder, trial, ".bvh"), skeleton, motion, 1.0 / s.fps)
        if trial in plan.passerby:
            passerby_truth_path(folder, trial).parent.mkdir(exist_ok=True)
            write_npz_atomic(passerby_truth_path(folder, trial), plan.passerby[trial].arrays())
        write_trial_sensors(trial_dir(folder, trial), skeleton, rig, motion, s.fps, plan.timelines[trial]["clap_frames"],
                            seed=s.seed, trial_index=ti, world_from_camera=plan.camera_poses[trial] if wobble else None,
                            clock_offset_s=float(plan.timelines[trial]["imu_clock_offset_s"]))


# ---------------------------------------------------------------------------------------------
# Reading the ground truth back (bcmocap.io.capture_folder; here with the studio's settings and scene).


def read_studio_model(folder: str | os.PathLike) -> tuple[dict, StudioSettings, Skeleton, Rig]:
    """``(manifest, settings, skeleton, rig)`` of a studio capture: ``capture.json`` (as read), its settings and
    the true model of ``ground_truth/`` (the rendered lenses and mounts;
    :func:`bcmocap.io.capture_folder.read_truth_model`).

    Raises:
        ValueError: not a studio capture, or a missing or malformed file (naming it).
    """
    manifest, skeleton, rig = capture_folder.read_truth_model(folder)
    return manifest.data, StudioSettings.from_dict(manifest.settings, str(manifest.path)), skeleton, rig


def load_ground_truth(path: str | os.PathLike) -> GroundTruth:
    """Read the ground truth of a capture folder written by :func:`write_capture`
    (:func:`bcmocap.io.capture_folder.load_ground_truth` with the settings as :class:`StudioSettings` and the scene
    as :class:`~bcmocap.sim.scene.TexturedScene`).

    Raises:
        ValueError: naming the file that is missing or malformed.
    """
    return capture_folder.load_ground_truth(path, parse_settings=StudioSettings.from_dict,
                                            parse_scene=TexturedScene.from_dict)
