"""Deformation gradients, transfer, the reused-ordering solver and closest points: known answers.

An affine map has the same gradient on every triangle, so the operators can be checked exactly
without any reference implementation: augmented gradient = A, reduced gradient = A projected on
the triangle's plane (A V V^+).
"""

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from exclone_addon.core import data, deformation, transfer
from exclone_addon.core import mesh as mesh_module
from exclone_addon.core.cloning import fit_faces, transfer_expressions
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import read_obj, triangle_normals, vertex_adjacency
from exclone_addon.core.proximity import TriangleSurface, closest_points_on_triangles
from exclone_addon.core.registration import ReusedOrderingSolver
from exclone_addon.core.transfer import Transfer

DEMO_HEAD = data.DEMO_HEAD_FILE
FORMULATIONS = deformation.FORMULATIONS


@pytest.fixture(scope="module")
def head():
    """The bundled demo head (4,244 vertices, a real, curved, non-uniform mesh)."""
    mesh = read_obj(DEMO_HEAD)
    return np.asarray(mesh.vertices, dtype=np.float64), mesh.triangles()


@pytest.fixture(scope="module")
def affine():
    rng = np.random.default_rng(7)
    a = np.eye(3) + 0.4 * rng.normal(size=(3, 3))
    assert abs(np.linalg.det(a)) > 0.1
    return a, rng.normal(size=3)


def full_gradients(rest, deformed, triangles):
    """deformation.corner_gradients of a mesh: rest (n, 3) to deformed (n, 3) or (E, n, 3) ->
    (T|E,T, 3, 3)."""
    return deformation.corner_gradients(rest[triangles], np.asarray(deformed)[..., triangles, :])


def blocks(stacked):
    """(3T, 3) in the operators' layout -> (T, 3, 3) gradients Q_j (undo the per-block transpose)."""
    return np.swapaxes(np.asarray(stacked).reshape(-1, 3, 3), 1, 2)


def plane_projections(vertices, triangles):
    """P_j = V_j V_j^+ (3x3): the orthogonal projection onto each triangle's plane."""
    n = triangle_normals(vertices, triangles)
    return np.eye(3) - n[:, :, None] * n[:, None, :]


def with_degenerate(vertices, triangles):
    """The mesh plus a collinear triangle and one with a repeated corner (both on new vertices)."""
    n = len(vertices)
    extra = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [3.0, 0.0, 1.0]]) + 10
    tris = np.vstack([triangles, [[n, n + 1, n + 2], [n + 3, n + 3, n]]])
    return np.vstack([vertices, extra]), tris


def test_augmented_operator_gives_the_affine_map_on_every_triangle(head, affine):
    v, tris = head
    a, t = affine
    g, ok = deformation.gradient_operator(v, tris, deformation.AUGMENTED)
    assert ok.all() and g.shape == (3 * len(tris), len(v) + len(tris))
    unknowns = deformation.unknowns_of(v, tris, deformation.AUGMENTED)
    q = blocks(g @ (unknowns @ a.T + t))
    np.testing.assert_allclose(q, np.broadcast_to(a, q.shape), atol=1e-8)
    # rest shape: identity on every triangle, exactly what stacked_identity stands for
    np.testing.assert_allclose(g @ unknowns, deformation.stacked_identity(len(tris)), atol=1e-9)


def test_reduced_operator_gives_the_affine_map_projected_on_each_plane(head, affine):
    v, tris = head
    a, t = affine
    g, ok = deformation.gradient_operator(v, tris, deformation.REDUCED)
    assert ok.all() and g.shape == (3 * len(tris), len(v))
    q = blocks(g @ (v @ a.T + t))
    expected = a @ plane_projections(v, tris)
    np.testing.assert_allclose(q, expected, atol=1e-8)
    # the reduced gradient drops the normal direction: Q n = 0
    n = triangle_normals(v, tris)
    assert np.abs(np.einsum("tij,tj->ti", q, n)).max() < 1e-8


def test_stacked_layout_round_trips_gradients(head, affine):
    v, tris = head
    a, t = affine
    q = full_gradients(v, v @ a.T + t, tris[:50])
    stacked = deformation.stack_gradients(q)
    assert stacked.shape == (150, 3)
    # (G @ X)[3j + c, r] = Q_j[r, c]
    j, r, c = 17, 2, 0
    assert stacked[3 * j + c, r] == q[j, r, c]
    np.testing.assert_array_equal(blocks(stacked), q)
    batch = deformation.stack_gradients(np.stack([q, 2 * q]))
    assert batch.shape == (2, 150, 3)
    np.testing.assert_array_equal(batch[1], 2 * stacked)


