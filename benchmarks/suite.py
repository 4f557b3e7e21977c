"""The evaluation suite (issue 42): seeds × motions × rooms × {clean, realistic}, each run through ``bcmocap batch``
with only what a user knows, reported with its spread.

Each run is a studio capture (``bcmocap.sim.studio``; ``--seconds`` of the motion, a ``--rom-seconds``
range-of-motion trial at ``--rom-tempo`` (default 6 s at 0.5: a 3 s one left a foot's centre undetermined) with the
ankles turned on still legs after the other joints (``--rom-protocol feet_after``: with every joint at once, a foot
camera registered in none of the frames where its ankle turned), 640×360 at 60 fps, the standard 18-camera rig):

- ``clean``: the default studio in the run's room with the run's motion; the one rendered lens is calibrated
  from its board video;
- ``realistic``: the studio's ``realistic`` preset (``bcmocap.sim.studio.REALISTIC``: blur, rolling shutter with a
  readout drawn per capture, wobble, exposure, noise, H.264, a lens unit per camera outside the solver's
  families, sub-frame starts, drifting clocks, audio latencies, IMU clock offsets), each unit calibrated from its
  own board video.

As a user would, each capture's lenses are what ``bcmocap calibrate`` (the model of ``LENS_MODELS``, or
``--lens-model``) makes of its board videos
(``bcmocap simulate --board-videos``), written into the capture's ``intrinsics/`` (the rendered units stay in
``ground_truth/``); captures with the same lens units (one condition and seed) share one calibration, as a user
calibrates a box of cameras once (:func:`calibrate_capture`). Then every capture of a condition goes through one ``bcmocap batch`` (``--cluster`` spreads it
over a Dask cluster) with that condition's config: the clean rows ``benchmarks/configs/tracking.toml``, the
realistic rows ``benchmarks/configs/realistic_shoot.toml`` (a data-sheet readout, the documented wobble default,
the solver estimating readout, time offsets and lens corrections).

Reported per condition and overall: mean, sd, 90th percentile and worst of the runs' mean joint position and
joint angle errors (after the §5.1 similarity alignment, from each run's ``metrics.json``), the same for the
initial motion (registration and IK alone), how often the solve improved on it (both errors), the registered
fractions, the registered camera-frames more than 10 cm from the truth (``benchmarks/registration_truth.py``: a
repeated pattern's copy), failures (counted, never dropped), the calibrated lenses' pixel error against the true lens (RMS and
max over the part of the image within ``COVERED_DEG`` of the axis, and over the whole image), the sub-frame
offsets and clock rates from the claps against the truth, and, where the solver estimated them, the cameras'
time offsets against the truth (relative to their mean: a common offset is a shift of the whole motion).

Everything lives in ``--out`` (``captures/NAME``, ``runs/CONDITION/NAME``); a rerun resumes (the studio, the
calibration and ``bcmocap run`` all resume). With ``--records DIR`` each finished run's record is also kept in
``DIR/NAME.json`` with the commit of the code it ran (the code must be committed: :data:`PIPELINE_CODE`), its
capture's studio settings, the suite's constants and the libraries' versions; runs with a record are not run again,
and ``--json`` summarises every record there of the planned grid: a grid longer than one sitting is run in parts
(``--only``) and its records committed, and the summary refuses a record that differs from this code in any of them. ``--quick`` runs one clean and one realistic walk in the textured
room (about 20 minutes on 2 cores); the full grid is every motion in every room realistic (20 runs) and every
motion in two rooms clean (10 runs).

    python benchmarks/suite.py --out /tmp/suite --quick --json benchmarks/results/suite_quick.json
    python benchmarks/suite.py --out /tmp/suite --json benchmarks/results/suite.json [--cluster local:2]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

MOTIONS = ("walk", "run", "jump", "scoop", "hop")
ROOMS = ("textured", "sparse", "repeated", "passerby")
CLEAN_ROOMS = ("textured", "repeated")
CONFIGS = {"clean": ROOT / "benchmarks" / "configs" / "tracking.toml",
           "realistic": ROOT / "benchmarks" / "configs" / "realistic_shoot.toml"}
# The lens model each condition calibrates: the clean studio renders the paper's FOV lens; a realistic capture's
# units (lenses with decentering and thin-prism terms, in front of tilted sensors) are calibrated as a user with
# such a box of cameras would, with the thin-prism fisheye (COLMAP's THIN_PRISM_FISHEYE), which leaves only the
# part of the tilt that acts on the distorted image (bcmocap.sim.lens_units).
LENS_MODELS = {"clean": "fov", "realistic": "thin_prism_fisheye"}
FIT_VIEWS = 120  # bcmocap calibrate --views: well-spread board views kept for each fit
COVERED_DEG = 80.0  # the part of the image the board covers well (and the body cameras use most)
# Reference photos of a room, where not the studio's 24: in the sparse room a user takes twice as many, with more
# overlap (15 degree steps around the room rather than 30), as photogrammetry guides advise where texture is weak
# (COLMAP's tutorial: "capture images with enough overlap"). With 24 photos the mapper joined 12 of the sparse room's
# (seed 2; consecutive photos of its painted walls shared no features); with 48 it joins 46. In the repeated room too:
# with 24 photos the reference of three of its captures came out 27-60 cm off the truth (a copy of the pattern joined
# for the right place); with 48, two of them are right (0.23 and 0.11 cm; the hop's, seed 0, is still 40.6 cm off;
# docs/benchmarks/suite.md, benchmarks/reference_aliases.py --rooms repeated --photos 48).
REFERENCE_PHOTOS = {"sparse": 48, "repeated": 48}
# What a run's figures depend on, besides the grid's own definition (each record keeps the studio settings of its
# capture and the suite's constants, checked against this script's) and the libraries (their versions, checked too):
# the code on the path of bcmocap run (git pathspecs; the KCS and marker commands, the viewer, the C3D reader and what
# only bcmocap init reads, the camera files' telemetry and chapters, and the simulate command and its GoPro
# files, which the suite does not call, are not on it).
PIPELINE_CODE = ("bcmocap", "benchmarks/configs", ":(exclude)bcmocap/kcs", ":(exclude)bcmocap/markers",
                 ":(exclude)bcmocap/viewer", ":(exclude)bcmocap/io/c3d.py", ":(exclude)bcmocap/io/gopro.py",
                 ":(exclude)bcmocap/frontend/telemetry.py", ":(exclude)bcmocap/frontend/assemble.py",
                 ":(exclude)bcmocap/frontend/init_command.py", ":(exclude)bcmocap/io/chapters.py",
                 ":(exclude)bcmocap/sim/gopro_files.py", ":(exclude)bcmocap/sim/studio_command.py")
LIBRARIES = ("jax", "jaxlib", "numpy", "scipy", "opencv-python-headless", "pycolmap", "equinox", "optimistix", "lineax",
             "av")


@dataclasses.dataclass(frozen=True)
class Run:
    condition: str
    motion: str
    room: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.condition}-{self.motion}-{self.room}-s{self.seed}"


def planned_runs(quick: bool, seeds: int) -> list[Run]:
    """The grid: ``--quick`` one clean and one realistic walk; else every motion in every room realistic and every
    motion in :data:`CLEAN_ROOMS` clean, seeds cycling over ``range(seeds)``."""
    if quick:
        return [Run("clean", "walk", "textured", 0), Run("realistic", "walk", "textured", 0)]
    realistic = [Run("realistic", m, r, i % seeds) for i, (m, r) in enumerate((m, r) for m in MOTIONS for r in ROOMS)]
    clean = [Run("clean", m, r, i % seeds) for i, (m, r) in enumerate((m, r) for m in MOTIONS for r in CLEAN_ROOMS)]
    return realistic + clean


def capture_settings(run: Run, args):
    from bcmocap.sim.studio import StudioSettings, preset_settings

    fields = dict(motion=run.motion, room=run.room, seed=run.seed, seconds=args.seconds, rom_seconds=args.rom_seconds,
                  rom_tempo=args.rom_tempo, rom_protocol=args.rom_protocol, reference_photos=REFERENCE_PHOTOS.get(run.room, 24))
    return preset_settings("realistic", **fields) if run.condition == "realistic" else StudioSettings(**fields)


def _lens_error(calibrated, truth) -> dict:
    """Pixel distance between the calibrated lens and the true one over the true lens's image: RMS and max within
    :data:`COVERED_DEG` of the axis and over the whole image; and, within :data:`COVERED_DEG`, RMS and max after the
    small camera rotation that best aligns the two (``*_after_rotation_px``: a lens error that a turn of the camera
    undoes, such as a principal point shifted by a decentred lens, is absorbed by the camera's mount rotation, which
    the skeleton stage estimates; :func:`bcmocap.calibrate.compare.turned_difference`), with that rotation (degrees)."""
    from bcmocap.calibrate.compare import camera_difference, turned_difference

    image = camera_difference(calibrated, truth, step=4)
    covered = camera_difference(calibrated, truth, step=4, max_angle_deg=COVERED_DEG)
    after, turn_deg = turned_difference(calibrated, truth, step=4, max_angle_deg=COVERED_DEG)
    return {"covered_rms_px": covered.rms_px, "covered_max_px": covered.max_px,
            "image_rms_px": image.rms_px, "image_max_px": image.max_px,
            "covered_rms_after_rotation_px": after.rms_px,
            "covered_max_after_rotation_px": after.max_px, "rotation_deg": turn_deg}


def lens_key(settings, rig, model: str, views: int) -> tuple[str, dict[str, list[str]]]:
    """What a capture's calibration depends on, hashed: its rendered lenses (``rig``: ``ground_truth/rig.json``), its
    seed (which places the board in the board videos), the board, the views and the fit; and ``{lens as JSON text:
    camera names}``. Captures of one condition and seed share their lens units (the studio draws them from the seed
    and the image size alone), so they share this key and calibrate alike."""
    import hashlib

    from bcmocap.cameras import camera_at
    from bcmocap.io.model_json import camera_to_dict
    from bcmocap.sim.board_video import STUDIO_BOARD

    lenses: dict[str, list[str]] = {}
    for index, name in enumerate(rig.names):
        lenses.setdefault(json.dumps(camera_to_dict(camera_at(rig.intrinsics, index)), sort_keys=True), []).append(name)
    what = {"lenses": sorted(lenses), "seed": settings.seed, "board": STUDIO_BOARD, "views": views,
            "frames_per_view": 2, "model": model, "fit_views": FIT_VIEWS, "max_frames": 300}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16], lenses


def _capture_lens_key(folder: Path, model: str, views: int) -> tuple[str, dict[str, list[str]]]:
    from bcmocap.sim.studio import read_studio_model

    _, settings, _, rig = read_studio_model(folder)
    return lens_key(settings, rig, model, views)


def _calibrate_lenses(folder: Path, model: str, views: int, shared: Path, log) -> None:
    """``shared/lenses.json`` ``{lens as JSON text: {"file": "lens_K", "rms_px", "board_video"}}`` and each lens's
    calibration files ``shared/lens_K.yml|.json|.coverage.png``: ``bcmocap calibrate``'s fit of the board video
    that the studio renders into ``folder/calibration/`` for each distinct lens."""
    from bcmocap.calibrate.fit import calibrate
    from bcmocap.calibrate.report import write_calibration
    from bcmocap.calibrate.views import detect_views, select_views
    from bcmocap.io.board import parse_board
    from bcmocap.sim.board_video import write_board_videos

    if not (folder / "calibration" / "lenses.json").exists():
        write_board_videos(folder, views=views, frames_per_view=2, progress=lambda name: log(f"  board video {name}"))
    table = json.loads((folder / "calibration" / "lenses.json").read_text())
    board = parse_board(table["board"])
    _, by_text = _capture_lens_key(folder, model, views)
    text_of = {cameras[0]: text for text, cameras in by_text.items()}
    shared.mkdir(parents=True, exist_ok=True)
    fits = {}
    for lens, cameras in table["lenses"].items():
        video = folder / "calibration" / f"{lens}.mp4"
        found = detect_views(video, board, max_frames=300)
        result = calibrate(found.subset(select_views(found, FIT_VIEWS)), model)
        write_calibration(shared / f"{lens}.yml", result)
        fits[text_of[cameras[0]]] = {"file": lens, "rms_px": float(result.rms_px), "board_video": str(video)}
    (shared / "lenses.json").write_text(json.dumps(fits, indent=1))


def calibrate_capture(folder: Path, model: str, views: int, log, shared_root: Path) -> dict:
    """Calibrate each lens of the capture's board videos and write it into ``intrinsics/`` for its cameras (as a user
    would with ``bcmocap calibrate … --out intrinsics/CAMERA.yml``); per lens its error against the truth.

    A calibration is done once per :func:`lens_key` and kept in ``shared_root/KEY/``: the captures of one condition
    and seed have the same lens units, board videos and fits (as a user calibrates their cameras once, not per
    take), and copy them from there; ``"calibrated_in"`` names the capture whose board videos were fitted."""

    from bcmocap.cameras import camera_at
    from bcmocap.frontend import read_capture
    from bcmocap.sim.studio import read_studio_model

    done = folder / "calibration" / "suite_lenses.json"
    report = json.loads(done.read_text()) if done.exists() else None
    if report is not None and any(row.get("model", "fov") != model for row in report.values()):
        report = None  # calibrated with another model before: again with this one
    if report is None:
        key, by_text = _capture_lens_key(folder, model, views)
        shared = shared_root / key
        if not (shared / "lenses.json").exists():
            _calibrate_lenses(folder, model, views, shared, log)
        fits = json.loads((shared / "lenses.json").read_text())
        report = {}
        for text, cameras in by_text.items():
            fit = fits[text]
            for camera in cameras:
                for suffix in (".yml", ".json", ".coverage.png"):
                    source = shared / f"{fit['file']}{suffix}"
                    if source.exists():
                        shutil.copyfile(source, folder / "intrinsics" / f"{camera}{suffix}")
            report[fit["file"]] = {"cameras": cameras, "model": model, "rms_px": fit["rms_px"],
                                   "calibrated_in": str(Path(fit["board_video"]).parent.parent.name)}
        done.parent.mkdir(exist_ok=True)
        done.write_text(json.dumps(report, indent=1))
    # Against the truth with this code, from the lenses the run reads (the capture's intrinsics/).
    _, _, _, rig = read_studio_model(folder)
    capture = read_capture(folder)
    for lens, row in report.items():
        camera = row["cameras"][0]
        calibrated = capture.cameras[capture.camera_index(camera)].intrinsics
        row.update(_lens_error(calibrated, camera_at(rig.intrinsics, rig.index(camera))))
        log(f"  {lens}: {row['covered_max_px']:.2f} px max within {COVERED_DEG:g} deg of the true lens, "
            f"{row['covered_max_after_rotation_px']:.2f} px after a {row['rotation_deg']:.3f} deg turn")
    return report


def clock_errors(folder: Path) -> dict:
    """The claps' sub-frame offsets (first clap's video frame) and clock rates against the studio's truth."""
    from bcmocap.frontend import read_capture, synchronize
    from bcmocap.sim.studio import load_ground_truth

    truth = load_ground_truth(folder).trials["capture"]
    capture = read_capture(folder)
    sync = synchronize(capture, "capture")
    first_clap = truth.video_frame_of(np.arange(len(sync.cameras)), truth.clap_frames[0])
    rates = truth.clock_rate / np.median(truth.clock_rate)
    return {"offset_error_frames_max": float(np.abs(sync.frame_offsets - first_clap).max()),
            "rate_error_ppm_max": float(1e6 * np.abs(sync.clock_rates - rates).max()),
            "offsets": np.asarray(sync.offsets).tolist(), "first_clap_true": first_clap.tolist(), "fps": float(capture.fps)}


