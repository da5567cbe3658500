"""Meshes as real characters come: vertices split at UV seams or for every polygon, a closed
(capped) head, n-gons, non-manifold edges, loose parts. Each is a case both as the target (the
demo head) and as the source (the bundled library): the clone works, and where the hazard
changes nothing about the surface, the clone is the one of the clean mesh."""
import numpy as np
import pytest

from exclone_addon.core import data
from exclone_addon.core.cloning import CloneSettings, clone_expressions
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, boundary_edges, diagonal, welded
from exclone_addon.core.surface import Surface

NAMES = ("jawOpen", "eyeBlink_L")
FAST = CloneSettings(preset="fast")
# A hazard that leaves the face's surface as it was (a cap under the neck, fins, loose bits)
# may move the clone this much, relative to the clean clone's size: the fit sees other borders.
NEAR_CLEAN = 0.1
# A fully unwelded target welds back to the demo head in another vertex order: closest-point
# ties break otherwise, which moves the clone by this much (measured: 0.3%; and with the fast
# preset the demo head's jawOpen passes the transfer's stretch bound (core.transfer.STRETCH_BOUND)
# in the file's order, 2.60x, not in the welded one, 2.49x: taken the share 0.41 of the way to
# its caps (core.transfer.BOUND_FADE) it moves by 0.86%, the clone by 0.74%; with the whole cap
# at once, 2.1% and 2.0%).
UNWELDED_ORDER = 0.01
# The library unwelded: its eyelashes, which ICT plants on the lids' edges, become one piece
# with the face (two sides of a cut look the same as a lash on a lid), which moves the clone by
# this much (measured: 12%).
UNWELDED_SOURCE = 0.2


# ------------------------------------------------------------------------------ the hazards

def split_at_midline(mesh):
    """The faces right of the midline (x > 0) get their own copies of the midline vertices, as
    an exporter splits a UV seam: (mesh, (k, 2) pairs of original and copy)."""
    v = mesh.vertices
    midline = np.flatnonzero(np.abs(v[:, 0]) <= 1e-9 * diagonal(v))
    copy_of = dict(zip(midline, len(v) + np.arange(len(midline))))
    faces = [np.array([copy_of.get(i, i) for i in f]) if v[f, 0].mean() > 0 else f
             for f in mesh.faces()]
    return (PolyMesh.from_faces(np.vstack([v, v[midline]]), faces),
            np.stack([midline, len(v) + np.arange(len(midline))], axis=1))


def unwelded(mesh):
    """Every polygon with its own vertices: (mesh, (L,) original vertex of every new one)."""
    loops = mesh.loop_vertices
    return PolyMesh(mesh.vertices[loops], mesh.loop_totals, np.arange(len(loops))), loops


def border_loops(mesh):
    """The open borders as closed vertex loops, each in the winding of its faces."""
    edges = _directed_border_edges(mesh)
    following = dict(edges)
    loops, seen = [], set()
    for start, _ in edges:
        if start in seen:
            continue
        loop, vertex = [], start
        while vertex not in seen:
            seen.add(vertex)
            loop.append(vertex)
            vertex = following[vertex]
        loops.append(np.array(loop))
    return loops


def _directed_border_edges(mesh):
    triangles = mesh.triangles()
    border = {tuple(e) for e in boundary_edges(triangles).tolist()}
    directed = triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    return [(a, b) for a, b in directed.tolist() if (min(a, b), max(a, b)) in border]


def capped(mesh, fan):
    """Every open border closed: by a fan around a new centre vertex, or by one polygon (an
    n-gon of the whole border). (mesh, number of added vertices)."""
    vertices, faces = [mesh.vertices], list(mesh.faces())
    for loop in border_loops(mesh):
        reverse = loop[::-1]                        # the cap faces the other way than the faces
        if fan:
            centre = len(np.vstack(vertices))
            vertices.append(mesh.vertices[loop].mean(axis=0, keepdims=True))
            faces += [np.array([centre, a, b]) for a, b in zip(reverse, np.roll(reverse, -1))]
        else:
            faces.append(reverse)
    return PolyMesh.from_faces(np.vstack(vertices), faces), len(np.vstack(vertices)) - len(mesh.vertices)


