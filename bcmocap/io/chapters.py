"""Takes split over chapter files: the chapters of one take found by their names, and joined into one file.

Action cameras split a long take into chapters (a GoPro at 4 GB: about 8 to 12 minutes of 4K), each a complete MP4
whose clock starts again at 0, the next chapter's first frame following the last one's last. GoPro names them by
chapter and file number (GoPro's "GoPro Camera File Naming Convention"):

- HERO6 and later: ``GXccnnnn.MP4`` (H.265; ``GH`` for H.264), chapter ``cc`` from 01, file ``nnnn``;
- HERO5 and earlier: ``GOPRnnnn.MP4`` for the first chapter, ``GPccnnnn.MP4`` from the second (``cc`` from 01).

:func:`take_chapters` gives the chapters of the take a file belongs to, in order; :func:`join_chapters` copies their
video and audio packets, unchanged, into one file (no decoding or encoding: a frame of the joined file is the frame of
its chapter), each chapter's timestamps shifted by the chapters before it. ``ValueError`` names the file at fault.
"""

from __future__ import annotations

import re
from fractions import Fraction
from pathlib import Path

__all__ = ["join_chapters", "take_chapters"]

_NEW = re.compile(r"^(G[HX])(\d\d)(\d{4})(\.[^.]+)$", re.IGNORECASE)  # HERO6+: GXccnnnn / GHccnnnn
_OLD_FIRST = re.compile(r"^(GOPR)(\d{4})(\.[^.]+)$", re.IGNORECASE)  # HERO5 and earlier: GOPRnnnn, then GPccnnnn
_OLD_NEXT = re.compile(r"^(GP)(\d\d)(\d{4})(\.[^.]+)$", re.IGNORECASE)


def _chapter_key(path: Path) -> tuple[str, str, int] | None:
    """``(family, file number + extension, chapter)`` of a GoPro chapter's name (chapter 0: HERO5's GOPR), else None."""
    name = path.name
    if m := _NEW.match(name):
        return m.group(1).upper(), (m.group(3) + m.group(4)).lower(), int(m.group(2))
    if m := _OLD_FIRST.match(name):
        return "GP", (m.group(2) + m.group(3)).lower(), 0
    if m := _OLD_NEXT.match(name):
        return "GP", (m.group(3) + m.group(4)).lower(), int(m.group(2))
    return None


def take_chapters(path: Path) -> list[Path]:
    """The chapters of ``path``'s take in order (its folder's files of the same GoPro file number), ``[path]`` for a
    file not named as a GoPro chapter. ValueError naming the take when a chapter is missing from the sequence."""
    path = Path(path)
    key = _chapter_key(path)
    if key is None:
        return [path]
    family, number, _ = key
    chapters = {}
    for sibling in path.parent.iterdir():
        other = _chapter_key(sibling)
        if other is not None and other[:2] == (family, number) and sibling.is_file():
            chapters[other[2]] = sibling
    order = sorted(chapters)
    first = 0 if family == "GP" else 1  # a HERO5 take starts with GOPRnnnn (chapter 0)
    expected = list(range(first, first + len(order)))
    if order != expected:
        missing = sorted(set(range(first, max(order) + 1)) - set(order))
        raise ValueError(f"{path}: chapter(s) {missing} of its take (GoPro file {number}) are missing from "
                         f"{path.parent} (found {', '.join(chapters[k].name for k in order)})")
    return [chapters[k] for k in order]


def join_chapters(chapters: list[Path], out: Path) -> list[float]:
    """Copy the chapters' video and audio packets into one MP4 ``out``, the clock running on (module docstring), and
    return where each chapter starts in it (s after its first frame).

    Each chapter's packets are shifted by the duration of the chapters before it, measured on its video track
    (its frames times their duration), so the joined video's frames are the chapters' frames back to back, and each
    chapter's audio keeps its place against its own video; an audio packet the previous chapter's end already covers
    (an encoder's priming, timed before its chapter's first frame) is left out.
    """
    import av

    out = Path(out)
    sources = []
    try:
        for path in chapters:
            try:
                sources.append(av.open(str(path)))
            except (av.FFmpegError, OSError, UnicodeDecodeError) as err:
                raise ValueError(f"{path}: FFmpeg (PyAV) cannot open it as a media file "
                                 f"({' '.join(str(err).split())})") from None
        layout = [(len(s.streams.video), len(s.streams.audio)) for s in sources]
        if layout[0][0] != 1 or any(x != layout[0] for x in layout):
            bad = next((p for p, x in zip(chapters, layout) if x != layout[0]), chapters[0])
            raise ValueError(f"{bad}: a chapter with {layout[chapters.index(bad)]} video and audio streams, where "
                             f"{chapters[0].name} has {layout[0]} (each chapter of a take: one video, the same audio)")
        with av.open(str(out), "w", format="mp4") as target:
            first = sources[0]
            kinds = [first.streams.video[0], *first.streams.audio[:1]]
            streams = [target.add_stream_from_template(s) for s in kinds]
            shift = Fraction(0)  # s: the duration of the chapters copied so far
            last = [None] * len(streams)  # s: each output stream's last decoding time
            starts = []
            for path, source in zip(chapters, sources):
                video = source.streams.video[0]
                chosen = [video, *source.streams.audio[:1]]
                starts.append(float(shift))
                start = video.start_time * video.time_base if video.start_time is not None else Fraction(0)
                end = start
                for packet in source.demux(chosen):
                    if packet.dts is None:
                        continue
                    index = chosen.index(packet.stream)
                    if index == 0 and packet.pts is not None:
                        end = max(end, (packet.pts + (packet.duration or 0)) * packet.time_base)
                    step = int(round((shift - start) / packet.time_base))
                    packet.pts = None if packet.pts is None else packet.pts + step
                    packet.dts += step
                    dts = packet.dts * packet.time_base
                    if last[index] is not None and dts <= last[index]:
                        if index == 0:
                            raise ValueError(f"{path}: its video packets go back in time past the previous chapter's end")
                        continue  # audio the previous chapter's end already covers (an encoder's priming)
                    last[index] = dts
                    packet.stream = streams[index]
                    target.mux(packet)
                if end <= start:
                    raise ValueError(f"{path}: its video track has no frames")
                shift += end - start
    except BaseException:
        out.unlink(missing_ok=True)
        raise
    finally:
        for source in sources:
            source.close()
    return starts
