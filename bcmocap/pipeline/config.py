"""Settings of ``bcmocap run``: defaults that work on the standard capture, a config file, flags.

A config file is TOML or JSON with any subset of the sections below; unknown sections or keys,
values of the wrong type (also inside lists), numbers that are not finite and values out of range
(see the comments below) are errors naming them. The settings used are saved with the outputs
(``DIR/config.json``), and a resumed run must use the same settings for the stages it reuses.

.. code-block:: toml

    [frontend]
    stride = 2            # use every n-th video frame (the solver runs at fps / stride); 1 to 1000
    rom_stride = 3        # the same for the range-of-motion trial
    max_features = 8000   # SIFT features per image, 100 to 1000000
    frames = 0            # at most this many frames per camera and trial (0: all)
    chunk_frames = 400    # register in chunks of at most this many processed frames, saved as done (0: whole trial)
    registration = "tracking" # tracking (KLT + PnP, SIFT at keyframes) | global (SIFT + reference matching of
                              # every frame: ~8x slower on the 10 s walk, as accurate)
    max_measurements = 300    # measurements per camera-frame kept for the solver (0: all)
    points = "reference"      # reference: the solver measures only the reference model's points (those
                              # triangulated from a body camera carry its pose error) | all
    rolling_shutter_readout = 0.0   # s from the first row to the last, at most a frame period: every frame is
                              # corrected for it by the cameras' gyros (trials/<trial>/imu.npz) before
                              # registration; 0: global shutter (bcmocap.frontend.rolling_shutter)
    gyro_timing = "clock"     # with a readout, when each frame was exposed on its gyro's clock: clock (the clap
                              # sync's frame time on imu.npz's clock) | frames (each camera's shift found in its
                              # own frames: sub-frame starts, an IMU clock offset; bcmocap.frontend.gyro_timing)
    estimate_readout = false  # with gyro_timing = "frames", find the readout there too (the one given is the start)
    self_calibration = false  # register both trials, estimate each camera's focal length and centre from them
                              # (reference points fixed), then register again through the corrected lenses,
                              # which the later stages start from (DIR/frontend/intrinsics.npz); twice the time

    [skeleton]
    root_origin = ["torso"]   # children whose joint centres' mean is the root's origin
    rest_seconds = []         # [from, to] s after the ROM trial's first clap; [] = from capture.json
    up_from = ["left_foot", "right_foot"]   # the world's +Z points from these joint centres ...
    up_to = "head"                          # ... to this one, in the rest pose
    max_centre_std_cm = 5.0   # a joint centre less certain than this (standard error) is not determined (degenerate)
    degenerate = "mirror"     # a ball joint the trials do not determine (moved about too few axes, or its centre
                              # less certain than max_centre_std_cm): mirror (warn, and give it its other side's
                              # centre mirrored through the body's midplane; both sides undetermined raise; a
                              # direction moved more than half min_spread, where the centre is certain enough, is
                              # kept; a hinge whose axis is fixed but centre is not keeps its axis, takes the centre) |
                              # hinge (moved about one axis only: warn, and fix its centre on that axis by the
                              # straight rest pose, as for a knee) | raise
    centre_trials = ["rom", "capture"]   # trials whose motion fits the joint centres: ["rom"] (the paper) |
                              # ["rom", "capture"] (all the motion there is; rest pose and virtual cameras stay
                              # the ROM trial's)
    unregistered_ends = "mirror"   # an end segment (a foot, a hand) whose cameras register in neither trial:
                              # mirror (warn, and give it its other side's joint centre and camera mounts mirrored
                              # through the body's midplane) | raise
    unregistered_rest = "mirror"   # a segment no rest frame registers and no gyro carries there: mirror (warn,
                              # and give it the rest orientation that puts its bone and its child joint's bend
                              # where its other side's are, mirrored) | raise

    [solver]
    window = 60               # frames per window, 2 to 100000
    overlap = 10              # frames shared by consecutive windows, 0 to window - 1
    windows = "sequential"    # sequential: each window starts from the one before (the paper) | independent:
                              # each from the initial motion, joined over the overlaps, then a pass over the
                              # seams (tasks on a cluster; bcmocap.solver.parallel)
    root_smoothness = 1000.0  # λ_O, px² per m² (and per rad²) of frame-to-frame change
    joint_smoothness = 10.0   # λ_A, px² per rad²
    homography = 1.0
    loss = "cauchy"           # none | huber | cauchy
    loss_scale = 8.0          # px
    terms = ["reprojection", "homography", "smoothness"]
    refine_rounds = 0         # after the solve, refine bone offsets, mounts and hinge axes with the motion on
                              # the same terms (user terms included), then solve again; 0 to 5 rounds
    rolling_shutter_readout = 0.0   # s from the first image row to the last (0: global shutter), 0 to 1; also
                                    # re-fits the registered camera poses under it (world stage)
    estimate_readout = false  # also solve for a correction to the readout (prior σ 10 ms)
    estimate_time_offsets = false  # also solve for each camera's time offset: its sub-frame start and audio
                                   # latency, which clap sync cannot see (prior σ 10 ms)
    self_calibration = false  # solve for each camera's focal length and centre (prior σ 1 %, 5 px); the world
                              # stage first estimates them with the range-of-motion trial's registered poses
    mount_compliance = [0.0, 0.0]   # σ of each camera's per-frame offset on its mount [m, deg]; [0, 0]: rigid
    registered_pose = [0.02, 1.0]   # σ [m, deg] of a prior holding a registered camera-frame with few measurements
                                    # at its registered pose; [0, 0]: off (bcmocap.residuals.registered_pose)
    registered_pose_below = 20      # ... where it has fewer measurements than this, 1 to 100000
    unmeasured_orientation = 5.0    # σ [deg] of a prior holding a camera-frame with neither a registration nor a
                                    # measurement, on a segment no camera of which is measured there, at the initial
                                    # motion's orientation (carried by its gyro where it could be); 0: off
                                    # (bcmocap.residuals.registered_pose)
    gyro_turn = 0.0           # σ (deg) of each camera's turn between frames against its gyro's (trials/capture/
                              # imu.npz, read at the frontend's gyro timing); 0: off (bcmocap.residuals.gyro)

    [[solver.user_terms]]     # a user's terms, any number of these tables (see bcmocap.solver.objective)
    factory = "mypackage.terms:imu_terms"   # 'module:name' importable from PYTHONPATH, called per window
    weight = 100.0            # every other key is a keyword argument of the factory (numbers, strings,
                              # booleans, lists of them)

    [outputs]
    pictures = true

    [cluster]
    address = ""              # "" (this process) | "local:N" (N worker processes here) | "tcp://HOST:PORT" (a
                              # running Dask scheduler); never changes a result (see bcmocap.pipeline.cluster)
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from pathlib import Path

from .cluster import parse_cluster

TERMS = ("reprojection", "homography", "smoothness")
LOSSES = ("none", "huber", "cauchy")
MAX_STRIDE = 1000
MAX_FEATURES = 1_000_000
MAX_WINDOW = 100_000  # frames; a solver window is allocated whole


@dataclasses.dataclass(frozen=True)
class FrontendConfig:
    stride: int = 2
    rom_stride: int = 3
    max_features: int = 8000
    frames: int = 0
    chunk_frames: int = 400
    registration: str = "tracking"
    max_measurements: int = 300
    points: str = "reference"
    rolling_shutter_readout: float = 0.0
    gyro_timing: str = "clock"
    estimate_readout: bool = False
    self_calibration: bool = False


@dataclasses.dataclass(frozen=True)
class SkeletonConfig:
    root_origin: tuple[str, ...] = ("torso",)
    rest_seconds: tuple[float, ...] = ()
    up_from: tuple[str, ...] = ("left_foot", "right_foot")
    up_to: str = "head"
    max_centre_std_cm: float = 5.0
    degenerate: str = "mirror"
    centre_trials: tuple[str, ...] = ("rom", "capture")
    unregistered_ends: str = "mirror"
    unregistered_rest: str = "mirror"


@dataclasses.dataclass(frozen=True)
class UserTermConfig:
    """One ``[[solver.user_terms]]`` table: a term factory's import path and its keyword arguments."""

    factory: str
    settings: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    window: int = 60
    overlap: int = 10
    windows: str = "sequential"
    root_smoothness: float = 1e3
    joint_smoothness: float = 1e1
    homography: float = 1.0
    loss: str = "cauchy"
    loss_scale: float = 8.0
    terms: tuple[str, ...] = TERMS
    refine_rounds: int = 0
    rolling_shutter_readout: float = 0.0
    estimate_readout: bool = False
    estimate_time_offsets: bool = False
    self_calibration: bool = False
    mount_compliance: tuple[float, ...] = (0.0, 0.0)
    registered_pose: tuple[float, ...] = (0.02, 1.0)
    registered_pose_below: int = 20
    unmeasured_orientation: float = 5.0
    gyro_turn: float = 0.0
    user_terms: tuple[UserTermConfig, ...] = ()


