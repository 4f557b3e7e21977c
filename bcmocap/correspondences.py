"""Correspondences: what the frontend (or the simulator) hands the solver.

Per camera and frame, the 2D measurements of known 3D scene points; per camera and frame that could
not be registered, 2D–2D matches with the previous frame (for the homography term); and the camera
poses that registration found (to initialise the skeleton's motion). Ragged data are padded to fixed
sizes with zero weights so every window has static shapes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .atomic import atomic_path


@dataclasses.dataclass
class Correspondences:
    """Measurements of a capture (T frames, C cameras).

    Attributes:
        points: ``(P, 3)`` scene points in the world (m).
        point_ids: ``(T, C, N)`` int32 index into ``points``, −1 for empty slots.
        pixels: ``(T, C, N, 2)`` measured pixel positions (OpenCV convention).
        weights: ``(T, C, N)`` inverse measurement variance (px⁻²); 0 for empty slots.
        homography_pixels: ``(T, C, M, 2)`` pixels in frame t of matches with frame t−1.
        homography_pixels_prev: ``(T, C, M, 2)`` the matched pixels in frame t−1.
        homography_weights: ``(T, C, M)``; 0 for empty slots (and for all of frame 0).
        world_from_camera: ``(T, C, 7)`` registered camera poses (wxyz_xyz); rows with
            ``registered`` False are ignored.
        registered: ``(T, C)`` bool, whether registration gave the camera's pose at that frame.
        fps: frame rate (Hz).
    """

    points: np.ndarray
    point_ids: np.ndarray
    pixels: np.ndarray
    weights: np.ndarray
    homography_pixels: np.ndarray
    homography_pixels_prev: np.ndarray
    homography_weights: np.ndarray
    world_from_camera: np.ndarray
    registered: np.ndarray
    fps: float

    def __post_init__(self):
        self.validate()

    @property
    def num_frames(self) -> int:
        return self.point_ids.shape[0]

    @property
    def num_cameras(self) -> int:
        return self.point_ids.shape[1]

    def validate(self, source: str = "Correspondences") -> None:
        """Raise ValueError naming the field whose shape or values are wrong."""
        if self.point_ids.ndim != 3:
            raise ValueError(f"{source}: point_ids must have shape (T, C, N), got {self.point_ids.shape}")
        if not np.issubdtype(np.asarray(self.point_ids).dtype, np.integer):
            raise ValueError(f"{source}: point_ids must be integers, got dtype {np.asarray(self.point_ids).dtype}")
        if np.asarray(self.registered).dtype != bool:
            raise ValueError(f"{source}: registered must be bool, got dtype {np.asarray(self.registered).dtype}")
        t, c, n = self.point_ids.shape
        if self.homography_weights.ndim != 3:
            raise ValueError(f"{source}: homography_weights must have shape (T, C, M), got {self.homography_weights.shape}")
        m = self.homography_weights.shape[2]
        expected = {
            "points": (len(self.points), 3),
            "pixels": (t, c, n, 2),
            "weights": (t, c, n),
            "homography_pixels": (t, c, m, 2),
            "homography_pixels_prev": (t, c, m, 2),
            "homography_weights": (t, c, m),
            "world_from_camera": (t, c, 7),
            "registered": (t, c),
        }
        for name, shape in expected.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"{source}: {name} has shape {got}, expected {shape}")
        if not np.all(np.isfinite(self.points)):
            raise ValueError(f"{source}: points contain NaN/inf (first: point "
                             f"{int(np.argmax(~np.all(np.isfinite(self.points), axis=1)))})")
        if self.point_ids.max(initial=-1) >= len(self.points):
            raise ValueError(f"{source}: point_ids reach {self.point_ids.max()} but there are {len(self.points)} points")
        for name in ("weights", "homography_weights"):
            w = getattr(self, name)
            if not np.all(np.isfinite(w)) or (w < 0).any():
                raise ValueError(f"{source}: {name} must be finite and non-negative")
        for name, wname in (("pixels", "weights"), ("homography_pixels", "homography_weights"), ("homography_pixels_prev", "homography_weights")):
            bad = (getattr(self, wname) > 0) & ~np.all(np.isfinite(getattr(self, name)), axis=-1)
            if bad.any():
                ti, ci, k = np.argwhere(bad)[0]
                raise ValueError(f"{source}: {name} has NaN/inf at frame {ti}, camera {ci}, slot {k}")
        bad = self.registered & ~np.all(np.isfinite(self.world_from_camera), axis=-1)
        if bad.any():
            ti, ci = np.argwhere(bad)[0]
            raise ValueError(f"{source}: world_from_camera has NaN/inf at registered frame {ti}, camera {ci}")
        if not self.fps > 0:
            raise ValueError(f"{source}: fps must be positive, got {self.fps}")
        if not np.isfinite(self.fps):
            raise ValueError(f"{source}: fps must be finite, got {self.fps}")

    def frames(self, start: int, stop: int) -> Correspondences:
        """The frames ``[start, stop)`` (homography rows stay tied to their frame)."""
        sl = slice(start, stop)
        return Correspondences(
            self.points, self.point_ids[sl], self.pixels[sl], self.weights[sl], self.homography_pixels[sl],
            self.homography_pixels_prev[sl], self.homography_weights[sl], self.world_from_camera[sl],
            self.registered[sl], self.fps,
        )

    @classmethod
    def concatenate(cls, parts: list[Correspondences]) -> Correspondences:
        """Consecutive stretches of one trial as one (a trial registered in chunks): frames in order, each
        part's points appended with its ids offset, measurement and homography slots padded to the widest
        part. The parts must share cameras and ``fps``."""
        if not parts:
            raise ValueError("Correspondences.concatenate: no parts")
        cams, fps = parts[0].num_cameras, parts[0].fps
        for k, part in enumerate(parts):
            if part.num_cameras != cams or part.fps != fps:
                raise ValueError(f"Correspondences.concatenate: part {k} has {part.num_cameras} cameras at "
                                 f"{part.fps:g} fps, part 0 {cams} at {fps:g}")
        n = max(p.point_ids.shape[2] for p in parts)
        m = max(p.homography_weights.shape[2] for p in parts)
        pad = pad_slots

        offsets = np.cumsum([0] + [len(p.points) for p in parts[:-1]])
        ids = [np.where(p.point_ids >= 0, p.point_ids + o, -1).astype(np.int32) for p, o in zip(parts, offsets)]
        return cls(
            np.concatenate([p.points for p in parts]).reshape(-1, 3),
            np.concatenate([pad(i, n, -1) for i in ids]),
            np.concatenate([pad(p.pixels, n, 0.0) for p in parts]),
            np.concatenate([pad(p.weights, n, 0.0) for p in parts]),
            np.concatenate([pad(p.homography_pixels, m, 0.0) for p in parts]),
            np.concatenate([pad(p.homography_pixels_prev, m, 0.0) for p in parts]),
            np.concatenate([pad(p.homography_weights, m, 0.0) for p in parts]),
            np.concatenate([p.world_from_camera for p in parts]),
            np.concatenate([p.registered for p in parts]),
            fps,
        )

    def save(self, path: str | Path) -> None:
        """Write an ``.npz`` file atomically (a temporary file in the same folder, then renamed)."""
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(tmp, **{f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)})

    @classmethod
    def load(cls, path: str | Path) -> Correspondences:
        """Read a file written by :meth:`save`; errors name the file and the missing field."""
        path = Path(path)
        try:
            archive = np.load(path)
        except (OSError, ValueError) as err:
            raise ValueError(f"{path}: not a readable correspondences file ({err})") from None
        with archive:
            fields = {}
            for f in dataclasses.fields(cls):
                if f.name not in archive:
                    raise ValueError(f"{path}: missing field '{f.name}'")
                fields[f.name] = archive[f.name]
        fields["fps"] = float(fields["fps"])
        fields["registered"] = fields["registered"].astype(bool)
        out = cls.__new__(cls)
        for k, v in fields.items():
            setattr(out, k, v)
        out.validate(str(path))
        return out


def pad_slots(a: np.ndarray, width: int, fill) -> np.ndarray:
    """``(T, C, n, …)`` measurement or homography slots padded along axis 2 to ``width`` with ``fill``."""
    extra = [(0, 0)] * a.ndim
    extra[2] = (0, width - a.shape[2])
    return np.pad(a, extra, constant_values=fill)
