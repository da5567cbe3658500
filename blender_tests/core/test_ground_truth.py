"""The ground-truth fixture itself (blender_tests/ground_truth.py): the remesh is a different,
clean mesh of the same surface, the lips stay apart, and the known answer is right."""
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from blender_tests.helpers import ground_truth as gt
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import triangle_areas, triangle_normals

ICT_FACE_VERTICES = 9409


@pytest.fixture(scope="module")
def library():
    """The bundled ICT-FaceKit library plus two expressions with an answer known in closed form."""
    lib = load_library()
    n = len(lib.mesh.vertices)
    names = list(lib.names) + ["zero", "shift"]
    deltas = np.concatenate([lib.deltas, np.zeros((1, n, 3)),
                             np.broadcast_to([0.3, -0.2, 0.5], (1, n, 3))])
    return lib, names, deltas


@pytest.fixture(scope="module")
def region(library):
    lib, names, deltas = library
    neutral, triangles = gt.face_region(lib.mesh.vertices, lib.mesh.loop_totals,
                                        lib.mesh.loop_vertices)
    half_open = 0.5 * deltas[names.index("jawOpen"), :ICT_FACE_VERTICES]
    return neutral, triangles, half_open


@pytest.fixture(scope="module")
def case(library):
    lib, names, deltas = library
    start = time.perf_counter()
    result = gt.make_case(lib.mesh.vertices, (lib.mesh.loop_totals, lib.mesh.loop_vertices),
                          names, deltas, seed=0, landmarks68=lib.landmarks68)
    result["seconds"] = time.perf_counter() - start
    R, s, t = result["similarity"]
    result["carried_back"] = gt.apply_similarity(result["target_vertices"],
                                                 *gt.invert_similarity(R, s, t))
    return result