def time_offset_errors(run_dir: Path, clocks: dict) -> dict | None:
    """The cameras' time offsets against the truth, in video frames, relative to their mean over the cameras (a common
    offset is a shift of the whole motion): camera ``c``'s frames are exposed ``offsets[c] - first_clap_true[c]``
    video frames after the run's frame times. Two estimates: the frontend's gyro timing (``gyro_timing`` of
    ``frontend/capture/registration.json``, ms) and the solver's (``static:time_offset`` of ``solve/motion.npz``, in
    the solver's frame periods, ``stride`` video frames each). None without either."""
    registration = run_dir / "frontend" / "capture" / "registration.json"
    if not registration.exists():
        return None
    report = json.loads(registration.read_text())
    true = np.asarray(clocks["offsets"], float) - np.asarray(clocks["first_clap_true"])
    true -= true.mean()
    out = {}
    if report.get("gyro_timing"):
        fps = float(clocks.get("fps", 60.0))
        gyro = np.asarray(report["gyro_timing"]["time_shift_ms"], float) * fps / 1e3
        error = (gyro - gyro.mean()) - true
        out["gyro"] = {"max_frames": float(np.abs(error).max()), "rms_frames": float(np.sqrt(np.mean(error**2))),
                       "readout_ms": report["gyro_timing"]["readout_ms"]}
    path = run_dir / "solve" / "motion.npz"
    if path.exists():
        with np.load(path) as data:
            if "static:time_offset" in data.files:
                found = np.asarray(data["static:time_offset"]).reshape(-1) * int(report["stride"])
                error = (found - found.mean()) - true
                out["solver"] = {"max_frames": float(np.abs(error).max()), "rms_frames": float(np.sqrt(np.mean(error**2)))}
    return out or None