def test_full_gradients_of_a_similarity_equal_it(head):
    v, tris = head
    rotation = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    s = 1.7
    q = full_gradients(v, s * v @ rotation.T + [1.0, -2.0, 3.0], tris)
    np.testing.assert_allclose(q, np.broadcast_to(s * rotation, q.shape), atol=1e-8)


def test_full_gradients_of_an_affine_map_match_it_in_plane(head, affine):
    """Sumner's 4th vertex is rebuilt from the deformed normal, so for a general affine map only
    the in-plane action is A; the normal goes to the deformed triangle's normal."""
    v, tris = head
    a, t = affine
    deformed = v @ a.T + t
    q = full_gradients(v, deformed, tris)
    p = plane_projections(v, tris)
    np.testing.assert_allclose(q @ p, a @ p, atol=1e-8)
    mapped_normal = np.einsum("tij,tj->ti", q, triangle_normals(v, tris))
    mapped_normal /= np.linalg.norm(mapped_normal, axis=1, keepdims=True)
    np.testing.assert_allclose(mapped_normal, triangle_normals(deformed, tris), atol=1e-8)
    batch = full_gradients(v, np.stack([v, deformed]), tris)
    assert batch.shape == (2, len(tris), 3, 3)
    np.testing.assert_allclose(batch[0], np.broadcast_to(np.eye(3), q.shape), atol=1e-9)


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_degenerate_triangles_get_zero_rows_and_no_nan(head, affine, formulation):
    v, tris = with_degenerate(*head)
    a, t = affine
    g, ok = deformation.gradient_operator(v, tris, formulation)
    assert ok[:-2].all() and not ok[-2:].any()
    assert np.isfinite(g.data).all()
    rows = g[3 * (len(tris) - 2):]
    assert rows.nnz == 0 or np.abs(rows.data).max() == 0
    x = deformation.unknowns_of(v, tris, formulation) @ a.T + t
    assert np.isfinite(g @ x).all()
    q = full_gradients(v, v @ a.T + t, tris)
    assert np.isfinite(q).all() and np.abs(q[-2:]).max() == 0


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_gradients_ignore_translation(head, formulation):
    v, tris = head
    g, _ = deformation.gradient_operator(v, tris, formulation)
    assert np.abs(g @ np.ones(g.shape[1])).max() < 1e-9


def test_smoothness_is_zero_for_an_affine_map_on_the_augmented_form(head, affine):
    v, tris = head
    a, t = affine
    g, _ = deformation.gradient_operator(v, tris, deformation.AUGMENTED)
    smooth = deformation.neighbour_difference(tris) @ g
    x = deformation.unknowns_of(v, tris, deformation.AUGMENTED) @ a.T + t
    assert np.abs(smooth @ x).max() < 1e-8
    np.testing.assert_array_equal(deformation.normal_completion(v, tris, deformation.AUGMENTED), 0)
    # and it is not trivially zero: a non-affine deformation is not smooth
    bent = x.copy()
    bent[: len(v), 2] += 0.3 * v[:, 0] ** 2
    assert np.abs(smooth @ bent).max() > 1e-3


def test_reduced_rest_shape_with_normal_completion_has_identity_gradients(head):
    """The reduced gradient at rest is the plane projector; the completion n n^T makes it I, so a
    smoothness term does not pull the rest shape flat."""
    v, tris = head
    g, _ = deformation.gradient_operator(v, tris, deformation.REDUCED)
    completed = g @ v + deformation.normal_completion(v, tris, deformation.REDUCED)
    np.testing.assert_allclose(completed, deformation.stacked_identity(len(tris)), atol=1e-9)
    assert np.abs(deformation.neighbour_difference(tris) @ completed).max() < 1e-9
    assert np.abs(deformation.neighbour_difference(tris) @ (g @ v)).max() > 0.1


def test_triangle_adjacency_on_a_strip():
    tris = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [5, 6, 7]])
    adj = deformation.triangle_adjacency(tris).toarray()
    expected = np.zeros((4, 4))
    expected[0, 1] = expected[1, 0] = expected[1, 2] = expected[2, 1] = 1
    np.testing.assert_array_equal(adj, expected)


