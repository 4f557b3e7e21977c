"""The rig file of a shoot (``rig.toml``): which camera sat on which body segment, with which lens, in which
video file, and the trials and the subject — the small human-readable sheet ``bcmocap init`` turns
camera files into a capture folder with.

Format (TOML; ``bcmocap init --template FILE`` writes the paper-like 18-camera rig as a starting point)::

    [trials]
    names = ["rom", "capture"]      # in recording order; `bcmocap run` needs "rom" and "capture"
    split = "claps"                 # "claps": two claps per trial in the cameras' audio; "times": below
    margin_s = 1.0                  # video kept before a trial's first clap and after its second (s)
    [trials.times]                  # split = "times": [start, end] s in each video's own clock
    rom = [5.0, 62.0]

    [subject]
    rest = { trial = "rom", after_first_clap_s = [0.5, 3.0] }
    measurements = [{ from = "left_thigh", to = "left_foot", metres = 0.88 }]

    [segments]                      # parents before children; joint "free" (the root), "ball", "hinge", "fixed"
    pelvis = { joint = "free" }
    torso = { parent = "pelvis", joint = "ball" }

    [cameras]                       # in the order the capture lists them
    chest = { segment = "torso", mount = "sternum, looking forward", lens = "wide", video = "GX010012.MP4" }

A camera's ``lens`` names a calibration file ``LENS.json`` or ``LENS.yml`` in the calibration folder (one
per lens model); without it the file is named after the camera. ``video`` is its file in the videos
folder (a string: one file holding every trial; a table ``{trial = file}``: one file per trial); without
it, ``CAMERA.<ext>`` or ``TRIAL/CAMERA.<ext>`` is looked for. ``times = {trial = [start, end]}`` on a
camera overrides ``[trials.times]`` for it. Every name (segment, camera, trial, lens) must be a plain
name (:func:`bcmocap.io.names.checked_name`), and a video path a relative path inside the videos folder.
Errors are ``ValueError`` naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import tomllib
from pathlib import Path, PurePosixPath

from ..io.capture_folder import TRIALS
from ..io.names import checked_name, checked_relative_path

__all__ = ["JOINTS", "RigCamera", "RigFile", "TEMPLATE", "format_rig_file", "read_rig_file"]

JOINTS = ("free", "ball", "hinge", "fixed")
SPLITS = ("claps", "times")
_CAMERA_FIELDS = ("segment", "mount", "lens", "video", "times")


@dataclasses.dataclass(frozen=True)
class RigCamera:
    """One camera of the rig file.

    Attributes:
        name: camera name; segment: the body segment it is strapped to.
        mount: a note on where and how it sits (kept in ``rig.json``; the mount itself is estimated).
        lens: calibration file name (without extension) in the calibration folder, None: the camera's name.
        video: its file in the videos folder (one file for every trial), a ``{trial: file}`` mapping, or
            None (looked for by the camera's name).
        times: ``{trial: (start_s, end_s)}`` overriding the trials' times for this camera's video.
    """

    name: str
    segment: str
    mount: str = ""
    lens: str | None = None
    video: PurePosixPath | dict[str, PurePosixPath] | None = None
    times: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class RigFile:
    """A parsed rig file (module docstring).

    Attributes:
        segments: ``(name, parent or None, joint)`` per body segment, parents first.
        cameras: the cameras, in file order.
        trials: trial names in recording order; split: "claps" or "times"; margin_s: video kept around a
            trial's claps (s); times: ``{trial: (start_s, end_s)}`` in each video's clock.
        rest: ``{"trial": name, "after_first_clap_s": [from, to]}`` or None.
        measurements: ``({"from", "to", "metres"}, …)`` between joint centres, rest pose (with ``segments`` and
            ``rest``, the manifest's subject: :func:`bcmocap.io.capture_folder.subject_record`).
        path: the file it was read from (None for one built in code).
    """

    segments: tuple[tuple[str, str | None, str], ...]
    cameras: tuple[RigCamera, ...]
    trials: tuple[str, ...] = TRIALS
    split: str = "claps"
    margin_s: float = 1.0
    times: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    rest: dict | None = None
    measurements: tuple[dict, ...] = ()
    path: Path | None = dataclasses.field(default=None, compare=False)

    @property
    def segment_names(self) -> tuple[str, ...]:
        return tuple(s[0] for s in self.segments)


def _table(value, where: str, source) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{source}: {where} must be a table, got {type(value).__name__} {value!r}")
    return value


def _unknown(table: dict, allowed, where: str, source) -> None:
    extra = sorted(set(table) - set(allowed))
    if extra:
        raise ValueError(f"{source}: {where}: unknown field {extra[0]!r} (fields: {', '.join(allowed)})")


def _text(value, where: str, source) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{source}: {where} must be a string, got {type(value).__name__} {value!r}")
    return value


def _number(value, where: str, source) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{source}: {where} must be a finite number, got {value!r}")
    return float(value)


def _times(value, trials, where: str, source) -> dict[str, tuple[float, float]]:
    out = {}
    for trial, span in _table(value, where, source).items():
        if trial not in trials:
            raise ValueError(f"{source}: {where}.{trial}: no such trial (trials.names: {list(trials)})")
        if not isinstance(span, list) or len(span) != 2:
            raise ValueError(f"{source}: {where}.{trial} must be [start, end] in seconds, got {span!r}")
        start, end = (_number(x, f"{where}.{trial}", source) for x in span)
        if not 0 <= start < end:
            raise ValueError(f"{source}: {where}.{trial} = [{start}, {end}]: need 0 <= start < end (s)")
        out[trial] = (start, end)
    return out


def read_rig_file(path: str | os.PathLike) -> RigFile:
    """Read and check a rig file (module docstring for the format).

    Raises:
        ValueError: naming the file and the field: not TOML, a missing or unknown field, a name that is not
            plain, a camera on an unknown segment, a measurement or rest trial that does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: rig file missing")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path}: not valid TOML ({err})") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a UTF-8 text file ({err})") from None
    return _parse(data, path)


def _parse(data: dict, path) -> RigFile:
    _unknown(data, ("trials", "subject", "segments", "cameras"), "top level", path)
    for key in ("segments", "cameras"):
        if key not in data:
            raise ValueError(f"{path}: missing table [{key}]")

    trials_table = _table(data.get("trials", {}), "[trials]", path)
    _unknown(trials_table, ("names", "split", "margin_s", "times"), "[trials]", path)
    names = trials_table.get("names", list(TRIALS))
    if not isinstance(names, list) or not names:
        raise ValueError(f"{path}: trials.names must be a non-empty list of names, got {names!r}")
    trials = tuple(checked_name(t, f"trials.names[{i}]", path) for i, t in enumerate(names))
    if len(set(trials)) != len(trials):
        raise ValueError(f"{path}: trials.names names a trial twice: {list(trials)}")
    split = trials_table.get("split", "claps")
    if split not in SPLITS:
        raise ValueError(f"{path}: trials.split must be one of {list(SPLITS)}, got {split!r}")
    margin = _number(trials_table.get("margin_s", 1.0), "trials.margin_s", path)
    if margin < 0:
        raise ValueError(f"{path}: trials.margin_s must be >= 0, got {margin}")
    times = _times(trials_table.get("times", {}), trials, "trials.times", path)

    segments = []
    for name, spec in _table(data["segments"], "[segments]", path).items():
        name = checked_name(name, f"segments.{name}", path)
        spec = _table(spec, f"segments.{name}", path)
        _unknown(spec, ("parent", "joint"), f"segments.{name}", path)
        joint = spec.get("joint")
        if joint not in JOINTS:
            raise ValueError(f"{path}: segments.{name}.joint must be one of {list(JOINTS)}, got {joint!r}")
        parent = spec.get("parent")
        if parent is not None and parent not in [s[0] for s in segments]:
            raise ValueError(f"{path}: segments.{name}.parent {parent!r} is not a segment listed before it")
        if (parent is None) != (joint == "free"):
            raise ValueError(f"{path}: segments.{name}: the root (no parent) and only the root has joint 'free'")
        segments.append((name, parent, joint))
    if sum(s[1] is None for s in segments) != 1:
        raise ValueError(f"{path}: [segments] must have exactly one root (a segment without parent)")
    segment_names = [s[0] for s in segments]

    cameras = []
    for name, spec in _table(data["cameras"], "[cameras]", path).items():
        where = f"cameras.{name}"
        name = checked_name(name, where, path)
        spec = _table(spec, where, path)
        _unknown(spec, _CAMERA_FIELDS, where, path)
        segment = spec.get("segment")
        if segment not in segment_names:
            raise ValueError(f"{path}: {where}.segment {segment!r} is not a segment of [segments] "
                             f"({', '.join(segment_names)})")
        lens = spec.get("lens")
        lens = None if lens is None else checked_name(lens, f"{where}.lens", path)
        video = spec.get("video")
        if isinstance(video, dict):
            unknown = sorted(set(video) - set(trials))
            if unknown:
                raise ValueError(f"{path}: {where}.video.{unknown[0]}: no such trial (trials.names: {list(trials)})")
            video = {t: checked_relative_path(v, f"{where}.video.{t}", path) for t, v in video.items()}
        elif video is not None:
            video = checked_relative_path(video, f"{where}.video", path)
        cameras.append(RigCamera(name, segment, _text(spec.get("mount", ""), f"{where}.mount", path), lens, video,
                                 _times(spec.get("times", {}), trials, f"{where}.times", path)))
    if not cameras:
        raise ValueError(f"{path}: [cameras] lists no camera")

    subject = _table(data.get("subject", {}), "[subject]", path)
    _unknown(subject, ("rest", "measurements"), "[subject]", path)
    rest = None
    if "rest" in subject:
        rest = _table(subject["rest"], "subject.rest", path)
        _unknown(rest, ("trial", "after_first_clap_s"), "subject.rest", path)
        if rest.get("trial") not in trials:
            raise ValueError(f"{path}: subject.rest.trial {rest.get('trial')!r} is not one of trials.names {list(trials)}")
        span = rest.get("after_first_clap_s")
        if not isinstance(span, list) or len(span) != 2:
            raise ValueError(f"{path}: subject.rest.after_first_clap_s must be [from, to] in seconds, got {span!r}")
        start, end = (_number(x, "subject.rest.after_first_clap_s", path) for x in span)
        if not 0 <= start < end:
            raise ValueError(f"{path}: subject.rest.after_first_clap_s = [{start}, {end}]: need 0 <= from < to")
        rest = {"trial": rest["trial"], "after_first_clap_s": [start, end]}
    measurements = subject.get("measurements", [])
    if not isinstance(measurements, list):
        raise ValueError(f"{path}: subject.measurements must be a list of {{from, to, metres}}, got {measurements!r}")
    checked = []
    for i, m in enumerate(measurements):
        where = f"subject.measurements[{i}]"
        m = _table(m, where, path)
        _unknown(m, ("from", "to", "metres"), where, path)
        for key in ("from", "to"):
            if m.get(key) not in segment_names:
                raise ValueError(f"{path}: {where}.{key} {m.get(key)!r} is not a segment of [segments]")
        metres = _number(m.get("metres"), f"{where}.metres", path)
        if metres <= 0:
            raise ValueError(f"{path}: {where}.metres must be positive, got {metres}")
        checked.append({"from": m["from"], "to": m["to"], "metres": metres})
    return RigFile(tuple(segments), tuple(cameras), trials, split, margin, times, rest, tuple(checked), path)


# ---------------------------------------------------------------------------------------------
# Writing a rig file (the template).


def _string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)  # a JSON string is a TOML basic string