def with_ngons(mesh, count=40, seed=0):
    """`count` disjoint pairs of polygons that share an edge merged into one polygon each."""
    faces = [list(f) for f in mesh.faces()]
    owner = {}
    for p, f in enumerate(faces):
        for a, b in zip(f, f[1:] + f[:1]):
            owner[(a, b)] = p
    rng, merged, used = np.random.default_rng(seed), [], set()
    for p in rng.permutation(len(faces)):
        if len(merged) == count:
            break
        f = faces[p]
        for a, b in zip(f, f[1:] + f[:1]):
            q = owner.get((b, a))
            if q is not None and p not in used and q not in used and len(set(f) & set(faces[q])) == 2:
                merged.append(_merged(f, faces[q], a, b))
                used |= {p, q}
    kept = [np.array(f) for p, f in enumerate(faces) if p not in used]
    return PolyMesh.from_faces(mesh.vertices, kept + [np.array(m) for m in merged]), len(merged)


def _merged(first, second, a, b):
    """The polygon around both polygons, which share the edge a->b (b->a in `second`)."""
    i, j = first.index(b), second.index(a)
    around_first = first[i:] + first[:i]            # b ... a
    around_second = second[j:] + second[:j]         # a ... b
    return around_first + around_second[1:-1]


def with_fins(mesh, count=30, seed=1):
    """`count` triangles on edges of the mesh, reaching inwards (three faces on each of those
    edges, as an inner wall left by a modeller), each with a new tip vertex: (mesh, the edges'
    first vertices, one per new vertex)."""
    triangles = mesh.triangles()
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(triangles), count, replace=False)
    chosen, v = triangles[rows], mesh.vertices
    inward = -Surface(v, triangles).triangle_normals[rows]
    tips = (v[chosen[:, 0]] + v[chosen[:, 1]]) / 2 + 0.01 * diagonal(v) * inward
    n = len(v)
    fins = [np.array([a, b, n + k]) for k, (a, b, _) in enumerate(chosen)]
    return PolyMesh.from_faces(np.vstack([v, tips]), list(mesh.faces()) + fins), chosen[:, 0]


def with_loose_parts(mesh, near_at=(0.6, 0.0, 0.0)):
    """Floating triangles (one near the head, at near_at x the diagonal from its centre; one far
    away) and two loose vertices: (mesh, number of added vertices)."""
    v = mesh.vertices
    size = diagonal(v)
    centre = v.mean(axis=0)
    near = centre + np.multiply(near_at, size) + 0.01 * size * np.eye(3)
    far = centre + [10 * size, 0.0, 0.0] + 0.01 * size * np.eye(3)
    loose = centre + np.array([[0.0, 5 * size, 0.0], [0.0, 0.0, 0.0]])
    n = len(v)
    faces = list(mesh.faces()) + [np.arange(n, n + 3), np.arange(n + 3, n + 6)]
    return PolyMesh.from_faces(np.vstack([v, near, far, loose]), faces), 8


# ------------------------------------------------------------------------------ fixtures

@pytest.fixture(scope="module")
def library():
    return load_library().subset(list(NAMES))


@pytest.fixture(scope="module")
def head():
    return data.demo_head()


def clone(library, source=None, deltas=None, target=None, source_landmarks=None):
    """The library's expressions (or the given source's) cloned onto the target (the demo head)."""
    if source is None:
        source, deltas, source_landmarks = library.mesh, library.deltas, library.automatic_landmarks
    return clone_expressions(source, deltas, list(NAMES), target if target is not None
                             else data.demo_head(), source_landmarks=source_landmarks,
                             settings=FAST).deltas


@pytest.fixture(scope="module")
def clean(library):
    """The clone of the clean library onto the clean demo head."""
    return clone(library)


def relative_change(result, reference):
    return np.linalg.norm(result - reference) / np.linalg.norm(reference)


def widest_crack(mesh, deltas, pairs):
    """The largest distance, over the expressions, between two copies of one vertex."""
    moved = mesh.vertices[None] + deltas
    return np.linalg.norm(moved[:, pairs[:, 0]] - moved[:, pairs[:, 1]], axis=2).max()


