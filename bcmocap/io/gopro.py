"""GoPro telemetry: the gyroscope and accelerometer in a GoPro MP4's GPMF track (HERO5 and later, Fusion, MAX).

GoPro cameras record their IMU in the file, in a timed metadata track of GPMF payloads (GoPro's KLV format, one payload
per second holding a few hundred samples per sensor). :func:`read_gopro_imu` reads it with ``py-gpmf-parser`` (Python
bindings of GoPro's own C parser, ``gopro/gpmf-parser``): its scaled samples, and its timing, which GoPro leaves out of
the samples on purpose (a sensor's crystal is not the video's) and recovers from the payloads' times on the MP4 clock
(each payload's time on the MP4 clock and the samples it holds: :func:`_samples`).

**Time.** Sample ``k`` of a sensor is at ``first + k / rate`` s on the file's clock, shifted so that 0 is the first
video frame (the convention of :func:`~bcmocap.io.media.read_audio_track`): audio, video and telemetry of one file on
one clock. The payload times fix it to tens of milliseconds (``GetGPMFSampleRate`` fits payloads one second long);
the frontend's gyro timing (:mod:`bcmocap.frontend.gyro_timing`) finds the rest against the frames.

**Axes.** The samples are returned in GoPro's IMU axes, the labels of the gpmf-parser README's figure ("IMU
Orientation Uses These Axis Labels"): Z up out of the camera's top, X to the camera's left and Y out of its back,
seen from behind the camera (:data:`CAMERA_FROM_GOPRO_IMU` turns them into the camera frame of this project: x right, y
down, z along the lens). A file's channels are in those axes by its own ``ORIO`` (the order the parser writes them in
after the ``MTRX``/``ORIN`` the camera gives: HERO6 later firmware, HERO8 and later, MAX), else by the README's
per-model table for files that give none (HERO5 and Karma: Z, X, Y; HERO6 and HERO7: Y, −X, Z; Fusion: −Y, X, Z).
A file of another model without ``ORIO`` is refused, naming its device.

Errors are ``ValueError`` naming the file.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

__all__ = ["CAMERA_FROM_GOPRO_IMU", "GoProImu", "SensorSamples", "read_gopro_imu"]

#: wxyz rotation of GoPro's IMU axes (module docstring) into the camera frame (x right, y down, z along the lens):
#: X (camera's left) → −x, Y (out of its back) → −z, Z (up) → −y.
CAMERA_FROM_GOPRO_IMU = np.array([0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5)])

# Channel order of files that carry no ORIO, by device name (gpmf-parser README, "HERO5 Black and Session",
# "Fusion Adds and Changes", "HERO6 Black Adds and Changes"; HERO7 supports all HERO6 metadata): axis letter, sign.
_MODEL_CHANNELS = (
    (("hero6", "hero7"), "Y-XZ"),
    (("fusion",), "-YXZ"),
    (("hero5", "camera"), "ZXY"),  # HERO5 firmware names its device "Camera"
)


@dataclasses.dataclass(frozen=True)
class SensorSamples:
    """One sensor's samples.

    Attributes:
        time_s: ``(N,)`` s after the file's first video frame.
        values: ``(N, 3)`` in GoPro's IMU axes (X, Y, Z: module docstring), SI units (rad/s, m/s²).
        rate_hz: the sample rate on the file's clock (Hz).
    """

    time_s: np.ndarray
    values: np.ndarray
    rate_hz: float


@dataclasses.dataclass(frozen=True)
class GoProImu:
    """The IMU of one GoPro file.

    Attributes:
        path: the file. device: its GPMF device name (``DVNM``: "Camera" for HERO5, "Hero6 Black", "GoPro Max", ...).
        gyro: angular velocity (rad/s). accel: specific force (m/s²), or None where the file has no accelerometer.
        channels: how the file's channels became the X, Y, Z axes (``"ORIO ZXY"``, or ``"table ZXY"``).
        camera_from_imu: ``(4,)`` wxyz, the axes into the camera frame (:data:`CAMERA_FROM_GOPRO_IMU`).
    """

    path: Path
    device: str
    gyro: SensorSamples
    accel: SensorSamples | None
    channels: str
    camera_from_imu: np.ndarray = dataclasses.field(default_factory=lambda: CAMERA_FROM_GOPRO_IMU.copy())


def _text(stream) -> str:
    import py_gpmf_parser as gpmf

    raw = gpmf.GPMF_RawData(stream)
    return bytes(raw[: gpmf.GPMF_Repeat(stream) * gpmf.GPMF_StructSize(stream)]).split(b"\0")[0].decode("latin-1").strip()


def _stream_tags(payload, size: int, sensor: str) -> dict[str, str]:
    """The text tags (``DVNM``, ``STNM``, ``ORIN``, ``ORIO``) before ``sensor``'s samples in one payload."""
    import py_gpmf_parser as gpmf

    ok, stream = gpmf.GPMF_Init(payload, size)
    if ok != gpmf.GPMF_ERROR.GPMF_OK:
        return {}
    tags: dict[str, str] = {}
    while True:
        key = gpmf.fourCC_to_string(gpmf.GPMF_Key(stream))
        if key == "STRM":
            tags.pop("STNM", None), tags.pop("ORIN", None), tags.pop("ORIO", None)  # a new stream's own tags
        elif key in ("DVNM", "STNM", "ORIN", "ORIO") and gpmf.GPMF_Type(stream) == ord("c"):
            tags[key] = _text(stream)
        elif key == sensor:
            return tags
        if gpmf.GPMF_Next(stream, gpmf.GPMF_RECURSE_LEVELS) != gpmf.GPMF_ERROR.GPMF_OK:
            return {}