@pytest.fixture(scope="module")
def transfers(head):
    """Transfer onto the head itself (every triangle takes its own source gradient, weight 1), per
    formulation; plus two vertices that no triangle uses."""
    v, tris = head
    v = np.vstack([v, [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]])
    return {f: Transfer(v, tris, np.ones(len(tris)), f) for f in FORMULATIONS}


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_transfer_of_a_zero_expression_is_zero(head, transfers, formulation):
    v, tris = head
    gradients = full_gradients(v, v[None], tris)
    n = len(v) + 2
    anchors = np.arange(0, len(v), 97)
    d = transfers[formulation](gradients, np.zeros((1, len(anchors), 3)), anchors)
    assert d.shape == (1, n, 3)
    diag = np.linalg.norm(np.ptp(v, axis=0))
    assert np.abs(d).max() < 1e-12 * diag
    # without anchors too (each part is re-centred)
    assert np.abs(transfers[formulation](gradients)).max() < 1e-12 * diag


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_transfer_of_a_translation_is_the_anchored_translation(head, transfers, formulation):
    v, tris = head
    shift = np.array([0.3, -0.7, 0.2])
    gradients = full_gradients(v, (v + shift)[None], tris)
    anchors = np.arange(0, len(v), 50)
    d = transfers[formulation](gradients, np.broadcast_to(shift, (1, len(anchors), 3)), anchors)
    np.testing.assert_allclose(d[0, : len(v)], np.broadcast_to(shift, (len(v), 3)), atol=1e-9)
    np.testing.assert_array_equal(d[0, len(v):], 0.0)   # unreferenced vertices stay put


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_transfer_of_an_affine_map_onto_the_same_mesh_is_that_map(head, transfers, affine, formulation):
    v, tris = head
    a, t = affine
    rotation = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    shapes = np.stack([v @ a.T + t - v, 1.3 * v @ rotation.T - v])       # two expressions
    gradients = full_gradients(v, v + shapes, tris)
    anchors = np.arange(0, len(v), 61)
    d = transfers[formulation](gradients, shapes[:, anchors], anchors)
    # Transfer's whisper of regularisation (1e-10 of the diagonal) costs ~2e-7 of the size here
    scale = np.abs(shapes).max()
    assert np.abs(d[:, : len(v)] - shapes).max() < 1e-5 * scale
    np.testing.assert_array_equal(d[:, len(v):], 0.0)


def test_transfer_ignores_gradients_of_uncovered_triangles(head):
    """Target triangles with weight 0 take the identity, whatever gradient they are handed."""
    v, tris = head
    transfer = Transfer(v, tris, np.zeros(len(tris)), deformation.REDUCED)
    gradients = full_gradients(v, (1.5 * v)[None], tris)
    d = transfer(gradients, np.full((1, 3, 3), [0.0, 0.0, 0.2]), np.array([0, 1, 2]))
    np.testing.assert_allclose(d[0], np.broadcast_to([0.0, 0.0, 0.2], v.shape), atol=1e-9)


