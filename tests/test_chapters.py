"""A take split over chapter files (bcmocap.io.chapters): found by GoPro's names, joined frame for frame, and
``bcmocap init`` on a rig file that names a take's first chapter."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_init import CAMERAS, CLAPS, FPS, HEIGHT, LAST, RATE, STARTS, WIDTH, global_frame, image_of, run_init, shoot, \
    track_of, write_rig  # noqa: F401  (shoot: the fixture)

from bcmocap.frontend import read_capture, synchronize
from bcmocap.io.chapters import join_chapters, take_chapters
from bcmocap.io.media import MediaWriter, probe_media


def write_chapters(folder: Path, names: list[str], c: int, first: int, last: int, split: list[int]) -> list[Path]:
    """Camera ``c``'s take of global frames ``first … last`` as chapters starting at the global frames ``split``."""
    track = track_of(c, first, last)
    per_frame = round(RATE / FPS)
    bounds = [first, *split, last + 1]
    paths = []
    for name, a, b in zip(names, bounds[:-1], bounds[1:]):
        writer = MediaWriter(folder / name, FPS, (WIDTH, HEIGHT), RATE)
        writer.write_audio(track[(a - first) * per_frame:(b - first) * per_frame])
        writer.write([image_of(g) for g in range(a, b)])
        writer.close()
        paths.append(folder / name)
    return paths


def chaptered_shoot(shoot: Path, tmp_path: Path, named: str) -> Path:
    """A copy of the shoot whose head camera's take is two chapters (split at global frame 90, between the trials'
    claps), GX010003.MP4 and GX020003.MP4, the rig file naming ``named`` for it."""
    folder = tmp_path / "shoot"
    shutil.copytree(shoot, folder)
    (folder / "videos" / "head.mp4").unlink()
    write_chapters(folder / "videos", ["GX010003.MP4", "GX020003.MP4"], 0, STARTS[0], LAST, [90])
    write_rig(folder / "rig.toml", {"head": {"segment": "head", "mount": "forehead", "lens": "wide", "video": named},
                                    "chest": {"segment": "torso", "lens": "wide"},
                                    "left_foot": {"segment": "left_foot"}}, {"margin_s": 0.5})
    return folder


def decoded(path: Path) -> list[int]:
    video = cv2.VideoCapture(str(path))
    frames = []
    while (got := video.read())[0]:
        frames.append(global_frame(got[1]))
    video.release()
    return frames


def test_a_take_s_chapters_are_found_by_their_names(tmp_path):
    for name in ("GX010042.MP4", "GX020042.MP4", "GX030042.MP4", "GX010043.MP4", "GH010042.MP4", "GOPR0007.MP4",
                 "GP010007.MP4", "GP020007.MP4", "clip.mp4"):
        (tmp_path / name).write_bytes(b"")
    names = lambda path: [p.name for p in take_chapters(path)]  # noqa: E731
    assert names(tmp_path / "GX020042.MP4") == ["GX010042.MP4", "GX020042.MP4", "GX030042.MP4"]  # any chapter names it
    assert names(tmp_path / "GX010043.MP4") == ["GX010043.MP4"]
    assert names(tmp_path / "GH010042.MP4") == ["GH010042.MP4"]  # H.264 and H.265 takes are not one take
    assert names(tmp_path / "GOPR0007.MP4") == ["GOPR0007.MP4", "GP010007.MP4", "GP020007.MP4"]  # HERO5's naming
    assert names(tmp_path / "clip.mp4") == ["clip.mp4"]
    (tmp_path / "GX020042.MP4").unlink()
    with pytest.raises(ValueError, match=r"GX010042.MP4: chapter\(s\) \[2\] of its take \(GoPro file 0042.mp4\) are "
                                         r"missing .* \(found GX010042.MP4, GX030042.MP4\)"):
        take_chapters(tmp_path / "GX010042.MP4")


def test_joined_chapters_are_the_take_frame_for_frame_with_its_sound(tmp_path):
    chapters = write_chapters(tmp_path, ["GX010001.MP4", "GX020001.MP4", "GX030001.MP4"], 0, 0, 119, [45, 90])
    whole = tmp_path / "whole.mp4"
    write_chapters(tmp_path, ["whole.mp4"], 0, 0, 119, [])
    starts = join_chapters(chapters, tmp_path / "joined.mp4")
    np.testing.assert_allclose(starts, [0.0, 1.5, 3.0], atol=1e-9)
    assert decoded(tmp_path / "joined.mp4") == list(range(120))
    info = probe_media(tmp_path / "joined.mp4")
    assert info.num_frames == 120 and info.fps == FPS and info.audio_rate == RATE
    from bcmocap.frontend.sync import clap_candidates
    from bcmocap.io.media import read_audio_track

    joined_claps = np.sort(clap_candidates(read_audio_track(tmp_path / "joined.mp4")[0], RATE, max_count=3)[0])
    whole_claps = np.sort(clap_candidates(read_audio_track(whole)[0], RATE, max_count=3)[0])
    assert np.all(np.abs(joined_claps - whole_claps) <= 0.002 * RATE)  # the claps within 2 ms of the unsplit take's


def test_init_joins_the_chapters_a_rig_file_names(shoot, tmp_path, capsys):  # noqa: F811
    # The rig file names the take's first chapter: the capture is the one the unsplit take gives.
    folder = chaptered_shoot(shoot, tmp_path, "GX010003.MP4")
    assert run_init(folder, tmp_path / "joined") == 0
    assert "joined 2 chapters of one take: GX010003.MP4, GX020003.MP4" in capsys.readouterr().out
    assert run_init(shoot, tmp_path / "whole") == 0
    joined, whole = read_capture(tmp_path / "joined"), read_capture(tmp_path / "whole")
    video = tmp_path / "joined" / "videos" / "head.mp4"
    assert video.is_file() and not video.is_symlink() and not (tmp_path / "joined" / ".chapters").exists()
    for trial in whole.trials:
        assert synchronize(joined, trial).offsets.tolist() == synchronize(whole, trial).offsets.tolist()
        a, b = joined.trial_video(trial, "head"), whole.trial_video(trial, "head")
        assert (a.first_frame, a.num_frames) == (b.first_frame, b.num_frames)
        frames = [global_frame(image) for _, image in joined.frames(trial, "head")]
        assert frames == [global_frame(image) for _, image in whole.frames(trial, "head")]
    assert joined.manifest["claps"] == whole.manifest["claps"]
    assert CAMERAS[0] == "head" and CLAPS[1] < 90 < CLAPS[2]


def test_a_rig_file_naming_a_later_chapter_is_refused(shoot, tmp_path, capsys):  # noqa: F811
    # GX020003 is the second chapter of the take GX010003 starts: naming it for a trial would join it to the first.
    folder = chaptered_shoot(shoot, tmp_path, "GX020003.MP4")
    assert run_init(folder, tmp_path / "capture") == 2
    err = capsys.readouterr().err
    assert "cameras.head.video names GX020003.MP4" in err and "chapter 2 of the take that starts with GX010003" in err
    assert not (tmp_path / "capture").exists()


def test_a_hero5_take_without_its_first_chapter_is_refused(tmp_path):
    for name in ("GP010007.MP4", "GP020007.MP4"):
        (tmp_path / name).write_bytes(b"")
    with pytest.raises(ValueError, match=r"GP010007.MP4: chapter\(s\) \[0\] of its take"):
        take_chapters(tmp_path / "GP010007.MP4")