def _channel_axes(path: Path, device: str, tags: dict[str, str]) -> tuple[str, np.ndarray]:
    """``(description, (3, 3) matrix)`` taking a sample's channels to the X, Y, Z axes."""
    if tags.get("ORIO"):
        order, source = "".join(tags["ORIO"].split()), "ORIO"
    else:
        lowered = device.lower()
        order = next((o for names, o in _MODEL_CHANNELS if any(n in lowered for n in names)), None)
        if order is None:
            raise ValueError(f"{path}: GoPro device {device!r} gives no ORIO for its IMU channels and is not a model "
                             "whose channel order is published (HERO5, HERO6, HERO7, Fusion); its axes are unknown")
        source = "table"
    letters, signs, sign = [], [], 1.0
    for char in order:
        if char == "-":
            sign = -1.0
            continue
        letters.append(char.upper())
        signs.append(-sign if char.islower() else sign)  # ORIO: a lowercase letter is a negative axis
        sign = 1.0
    if sorted(letters) != ["X", "Y", "Z"]:
        raise ValueError(f"{path}: IMU channel order {order!r} ({source}) is not a permutation of X, Y, Z")
    to_axes = np.zeros((3, 3))
    for channel, (letter, s) in enumerate(zip(letters, signs)):
        to_axes["XYZ".index(letter), channel] = s
    return f"{source} {order}", to_axes