def registrations_off(run_dir: Path, capture_dir: Path) -> dict | None:
    """Per trial, the registered camera-frames and those more than 10 cm from the truth, with the cameras they
    belong to (:func:`registration_truth.registration_errors`), and the reference photos' residual against the
    truth; None where the range-of-motion trial's registration is missing, ``{"error": …}`` where they cannot be
    compared (a record is kept either way)."""
    from registration_truth import registration_errors

    if not (run_dir / "frontend" / "rom" / "registration.json").exists():
        return None
    try:
        found = registration_errors(run_dir, capture_dir)
    except (OSError, ValueError, KeyError, np.linalg.LinAlgError) as exc:
        return {"error": str(exc)}
    out = {trial: {k: row[k] for k in ("registered", "off", "cameras_with_off")} for trial, row in found["trials"].items()}
    return {**out, "reference_photo_residual_cm": found["reference_photo_residual_cm"]}


#: A run whose reference photos are this far (cm, median) from the truth is left out of the registrations' count:
#: every registration against such a model looks off (:mod:`registration_truth`).
REFERENCE_OFF_CM = 10.0


def _registrations_total(rows: list[dict]) -> dict:
    """The runs' registrations off summed per trial, over the runs measured against a right reference."""
    measured = [r["registrations_off"] for r in rows
                if (r.get("registrations_off") or {}).get("reference_photo_residual_cm") is not None
                and r["registrations_off"]["reference_photo_residual_cm"] <= REFERENCE_OFF_CM]
    out = {"runs_measured": len(measured)}
    for key, field in (("{}", "off"), ("{}_registered", "registered")):
        out.update({key.format(trial): sum((m.get(trial) or {}).get(field, 0) for m in measured) for trial in ("rom", "capture")})
    return out


