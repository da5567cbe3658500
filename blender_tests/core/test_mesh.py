"""core.mesh: triangulation, OBJ round trip, user-facing errors (known answers)."""
import numpy as np
import pytest

from exclone_addon.core.mesh import (MeshError, PolyMesh, boundary_edges, check_mesh, read_obj,
                                     triangulate, vertex_parts, write_obj)


def test_fan_triangulation_of_mixed_polygons():
    totals = np.array([3, 4, 5])
    loops = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11])
    tris = triangulate(totals, loops)
    assert tris.tolist() == [[0, 1, 2], [3, 4, 5], [3, 5, 6], [7, 8, 9], [7, 9, 10], [7, 10, 11]]


def test_polygon_with_two_corners_is_an_error():
    with pytest.raises(MeshError, match="fewer than 3"):
        triangulate(np.array([2]), np.array([0, 1]))


def test_obj_round_trip_keeps_order_and_positions(tmp_path):
    rng = np.random.default_rng(0)
    mesh = PolyMesh.from_faces(rng.normal(size=(6, 3)), [[0, 1, 2, 3], [2, 3, 4], [4, 5, 0]])
    write_obj(tmp_path / "m.obj", mesh, header="test")
    back = read_obj(tmp_path / "m.obj")
    assert np.allclose(back.vertices, mesh.vertices, rtol=1e-6, atol=1e-7)
    assert [f.tolist() for f in back.faces()] == [f.tolist() for f in mesh.faces()]


def test_mesh_without_polygons_has_no_faces(tmp_path):
    mesh = PolyMesh(np.zeros((3, 3)), np.zeros(0, dtype=int), np.zeros(0, dtype=int))
    assert mesh.faces() == []
    write_obj(tmp_path / "points.obj", mesh)
    assert "f " not in (tmp_path / "points.obj").read_text()


def test_obj_face_referring_to_missing_vertex_is_an_error(tmp_path):
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")
    with pytest.raises(MeshError, match="does not exist"):
        read_obj(tmp_path / "bad.obj")


@pytest.mark.parametrize("text,message", [
    ("v \nv 1 0 0\n", "line 1: malformed vertex line"),
    ("v 0 0\nv 1 0\nv 0 1\n", "line 1: malformed vertex"),     # six numbers, not two vertices
    ("v 0 0 0\nv 1 zero 0\n", "line 2: malformed vertex"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 two 3\n", "line 4: malformed face"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n", "does not exist"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "does not exist"),   # OBJ counts from 1
])
def test_malformed_obj_lines_are_named(tmp_path, text, message):
    (tmp_path / "bad.obj").write_text(text)
    with pytest.raises(MeshError, match=message):
        read_obj(tmp_path / "bad.obj")


def test_obj_negative_indices_and_extra_vertex_values(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0 1 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2/5 -1//7\n")
    mesh = read_obj(tmp_path / "m.obj")
    assert mesh.vertices.shape == (3, 3) and mesh.faces()[0].tolist() == [0, 1, 2]


@pytest.mark.parametrize("vertices,triangles,message", [
    (np.zeros((0, 3)), np.zeros((0, 3), dtype=int), "empty"),
    (np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), "NaN"),
    (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]), "degenerate"),
])
def test_unusable_meshes_get_a_clear_message(vertices, triangles, message):
    with pytest.raises(MeshError, match=message):
        check_mesh(vertices, triangles, "target mesh")


def test_parts_and_open_borders():
    # two separate triangles: two parts, six border edges
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    parts = vertex_parts(7, tris)            # vertex 6 is on no triangle: a part of its own
    assert len(set(parts[:3])) == 1 and len(set(parts[3:6])) == 1
    assert len(set(parts)) == 3
    assert len(boundary_edges(tris)) == 6


def test_surface_answers_once_and_a_moved_copy_keeps_sign_and_connections():
    """core.surface.Surface: an open pyramid wound inwards, a separate triangle and a vertex on
    nothing; every answer is computed once, and a moved copy keeps sign, parts and borders."""
    from exclone_addon.core.mesh import diagonal, triangle_normals
    from exclone_addon.core.surface import Surface
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1],
                         [5, 0, 1], [6, 0, 1], [5, 1, 1], [9, 9, 9]])
    pyramid = [[0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]]
    surface = Surface(vertices, pyramid + [[5, 6, 7]])
    assert surface.search is surface.search and surface.vertex_normals is surface.vertex_normals
    assert surface.diagonal == diagonal(vertices, np.arange(8))       # vertex 8 is on nothing
    assert np.array_equal(surface.border_ids, [0, 1, 2, 3, 5, 6, 7])
    tent = surface.parts_holding([4])
    assert np.array_equal(tent.triangles, pyramid)
    assert surface.parts_holding([4, 5]) is surface
    # 4 base edges once, 4 slanted ones (length sqrt(1.5)) twice
    assert tent.mean_edge_length == pytest.approx((4 + 8 * np.sqrt(1.5)) / 12)
    # the outward sign turns the inward winding's normals out of the pyramid
    assert tent.sign == -1.0
    assert tent.triangle_normals[0] @ [0, -1, 0] > 0.5      # the face over the y = 0 edge
    np.testing.assert_allclose(tent.triangle_normals, -triangle_normals(vertices, tent.triangles))
    squashed = tent.moved(vertices * [1, 1, 0.01])          # moving never turns it inside out
    assert squashed.sign == tent.sign and squashed.border_edges is tent.border_edges
    assert tent.closest([[0.5, 0.5, 3.0]])[2][0] == pytest.approx(2.0)


