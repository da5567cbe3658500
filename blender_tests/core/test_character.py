"""core/character: the head cut out of a mesh (its cut held still, results spread back), the
guide's cross-check of the landmarks against FaceMesh's points, and the separate parts kept with
the head. Known answers on small hand-made meshes (the face finding itself is tested on the
shared characters)."""
import numpy as np

from exclone_addon.core.character import (FAR_FROM_FACEMESH, FaceGuide, _with_inner_parts,
                                          head_cut)
from exclone_addon.core.mesh import PolyMesh
from exclone_addon.core.orientation import FaceFrame


def grid(columns, rows):
    """A (columns x rows) grid of unit quads in the x-z plane, vertex id = row * (columns+1) + col."""
    xs, zs = np.meshgrid(np.arange(columns + 1), np.arange(rows + 1))
    vertices = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1).astype(float)
    faces = [[r * (columns + 1) + c, r * (columns + 1) + c + 1, (r + 1) * (columns + 1) + c + 1,
              (r + 1) * (columns + 1) + c] for r in range(rows) for c in range(columns)]
    return PolyMesh.from_faces(vertices, faces)


def test_the_head_is_the_polygons_wholly_inside_and_its_cut_is_held():
    mesh = grid(3, 4)
    region = mesh.vertices[:, 2] >= 2          # rows 2..4 of vertices: the top two rows of quads
    head = head_cut(mesh, region)
    assert len(head.mesh.loop_totals) == 6
    assert head.vertex_ids.tolist() == list(range(8, 20))
    # the cut: the vertices the head shares with the quads below it (z = 2)
    assert sorted(head.own_ids(head.fixed).tolist()) == [8, 9, 10, 11]
    assert np.array_equal(head.mesh.vertices, mesh.vertices[head.vertex_ids])
    deltas = np.ones((2, len(head.vertex_ids), 3))
    whole = head.spread(deltas)
    assert whole.shape == (2, 20, 3)
    assert np.all(whole[:, :8] == 0) and np.all(whole[:, 8:] == 1)
    assert head.head_ids([8, 19]).tolist() == [0, 11]
    assert head.head_ids([3, 9]) is None       # vertex 3 lies below the cut


def test_a_region_vertex_on_no_inside_polygon_stays_out():
    mesh = grid(2, 2)
    region = np.zeros(9, dtype=bool)
    region[[0, 1, 3, 4, 5]] = True             # one whole quad (0,1,4,3) and a stray vertex 5
    head = head_cut(mesh, region)
    assert head.vertex_ids.tolist() == [0, 1, 3, 4]
    assert sorted(head.own_ids(head.fixed).tolist()) == [1, 3, 4]


def guide_on(points, eye_distance=1.0):
    return FaceGuide(FaceFrame(np.eye(3), np.zeros(3), 10.0, 0.0), points, eye_distance)


def test_a_landmark_far_across_the_face_is_replaced_by_the_front_most_vertex_on_the_ray():
    # the skin at x = 0 (two layers: the front one at z = 1, a deeper one at z = 0) and at x = 1
    vertices = np.array([[0, 0, 1.0], [0, 0, 0.0], [1, 0, 1.0], [1, 0, 0.0]])
    guide = guide_on({"nose_tip": np.array([0, 0, 0.2]), "eye_outer_left": np.array([1, 0, -3.0])})
    names, ids = guide.cross_checked(["nose_tip", "eye_outer_left"], [2, 2], vertices,
                                     np.arange(4))
    found = dict(zip(names, ids.tolist()))
    # nose_tip was 1 eye distance across from FaceMesh's: the front-most vertex on the ray
    assert found["nose_tip"] == 0
    # eye_outer_left is 4 eye distances deeper but not across: geometry's is kept
    assert found["eye_outer_left"] == 2


def test_a_landmark_within_the_limit_is_kept_and_a_missing_one_is_taken_from_facemesh():
    vertices = np.array([[0, 0, 0.0], [0.5 * FAR_FROM_FACEMESH, 0, 0], [0, 5, 0]])
    guide = guide_on({"nose_tip": np.zeros(3), "chin": np.array([0, 5, -1.0])})
    names, ids = guide.cross_checked(["nose_tip"], [1], vertices, np.arange(3))
    assert dict(zip(names, ids.tolist())) == {"nose_tip": 1, "chin": 2}
    assert names == ["nose_tip", "chin"]       # in landmarks.NAMES order


def test_separate_parts_inside_the_heads_box_are_kept_with_it():
    head = grid(4, 4)
    eye = PolyMesh.from_faces(np.array([[1.2, 0, 2.2], [1.8, 0, 2.2], [1.5, 0, 2.8]]),
                              [[0, 1, 2]])
    prop = PolyMesh.from_faces(np.array([[9.0, 0, 0], [10, 0, 0], [9, 0, 1]]), [[0, 1, 2]])
    count = len(head.vertices)
    mesh = PolyMesh(np.vstack([head.vertices, eye.vertices, prop.vertices]),
                    np.concatenate([head.loop_totals, eye.loop_totals, prop.loop_totals]),
                    np.concatenate([head.loop_vertices, eye.loop_vertices + count,
                                    prop.loop_vertices + count + 3]))
    region = np.zeros(len(mesh.vertices), dtype=bool)
    region[:count] = True
    region[np.flatnonzero(mesh.vertices[:count, 2] < 1)] = False   # below the cut
    kept = _with_inner_parts(mesh, mesh.triangles(), region)
    assert kept[count:count + 3].all()         # the eye, inside the head's box
    assert not kept[count + 3:].any()          # the prop, far outside
    assert np.array_equal(kept[:count], region[:count])
