"""PLY output: round trips (ascii and binary), colours, camera paths with NaN, hand-parsed headers, plyfile."""

from __future__ import annotations

import numpy as np
import pytest

from bcmocap.io.ply import (
    read_ply,
    read_ply_elements,
    write_camera_paths_ply,
    write_ply,
    write_ply_pieces,
)


def header_of(path) -> list[str]:
    """Header lines, parsed by hand (independent of bcmocap's reader)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii").splitlines()


def element_counts(lines: list[str]) -> dict[str, int]:
    return {w[1]: int(w[2]) for w in (line.split() for line in lines) if w[0] == "element"}


def random_cloud(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * [5.0, 5.0, 1.0], rng.integers(0, 256, size=(n, 3), dtype=np.uint8)


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("double", [True, False])
def test_round_trip_with_colours(tmp_path, binary, double):
    pts, rgb = random_cloud()
    path = write_ply(tmp_path / "scene.ply", pts, rgb, binary=binary, double=double)
    lines = header_of(path)
    assert lines[0] == "ply"
    assert lines[1] == ("format binary_little_endian 1.0" if binary else "format ascii 1.0")
    assert element_counts(lines) == {"vertex": 50}
    ptype = "double" if double else "float"
    props = [line for line in lines if line.startswith("property")]
    assert props == [f"property {ptype} {a}" for a in "xyz"] + [f"property uchar {c}" for c in ("red", "green", "blue")]
    back, back_rgb = read_ply(path)
    if double:
        np.testing.assert_array_equal(back, pts)  # exact for float64 in both encodings
    else:
        np.testing.assert_array_equal(back, pts.astype(np.float32).astype(np.float64))
    assert back_rgb.dtype == np.uint8
    np.testing.assert_array_equal(back_rgb, rgb)
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]  # no temporary file left


def test_binary_size_and_layout(tmp_path):
    pts, rgb = random_cloud(7)
    path = write_ply(tmp_path / "a.ply", pts, rgb)
    data = path.read_bytes()
    body = data[data.index(b"end_header\n") + len(b"end_header\n") :]
    assert len(body) == 7 * (3 * 8 + 3)
    rows = np.frombuffer(body, dtype=[("p", "<f8", 3), ("c", "u1", 3)])
    np.testing.assert_array_equal(rows["p"], pts)
    np.testing.assert_array_equal(rows["c"], rgb)


def test_without_colours_and_empty(tmp_path):
    pts, _ = random_cloud(5)
    back, rgb = read_ply(write_ply(tmp_path / "p.ply", pts, binary=False))
    assert rgb is None
    np.testing.assert_array_equal(back, pts)
    back, rgb = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3))))
    assert back.shape == (0, 3) and rgb is None


def test_overwrite_replaces_file(tmp_path):
    path = tmp_path / "s.ply"
    write_ply(path, np.ones((10, 3)))
    write_ply(path, np.zeros((3, 3)), binary=False)
    back, _ = read_ply(path)
    np.testing.assert_array_equal(back, np.zeros((3, 3)))


def test_write_errors(tmp_path):
    pts, rgb = random_cloud(4)
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        write_ply(tmp_path / "x.ply", pts[:, :2])
    bad = pts.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf in 1 of 4 rows.*row 2"):
        write_ply(tmp_path / "x.ply", bad)
    with pytest.raises(ValueError, match=r"colors must have shape \(4, 3\)"):
        write_ply(tmp_path / "x.ply", pts, rgb[:3])
    with pytest.raises(ValueError, match="colors must be integers"):
        write_ply(tmp_path / "x.ply", pts, rgb / 255.0)
    with pytest.raises(ValueError, match="0..255"):
        write_ply(tmp_path / "x.ply", pts, np.full((4, 3), 256))
    with pytest.raises(ValueError, match="0..255"):
        write_ply(tmp_path / "x.ply", pts, np.full((4, 3), -1))
    assert not (tmp_path / "x.ply").exists()


def test_points_written_in_pieces_equal_write_ply(tmp_path):
    rng = np.random.default_rng(5)
    points = rng.normal(size=(1000, 3))
    write_ply_pieces(tmp_path / "pieces.ply", 1000, (points[a:a + 300] for a in range(0, 1000, 300)))
    write_ply(tmp_path / "whole.ply", points)
    assert (tmp_path / "pieces.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    with pytest.raises(ValueError, match="the pieces hold 999 points, the header says 1000"):
        write_ply_pieces(tmp_path / "pieces.ply", 1000, [points[:999]])
    with pytest.raises(ValueError, match="the pieces hold more than 10 points, the header says 10"):
        write_ply_pieces(tmp_path / "short.ply", 10, [points[:11]])
    assert not (tmp_path / "short.ply").exists()
    bad = points[:5].copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf in 1 of 5 rows"):
        write_ply_pieces(tmp_path / "bad.ply", 5, [bad])
    np.testing.assert_array_equal(read_ply(tmp_path / "pieces.ply")[0], points)


def test_read_errors_name_the_file(tmp_path):
    not_ply = tmp_path / "notes.ply"
    not_ply.write_text("hello\n")
    with pytest.raises(ValueError, match="notes.ply: not a PLY file"):
        read_ply(not_ply)
    big = tmp_path / "big.ply"
    big.write_bytes(b"ply\nformat binary_big_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n")
    with pytest.raises(ValueError, match="big.ply:2: format 'binary_big_endian' is not supported"):
        read_ply(big)
    short = tmp_path / "short.ply"
    write_ply(short, np.ones((4, 3)))
    short.write_bytes(short.read_bytes()[:-5])
    with pytest.raises(ValueError, match="short.ply: the file ends inside element 'vertex'"):
        read_ply(short)
    short_ascii = tmp_path / "short_ascii.ply"
    write_ply(short_ascii, np.ones((4, 3)), binary=False)
    short_ascii.write_text(short_ascii.read_text().rsplit("\n", 2)[0] + "\n")
    with pytest.raises(ValueError, match="short_ascii.ply: the file ends inside element 'vertex'"):
        read_ply(short_ascii)
    no_xyz = tmp_path / "noxyz.ply"
    no_xyz.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n")
    with pytest.raises(ValueError, match="noxyz.ply: the vertex element has no x/y/z property"):
        read_ply(no_xyz)
    bad_num = tmp_path / "badnum.ply"
    bad_num.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 two 3\n")
    with pytest.raises(ValueError, match="badnum.ply: element 'vertex' holds a value that is not a number"):
        read_ply(bad_num)


def test_reads_mesh_with_faces_after_vertices(tmp_path):
    """A typical mesh file (faces as list properties after the vertices) still yields its vertices."""
    mesh = tmp_path / "mesh.ply"
    mesh.write_text(
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0.5\n3 0 1 2\n"
    )
    pts, rgb = read_ply(mesh)
    np.testing.assert_array_equal(pts, [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]])
    assert rgb is None


# ---- camera paths -----------------------------------------------------------------------------------


def camera_paths():
    t = np.linspace(0, 1, 6)
    centres = np.stack(
        [np.stack([t, np.zeros(6), np.ones(6)], 1), np.stack([np.zeros(6), t, 2 * np.ones(6)], 1), np.full((6, 3), np.nan)],
        axis=1,
    )  # (6, 3, 3): camera 2 never registered
    centres[2, 0, 1] = np.nan  # camera 0 misses frame 2 (one NaN coordinate is enough)
    centres[5, 1] = np.nan  # camera 1 misses the last frame
    return centres


@pytest.mark.parametrize("binary", [True, False])
def test_camera_paths_vertices_and_edges(tmp_path, binary):
    centres = camera_paths()
    path = write_camera_paths_ply(tmp_path / "cams.ply", centres, binary=binary)
    lines = header_of(path)
    # 5 + 5 valid centres; edges: camera 0 frames 0-1, 3-4, 4-5; camera 1 frames 0-1 … 3-4.
    assert element_counts(lines) == {"vertex": 10, "edge": 7}
    assert lines[-4:] == ["element edge 7", "property int vertex1", "property int vertex2", "end_header"]
    elements = read_ply_elements(path)
    v, e = elements["vertex"], elements["edge"]
    np.testing.assert_array_equal(v["camera"], [0] * 5 + [1] * 5)
    np.testing.assert_array_equal(v["frame"], [0, 1, 3, 4, 5, 0, 1, 2, 3, 4])
    pts = np.stack([v["x"], v["y"], v["z"]], 1)
    np.testing.assert_array_equal(pts, centres[v["frame"], v["camera"]])
    edges = np.stack([e["vertex1"], e["vertex2"]], 1)
    np.testing.assert_array_equal(edges, [[0, 1], [2, 3], [3, 4], [5, 6], [6, 7], [7, 8], [8, 9]])
    # every edge joins adjacent frames of one camera
    assert np.all(v["camera"][edges[:, 0]] == v["camera"][edges[:, 1]])
    assert np.all(v["frame"][edges[:, 1]] - v["frame"][edges[:, 0]] == 1)
    back, rgb = read_ply(path)
    np.testing.assert_array_equal(back, pts)
    assert len({tuple(c) for c in rgb[:5]}) == 1 and tuple(rgb[0]) != tuple(rgb[5])


def test_camera_paths_bridge_gaps_and_colours(tmp_path):
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    path = write_camera_paths_ply(tmp_path / "c.ply", camera_paths(), colors_per_camera=colours, bridge_gaps=True)
    elements = read_ply_elements(path)
    edges = np.stack([elements["edge"]["vertex1"], elements["edge"]["vertex2"]], 1)
    np.testing.assert_array_equal(edges, [[0, 1], [1, 2], [2, 3], [3, 4], [5, 6], [6, 7], [7, 8], [8, 9]])
    _, rgb = read_ply(path)
    np.testing.assert_array_equal(rgb, [[255, 0, 0]] * 5 + [[0, 255, 0]] * 5)


def test_camera_paths_errors_and_all_missing(tmp_path):
    with pytest.raises(ValueError, match=r"centres must have shape \(T, C, 3\)"):
        write_camera_paths_ply(tmp_path / "c.ply", np.zeros((4, 3)))
    inf = np.zeros((2, 1, 3))
    inf[1, 0, 0] = np.inf
    with pytest.raises(ValueError, match="inf"):
        write_camera_paths_ply(tmp_path / "c.ply", inf)
    with pytest.raises(ValueError, match=r"colors_per_camera must have shape \(2, 3\)"):
        write_camera_paths_ply(tmp_path / "c.ply", np.zeros((3, 2, 3)), colors_per_camera=np.zeros((3, 3), np.uint8))
    path = write_camera_paths_ply(tmp_path / "none.ply", np.full((4, 2, 3), np.nan), binary=False)
    assert element_counts(header_of(path)) == {"vertex": 0, "edge": 0}
    pts, rgb = read_ply(path)
    assert pts.shape == (0, 3) and rgb.shape == (0, 3)


# ---- an independent reader --------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
def test_plyfile_reads_our_files(tmp_path, binary):
    plyfile = pytest.importorskip("plyfile")
    pts, rgb = random_cloud(20, seed=4)
    ply = plyfile.PlyData.read(str(write_ply(tmp_path / "s.ply", pts, rgb, binary=binary)))
    assert ply.text is (not binary)
    vertex = ply["vertex"]
    assert vertex.count == 20
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), pts)
    np.testing.assert_array_equal(np.stack([vertex["red"], vertex["green"], vertex["blue"]], 1), rgb)
    assert vertex["red"].dtype == np.uint8

    centres = camera_paths()
    ply = plyfile.PlyData.read(str(write_camera_paths_ply(tmp_path / "c.ply", centres, binary=binary)))
    assert [e.name for e in ply.elements] == ["vertex", "edge"]
    assert ply["vertex"].count == 10 and ply["edge"].count == 7
    v1, v2 = ply["edge"]["vertex1"], ply["edge"]["vertex2"]
    cams = ply["vertex"]["camera"]
    assert np.all(cams[v1] == cams[v2])
    frames = ply["vertex"]["frame"]
    np.testing.assert_array_equal(ply["vertex"]["x"], centres[frames, cams, 0])


@pytest.mark.parametrize("text", [True, False])
def test_reads_files_written_by_plyfile(tmp_path, text):
    plyfile = pytest.importorskip("plyfile")
    pts, rgb = random_cloud(9, seed=5)
    rows = np.empty(9, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, axis in enumerate("xyz"):
        rows[axis] = pts[:, k]
    rows["nx"] = 1.0
    rows["red"], rows["green"], rows["blue"] = rgb.T
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(rows, "vertex"), plyfile.PlyElement.describe(faces, "face")], text=text
    )
    path = tmp_path / "theirs.ply"
    ply.write(str(path))
    back, back_rgb = read_ply(path)
    np.testing.assert_array_equal(back, pts.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(back_rgb, rgb)
