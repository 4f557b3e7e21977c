"""C3D reading through ezc3d: a real file (units, rate, labels, gaps) and files written here (bad input)."""

from pathlib import Path

import ezc3d
import numpy as np
import pytest

from bcmocap.io import read_c3d

DATA = Path(__file__).parent / "data" / "c3d"
SAMPLE = DATA / "BTKData_c3d.org_sample01_Eb015pr.c3d"


def write_c3d(path, positions_m, labels, rate=100.0, units="mm"):
    """A C3D file of ``(F, M, 3)`` positions (m, NaN gaps) in the given unit."""
    scale = {"mm": 1000.0, "cm": 100.0, "m": 1.0}[units]
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    p = np.asarray(positions_m, float) * scale
    data = np.ones((4, p.shape[1], p.shape[0]))
    data[:3] = np.transpose(p, (2, 1, 0))
    c["data"]["points"] = data
    c.write(str(path))
    return path


def test_real_file_units_rate_labels():
    d = read_c3d(SAMPLE)
    assert d.frame_rate_hz == 50.0 and d.units == "mm"
    assert d.positions.shape == (450, 26, 3)  # POINT:USED = 26 although 48 labels are declared
    assert d.labels[:3] == ("RFT1", "RFT2", "RFT3") and d.labels[-1] == "pv4"
    # millimetres became metres: a lab-sized capture volume, feet near the floor
    assert 0.5 < np.nanmax(np.abs(d.positions)) < 5.0
    assert np.nanmin(d.positions[..., 2]) < 0.1
    # invalid samples (negative residual) are NaN gaps, and there are some in this file
    assert np.isnan(d.positions).any() and np.isfinite(d.positions).mean() > 0.9
    # the distance between two markers of the same foot is a few centimetres
    dist = np.linalg.norm(d.positions[:, 0] - d.positions[:, 1], axis=-1)
    assert 0.02 < np.nanmedian(dist) < 0.3


@pytest.mark.parametrize("units", ["mm", "cm", "m"])
def test_units_are_converted_to_metres(tmp_path, units):
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, size=(20, 3, 3))
    p[5, 1] = np.nan
    d = read_c3d(write_c3d(tmp_path / "t.c3d", p, ["A", "B", "C"], rate=240.0, units=units))
    assert d.frame_rate_hz == 240.0
    np.testing.assert_allclose(d.positions[np.isfinite(p)], p[np.isfinite(p)], atol=1e-5)
    assert np.isnan(d.positions[5, 1]).all()


def test_marker_selection_and_subject_prefix(tmp_path):
    p = np.random.default_rng(1).uniform(size=(10, 3, 3))
    path = write_c3d(tmp_path / "t.c3d", p, ["Bob:A", "Bob:B", "Bob:LFEO"])
    d = read_c3d(path)
    assert d.labels == ("Bob:A", "Bob:B") and d.excluded == ("Bob:LFEO",)  # a Plug-in Gait bone point
    assert read_c3d(path, keep_modelled=True).positions.shape[1] == 3
    d = read_c3d(path, markers=["B", "Bob:A"])
    assert d.labels == ("Bob:B", "Bob:A")
    np.testing.assert_allclose(d.positions[:, 0], p[:, 1], atol=1e-5)
    with pytest.raises(ValueError, match=r"no marker labelled \['Z'\]"):
        read_c3d(path, markers=["Z"])


def test_computed_points_of_other_systems_are_left_out(tmp_path):
    from bcmocap.io.c3d import MODELLED_POINT_PATTERN

    p = np.random.default_rng(2).uniform(size=(10, 4, 3))
    d = read_c3d(write_c3d(tmp_path / "t.c3d", p, ["RKNE", "VMID", "VMID", "RKNE"]))  # labels repeated, as MAC's
    assert d.labels == ("RKNE", "RKNE#2") and d.excluded == ("VMID", "VMID#2")

    # Motion Analysis's Helen Hayes virtual points and OpenSim's joint centres are computed, not seen
    for label in ("VSAC", "VMID", "VPEL", "VRHI", "VLKN", "VRAN", "VLHA", "VRTO", "VRHE", "LHJC", "RKJC", "RAJC"):
        assert MODELLED_POINT_PATTERN.match(label), label
    # markers with similar names are kept
    for label in ("V1", "VRBAC", "RHEE", "LKNE", "RASI", "LFHD", "VCLAV", "RHJ", "L_HJC2"):
        assert not MODELLED_POINT_PATTERN.match(label), label


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_c3d(tmp_path / "missing.c3d")
    junk = tmp_path / "junk.c3d"
    junk.write_bytes(b"not a c3d file" * 20)
    with pytest.raises(ValueError, match="junk.c3d: not a readable C3D file"):
        read_c3d(junk)
    # 100 frames but no 3D point
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100]
    c["data"]["points"] = np.zeros((4, 0, 100))
    c.write(str(tmp_path / "empty.c3d"))
    with pytest.raises(ValueError, match="empty.c3d: the C3D file has no 3D points"):
        read_c3d(tmp_path / "empty.c3d")
    p = np.zeros((5, 1, 3)) + 0.5
    path = write_c3d(tmp_path / "furlong.c3d", p, ["A"])
    c = ezc3d.c3d(str(path))
    c["parameters"]["POINT"]["UNITS"]["value"] = ["furlong"]
    c.write(str(path))
    with pytest.raises(ValueError, match="POINT:UNITS is 'furlong'"):
        read_c3d(path)


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.95])
def test_a_truncated_file_is_refused_not_read_short(tmp_path, fraction):
    """ezc3d reads a truncated file's complete frames and adjusts the header it returns; the raw header's
    frame count gives the truncation away."""
    data = SAMPLE.read_bytes()
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(ValueError, match=r"cut\.c3d: truncated: the header announces 450 frames, the file holds"):
        read_c3d(cut)


def test_a_header_whose_analog_frame_size_differs_from_the_parameters_is_refused(tmp_path):
    # c3d.org's EVaRT sample says 476 analog values a frame (28 channels x 17) where ANALOG:RATE / POINT:RATE gives
    # 16 samples: read by the parameters, every frame after the first came from the wrong bytes (garbled points).
    import shutil
    import struct

    source = Path(__file__).parent / "data" / "c3d" / "BTKData_c3d.org_sample01_Eb015pr.c3d"  # 16 channels x 4
    assert read_c3d(source).positions.shape == (450, 26, 3)
    bad = tmp_path / "bad.c3d"
    shutil.copyfile(source, bad)
    with open(bad, "r+b") as f:
        f.seek(4)
        f.write(struct.pack("<H", 16 * 5))
    with pytest.raises(ValueError, match=r"bad\.c3d: the header puts 80 analog values in each frame, the ANALOG "
                                         r"parameters 16 channels × 4 samples"):
        read_c3d(bad)