def _spread(values: list[float]) -> dict:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    if not len(v):
        return {"mean": None, "sd": None, "p90": None, "max": None}
    return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def summarise(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["ok"]]
    improved = [r for r in ok if r["solved"]["joint_position_error_cm"] < r["initial"]["joint_position_error_cm"]
                and r["solved"]["joint_angle_error_deg"] < r["initial"]["joint_angle_error_deg"]]
    return {
        "runs": len(rows), "failed": len(rows) - len(ok),
        "joint_position_error_cm": _spread([r["solved"]["joint_position_error_cm"] for r in ok]),
        "joint_angle_error_deg": _spread([r["solved"]["joint_angle_error_deg"] for r in ok]),
        "initial_joint_position_error_cm": _spread([r["initial"]["joint_position_error_cm"] for r in ok]),
        "initial_joint_angle_error_deg": _spread([r["initial"]["joint_angle_error_deg"] for r in ok]),
        "solve_improved_fraction": len(improved) / len(ok) if ok else None,
        "registered_capture": _spread([r.get("registered_capture") for r in ok]),
        "lens_covered_max_px": _spread([lens["covered_max_px"] for r in rows for lens in r["lenses"].values()]),
        "lens_covered_max_after_rotation_px": _spread([lens["covered_max_after_rotation_px"] for r in rows
                                                       for lens in r["lenses"].values()]),
        "clap_offset_error_frames_max": _spread([r["clocks"]["offset_error_frames_max"] for r in rows]),
        "clap_rate_error_ppm_max": _spread([r["clocks"]["rate_error_ppm_max"] for r in rows]),
        "gyro_time_offset_error_frames_max": _spread([((r.get("time_offsets") or {}).get("gyro") or {}).get("max_frames")
                                                      for r in rows]),
        "registered_camera_frames_off": _registrations_total(rows),
        "solver_time_offset_error_frames_max": _spread([((r.get("time_offsets") or {}).get("solver") or {}).get("max_frames")
                                                        for r in rows]),
    }


