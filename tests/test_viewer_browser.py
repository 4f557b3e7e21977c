"""bcmocap view in a real browser: headless Chromium loads the page of `bcmocap view` on a small run folder,
the scene is drawn, and the time slider, a gizmo and "save" work end to end.

Skipped (with the reason) only where Chromium is not installed; `.ci/run` installs Debian's `chromium`.
Set BCMOCAP_VIEWER_SCREENSHOT=FILE.png to keep the screenshot (the README's docs/viewer.png comes from here).
"""

import argparse
import json
import os
import shutil
import threading
import time

import numpy as np
import pytest

from bcmocap.viewer.browser import Browser, colour_pixels, find_chromium, free_port
from viewer_run import make_run_folder

pytestmark = pytest.mark.slow  # about 40 s on 2 cores, most of it Chromium drawing WebGL in software


def _wait(condition, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def test_view_in_headless_chromium(tmp_path):
    if find_chromium() is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)")
    from bcmocap.pipeline.view_command import add_view_command, serve
    from bcmocap.viewer.app import BONE

    run = tmp_path / "run"
    truth_skeleton, _, _, true_joints = make_run_folder(run)
    original_model = (run / "model" / "skeleton.json").read_text()
    port = free_port()
    parser = argparse.ArgumentParser(prog="bcmocap")
    add_view_command(parser.add_subparsers())
    args = parser.parse_args(["view", str(run), "--port", str(port)])
    ready, stop, viewers = threading.Event(), threading.Event(), []
    server_thread = threading.Thread(target=serve, args=(args, lambda v: (viewers.append(v), ready.set()), stop))
    server_thread.start()
    try:
        assert ready.wait(120), "bcmocap view did not start"
        viewer = viewers[0]
        with Browser(1280, 800) as browser:
            browser.open(f"http://127.0.0.1:{port}/")
            client = _wait(lambda: next(iter(viewer.server.get_clients().values()), None), 90, "the page to connect")
            render = client.get_render(360, 640, timeout=90)  # the browser's WebGL canvas, through viser
            assert render.shape == (360, 640, 3) and render.std() > 5, "the 3D view is blank"
            shot = _wait(lambda: (lambda png: png if colour_pixels(png, BONE, left_fraction=0.65) > 40 else None)(
                browser.screenshot()), 90, "the skeleton's bones to be drawn")
            assert colour_pixels(shot, (255, 255, 255)) < 0.97 * 1280 * 800, "the page is blank"

            # the scene, through viser's Python API
            scene = viewer.server.scene
            joints, cameras = len(truth_skeleton.names), 18
            assert scene.get_handle_by_name("/estimate/joints").batched_positions.shape == (joints, 3)
            assert scene.get_handle_by_name("/cameras/bodies").batched_positions.shape == (cameras, 3)
            assert scene.get_handle_by_name("/cameras/frusta").points.shape == (cameras * 8, 2, 3)
            assert viewer.truth_joints is None  # the run's capture has no ground truth

            # the time slider: the server's state and the browser's panel follow
            viewer.slider.value = 20
            np.testing.assert_allclose(viewer.joint_meshes.batched_positions[7], viewer.joints[20, 7], atol=1e-6)
            _wait(lambda: "20" in (browser.evaluate("Array.from(document.querySelectorAll('input'))"
                                                    ".map(i => i.value).join(' ')") or "").split(), 30,
                  "the browser's frame field to show 20")

            # the camera view (read in the background once the page has the first frame) and a screenshot
            assert viewer.ready.wait(60), "the videos, scene points and pictures were not read"
            viewer.camera_menu.value = "chest"
            assert "median residual" in viewer.camera_text.content
            viewer.edit_menu.value = "joint: left_shin"
            browser.dismiss_notifications()
            time.sleep(2.0)
            png = browser.screenshot(tmp_path / "viewer.png")
            assert colour_pixels(png, BONE, left_fraction=0.65) > 40
            if os.environ.get("BCMOCAP_VIEWER_SCREENSHOT"):
                shutil.copyfile(tmp_path / "viewer.png", os.environ["BCMOCAP_VIEWER_SCREENSHOT"])

            # a gizmo drag, then save
            knee = viewer.model.names.index("left_shin")
            target = viewer.joints[20, knee] + np.array([0.0, 0.0, 0.04])
            assert viewer.drag_to(target), viewer.status
            np.testing.assert_allclose(viewer.joint_meshes.batched_positions[knee], target, atol=1e-6)
            viewer.save_button.value = True  # a click
            assert "Saved model version 2" in viewer.status, viewer.status
            _wait(lambda: "Saved model version 2" in browser.evaluate("document.body.innerText"), 30,
                  "the panel to say the model was saved")
    finally:
        stop.set()
        server_thread.join(30)
    assert not server_thread.is_alive()
    saved = json.loads((run / "model" / "skeleton.json").read_text())
    assert json.loads((run / "model" / "versions" / "001" / "skeleton.json").read_text()) == json.loads(original_model)
    assert saved == json.loads((run / "model" / "versions" / "002" / "skeleton.json").read_text())
    old = np.asarray(json.loads(original_model)["offsets_m"])
    changed = np.flatnonzero(np.abs(np.asarray(saved["offsets_m"]) - old).max(axis=1) > 1e-6)
    names = saved["names"]
    assert [names[k] for k in changed] == ["left_shin", "left_foot"]  # the knee, and the foot kept in place
    assert list(json.loads((run / "run.json").read_text())["stages"]) == ["frontend", "world", "skeleton"]