# ------------------------------------------------------------------------------- OBJ reader
def reference_obj(path):
    """The plain reading read_obj must match: each line on its own, Python's float() and int()."""
    vertices, faces = [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            words = line.split()[1:]
            if line.startswith("v "):
                vertices.append([float(word) for word in words[:3]])
            elif line.startswith("f "):
                faces.append([int(word.split("/")[0]) for word in words])
    n = len(vertices)
    loops = [i + n if i < 0 else i - 1 for face in faces for i in face]
    return (np.array(vertices, dtype=np.float64).reshape(-1, 3),
            np.array([len(face) for face in faces], dtype=np.int64), np.array(loops, dtype=np.int64))


def assert_reads_as_reference(path):
    mesh, (vertices, totals, loops) = read_obj(path), reference_obj(path)
    assert np.array_equal(mesh.vertices, vertices, equal_nan=True)
    assert mesh.loop_totals.tolist() == totals.tolist()
    assert mesh.loop_vertices.tolist() == loops.tolist()
    assert mesh.vertices.dtype == np.float64 and mesh.loop_vertices.dtype == np.int64
    only = read_obj(path, faces=False)
    assert np.array_equal(only.vertices, vertices, equal_nan=True) and not len(only.loop_totals)


EVERY_SYNTAX = [
    # plain triangles, no newline at the end
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3",
    # v/vt/vn forms, mixed polygon sizes, negative ids, comments, groups, other records
    "# made by hand\nmtllib x.mtl\no head\nv 0 0 0\nv 1.5 0 0\nv 1 1 0\nv 0 1e-3 -2.25E+2\n"
    "vt 0 0\nvn 0 0 1\ng part\nusemtl skin\ns off\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -4//1 -3//1 -1//1\n"
    "f 2/1 3/1 4/1\nl 1 2\n",
    # CRLF and old-Mac line ends, tabs, repeated spaces, blank lines, a vertex colour
    "v 0 0 0 1 0 0\r\nv 1\t0 0\r\n\r\nv 0  1   0\rf 1 2 3\r\n",
    # the same corner count everywhere (numpy's reshape path) with four-number vertices
    "v 0 0 0 1\nv 1 0 0 1\nv 1 1 0 1\nv 0 1 0 1\nf 4 3 2 1\nf 1 2 3 4\n",
    # a line longer than the bulk reader takes, Python number spellings, a face without corners
    "v 0 0 0 " + "0 " * 150 + "\nv 1_0 +2 -0\nv inf -nan 1.\nf 1 2 3\nf \n",
    # indented lines are no records; a record's own word again inside a line
    "  v 9 9 9\nv 0 0 0 v\nv 1 0 0\nv 0 1 0\n f 9 9 9\nf 1 2 3\n",
    # vertices only
    "v 1 2 3\nv 4 5 6\n",
    # nothing at all
    "",
]


@pytest.mark.parametrize("text", EVERY_SYNTAX)
def test_obj_reader_matches_a_plain_reading(tmp_path, text):
    path = tmp_path / "m.obj"
    path.write_bytes(text.encode("utf-8"))
    assert_reads_as_reference(path)


def test_obj_reader_matches_a_plain_reading_of_real_files(shared_data):
    from exclone_addon.core import data
    paths = sorted(data.DATA_DIR.glob("*.obj")) + sorted(shared_data.rglob("*.obj"))
    assert len(paths) >= 10
    for path in paths:
        assert_reads_as_reference(path)


def test_vertices_only_skips_malformed_faces_but_not_vertices(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 two 3\nf 1 2 9\n")
    assert read_obj(path, faces=False).vertices.shape == (3, 3)
    with pytest.raises(MeshError, match="line 4: malformed face"):
        read_obj(path)
    path.write_text("v 0 0 0\nv 1 0\n")
    with pytest.raises(MeshError, match="line 2: malformed vertex"):
        read_obj(path, faces=False)