@dataclasses.dataclass(frozen=True)
class OutputsConfig:
    pictures: bool = True


@dataclasses.dataclass(frozen=True)
class ClusterConfig:
    address: str = ""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything ``bcmocap run`` can be told (see the module docstring for the meaning of each key)."""

    frontend: FrontendConfig = FrontendConfig()
    skeleton: SkeletonConfig = SkeletonConfig()
    solver: SolverConfig = SolverConfig()
    outputs: OutputsConfig = OutputsConfig()
    cluster: ClusterConfig = ClusterConfig()

    def __post_init__(self):
        for section in dataclasses.fields(self):
            part = getattr(self, section.name)
            for field in dataclasses.fields(part):
                value = getattr(part, field.name)
                items = value if isinstance(value, tuple) else (value,)
                finite = all(math.isfinite(v) for v in items if isinstance(v, float))
                _check(finite, f"{section.name}.{field.name}", "must be finite", value)
        f, k, s = self.frontend, self.skeleton, self.solver
        _check(1 <= f.stride <= MAX_STRIDE, "frontend.stride", f"must be in [1, {MAX_STRIDE}]", f.stride)
        _check(1 <= f.rom_stride <= MAX_STRIDE, "frontend.rom_stride", f"must be in [1, {MAX_STRIDE}]", f.rom_stride)
        _check(100 <= f.max_features <= MAX_FEATURES, "frontend.max_features", f"must be in [100, {MAX_FEATURES}]",
               f.max_features)
        _check(f.frames >= 0, "frontend.frames", "must be ≥ 0", f.frames)
        _check(f.chunk_frames >= 0, "frontend.chunk_frames", "must be ≥ 0", f.chunk_frames)
        _check(f.registration in ("tracking", "global"), "frontend.registration", "must be 'tracking' or 'global'",
               f.registration)
        _check(f.max_measurements >= 0, "frontend.max_measurements", "must be ≥ 0", f.max_measurements)
        _check(f.points in ("all", "reference"), "frontend.points", "must be 'all' or 'reference'", f.points)
        _check(0.0 <= f.rolling_shutter_readout <= 1.0, "frontend.rolling_shutter_readout", "must be in [0, 1] s",
               f.rolling_shutter_readout)
        _check(not (f.rolling_shutter_readout > 0 and s.rolling_shutter_readout > 0), "solver.rolling_shutter_readout",
               "must be 0 when frontend.rolling_shutter_readout corrects the frames by the gyros (the measurements are "
               "a global shutter's then)", s.rolling_shutter_readout)
        _check(f.gyro_timing in ("clock", "frames"), "frontend.gyro_timing", "must be 'clock' or 'frames'", f.gyro_timing)
        _check(f.gyro_timing == "clock" or f.rolling_shutter_readout > 0, "frontend.gyro_timing",
               "'frames' needs a rolling_shutter_readout to correct (and to start the readout's search from)",
               f.gyro_timing)
        _check(not f.estimate_readout or (f.gyro_timing == "frames" and f.rolling_shutter_readout > 0),
               "frontend.estimate_readout", "needs gyro_timing = 'frames' and a rolling_shutter_readout to start from",
               f.estimate_readout)
        _check(len(k.rest_seconds) in (0, 2) and (not k.rest_seconds or k.rest_seconds[0] < k.rest_seconds[1]),
               "skeleton.rest_seconds", "must be [] or [from, to] with from < to", list(k.rest_seconds))
        _check(k.max_centre_std_cm > 0, "skeleton.max_centre_std_cm", "must be > 0", k.max_centre_std_cm)
        _check(k.degenerate in ("raise", "hinge", "mirror"), "skeleton.degenerate", "must be 'raise', 'hinge' or 'mirror'",
               k.degenerate)
        _check(k.unregistered_ends in ("raise", "mirror"), "skeleton.unregistered_ends", "must be 'raise' or 'mirror'",
               k.unregistered_ends)
        _check(k.unregistered_rest in ("raise", "mirror"), "skeleton.unregistered_rest", "must be 'raise' or 'mirror'",
               k.unregistered_rest)
        _check(tuple(k.centre_trials) in (("rom",), ("rom", "capture")), "skeleton.centre_trials",
               "must be [\"rom\"] or [\"rom\", \"capture\"]", list(k.centre_trials))
        _check(2 <= s.window <= MAX_WINDOW, "solver.window", f"must be in [2, {MAX_WINDOW}]", s.window)
        _check(0 <= s.overlap < s.window, "solver.overlap", "must be in [0, window)", s.overlap)
        _check(s.windows in ("sequential", "independent"), "solver.windows", "must be 'sequential' or 'independent'",
               s.windows)
        _check(isinstance(s.refine_rounds, int) and 0 <= s.refine_rounds <= 5, "solver.refine_rounds", "must be an integer in [0, 5]",
               s.refine_rounds)
        for name in ("root_smoothness", "joint_smoothness", "homography", "loss_scale"):
            _check(getattr(s, name) >= 0, f"solver.{name}", "must be ≥ 0", getattr(s, name))
        _check(0.0 <= s.rolling_shutter_readout <= 1.0, "solver.rolling_shutter_readout", "must be in [0, 1] s",
               s.rolling_shutter_readout)
        for name in ("mount_compliance", "registered_pose"):  # σ pairs [m, deg]
            sigma = getattr(s, name)
            _check(len(sigma) == 2 and 0.0 <= sigma[0] <= 1.0 and 0.0 <= sigma[1] <= 30.0 and (all(sigma) or not any(sigma)),
                   f"solver.{name}", "must be [m, deg], both 0 or both > 0 (at most 1 m, 30 deg)", list(sigma))
        _check(isinstance(s.registered_pose_below, int) and 1 <= s.registered_pose_below <= 100000,
               "solver.registered_pose_below", "must be an integer in [1, 100000]", s.registered_pose_below)
        _check(0.0 <= s.gyro_turn <= 30.0, "solver.gyro_turn", "must be in [0, 30] deg (0: off)", s.gyro_turn)
        _check(0.0 <= s.unmeasured_orientation <= 180.0, "solver.unmeasured_orientation", "must be in [0, 180] deg (0: off)",
               s.unmeasured_orientation)
        _check(s.loss in LOSSES, "solver.loss", f"must be one of {LOSSES}", s.loss)
        bad = [t for t in s.terms if t not in TERMS]
        _check(not bad, "solver.terms", f"must be a subset of {TERMS}", list(s.terms))
        _check("reprojection" in s.terms, "solver.terms", "must include 'reprojection'", list(s.terms))
        try:
            parse_cluster(self.cluster.address)
        except ValueError as exc:
            raise ValueError(f"config: cluster.address: {exc}") from None

    def to_dict(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict, where: str = "config") -> RunConfig:
        """Defaults overridden by ``data`` (nested sections); unknown sections and keys raise ValueError."""
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a table of sections, got {type(data).__name__}")
        sections = {}
        for field in dataclasses.fields(cls):
            default = getattr(cls(), field.name)
            given = data.get(field.name, {})
            if not isinstance(given, dict):
                raise ValueError(f"{where}: [{field.name}] must be a table, got {given!r}")
            sections[field.name] = _override(default, given, f"{where}: {field.name}")
        unknown = sorted(set(data) - set(sections))
        if unknown:
            raise ValueError(f"{where}: unknown section [{unknown[0]}] (sections: {', '.join(sections)})")
        return cls(**sections)

    def with_overrides(self, overrides: dict[str, object]) -> RunConfig:
        """A copy with dotted keys replaced, e.g. ``{"solver.window": 30}`` (from command-line flags)."""
        data = self.to_dict()
        for key, value in overrides.items():
            section, _, name = key.partition(".")
            if section not in data or name not in data[section]:
                raise ValueError(f"unknown setting {key!r}")
            data[section][name] = value
        return RunConfig.from_dict(data)


def _check(ok: bool, key: str, message: str, value) -> None:
    if not ok:
        raise ValueError(f"config: {key} {message}, got {value!r}")


def _override(default, given: dict, where: str):
    fields = {f.name: f for f in dataclasses.fields(default)}
    unknown = sorted(set(given) - set(fields))
    if unknown:
        raise ValueError(f"{where}.{unknown[0]} is not a setting (settings: {', '.join(fields)})")
    values = {}
    for name, value in given.items():
        current = getattr(default, name)
        if fields[name].type == "tuple[UserTermConfig, ...]":
            value = _user_terms(value, f"{where}.{name}")
        elif isinstance(current, tuple):
            numbers = fields[name].type == "tuple[float, ...]"
            kind = (int, float) if numbers else str
            if not isinstance(value, (list, tuple)) or any(isinstance(v, bool) or not isinstance(v, kind) for v in value):
                raise ValueError(f"{where}.{name} must be a list of {'numbers' if numbers else 'strings'}, got {value!r}")
            value = tuple(float(v) if numbers else v for v in value)
        elif isinstance(current, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{where}.{name} must be true or false, got {value!r}")
        elif isinstance(current, int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{where}.{name} must be an integer, got {value!r}")
        elif isinstance(current, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{where}.{name} must be a number, got {value!r}")
            value = float(value)
        elif isinstance(current, str) and not isinstance(value, str):
            raise ValueError(f"{where}.{name} must be a string, got {value!r}")
        values[name] = value
    return dataclasses.replace(default, **values)


def _user_terms(value, where: str) -> tuple[UserTermConfig, ...]:
    """``[[solver.user_terms]]`` tables (or their saved form, ``{"factory", "settings"}``) → configs."""
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where} must be a list of tables ([[solver.user_terms]]), got {value!r}")
    out = []
    for i, table in enumerate(value):
        here = f"{where}[{i}]"
        if isinstance(table, UserTermConfig):
            table = dataclasses.asdict(table)
        if not isinstance(table, dict) or not isinstance(table.get("factory"), str):
            raise ValueError(f"{here} must be a table with a 'factory' string ('module:name'), got {table!r}")
        settings = dict(table.get("settings", {})) if set(table) <= {"factory", "settings"} else \
            {k: v for k, v in table.items() if k != "factory"}
        for key, setting in settings.items():
            items = setting if isinstance(setting, list) else [setting]
            if not all(isinstance(v, (bool, int, float, str)) for v in items):
                raise ValueError(f"{here}.{key} must be a number, string, boolean or a list of them, got {setting!r}")
            if not all(math.isfinite(v) for v in items if isinstance(v, float)):
                raise ValueError(f"{here}.{key} must be finite, got {setting!r}")
        out.append(UserTermConfig(table["factory"], settings))
    return tuple(out)


def load_config(path: str | Path | None) -> RunConfig:
    """Defaults, overridden by a TOML (``.toml``) or JSON file when ``path`` is given.

    Raises:
        ValueError: unreadable file, bad syntax, unknown keys or values out of range, naming the file.
    """
    if path is None:
        return RunConfig()
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the config file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from None
    try:
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'} ({exc})") from None
    try:
        return RunConfig.from_dict(data, str(path))
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg.removeprefix('config: ')}") from None