# ------------------------------------------------------------------------------ the weld

def test_weld_joins_copies_and_leaves_a_clean_mesh_as_it_is(head):
    same, index = welded(head)
    assert same is head and np.array_equal(index, np.arange(len(head.vertices)))
    split, pairs = split_at_midline(head)
    back, index = welded(split)
    assert np.array_equal(back.vertices, head.vertices)
    assert np.array_equal(back.loop_vertices, head.loop_vertices)
    assert np.array_equal(index[pairs[:, 1]], pairs[:, 0])
    loose, original = unwelded(head)
    back, index = welded(loose)
    assert len(back.vertices) == len(head.vertices)
    assert np.array_equal(back.vertices[index], head.vertices[original])


def test_a_concave_ngon_is_cut_without_folds():
    """An L-shaped hexagon: a fan from its first corner would fold a triangle outside it."""
    from exclone_addon.core.mesh import triangle_areas, triangle_normals
    corners = np.array([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]])
    for turn in (corners, corners[::-1]):
        triangles = PolyMesh.from_faces(turn, [np.arange(6)]).triangles()
        assert len(triangles) == 4
        assert np.isclose(triangle_areas(turn, triangles).sum(), 3.0)
        normals = triangle_normals(turn, triangles)
        assert np.allclose(normals, normals[0]), "every triangle in the polygon's winding"


def test_landmarks_of_a_split_or_unwelded_head_are_the_welded_ones(head):
    """The automatic landmarks (what Auto Landmarks stores) of a head split at a seam or fully
    unwelded: the demo head's, at one of each vertex's copies (before: "the face's profile is
    too small to find its nose")."""
    from exclone_addon.core.cloning import found_landmarks
    names, ids = found_landmarks(head)
    split, _ = split_at_midline(head)
    assert found_landmarks(split)[0] == names and np.array_equal(found_landmarks(split)[1], ids)
    loose, original = unwelded(head)
    loose_names, loose_ids = found_landmarks(loose)
    assert loose_names == names and np.array_equal(original[loose_ids], ids)


# ------------------------------------------------------------------------------ as the target

def test_target_split_at_a_seam_opens_no_crack(library, head, clean):
    split, pairs = split_at_midline(head)
    assert len(pairs) > 20, "the demo head has a midline to split"
    result = clone(library, target=split)
    assert widest_crack(split, result, pairs) <= 1e-6 * diagonal(head.vertices)
    # the welded target is the demo head itself: the same clone, and the copies move alike
    n = len(head.vertices)
    np.testing.assert_allclose(result[:, :n], clean, atol=1e-9 * diagonal(head.vertices))


def test_fully_unwelded_target_clones_like_the_welded_one(library, head, clean):
    """Every polygon with its own corners: the clone is the welded mesh's, copied to every
    corner, and the welded mesh is the demo head in another vertex order (so the same clone up to
    the order's rounding and tie-breaks)."""
    loose, original = unwelded(head)
    result = clone(library, target=loose)
    size = diagonal(head.vertices)
    first = np.unique(original, return_index=True)[1]
    copies = np.stack([first[head.loop_vertices], np.arange(len(original))], axis=1)
    assert widest_crack(loose, result, copies) <= 1e-6 * size
    joined, index = welded(loose)
    np.testing.assert_allclose(result, clone(library, target=joined)[:, index], atol=1e-9 * size)
    assert relative_change(result[:, first], clean) <= UNWELDED_ORDER


def test_capped_target_works(library, head, clean):
    """The neck closed by a fan around a new vertex: the automatic landmarks find the face. Closed
    by one polygon, the landmarks found on the clean head serve (automatic ones find the nose on
    the chin there) and the rest of the pipeline clones as on the open head."""
    n = len(head.vertices)
    closed, _ = capped(head, fan=True)
    assert len(border_loops(closed)) == 0
    assert relative_change(clone(library, target=closed)[:, :n], clean) <= NEAR_CLEAN
    closed, added = capped(head, fan=False)
    assert added == 0 and len(border_loops(closed)) == 0
    found = clone_expressions(library.mesh, library.deltas, list(NAMES), head,
                              source_landmarks=library.automatic_landmarks, settings=FAST)
    pairs = {"source": found.source_landmarks, "target": found.target_landmarks}

    def clone_with_pairs(target):
        return clone_expressions(library.mesh, library.deltas, list(NAMES), target,
                                 landmarks=pairs, settings=FAST).deltas
    assert relative_change(clone_with_pairs(closed), clone_with_pairs(head)) <= NEAR_CLEAN