FIGURE_FUNCTIONS = ("capture_settings", "_lens_error", "lens_key", "_capture_lens_key", "_calibrate_lenses",
                    "calibrate_capture", "clock_errors", "time_offset_errors", "registrations_off")


def figure_code(text: str) -> str:
    """A hash of :data:`FIGURE_FUNCTIONS` in ``text`` (this script's source at some commit): the functions that make
    a capture's settings, its calibration and the figures a record keeps, as syntax trees without their docstrings
    and import statements (where a module is imported does not change a figure)."""
    import ast
    import hashlib

    digest = hashlib.sha256()
    for node in ast.parse(text).body:
        if isinstance(node, ast.FunctionDef) and node.name in FIGURE_FUNCTIONS:
            body = [n for n in node.body if not isinstance(n, (ast.Import, ast.ImportFrom))]
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                body = body[1:]
            node.body = body
            digest.update(ast.dump(node).encode())
    return digest.hexdigest()[:16]


def suite_constants() -> dict:
    """The suite's constants that shape a run, the libraries' versions, :func:`figure_code` of this script and a hash of
    ``registration_truth.py`` (the records' ``registrations_off``)."""
    import hashlib
    from importlib.metadata import version

    return {"lens_models": LENS_MODELS, "fit_views": FIT_VIEWS, "covered_deg": COVERED_DEG,
            "reference_photos": REFERENCE_PHOTOS, "configs": {k: str(v.relative_to(ROOT)) for k, v in CONFIGS.items()},
            "libraries": {name: version(name) for name in LIBRARIES},
            "figure_code": figure_code(Path(__file__).read_text()),
            "registration_truth_code": hashlib.sha256((Path(__file__).resolve().parent / "registration_truth.py")
                                                      .read_bytes()).hexdigest()[:16]}