def undirected_edges(triangles):
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                    triangles[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def corner_angles(vertices, triangles):
    """(F, 3) interior angles in degrees."""
    c = vertices[triangles]
    angles = []
    for j in range(3):
        a, b = c[:, (j + 1) % 3] - c[:, j], c[:, (j + 2) % 3] - c[:, j]
        cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(angles, axis=1)


def point_triangle_distances(points, corners):
    """Exact distance from each point to its triangle (points (m, 3), corners (m, 3, 3))."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    height = ((points - a) * normal).sum(1)
    foot = points - height[:, None] * normal
    inside = np.ones(len(points), dtype=bool)
    for p, q in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(q - p, foot - p) * normal).sum(1) >= 0
    edge_distances = []
    for p, q in ((a, b), (b, c), (c, a)):
        d = q - p
        u = np.clip(((points - p) * d).sum(1) / (d * d).sum(1), 0.0, 1.0)
        edge_distances.append(np.linalg.norm(points - (p + u[:, None] * d), axis=1))
    return np.where(inside, np.abs(height), np.min(edge_distances, axis=0))


def surface_distance(points, vertices, triangles):
    """Distance from each point to the closest of the triangles whose centroid is near it.

    A point on a triangle is within the longest edge of its centroid, so for points on (or
    very near) the surface this is the exact closest-point distance."""
    reach = np.linalg.norm(vertices[triangles] - vertices[np.roll(triangles, 1, axis=1)],
                           axis=2).max()
    near = cKDTree(vertices[triangles].mean(1)).query_ball_point(points, reach)
    point_ids = np.repeat(np.arange(len(points)), [len(n) for n in near])
    triangle_ids = np.concatenate(near).astype(np.int64)
    d = point_triangle_distances(points[point_ids], vertices[triangles[triangle_ids]])
    best = np.full(len(points), np.inf)
    np.minimum.at(best, point_ids, d)
    return best


def test_remesh_size_and_time(case):
    n = len(case["target_vertices"])
    assert 5000 <= n <= 10000
    assert case["seconds"] < 15.0, f"make_case took {case['seconds']:.1f} s"


def test_topology_is_new(case, region):
    _, triangles, _ = region
    assert len(case["target_vertices"]) != ICT_FACE_VERTICES
    assert len(case["target_triangles"]) != len(triangles)
    # almost no new vertex sits on a source vertex (the border resampling starts each loop on one)
    on_source_vertex = (case["barycentric"] > 1 - 1e-9).any(axis=1)
    assert on_source_vertex.sum() <= 10


def test_remesh_is_a_clean_surface_with_the_same_borders(case, region):
    neutral, triangles, _ = region
    new_tris = case["target_triangles"]
    n_new = len(case["target_vertices"])
    assert np.array_equal(np.unique(new_tris), np.arange(n_new)), "unused or missing vertices"
    edges, uses = undirected_edges(new_tris)
    assert uses.max() == 2, "an edge is shared by more than two triangles"
    source_edges, _ = undirected_edges(triangles)
    euler_new = n_new - len(edges) + len(new_tris)
    euler_source = ICT_FACE_VERTICES - len(source_edges) + len(triangles)
    assert euler_new == euler_source == -2          # one surface: outer border, mouth, two eyes
    new_loops, source_loops = gt.boundary_loops(new_tris), gt.boundary_loops(triangles)
    assert len(new_loops) == len(source_loops) == 4
    # every new border vertex lies on the source border (its weight is on one border edge)
    source_border_vertices = set(np.concatenate(source_loops).tolist())
    source_border_edges = {frozenset(e) for loop in source_loops
                           for e in zip(loop.tolist(), np.roll(loop, -1).tolist())}
    for v in np.concatenate(new_loops):
        support = case["source_triangle"][v][case["barycentric"][v] > 1e-12].tolist()
        assert (len(support) == 1 and support[0] in source_border_vertices) \
            or frozenset(support) in source_border_edges, f"new border vertex {v} is inside"
    # same orientation as the source surface
    carried = case["carried_back"]
    new_normals = triangle_normals(carried, new_tris)
    source_normals = triangle_normals(neutral, case["source_triangle"])
    agree = (new_normals * source_normals[new_tris[:, 0]]).sum(1) > 0
    assert agree.mean() > 0.99


def test_remesh_triangle_quality_and_coverage(case, region):
    neutral, triangles, half_open = region
    new_tris = case["target_triangles"]
    half_open_new = gt.evaluate_at(neutral + half_open, case["source_triangle"],
                                   case["barycentric"])
    # remeshed on the half-open mouth: isotropic there
    assert corner_angles(half_open_new, new_tris).min() > 15.0
    # carried back to the neutral, the closing mouth corners squeeze a few triangles
    neutral_min = corner_angles(case["carried_back"], new_tris).min(axis=1)
    assert neutral_min.min() > 3.0
    assert (neutral_min < 10.0).mean() < 0.001
    new_edges, _ = undirected_edges(new_tris)
    source_edges, _ = undirected_edges(triangles)
    carried = case["carried_back"]
    new_length = np.linalg.norm(carried[new_edges[:, 0]] - carried[new_edges[:, 1]], axis=1)
    source_length = np.linalg.norm(neutral[source_edges[:, 0]] - neutral[source_edges[:, 1]],
                                   axis=1)
    assert 0.9 < new_length.mean() / source_length.mean() < 1.6
    assert new_length.std() / new_length.mean() < 0.3      # the source's is 0.57
    # covers the source surface (the border chords cut off a sliver of it)
    area_ratio = triangle_areas(carried, new_tris).sum() / triangle_areas(neutral, triangles).sum()
    assert 0.97 < area_ratio <= 1.0 + 1e-9


def test_new_vertices_lie_on_the_neutral_surface(case, region):
    neutral, triangles, _ = region
    diagonal = np.linalg.norm(np.ptp(neutral, axis=0))
    distance = surface_distance(case["carried_back"], neutral, triangles)
    assert distance.max() < 1e-6 * diagonal


def test_surface_distance_detects_points_off_the_surface(region):
    neutral, triangles, _ = region
    normals = triangle_normals(neutral, triangles[:50])
    points = neutral[triangles[:50]].mean(1) + 0.01 * normals
    assert np.allclose(surface_distance(points, neutral, triangles), 0.01, rtol=0.05)


def test_lips_are_not_welded(case, library, region):
    lib, _, _ = library
    neutral, triangles, _ = region
    diagonal = np.linalg.norm(np.ptp(neutral, axis=0))
    side = gt.mouth_sides(neutral, triangles, lib.landmarks68[gt.ICT_INNER_LIP_LANDMARKS],
                          band=0.05 * diagonal, margin=0.01 * diagonal)
    corner_sides = side[case["source_triangle"]]
    new_side = np.where((corner_sides == corner_sides[:, :1]).all(1), corner_sides[:, 0], 0)
    assert (new_side == 1).sum() > 30 and (new_side == -1).sum() > 30, "lip labels are vacuous"

    def welded(new_triangles):
        s = new_side[new_triangles]
        return (s == 1).any(1) & (s == -1).any(1)

    assert not welded(case["target_triangles"]).any()
    # the check does catch a triangle across the mouth
    carried = case["carried_back"]
    upper, lower = np.flatnonzero(new_side == 1), np.flatnonzero(new_side == -1)
    pair = cKDTree(carried[lower]).query(carried[upper])
    closest_upper = np.argmin(pair[0])
    across = np.array([[upper[closest_upper], lower[pair[1][closest_upper]], upper[0]]])
    assert welded(across).all()


@pytest.mark.parametrize("seed", range(6))
def test_random_similarity_round_trips(seed):
    R, s, t = gt.random_similarity(seed, translation_scale=10.0)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.degrees(Rotation.from_matrix(R).magnitude()) <= 30.0 + 1e-9
    assert 0.5 <= s <= 2.0 and np.all(np.abs(t) <= 10.0)
    points = np.random.default_rng(seed).normal(size=(50, 3))
    moved = gt.apply_similarity(points, R, s, t)
    assert np.allclose(gt.apply_similarity(moved, *gt.invert_similarity(R, s, t)), points,
                       atol=1e-12)
    # a similarity keeps ratios of distances and moves the points for real
    d_before, d_after = np.linalg.norm(points[1:] - points[0], axis=1), \
        np.linalg.norm(moved[1:] - moved[0], axis=1)
    assert np.allclose(d_after, s * d_before)
    assert not np.allclose(moved, points)


def test_similarities_differ_between_seeds():
    angles = [Rotation.from_matrix(gt.random_similarity(seed)[0]).magnitude() for seed in range(6)]
    assert len(set(np.round(angles, 9))) == 6


def test_evaluate_at_reproduces_source_vertices(region, library, case):
    neutral, triangles, _ = region
    _, _, deltas = library
    region_deltas = deltas[:, :ICT_FACE_VERTICES]
    for corner in range(3):
        one_hot = np.zeros((len(triangles), 3))
        one_hot[:, corner] = 1.0
        assert np.array_equal(gt.evaluate_at(neutral, triangles, one_hot),
                              neutral[triangles[:, corner]])
        assert np.array_equal(gt.evaluate_at(region_deltas[:3], triangles, one_hot),
                              region_deltas[:3, triangles[:, corner]])
    # and in the case: new vertices that sit on a source vertex carry it back exactly
    weights = case["barycentric"]
    on_vertex = np.flatnonzero(weights.max(1) == 1.0)
    assert len(on_vertex) > 0
    source_ids = case["source_triangle"][on_vertex, weights[on_vertex].argmax(1)]
    assert np.allclose(case["carried_back"][on_vertex], neutral[source_ids], rtol=0, atol=1e-12)


def test_evaluate_at_interpolates_linearly(region):
    neutral, triangles, _ = region
    weights = np.random.default_rng(0).dirichlet(np.ones(3), size=len(triangles))
    expected = (weights[:, :, None] * neutral[triangles]).sum(1)
    assert np.allclose(gt.evaluate_at(neutral, triangles, weights), expected, atol=1e-12)


def test_truth_deltas_follow_the_similarity(case, library):
    _, names, deltas = library
    R, s, t = case["similarity"]
    truth = case["truth_deltas"]
    assert truth.shape == (len(names), len(case["target_vertices"]), 3)
    scale = np.abs(case["target_vertices"]).max()
    assert np.abs(truth[names.index("zero")]).max() < 1e-12 * scale
    # a rigid shift of the source is the same shift, rotated and scaled, everywhere
    assert np.allclose(truth[names.index("shift")], s * R @ np.array([0.3, -0.2, 0.5]),
                       rtol=0, atol=1e-9 * scale)
    # jawOpen: the similarity keeps the length of every displacement up to the scale
    jaw = names.index("jawOpen")
    source_jaw = gt.evaluate_at(deltas[jaw, :ICT_FACE_VERTICES], case["source_triangle"],
                                case["barycentric"])
    assert np.allclose(np.linalg.norm(truth[jaw], axis=1), s * np.linalg.norm(source_jaw, axis=1),
                       rtol=0, atol=1e-9 * scale)
    assert np.linalg.norm(truth[jaw], axis=1).max() > 1.0 * s   # jawOpen moves the chin ~4 cm


def test_target_landmarks_sit_on_the_source_landmarks(case, region):
    neutral, _, _ = region
    carried = case["carried_back"]
    gap = np.linalg.norm(carried[case["target_landmarks"]] - neutral[case["source_landmarks"]],
                         axis=1)
    edges, _ = undirected_edges(case["target_triangles"])
    mean_edge = np.linalg.norm(carried[edges[:, 0]] - carried[edges[:, 1]], axis=1).mean()
    assert gap.max() < mean_edge


def test_relative_error():
    truth = np.random.default_rng(1).normal(size=(3, 40, 3))
    truth[1] = 0.0
    errors = gt.relative_error(1.1 * truth, truth)
    assert np.isclose(errors[0], 0.1) and np.isclose(errors[2], 0.1)
    assert np.isnan(errors[1])
    assert np.array_equal(gt.relative_error(truth, truth)[[0, 2]], [0.0, 0.0])
    offset = truth + 5.0              # a constant offset is an error too
    assert gt.relative_error(offset, truth)[0] > 1.0
    with pytest.raises(ValueError):
        gt.relative_error(truth[:, :10], truth)


def test_remesh_is_deterministic_per_seed(case, region):
    neutral, triangles, half_open = region
    again = gt.remesh_face_region(neutral, triangles, half_open, seed=0)
    assert np.array_equal(again[1], case["target_triangles"])
    assert np.array_equal(again[3], case["barycentric"])
    other = gt.remesh_face_region(neutral, triangles, half_open, seed=1)
    assert len(other[0]) != len(again[0]) or not np.allclose(other[0], again[0])


def test_make_case_needs_jaw_open(library):
    lib, names, deltas = library
    renamed = ["mouthOpen" if name == "jawOpen" else name for name in names]
    with pytest.raises(ValueError, match="jawOpen"):
        gt.make_case(lib.mesh.vertices, (lib.mesh.loop_totals, lib.mesh.loop_vertices), renamed,
                     deltas, seed=0)