def grid(count):
    """A flat (count x count)-vertex grid on the unit square, two triangles per cell."""
    x, y = np.meshgrid(np.linspace(0.0, 1.0, count), np.linspace(0.0, 1.0, count), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    ids = np.arange(count * count).reshape(count, count)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_fixed_vertices_stay_exactly_still_in_every_expression(head, affine, formulation):
    v, tris = head
    a, t = affine
    shapes = np.stack([v @ a.T + t - v, np.broadcast_to([0.3, -0.1, 0.2], v.shape), 0.4 * v])
    gradients = full_gradients(v, v + shapes, tris)
    fixed = np.arange(5, len(v), 37)
    system = Transfer(v, tris, np.ones(len(tris)), formulation, fixed=fixed)
    anchors = np.arange(0, len(v), 61)
    d = system(gradients, shapes[:, anchors], anchors)
    assert np.all(d[:, fixed] == 0.0)
    assert np.abs(d[[0, 2]]).max() > 1e-2 * np.abs(shapes).max()      # the rest still moves


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_an_affine_map_about_a_fixed_vertex_is_that_map(head, affine, formulation):
    """A linear map about vertex p keeps p in place: holding p gives the map itself, on p's
    connected part, with p exactly still."""
    v, tris = head
    a, _ = affine
    p = int(tris[0, 0])
    shape = (v - v[p]) @ a.T + v[p] - v
    gradients = full_gradients(v, (v + shape)[None], tris)
    system = Transfer(v, tris, np.ones(len(tris)), formulation, fixed=[p])
    d = system(gradients)[0]
    part = system.parts == system.parts[p]
    assert np.all(d[p] == 0.0)
    assert np.abs(d[part] - shape[part]).max() < 1e-5 * np.abs(shape).max()


def test_a_part_holding_fixed_vertices_is_not_re_translated(head):
    """A translation's gradients are the identity: with a vertex of the part held, the anchors
    (which say 'move by the shift') must not move the part away from its fixed vertex."""
    v, tris = head
    shift = np.array([0.3, -0.7, 0.2])
    gradients = full_gradients(v, (v + shift)[None], tris)
    anchors = np.arange(0, len(v), 50)
    system = Transfer(v, tris, np.ones(len(tris)), deformation.REDUCED, fixed=[int(tris[0, 0])])
    d = system(gradients, np.broadcast_to(shift, (1, len(anchors), 3)), anchors)
    part = system.parts == system.parts[tris[0, 0]]
    assert np.abs(d[0, part]).max() < 1e-9 * np.abs(shift).max()


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_a_bump_with_its_border_held_is_transferred_smoothly_with_the_border_still(formulation):
    """The gradients of a smooth bump that leaves the border of a flat grid in place, with that
    border fixed and no anchors: the solution is the bump itself (smooth, no step at the border)
    and the border does not move at all."""
    vertices, triangles = grid(31)
    x, y = vertices[:, 0], vertices[:, 1]
    bump = np.zeros_like(vertices)
    bump[:, 2] = 0.2 * np.sin(np.pi * x) * np.sin(np.pi * y)
    bump[:, 0] = 0.05 * np.sin(np.pi * x) ** 2 * np.sin(np.pi * y)
    border = np.flatnonzero((x == 0) | (x == 1) | (y == 0) | (y == 1))
    gradients = full_gradients(vertices, (vertices + bump)[None], triangles)
    system = Transfer(vertices, triangles, np.ones(len(triangles)), formulation, fixed=border)
    d = system(gradients)[0]
    assert np.all(d[border] == 0.0)
    assert np.abs(d - bump).max() < 1e-3 * np.abs(bump).max()


def test_fixed_vertex_ids_outside_the_mesh_are_refused(head):
    v, tris = head
    with pytest.raises(ExCloneError, match="fixed vertex ids"):
        Transfer(v, tris, np.ones(len(tris)), fixed=[len(v)])


def test_a_fits_fixed_vertices_stay_still_in_the_clone():
    """FaceFit.fixed_vertices (welded numbering) reach the transfer: the demo head's open border
    (its neck cut) is held, every copy of those vertices stays exactly where it is, the face
    still moves."""
    library = load_library()
    fit = fit_faces(library.mesh, data.demo_head(), source_landmarks=library.automatic_landmarks)
    border = mesh_module.boundary_vertices(fit.target_region.triangles)
    held = dataclasses.replace(fit, fixed_vertices=border, _transfer=None)
    free, fixed = (transfer_expressions(f, library.deltas[:8], list(library.names[:8])).deltas
                   for f in (fit, held))
    own = np.isin(fit.welded_target.index, border)
    assert own.any() and np.all(fixed[:, own] == 0.0)
    assert np.abs(free[:, own]).max() > 0
    assert np.abs(fixed).max() > 0.5 * np.abs(free).max()


def test_the_gradient_a_fit_makes_while_it_waits_is_the_target_regions_own():
    """The fit makes the whole target's gradient operator while its landmarks are found and
    gives the transfer the target region's rows: on the demo head with a detached part beside
    it (no landmark on it: outside the region) they are the region's own operator to the bit,
    and the clone is the one a transfer that makes it itself gives, to the bit."""
    library = load_library()
    head = data.demo_head()
    triangles = head.triangles()
    # a copy of the head's first 200 triangles, moved well away: a separate part
    ids, piece = np.unique(triangles[:200], return_inverse=True)
    target = mesh_module.PolyMesh.from_faces(
        np.vstack([head.vertices, head.vertices[ids] + [0.0, 0.0, 10.0]]),
        np.vstack([triangles, len(head.vertices) + piece.reshape(-1, 3)]))
    fit = fit_faces(library.mesh, target, source_landmarks=library.automatic_landmarks)
    region = fit.target_region
    assert len(region.triangles) < len(fit.welded_target.surface.triangles)
    own = deformation.gradient_operator(region.vertices, region.triangles, fit.formulation)[0]
    made = fit._gradient
    assert made is not None and made.shape == own.shape
    for name in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(made, name), getattr(own, name))
    names = list(library.names[:8])
    ahead = transfer_expressions(fit, library.deltas[:8], names).deltas
    itself = transfer_expressions(dataclasses.replace(fit, _gradient=None, _transfer=None,
                                                      _rims=None), library.deltas[:8], names).deltas
    assert np.abs(ahead).max() > 0 and np.array_equal(ahead, itself)


