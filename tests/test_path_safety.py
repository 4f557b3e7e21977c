"""A capture folder is untrusted input: names in it never make a command read or write outside its folders.

The hostile captures here are the hand-made 2-camera folder of test_frontend_capture with one name or path
replaced; every command that reads a capture must refuse them with one line naming the file and field, and
leave a sentinel folder beside the output untouched.
"""

import json
import re
import shutil

import numpy as np
import pytest

from bcmocap.cli import main
from bcmocap.frontend import read_capture
from bcmocap.frontend.features import write_camera_features
from bcmocap.io.names import checked_name, checked_relative_path

from test_frontend_capture import make_capture

HOSTILE_NAMES = ["..", ".", "../victim", "/tmp/victim", "a/b", "a\\b", "a\x00b", "", ".hidden", "x" * 200, "new\nline"]


@pytest.fixture(scope="module")
def clean_capture(tmp_path_factory):
    return make_capture(tmp_path_factory.mktemp("safety") / "capture")


@pytest.mark.parametrize("name", HOSTILE_NAMES + [5, None, ["head"]])
def test_hostile_names_are_refused(name):
    with pytest.raises(ValueError, match=r"rig\.json: cameras\[0\]\.name"):
        checked_name(name, "cameras[0].name", "rig.json")


@pytest.mark.parametrize("name", ["head", "left_foot", "cam-01", "GoPro+7.2", "_x"])
def test_plain_names_pass(name):
    assert checked_name(name, "cameras[0].name", "rig.json") == name


@pytest.mark.parametrize("path", ["/etc/passwd", "../x.json", "intrinsics/../../x.json", "", "a\\..\\b", "a\x00"])
def test_relative_paths_must_stay_inside(path):
    with pytest.raises(ValueError, match=r"rig\.json: cameras\[1\]\.lens"):
        checked_relative_path(path, "cameras[1].lens", "rig.json")
    assert str(checked_relative_path("intrinsics/./head.json", "lens", "rig.json")) == "intrinsics/head.json"


def _hostile(clean, tmp_path, edit):
    """A copy of the clean capture with ``edit(manifest, rig)`` applied to its JSON files."""
    folder = shutil.copytree(clean, tmp_path / "capture")
    manifest = json.loads((folder / "capture.json").read_text())
    rig = json.loads((folder / "rig.json").read_text())
    edit(manifest, rig)
    (folder / "capture.json").write_text(json.dumps(manifest))
    (folder / "rig.json").write_text(json.dumps(rig))
    return folder


def _rename_camera(name):
    def edit(manifest, rig):
        manifest["cameras"][0] = rig["cameras"][0]["name"] = name
    return edit


def _rename_trial(name):
    def edit(manifest, rig):
        manifest["trials"][1] = name
    return edit


def _lens(path):
    def edit(manifest, rig):
        rig["cameras"][1]["lens"] = path
    return edit


CASES = {
    "camera ..": (_rename_camera("../../victim"), r"rig\.json: cameras\[0\]\.name '\.\./\.\./victim'"),
    "camera absolute": (_rename_camera("VICTIM"), r"rig\.json: cameras\[0\]\.name '/.*victim'"),
    "camera number": (_rename_camera(7), r"rig\.json: cameras\[0\]\.name must be a string, got int"),
    "trial ..": (_rename_trial("../victim"), r"capture\.json: trials\[1\] '\.\./victim'"),
    "trial absolute": (_rename_trial("VICTIM"), r"capture\.json: trials\[1\] '/.*victim'"),
    "lens outside": (_lens("/etc/passwd"), r"rig\.json: cameras\[1\]\.lens '/etc/passwd'"),
    "lens ..": (_lens("../../victim/lens.json"), r"rig\.json: cameras\[1\]\.lens"),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("command", ["frontend", "run"])
def test_commands_refuse_hostile_captures_and_touch_nothing_outside(clean_capture, tmp_path, capsys, case, command):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("the user's file")
    edit, message = CASES[case]
    absolute_victim = str(victim)

    def with_victim(manifest, rig):  # an absolute name points at this test's victim folder
        edit(manifest, rig)
        for entry in [manifest, *rig["cameras"]]:
            for key, value in list(entry.items()):
                if isinstance(value, str) and "VICTIM" in value:
                    entry[key] = value.replace("VICTIM", absolute_victim)
                if isinstance(value, list):
                    entry[key] = [absolute_victim if v == "VICTIM" else v for v in value]

    capture = _hostile(clean_capture, tmp_path, with_victim)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    out = tmp_path / "out" / "nested"
    assert main([command, str(capture), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"bcmocap {command}: ") and re.search(message, err), err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if not p.is_relative_to(tmp_path / "out")) \
        == before
    assert (victim / "precious.txt").read_text() == "the user's file"
    with pytest.raises(ValueError):
        read_capture(capture)


def test_the_feature_cache_never_replaces_a_folder_it_did_not_write(tmp_path):
    frames = [(np.zeros((1, 2)), np.zeros((1, 128), np.uint8))]
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("years of work")
    with pytest.raises(ValueError, match=r"user: holds files that are not features \(thesis\.tex\)"):
        write_camera_features(user, {}, frames)
    assert (user / "thesis.tex").read_text() == "years of work"
    (tmp_path / "link").symlink_to(user, target_is_directory=True)
    with pytest.raises(ValueError, match="link: exists and is not a features folder"):
        write_camera_features(tmp_path / "link", {}, frames)
    assert sorted(p.name for p in user.iterdir()) == ["thesis.tex"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "user"]  # no temporary folder left
    write_camera_features(tmp_path / "cache", {}, frames)
    write_camera_features(tmp_path / "cache", {"again": 1}, frames)  # its own folder is replaced