def _key(name: str) -> str:
    """A TOML key: bare when it can be ('.' would make it a dotted key, '+' is not allowed), else quoted."""
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else _string(name)


def _inline(fields: dict) -> str:
    return "{ " + ", ".join(f"{_key(k)} = {v}" for k, v in fields.items()) + " }"


def _span(span) -> str:
    return f"[{float(span[0])!r}, {float(span[1])!r}]"


def _camera_line(camera: RigCamera) -> str:
    fields = {"segment": _string(camera.segment)}
    if camera.mount:
        fields["mount"] = _string(camera.mount)
    if camera.lens is not None:
        fields["lens"] = _string(camera.lens)
    if isinstance(camera.video, dict):
        fields["video"] = _inline({t: _string(str(v)) for t, v in camera.video.items()})
    elif camera.video is not None:
        fields["video"] = _string(str(camera.video))
    if camera.times:
        fields["times"] = _inline({t: _span(s) for t, s in camera.times.items()})
    return f"{_key(camera.name)} = {_inline(fields)}"


def format_rig_file(rig: RigFile) -> str:
    """``rig`` as a commented rig file that :func:`read_rig_file` reads back to an equal :class:`RigFile`."""
    lines = [
        "# bcmocap rig file: the cameras of a shoot and where they sat (read by `bcmocap init`).",
        "# Names of trials, segments, cameras and lenses: letters, digits, _ . + - (no spaces or slashes).",
        "",
        "[trials]",
        f"names = [{', '.join(map(_string, rig.trials))}]"
        "  # in recording order; `bcmocap run` needs \"rom\" and \"capture\"",
        f"split = {_string(rig.split)}"
        "  # \"claps\": two claps per trial, found in the cameras' own audio; \"times\": [trials.times]",
        f"margin_s = {float(rig.margin_s)!r}  # video kept before a trial's first clap and after its second (s)",
        "",
    ]
    if rig.times:
        lines += ["[trials.times]  # [start, end] in seconds of each video's own clock (split = \"times\")"]
        lines += [f"{_key(t)} = {_span(s)}" for t, s in rig.times.items()] + [""]
    else:
        lines += ["# [trials.times]  # with split = \"times\": [start, end] in seconds of each video's own clock",
                  *(f"# {_key(t)} = [0.0, 60.0]" for t in rig.trials), ""]
    lines += ["[subject]"]
    if rig.rest is not None:
        rest = {"trial": _string(rig.rest["trial"]), "after_first_clap_s": _span(rig.rest["after_first_clap_s"])}
        lines += [f"rest = {_inline(rest)}  # when the rest pose was held (s after the trial's first clap)"]
    else:
        lines += ["# When the subject held the rest pose (straight, arms down), in seconds after the first clap:",
                  "# rest = { trial = \"rom\", after_first_clap_s = [0.5, 3.0] }"]
    if rig.measurements:
        lines += ["measurements = [  # tape-measured distances between joint centres, rest pose (m)"]
        lines += [f"  {_inline({'from': _string(m['from']), 'to': _string(m['to']), 'metres': repr(float(m['metres']))})},"
                  for m in rig.measurements] + ["]"]
    else:
        lines += ["# Tape-measured distances between joint centres in the rest pose (m); they fix the scale:",
                  "# measurements = [",
                  "#   { from = \"left_thigh\", to = \"left_foot\", metres = 0.88 },  # hip to ankle",
                  "#   { from = \"left_upper_arm\", to = \"left_hand\", metres = 0.56 },  # shoulder to wrist",
                  "# ]"]
    lines += ["", "[segments]  # body segment = { parent, joint }: parents first; joint free (root), ball, hinge, fixed"]
    for name, parent, joint in rig.segments:
        fields = ({} if parent is None else {"parent": _string(parent)}) | {"joint": _string(joint)}
        lines.append(f"{_key(name)} = {_inline(fields)}")
    lines += [
        "",
        "[cameras]",
        "# camera = { segment, mount (a note on where it sits), lens (calibration file LENS.json|.yml in --calibration;",
        "#            default CAMERA.json|.yml), video (its file in --videos; default CAMERA.<ext> holding every trial,",
        "#            or TRIAL/CAMERA.<ext>; a table { trial = file } for one file per trial), times (per trial, overrides",
        "#            [trials.times]) }",
    ]
    lines += [_camera_line(c) for c in rig.cameras]
    return "\n".join(lines) + "\n"