def test_cholesky_and_superlu_give_the_same_clone_of_the_library_on_the_demo_head(monkeypatch):
    """The sparse Cholesky and its SuperLU fallback solve the same system: every bundled
    expression cloned onto the demo head agrees to 1e-9 of the largest displacement."""
    pytest.importorskip("cholespy")
    library = load_library()
    fit = fit_faces(library.mesh, data.demo_head(), source_landmarks=library.automatic_landmarks)
    names = list(library.names)
    by_cholesky = transfer_expressions(fit, library.deltas, names).deltas
    assert fit._transfer.factorisation == transfer.CHOLESKY
    monkeypatch.setattr(transfer, "cholespy", None)      # as in a Blender without the wheel
    unfactorised = dataclasses.replace(fit, _transfer=None)
    by_lu = transfer_expressions(unfactorised, library.deltas, names).deltas
    assert unfactorised._transfer.factorisation == transfer.LU
    scale = np.abs(by_lu).max()
    assert scale > 0
    assert np.abs(by_cholesky - by_lu).max() <= 1e-9 * scale


def test_factorised_falls_back_to_superlu_on_an_indefinite_matrix():
    rng = np.random.default_rng(3)
    # positive diagonal, one negative eigenvalue (the 2x2 block [[1, 2], [2, 1]])
    matrix = sp.csc_matrix(np.array([[1.0, 2.0, 0.0, 0.0], [2.0, 1.0, 0.1, 0.0],
                                     [0.0, 0.1, 2.0, 0.3], [0.0, 0.0, 0.3, 3.0]]))
    assert np.linalg.eigvalsh(matrix.toarray()).min() < 0
    rhs = rng.normal(size=(4, 6))
    name, solve = transfer.factorised(matrix)
    assert name == transfer.LU
    np.testing.assert_allclose(matrix @ solve(rhs), rhs, atol=1e-12)


def test_factorised_uses_cholesky_on_a_positive_definite_matrix_and_solves_every_column(head):
    pytest.importorskip("cholespy")
    v, tris = head
    adjacency = vertex_adjacency(len(v), tris).astype(np.float64)
    laplacian = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    matrix = (laplacian + 1e-3 * sp.identity(len(v))).tocsc()
    rhs = np.random.default_rng(5).normal(size=(len(v), 9))
    name, solve = transfer.factorised(matrix)
    assert name == transfer.CHOLESKY
    np.testing.assert_allclose(solve(rhs), spsolve(matrix, rhs), rtol=0, atol=1e-9)


def test_a_singular_transfer_system_is_a_user_error():
    """Neither factorisation solves an exactly singular matrix: the user is told to clean up."""
    zero_row = sp.diags([1.0, 0.0, 2.0]).tocsc()
    dependent_rows = sp.csc_matrix(np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]))
    for matrix in (zero_row, dependent_rows):
        with pytest.raises(ExCloneError, match="no unique solution"):
            transfer.factorised(matrix)


def test_reused_ordering_solver_matches_spsolve_on_a_changing_diagonal(head):
    v, tris = head
    adjacency = vertex_adjacency(len(v), tris).astype(np.float64)
    laplacian = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    base = (laplacian @ laplacian + 1e-3 * sp.identity(len(v))).tocsr()
    rng = np.random.default_rng(3)
    solver = ReusedOrderingSolver()
    for step in range(4):
        diagonal = rng.uniform(0.0, 10.0 ** step, size=len(v)) * (rng.random(len(v)) < 0.7)
        matrix = (base + sp.diags(diagonal)).tocsr()
        rhs = rng.normal(size=(len(v), 3))
        got = solver.solve(matrix, rhs)
        expected = spsolve(matrix.tocsc(), rhs)
        np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
    assert solver.perm is not None