def _samples(path: Path, handle, sensor: str, origin_s: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(time_s (N,), channels (N, 3), rate)`` of one sensor over every payload, or None without it.

    The times: payload ``i``, which starts at ``start_i`` s on the MP4 clock, holds samples ``K_i`` onwards
    (``K_i`` the samples of the payloads before it), so ``start_i ≈ t_0 + K_i / rate``, fitted by least squares over
    every payload but the last (the recording stops inside it: a HERO5's last payload of a second holds a tenth of its
    samples; ``GetGPMFSampleRate``, which counts it whole, reads the HERO5 sample's 398 Hz gyro as 385 Hz).
    """
    import py_gpmf_parser as gpmf

    fourcc = gpmf.Str2FourCC(sensor)
    chunks, starts, spans = [], [], []
    resource = 0  # one buffer, grown as needed and reused for every payload
    for index in range(gpmf.GetNumberPayloads(handle)):
        size = gpmf.GetPayloadSize(handle, index)
        resource = gpmf.GetPayloadResource(handle, resource, size)
        payload = gpmf.GetPayload(handle, resource, index, size)
        ok, stream = gpmf.GPMF_Init(payload, size)
        if ok != gpmf.GPMF_ERROR.GPMF_OK:
            continue
        if gpmf.GPMF_FindNext(stream, fourcc, gpmf.GPMF_RECURSE_LEVELS_AND_TOLERANT) != gpmf.GPMF_ERROR.GPMF_OK:
            continue
        count, width = gpmf.GPMF_Repeat(stream), gpmf.GPMF_ElementsInStruct(stream)
        if not count or width != 3:
            continue
        ok, data = gpmf.GPMF_ScaledData(stream, count * width * 8, 0, count, gpmf.GPMF_SampleType.DOUBLE)
        if ok != gpmf.GPMF_ERROR.GPMF_OK:
            raise ValueError(f"{path}: GPMF payload {index} has {sensor} samples the parser cannot scale")
        _, start, stop = gpmf.GetPayloadTime(handle, index)
        chunks.append(np.asarray(data[: count * width], np.float64).reshape(count, width))
        starts.append(float(start))
        spans.append(float(stop) - float(start))
    if not chunks:
        return None
    counts = np.array([len(c) for c in chunks])
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    if len(chunks) >= 3:  # every payload's start but the last's
        design = np.stack([np.ones(len(chunks) - 1), first[:-1]], axis=1)
        t0, period = np.linalg.lstsq(design, np.array(starts[:-1]), rcond=None)[0]
    else:  # the first payload's own span (a file of one or two payloads: seconds long)
        period = spans[0] / counts[0]
        t0 = starts[0]
    if not (np.isfinite(period) and period > 0):
        raise ValueError(f"{path}: the GPMF payload times give no sample rate for its {sensor} samples")
    values = np.concatenate(chunks)
    return t0 - origin_s + np.arange(len(values)) * period, values, float(1.0 / period)


def _video_origin(path: Path) -> float:
    """Time (s) of the file's first video frame on its MP4 clock (ValueError naming a file FFmpeg cannot open)."""
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: FFmpeg (PyAV) cannot open it as a media file ({' '.join(str(err).split())})") from None
    with container:
        video = container.streams.video[0] if container.streams.video else None
        if video is None or video.start_time is None or video.time_base is None:
            return 0.0
        return float(video.start_time * video.time_base)


def read_gopro_imu(path: str | os.PathLike) -> GoProImu | None:
    """The gyroscope and accelerometer of a GoPro file (module docstring), or None for a file without a GPMF track
    or without gyro samples in it (another camera's file, or a GoPro file whose telemetry was stripped).

    Raises:
        ValueError: naming the file, where it is missing, or its GPMF track is damaged or of unknown axes.
    """
    import py_gpmf_parser as gpmf

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: missing (expected a camera file)")
    origin = _video_origin(path)
    handle = gpmf.OpenMP4Source(str(path), gpmf.MOV_GPMF_TRAK_TYPE, gpmf.MOV_GPMF_TRAK_SUBTYPE, 0)
    if not handle:
        return None
    try:
        if gpmf.GetNumberPayloads(handle) < 1:
            return None
        gyro = _samples(path, handle, "GYRO", origin)
        if gyro is None:
            return None
        accel = _samples(path, handle, "ACCL", origin)
        size = gpmf.GetPayloadSize(handle, 0)
        payload = gpmf.GetPayload(handle, gpmf.GetPayloadResource(handle, 0, size), 0, size)
        tags = _stream_tags(payload, size, "GYRO")
    finally:
        gpmf.CloseSource(handle)
    device = tags.get("DVNM", "")
    channels, to_axes = _channel_axes(path, device, tags)
    for name, found in (("GYRO", gyro), ("ACCL", accel)):
        if found is not None and not (np.all(np.isfinite(found[1])) and np.all(np.diff(found[0]) > 0)):
            raise ValueError(f"{path}: the GPMF track's {name} samples are not finite or not in time order")
    return GoProImu(path, device, SensorSamples(gyro[0], gyro[1] @ to_axes.T, gyro[2]),
                    None if accel is None else SensorSamples(accel[0], accel[1] @ to_axes.T, accel[2]), channels)


# ---------------------------------------------------------------------------------------------
# Writing: a GPMF track as a GoPro writes one, for the studio's camera files.


def _klv(key: str, kind: str, size: int, repeat: int, data: bytes) -> bytes:
    """One GPMF key-length-value: the key, the type, the structure size, the repeat count, the data padded to 4 bytes."""
    import struct

    if len(key) != 4 or repeat > 0xFFFF or size > 0xFF:
        raise ValueError(f"GPMF {key!r}: {repeat} structures of {size} bytes do not fit one KLV")
    return key.encode("ascii") + struct.pack(">cBH", kind.encode("latin-1"), size, repeat) + data + b"\0" * (-len(data) % 4)


def _text_klv(key: str, text: str) -> bytes:
    data = text.encode("latin-1")
    return _klv(key, "c", 1, len(data), data)


def _sensor_stream(name: str, key: str, unit: str, values: np.ndarray, scale: float) -> bytes:
    """A ``STRM`` of one 3-axis sensor: its name, unit, scale, ``ORIO XYZ`` and ``values`` ``(N, 3)`` as int16 × scale
    (the scale lowered where the values would not fit, as far as 1)."""
    import struct

    if not np.all(np.isfinite(values)):
        raise ValueError(f"GPMF {key}: values that are not finite")
    largest = float(np.abs(values).max(initial=0.0))
    scale = float(max(1, min(int(scale), int(32767 // largest) if largest > 0 else int(scale))))
    raw = np.round(np.asarray(values, np.float64) * scale)
    if np.abs(raw).max(initial=0.0) > 32767:
        raise ValueError(f"GPMF {key}: values up to {largest:.4g} {unit} do not fit int16")
    body = (_text_klv("STNM", name) + _text_klv("SIUN", unit) + _klv("SCAL", "s", 2, 1, struct.pack(">h", int(scale)))
            + _text_klv("ORIO", "XYZ") + _klv(key, "s", 6, len(raw), raw.astype(">i2").tobytes()))
    return _klv("STRM", "\0", 1, len(body), body)


def gpmf_payload(gyro: np.ndarray, accel: np.ndarray, device: str = "bcmocap studio") -> bytes:
    """One GPMF payload (a ``DEVC`` with a gyro and an accelerometer stream in GoPro's IMU axes, ``ORIO XYZ``):
    ``gyro`` ``(N, 3)`` rad/s (scale 1000: ±32 rad/s in steps of 1 mrad/s, lower for faster turns), ``accel``
    ``(M, 3)`` m/s² (scale 100)."""
    import struct

    body = (_klv("DVID", "L", 4, 1, struct.pack(">I", 1)) + _text_klv("DVNM", device)
            + _sensor_stream("Gyroscope", "GYRO", "rad/s", gyro, 1000.0)
            + _sensor_stream("Accelerometer", "ACCL", "m/s\xb2", accel, 100.0))
    return _klv("DEVC", "\0", 1, len(body), body)


def write_gopro_file(source: str | os.PathLike, out: str | os.PathLike, gyro: SensorSamples, accel: SensorSamples,
                     *, device: str = "bcmocap studio") -> Path:
    """``source``'s video and audio (packets copied) with a GPMF track of ``gyro`` and ``accel`` (times in s after the
    file's first video frame, values in GoPro's IMU axes), a payload per second of the file as a GoPro writes it, into
    the MP4 ``out`` (written under a temporary name and renamed when complete; ValueError naming ``out``);
    :func:`read_gopro_imu` reads them back (to the int16 steps of :func:`gpmf_payload`)."""
    import av

    source, out = Path(source), Path(out)
    end = max(float(gyro.time_s[-1]), float(accel.time_s[-1]))
    origin_ms = int(round(1000 * _video_origin(source)))  # the times are after the first video frame, not the MP4's 0
    partial = out.with_name(f".{out.name}.partial")
    try:
        with av.open(str(source)) as media, av.open(str(partial), "w", format="mp4") as target:
            _mux_with_gpmf(media, target, gyro, accel, device, end, origin_ms)
        partial.replace(out)
    except ValueError as err:
        partial.unlink(missing_ok=True)
        raise ValueError(f"{out}: {err}") from None
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return out


def _mux_with_gpmf(media, target, gyro: SensorSamples, accel: SensorSamples, device: str, end: float,
                   origin_ms: int) -> None:
    """``media``'s video and audio packets, then a GPMF payload per second of samples, into ``target``."""
    import fractions

    import av

    streams = {s: target.add_stream_from_template(s) for s in (*media.streams.video, *media.streams.audio)}
    data = target.add_data_stream("bin_data")
    data.codec_tag = "gpmd"  # the mp4 muxer's GoPro metadata track ("GoPro MET")
    for packet in media.demux(list(streams)):
        if packet.dts is not None:
            packet.stream = streams[packet.stream]
            target.mux(packet)
    for second in range(int(np.floor(end)) + 1):
        g = (gyro.time_s >= second) & (gyro.time_s < second + 1)
        a = (accel.time_s >= second) & (accel.time_s < second + 1)
        if not (g.any() and a.any()):
            continue
        packet = av.Packet(gpmf_payload(gyro.values[g], accel.values[a], device))
        packet.stream = data
        packet.time_base = fractions.Fraction(1, 1000)
        packet.pts = packet.dts = origin_ms + 1000 * second
        # a second each; the last until its last sample's period ends (a file of one payload keeps its rate)
        last = float(gyro.time_s[g][-1]) + 1.0 / gyro.rate_hz - second
        packet.duration = 1000 if second + 1 <= end else max(1, int(round(1000 * min(last, 1.0))))
        target.mux(packet)
