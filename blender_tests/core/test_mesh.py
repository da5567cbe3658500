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