def brute_closest(points, a, b, c):
    """Closest point per row: the plane projection if inside, else the best of the three edges."""
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    foot = points - np.einsum("ij,ij->i", points - a, normal)[:, None] * normal
    inside = np.ones(len(points), dtype=bool)
    for p, q in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(q - p, foot - p), normal) >= 0
    best = foot.copy()
    best_distance = np.where(inside, np.linalg.norm(points - foot, axis=1), np.inf)
    for p, q in ((a, b), (b, c), (c, a)):
        d = q - p
        u = np.clip(np.einsum("ij,ij->i", points - p, d) / np.einsum("ij,ij->i", d, d), 0, 1)
        on_edge = p + u[:, None] * d
        dist = np.linalg.norm(points - on_edge, axis=1)
        better = ~inside & (dist < best_distance)
        best[better], best_distance[better] = on_edge[better], dist[better]
    return best


def test_closest_points_on_triangles_match_brute_force():
    rng = np.random.default_rng(11)
    m = 20000
    a, b, c = rng.normal(size=(3, m, 3))
    points = rng.normal(size=(m, 3)) * 2.0      # every Voronoi region of the triangles gets hits
    closest, bary = closest_points_on_triangles(points, a, b, c)
    expected = brute_closest(points, a, b, c)
    np.testing.assert_allclose(closest, expected, atol=1e-9)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(axis=1), 1.0)
    np.testing.assert_allclose(bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c, closest,
                               atol=1e-12)


def test_closest_points_on_degenerate_triangles_are_finite():
    a = np.array([[0.0, 0, 0], [1.0, 1, 1]])
    b = np.array([[1.0, 0, 0], [1.0, 1, 1]])
    c = np.array([[2.0, 0, 0], [1.0, 1, 1]])        # collinear; a single point
    closest, bary = closest_points_on_triangles(np.array([[1.5, 1.0, 0], [0.0, 0, 0]]), a, b, c)
    assert np.isfinite(closest).all() and np.isfinite(bary).all()
    np.testing.assert_allclose(closest[1], [1.0, 1, 1])
    # the collinear one still lands on its segment, at the foot of the point
    np.testing.assert_allclose(closest[0], [1.5, 0, 0], atol=1e-12)


def test_triangle_surface_closest_matches_brute_force_over_all_triangles(head):
    v, tris = head
    rng = np.random.default_rng(5)
    diag = np.linalg.norm(np.ptp(v, axis=0))
    on = rng.integers(0, len(v), 300)
    points = v[on] + rng.normal(size=(300, 3)) * 0.01 * diag      # near the surface
    _, _, dist, _ = TriangleSurface(v, tris).closest(points)
    brute = np.empty(len(points))
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    for i, p in enumerate(points):
        p_rep = np.broadcast_to(p, a.shape)
        brute[i] = np.linalg.norm(brute_closest(p_rep, a, b, c) - p, axis=1).min()
    np.testing.assert_allclose(dist, brute, atol=1e-9 * diag)


def test_largest_stretch_is_the_in_plane_maps_largest_singular_value():
    # the straddle check's stretch (core.transfer) from the edges' Gram matrices against numpy's
    # SVD of the map D R^+ that takes each triangle's rest edges R to its deformed edges D
    rng = np.random.default_rng(3)
    rest, deformed = rng.normal(size=(2, 200, 3, 2))
    expected = [np.linalg.svd(d @ np.linalg.pinv(r), compute_uv=False)[0]
                for r, d in zip(rest, deformed)]
    gram = [transfer._gram(edges[..., 0], edges[..., 1]) for edges in (rest, deformed)]
    assert np.allclose(transfer._largest_stretch(*gram), expected, rtol=1e-9)
    flat = np.stack([rest[:, :, 0], 2 * rest[:, :, 0]], axis=-1)        # degenerate rest: 0
    assert not transfer._largest_stretch(transfer._gram(flat[..., 0], flat[..., 1]), gram[1]).any()