def test_target_with_ngons_fins_and_loose_parts_works(library, head, clean):
    n = len(head.vertices)
    ngons, merged = with_ngons(head)
    assert merged == 40
    assert relative_change(clone(library, target=ngons), clean) <= NEAR_CLEAN
    fins, _ = with_fins(head)
    result = clone(library, target=fins)
    assert np.isfinite(result).all() and relative_change(result[:, :n], clean) <= NEAR_CLEAN
    # a triangle beside the head or in front of its face; the far one and the loose vertices
    # would set the face's scale if the face were looked for on them
    for near_at in ((0.6, 0.0, 0.0), (0.0, 0.0, 0.6)):
        loose, added = with_loose_parts(head, near_at)
        result = clone(library, target=loose)
        assert relative_change(result[:, :n], clean) <= NEAR_CLEAN
        assert np.all(result[:, n + 3:] == 0.0), "a far triangle and loose vertices stay"


# ------------------------------------------------------------------------------ as the source

def test_unwelded_source_clones_like_the_welded_one(library, clean):
    """Every polygon of the library with its own corners (each with its vertex's motion): the
    clone of the welded source. (Unwelded, the eyelashes ICT plants on the lids join the face.)"""
    mesh, original = unwelded(library.mesh)
    names, ids = library.automatic_landmarks
    first = np.unique(original, return_index=True)[1]
    marks = (names, first[ids])
    result = clone(library, mesh, library.deltas[:, original], source_landmarks=marks)
    joined, index = welded(mesh)
    representatives = np.unique(index, return_index=True)[1]
    expected = clone(library, joined, library.deltas[:, original[representatives]],
                     source_landmarks=(names, index[first[ids]]))
    np.testing.assert_allclose(result, expected, atol=1e-9 * diagonal(data.demo_head().vertices))
    assert relative_change(result, clean) <= UNWELDED_SOURCE


def test_split_source_clones_like_the_library(library, clean):
    mesh, pairs = split_at_midline(library.mesh)
    assert len(pairs) > 20
    deltas = np.concatenate([library.deltas, library.deltas[:, pairs[:, 0]]], axis=1)
    result = clone(library, mesh, deltas, source_landmarks=library.automatic_landmarks)
    np.testing.assert_allclose(result, clean, atol=1e-9 * diagonal(data.demo_head().vertices))


def test_closed_source_works(library, clean):
    for fan in (True, False):
        mesh, added = capped(library.mesh, fan)
        deltas = np.concatenate([library.deltas, np.zeros((len(NAMES), added, 3))], axis=1)
        result = clone(library, mesh, deltas, source_landmarks=library.automatic_landmarks)
        assert relative_change(result, clean) <= NEAR_CLEAN, f"fan={fan}"


def test_source_with_ngons_fins_and_loose_parts_works(library, clean):
    marks = library.automatic_landmarks
    ngons, _ = with_ngons(library.mesh)
    assert relative_change(clone(library, ngons, library.deltas, source_landmarks=marks),
                           clean) <= NEAR_CLEAN
    fins, bases = with_fins(library.mesh)
    deltas = np.concatenate([library.deltas, library.deltas[:, bases]], axis=1)
    assert relative_change(clone(library, fins, deltas, source_landmarks=marks),
                           clean) <= NEAR_CLEAN
    loose, added = with_loose_parts(library.mesh)
    deltas = np.concatenate([library.deltas, np.zeros((len(NAMES), added, 3))], axis=1)
    assert relative_change(clone(library, loose, deltas, source_landmarks=marks),
                           clean) <= NEAR_CLEAN
