"""A model edited by hand (``bcmocap view``) becomes the run's model: a new version, later stages stale.

``DIR/model/skeleton.json`` and ``rig.json`` stay the model the ``initial`` and later stages read. Every
version is kept under ``DIR/model/versions/NNN/`` with a line in ``DIR/model/versions.json``: version 1
is the model the ``skeleton`` stage estimated (snapshotted on the first save, or whenever the current
files differ from the last version, e.g. after the stage was redone), then one version per save. Saving
holds the run folder's lock (:func:`~bcmocap.io.output_folder.locked_output`; two saves at once take turns), so
it never races a ``bcmocap run`` writing there, and forgets the ``initial`` stage and those after it in ``DIR/run.json``
(:meth:`~bcmocap.io.run_folder.RunLog.forget_from`) and the solver's checkpoint, so the next
``bcmocap run`` reuses frontend, world and skeleton and redoes ``initial``, ``solve`` and ``outputs``
with the edit. A changed ``skeleton`` setting re-estimates the model and so replaces the edit (the
versions stay).
"""

from __future__ import annotations

import datetime
import json
import re
from pathlib import Path

from ..atomic import write_json_atomic
from ..io.model_json import rig_to_dict, skeleton_to_dict
from ..io.output_folder import locked_output
from ..io.run_folder import MODEL_FILES, STAGES, RunLog, read_json, read_run_log

#: Seconds a save waits for the run folder's lock: another save holds it for milliseconds (two viewer clients
#: saving at once both get their version); a ``bcmocap run`` holds it for the whole run (the save is refused).
SAVE_WAIT_S = 10.0
#: The stage an edited model makes stale, with every stage after it.
STALE_FROM = "initial"


def _inside(root: Path, path: Path) -> Path:
    """``path`` if it resolves inside ``root`` (no symlink leads out of the run folder), else ValueError."""
    real_root, real = root.resolve(), path.resolve()
    if real != real_root and real_root not in real.parents:
        raise ValueError(f"{path} leads outside the run folder {root} (a symlink?); refusing to write there")
    return path


def model_versions(run_dir: str | Path) -> list[dict]:
    """The entries of ``DIR/model/versions.json`` (empty before the first save)."""
    path = Path(run_dir) / "model" / "versions.json"
    if not path.exists():
        return []
    entries = read_json(path).get("versions")
    if not isinstance(entries, list):
        raise ValueError(f"{path}: field 'versions' must be a list")
    for entry in entries:  # the folder names are read back: nothing may lead out of model/versions/
        if not (isinstance(entry, dict) and isinstance(entry.get("folder"), str) and re.fullmatch(r"\d{3,}", entry["folder"])):
            raise ValueError(f"{path}: every entry of 'versions' needs a 'folder' of digits (such as \"001\"), got {entry!r}")
    return entries


def save_model_version(run_dir: str | Path, skeleton, rig, note: str = "edited in bcmocap view") -> str:
    """Store ``skeleton`` and ``rig`` as the run's model and a new version; mark the later stages stale.

    Returns:
        A one-line message for the user (version number and what the next ``bcmocap run`` redoes).

    Raises:
        ValueError: not a run folder, another command writing to it, or a path leading outside it.
    """
    run_dir = Path(run_dir)
    data = read_run_log(run_dir)
    with locked_output(run_dir, wait_s=SAVE_WAIT_S):
        model = _inside(run_dir, run_dir / "model")
        versions_dir = _inside(run_dir, model / "versions")
        entries = model_versions(run_dir)
        now = datetime.datetime.now().isoformat(timespec="seconds")
        current = {name: model / name for name in MODEL_FILES}
        if all(p.is_file() for p in current.values()) and (
                not entries or not _same_files(current, versions_dir / entries[-1]["folder"])):
            source = "skeleton stage (estimated from the range-of-motion trial)" if not entries else \
                "model files found in model/ (the skeleton stage was redone or they were edited by hand)"
            entries.append(_store(versions_dir, len(entries) + 1, {n: json.loads(p.read_text())
                                                                   for n, p in current.items()}, source, now))
        payload = {"skeleton.json": skeleton_to_dict(skeleton), "rig.json": rig_to_dict(rig, skeleton)}
        entry = _store(versions_dir, len(entries) + 1, payload, note, now)
        entries.append(entry)
        for name, content in payload.items():
            write_json_atomic(_inside(run_dir, model / name), content)
        write_json_atomic(model / "versions.json", {
            "versions": entries, "current": entry["version"],
            "note": "model/skeleton.json and rig.json are the current version; each version's files are in "
                    "versions/NNN/"})
        log = RunLog(run_dir, Path(data["capture"]))
        if "skeleton" in log.data["stages"]:
            log.data["stages"]["skeleton"]["model_version"] = entry["version"]
        stale = [s for s in log.data["stages"] if s in _later_stages()]
        log.forget_from(STALE_FROM)
        for name in ("checkpoint.npz", "checkpoint.json"):  # a checkpoint of the old model must not be resumed
            path = run_dir / "solve" / name
            if path.is_file() or path.is_symlink():
                _inside(run_dir, path.parent)
                path.unlink()
    redo = ", ".join(stale) if stale else "nothing yet (those stages had not run)"
    return (f"Saved model version {entry['version']} in {model / 'versions' / entry['folder']}; stale: {redo}. "
            "Run `bcmocap run` again to redo them with the edit.")


def _later_stages() -> tuple[str, ...]:
    return STAGES[STAGES.index(STALE_FROM):]


def _store(versions_dir: Path, number: int, payload: dict, source: str, when: str) -> dict:
    folder = f"{number:03d}"
    for name, content in payload.items():
        write_json_atomic(_inside(versions_dir.parent.parent, versions_dir / folder / name), content)
    return {"version": number, "folder": folder, "source": source, "saved": when}


def _same_files(current: dict[str, Path], version: Path) -> bool:
    try:
        return all(json.loads(p.read_text()) == json.loads((version / n).read_text()) for n, p in current.items())
    except (OSError, ValueError):
        return False