def _standard_cameras() -> tuple[RigCamera, ...]:
    cameras = [
        RigCamera("waist_front", "pelvis", "belt, front; looking forward and a little down"),
        RigCamera("waist_left", "pelvis", "belt, left hip; looking left and a little down"),
        RigCamera("waist_right", "pelvis", "belt, right hip; looking right and a little down"),
        RigCamera("chest", "torso", "sternum; looking forward and a little up"),
        RigCamera("back", "torso", "between the shoulder blades; looking back and a little up"),
        RigCamera("head", "head", "forehead (headband); looking forward and up"),
    ]
    for side in ("left", "right"):
        cameras += [
            RigCamera(f"{side}_upper_arm", f"{side}_upper_arm", "outer side, mid-way; looking sideways, away from the body"),
            RigCamera(f"{side}_forearm", f"{side}_forearm", "outer side, mid-way; looking sideways, away from the body"),
            RigCamera(f"{side}_thigh", f"{side}_thigh", "outer side, mid-way; looking sideways and a little forward"),
            RigCamera(f"{side}_shin", f"{side}_shin", "outer side, mid-way; looking sideways and a little forward"),
            RigCamera(f"{side}_hand", f"{side}_hand", "back of the hand; looking up and forward"),
            RigCamera(f"{side}_foot", f"{side}_foot", "top of the foot (shoe laces); looking forward"),
        ]
    return tuple(cameras)


def _standard_segments() -> tuple[tuple[str, str | None, str], ...]:
    segments = [("pelvis", None, "free"), ("torso", "pelvis", "ball"), ("head", "torso", "ball")]
    for side in ("left", "right"):
        segments += [(f"{side}_upper_arm", "torso", "ball"), (f"{side}_forearm", f"{side}_upper_arm", "hinge"),
                     (f"{side}_hand", f"{side}_forearm", "ball"), (f"{side}_thigh", "pelvis", "ball"),
                     (f"{side}_shin", f"{side}_thigh", "hinge"), (f"{side}_foot", f"{side}_shin", "ball")]
    return tuple(segments)


#: The paper-like rig (the studio's 18 cameras on its 15-segment skeleton), what ``bcmocap init --template`` writes.
TEMPLATE = RigFile(_standard_segments(), _standard_cameras())