def settings_of(args) -> dict:
    """The options that shape the grid's runs (not where they are written, nor which of them this sitting runs)."""
    return {k: v for k, v in vars(args).items() if k not in ("out", "json", "only", "records", "cluster", "summarise")}


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=False)


def code_commit() -> str:
    """The commit of the code the runs use; SystemExit where :data:`PIPELINE_CODE` has uncommitted changes."""
    dirty = _git("status", "--porcelain", "--", *PIPELINE_CODE).stdout.strip()
    if dirty:
        raise SystemExit(f"--records: the code has uncommitted changes ({dirty.splitlines()[0].strip()} ...); commit "
                         "them, so that each record names the code it ran")
    return _git("rev-parse", "HEAD").stdout.strip()


def same_code(commit: str, head: str) -> bool:
    """Whether :data:`PIPELINE_CODE` is the same at ``commit`` and ``head``."""
    return commit == head or _git("diff", "--quiet", commit, head, "--", *PIPELINE_CODE).returncode == 0


def read_records(folder: Path, runs: list[Run], head: str, args) -> dict[str, dict]:
    """The records in ``folder`` of the planned ``runs`` (name → record); SystemExit for one of other code, other
    capture settings, other suite constants or other libraries. A failed run's record is kept like any other: a
    failure counts and is not run again until it is dropped by hand, with the reason logged."""
    records = {}
    expected = suite_constants()
    for run in runs:
        path = folder / f"{run.name}.json"
        if not path.exists():
            continue
        record = json.loads(path.read_text())
        if not same_code(record.get("commit", ""), head):
            changed = _git("diff", "--name-only", record.get("commit", ""), head, "--", *PIPELINE_CODE).stdout.split()
            raise SystemExit(f"{path}: a record of the code at {record.get('commit', '?')[:10]}, which differs from "
                             f"HEAD's ({head[:10]}) in {', '.join(changed[:5]) or 'unknown files'}; run it again "
                             "(remove the record)")
        capture = json.loads(json.dumps(capture_settings(run, args).to_dict()))
        constants = dict(record.get("suite_constants") or {})
        if "figure_code" not in constants:  # a record from before the hash: that of its commit's script
            constants["figure_code"] = figure_code(_git("show", f"{record.get('commit', '')}:benchmarks/suite.py").stdout)
        for what, got, want in (("capture settings", record.get("capture_settings"), capture),
                                ("suite constants", constants, expected)):
            if got != want:
                raise SystemExit(f"{path}: a record of other {what} ({got}, here {want}); run it again (remove it)")
        records[run.name] = record
    return records


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="working folder (captures and runs; a rerun resumes)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--quick", action="store_true", help="one clean and one realistic walk (development)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds cycled over the full grid (default 3)")
    ap.add_argument("--seconds", type=float, default=2.0, help="capture trial length (s, default 2)")
    ap.add_argument("--rom-seconds", type=float, default=6.0, help="range-of-motion trial length (s, default 6)")
    ap.add_argument("--rom-tempo", type=float, default=0.5, help="range-of-motion sweep speed (default 0.5)")
    ap.add_argument("--rom-protocol", default="feet_after", choices=["together", "feet_after"], help="what the subject does in the range-of-motion trial "
                    "(default feet_after: the ankles turned on still legs; bcmocap.sim.studio.ROM_PROTOCOLS)")
    ap.add_argument("--lens-model", choices=["fov", "opencv_fisheye", "thin_prism_fisheye"],
                    help="calibrated lens model of every run (default: LENS_MODELS, per condition)")
    ap.add_argument("--board-views", type=int, default=64, help="board placements per board video (default 64: about "
                    "a minute of waving the board, which the thin-prism fit needs; benchmarks/lens_units.py)")
    ap.add_argument("--cluster", help="bcmocap batch --cluster (e.g. local:2)")
    ap.add_argument("--only", help="comma-separated run names of the grid to run (e.g. realistic-run-sparse-s1); the "
                                   "results then hold those runs only, marked partial")
    ap.add_argument("--summarise", action="store_true", help="run nothing: summarise the --records there are into --json")
    ap.add_argument("--records", help="keep each finished run's record here (NAME.json, with the code's commit), skip "
                                      "runs with one, and summarise them all in --json (e.g. benchmarks/results/suite_runs)")
    args = ap.parse_args()

    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.precision import enable_float64
    from bcmocap.sim.studio import write_capture

    enable_float64()
    enable_compilation_cache()
    out = Path(args.out)
    runs = planned_runs(args.quick, args.seeds)
    if args.only:
        wanted = [name.strip() for name in args.only.split(",") if name.strip()]
        unknown = sorted(set(wanted) - {r.name for r in runs})
        if unknown:
            raise SystemExit(f"--only: {unknown} are not in the grid ({', '.join(r.name for r in runs)})")
        runs = [r for r in runs if r.name in wanted]
    records_dir = Path(args.records) if args.records else None
    head = code_commit() if records_dir else None
    grid = runs if not args.only else planned_runs(args.quick, args.seeds)
    kept = read_records(records_dir, grid, head, args) if records_dir else {}
    runs = [r for r in runs if r.name not in kept]
    if args.summarise:
        if not records_dir:
            raise SystemExit("--summarise needs --records")
        runs = []
    log = lambda text: print(text, flush=True)  # noqa: E731
    clock = time.perf_counter()
    prepared, rows = {}, []
    for run in runs:  # captures, board videos and calibrations (resumable)
        started = time.perf_counter()
        folder = out / "captures" / run.name
        manifest = folder / "capture.json"
        settings = capture_settings(run, args)
        written = json.loads(manifest.read_text()) if manifest.exists() else {}
        if written.get("complete"):  # its intrinsics/ hold the calibrated lenses now: never re-render over them
            if written.get("settings") != json.loads(json.dumps(settings.to_dict())):
                raise SystemExit(f"{folder}: a capture with other settings; give another --out")
        else:
            if folder.exists():  # a render cut short is rendered again whole (a resumed render is not checked
                shutil.rmtree(folder)  # to equal a whole one)
            log(f"{run.name}: rendering")
            write_capture(folder, settings, progress=False)
        log(f"{run.name}: calibrating")
        model = args.lens_model or LENS_MODELS[run.condition]
        prepared[run] = {"lenses": calibrate_capture(folder, model, args.board_views, log, out / "calibrations"),
                         "clocks": clock_errors(folder), "setup_seconds": round(time.perf_counter() - started, 1)}
    setup_seconds = time.perf_counter() - clock
    for condition in ("clean", "realistic"):
        chosen = [r for r in runs if r.condition == condition]
        if not chosen:
            continue
        command = [str(Path(sys.executable).with_name("bcmocap")), "batch", *[str(out / "captures" / r.name) for r in chosen],
                   "--out", str(out / "runs" / condition), "--config", str(CONFIGS[condition])]
        if args.cluster:
            command += ["--cluster", args.cluster]
        log(" ".join(command))
        subprocess.run(command, check=False)
        table = json.loads((out / "runs" / condition / "batch.json").read_text())["rows"]
        for run, row in zip(chosen, table):
            run_dir = Path(row["out"])
            record = {**dataclasses.asdict(run), "name": run.name, "ok": bool(row and row.get("ok")),
                      "seconds": row.get("seconds"), "error": row.get("error"),
                      "registered_rom": row.get("registered_rom"), "registered_capture": row.get("registered_capture"),
                      **prepared[run]}
            metrics_path = run_dir / "metrics.json"
            record["registrations_off"] = registrations_off(run_dir, out / "captures" / run.name)
            if record["ok"] and metrics_path.exists():
                metrics = json.loads(metrics_path.read_text())
                for which in ("initial", "solved"):
                    record[which] = {k: metrics[which][k]["mean"] for k in ("joint_position_error_cm", "joint_angle_error_deg")}
                record["time_offsets"] = time_offset_errors(run_dir, prepared[run]["clocks"])
            else:
                record["ok"] = False
            rows.append(record)
            if records_dir:
                write_json(str(records_dir / f"{run.name}.json"), {
                    **record, "commit": head, "settings": settings_of(args), "suite_constants": suite_constants(),
                    "capture_settings": json.loads(json.dumps(capture_settings(run, args).to_dict()))})
            if record["ok"]:
                log(f"{run.name}: {record['solved']['joint_position_error_cm']:.2f} cm, "
                    f"{record['solved']['joint_angle_error_deg']:.2f} deg (initial "
                    f"{record['initial']['joint_position_error_cm']:.2f} cm, {record['initial']['joint_angle_error_deg']:.2f} deg)")
            else:
                log(f"{run.name}: FAILED {record.get('error')}")
    if records_dir:  # every record of the grid (this sitting's and earlier ones'), in the grid's order
        kept = read_records(records_dir, grid, head, args)
        rows = [kept[r.name] for r in grid if r.name in kept]
        for row in rows:
            if row.get("settings") != settings_of(args):
                raise SystemExit(f"{records_dir / (row['name'] + '.json')}: a record of other settings ({row.get('settings')})")
    conditions = {c: summarise([r for r in rows if r["condition"] == c]) for c in ("clean", "realistic")
                  if any(r["condition"] == c for r in rows)}
    conditions["all"] = summarise(rows)
    missing = [r.name for r in grid if r.name not in {row["name"] for row in rows}]
    result = {"quick": args.quick, "partial": bool(missing), "missing": missing, "conditions": conditions, "runs": rows,
              "commit": head, "settings": settings_of(args),
              "setup_seconds": round(setup_seconds, 1), "seconds": round(time.perf_counter() - clock, 1),
              # the grid's time on this machine, run by run (studio, calibration and bcmocap run of each)
              "runs_seconds": round(sum((r.get("setup_seconds") or 0.0) + (r.get("seconds") or 0.0) for r in rows), 1),
              "machine": machine()}
    for name, c in conditions.items():
        p, a = c["joint_position_error_cm"], c["joint_angle_error_deg"]
        if p["mean"] is not None:
            log(f"{name:>10}: {c['runs']} runs, {c['failed']} failed; position {p['mean']:.2f} ± {p['sd']:.2f} cm "
                f"(p90 {p['p90']:.2f}, max {p['max']:.2f}); angle {a['mean']:.2f} ± {a['sd']:.2f} deg (p90 {a['p90']:.2f}, "
                f"max {a['max']:.2f}); solve improved {c['solve_improved_fraction']:.0%}")
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
