"""Ground truth for the cloning engine's quality tests: the same face, new topology, moved.

The ICT face region is remeshed to a different, isotropic triangle mesh that lies exactly on the
original surface; every new vertex is tied to a point (source triangle corners + barycentric
coordinates) of the source. Moving the new mesh by a known similarity gives a target whose exact
expressions are known: the similarity applied to each source expression evaluated at those
points.

The remesh works on the half-open mouth (neutral + 0.5 * jawOpen): there the lips are apart, so
the sampling and the triangulation never put a triangle across the mouth. The new vertices are
then carried back to the neutral at the same barycentric coordinates.

How the new topology is made: a least-squares conformal map (LSCM) flattens the half-open surface
(it keeps the mouth, eye and outer borders as holes/border); points are spread by Poisson-disk
sampling in 3D (the borders resampled at the same spacing first), triangulated by Delaunay in
the flat map (conformal, so angles survive the trip back), triangles outside the surface are
dropped, and a few rounds of Laplacian relaxation in the map even the spacing out.
"""
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.sparse.linalg import spsolve
from scipy.spatial import Delaunay, cKDTree
from scipy.spatial.transform import Rotation

from exclone_addon.core.mesh import PolyMesh, triangle_areas, triangulate

ICT_FACE_VERTEX_COUNT = 9409     # ICT-FaceKit: vertices 0-9408 are the face (one open surface)
ICT_INNER_LIP_LANDMARKS = slice(60, 68)   # iBUG 68: inner lip contour


def face_region(vertices, loop_totals, loop_vertices, vertex_count=ICT_FACE_VERTEX_COUNT):
    """The first `vertex_count` vertices and the triangles among them."""
    triangles = triangulate(loop_totals, loop_vertices)
    triangles = triangles[(triangles < vertex_count).all(axis=1)]
    return np.asarray(vertices[:vertex_count], dtype=np.float64), triangles


def boundary_loops(triangles):
    """Border loops as ordered vertex-id arrays (each border half-edge a->b once, manifold border)."""
    half = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    keys = half[:, 0].astype(np.int64) << 32 | half[:, 1]
    twins = half[:, 1].astype(np.int64) << 32 | half[:, 0]
    border = half[~np.isin(twins, keys)]
    following = dict(zip(border[:, 0].tolist(), border[:, 1].tolist()))
    if len(following) != len(border):
        raise ValueError("border is not manifold (a vertex starts two border edges)")
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        nxt = following[start]
        while nxt != start:
            loop.append(nxt)
            seen.add(nxt)
            nxt = following[nxt]
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def conformal_map(vertices, triangles, pins):
    """LSCM (Levy et al. 2002): 2D coordinates of every vertex, two `pins` held at their 3D distance."""
    p = vertices[triangles]
    e1 = p[:, 1] - p[:, 0]
    len1 = np.linalg.norm(e1, axis=1)
    x_axis = e1 / len1[:, None]
    normal = np.cross(e1, p[:, 2] - p[:, 0])
    y_axis = np.cross(normal / np.linalg.norm(normal, axis=1, keepdims=True), x_axis)
    local = np.zeros((len(triangles), 3, 2))
    local[:, 1, 0] = len1
    local[:, 2, 0] = np.einsum("ij,ij->i", p[:, 2] - p[:, 0], x_axis)
    local[:, 2, 1] = np.einsum("ij,ij->i", p[:, 2] - p[:, 0], y_axis)
    weight = 1.0 / np.sqrt(np.abs(local[:, 1, 0] * local[:, 2, 1]))    # 1 / sqrt(2 * area)
    rows, cols, vals = [], [], []
    t_index = np.arange(len(triangles))
    n = len(vertices)
    for j in range(3):
        k, m = (j + 1) % 3, (j + 2) % 3
        a = (local[:, m, 0] - local[:, k, 0]) * weight      # W_j = (x_m - x_k) + i (y_m - y_k)
        b = (local[:, m, 1] - local[:, k, 1]) * weight
        v = triangles[:, j]
        # real part of W U: a u - b v; imaginary part: b u + a v
        rows += [2 * t_index, 2 * t_index, 2 * t_index + 1, 2 * t_index + 1]
        cols += [v, n + v, v, n + v]
        vals += [a, -b, b, a]
    system = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(2 * len(triangles), 2 * n))
    pinned = np.array([pins[0], pins[1], n + pins[0], n + pins[1]])
    pinned_values = np.array([0.0, np.linalg.norm(vertices[pins[1]] - vertices[pins[0]]), 0.0, 0.0])
    free = np.setdiff1d(np.arange(2 * n), pinned)
    a_free = system[:, free]
    rhs = -(system[:, pinned] @ pinned_values)
    solution = np.empty(2 * n)
    solution[pinned] = pinned_values
    solution[free] = spsolve((a_free.T @ a_free).tocsc(), a_free.T @ rhs)
    return np.stack([solution[:n], solution[n:]], axis=1)


class _PlanarLocator:
    """Which triangle of a flat (2D) triangulation holds a point, and where (barycentric)."""

    def __init__(self, uv, triangles):
        self.corners = uv[triangles]
        self.tree = cKDTree(self.corners.mean(axis=1))

    def _barycentric(self, points, candidates):
        c = self.corners[candidates]                          # (m, k, 3, 2)
        d1, d2 = c[..., 1, :] - c[..., 0, :], c[..., 2, :] - c[..., 0, :]
        r = points[:, None, :] - c[..., 0, :]
        det = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        b1 = (r[..., 0] * d2[..., 1] - r[..., 1] * d2[..., 0]) / det
        b2 = (d1[..., 0] * r[..., 1] - d1[..., 1] * r[..., 0]) / det
        return np.stack([1.0 - b1 - b2, b1, b2], axis=-1)

    def locate(self, points, tolerance=1e-9):
        """(triangle index, barycentric, inside) per point; outside points get their best guess."""
        triangle = np.zeros(len(points), dtype=np.int64)
        bary = np.zeros((len(points), 3))
        inside = np.zeros(len(points), dtype=bool)
        todo = np.arange(len(points))
        for k in (16, 128):
            if len(todo) == 0:
                break
            _, candidates = self.tree.query(points[todo], k=min(k, len(self.corners)))
            b = self._barycentric(points[todo], candidates)
            best = b.min(axis=2).argmax(axis=1)
            pick = np.arange(len(todo))
            triangle[todo] = candidates[pick, best]
            bary[todo] = b[pick, best]
            inside[todo] = b[pick, best].min(axis=1) >= -tolerance
            todo = todo[~inside[todo]]
        return triangle, bary, inside


def _capped(vertices, triangles, holes):
    """The surface with each hole closed by a fan around an added centre vertex.

    Flattened with open holes, LSCM shrinks the mouth to a slit that folds over itself (the lips
    roll inwards); caps keep every hole open and convex-ish in the map.
    """
    centres = np.array([vertices[loop].mean(axis=0) for loop in holes])
    centre_ids = len(vertices) + np.arange(len(holes))
    # border half-edges run a->b with the surface on their left; a cap triangle runs b->a->centre
    fans = [np.stack([np.roll(loop, -1), loop, np.full(len(loop), c)], axis=1)
            for loop, c in zip(holes, centre_ids)]
    return np.vstack([vertices, centres]), np.vstack([triangles] + fans)


def _resample_loop(points, spacing):
    """Evenly spaced positions along a closed polyline: (segment index, fraction along it)."""
    closed = np.vstack([points, points[:1]])
    lengths = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    count = max(3, int(round(cumulative[-1] / spacing)))
    arc = np.arange(count) * cumulative[-1] / count
    segment = np.clip(np.searchsorted(cumulative, arc, side="right") - 1, 0, len(points) - 1)
    fraction = (arc - cumulative[segment]) / lengths[segment]
    return segment, fraction


def _poisson_samples(vertices, triangles, loops, radius, rng):
    """Border points every ~radius, then random surface points no closer than radius to any kept one.

    Returns (source triangle index, barycentric, next border sample along the same loop or -1)
    per sample; the border samples come first, loop after loop, in loop order.
    """
    edge_triangle = {}
    for t, tri in enumerate(triangles.tolist()):
        for j in range(3):
            edge_triangle[(tri[j], tri[(j + 1) % 3])] = (t, j)
    border_tri, border_bary, border_next = [], [], []
    for loop in loops:
        segment, fraction = _resample_loop(vertices[loop], radius)
        first = len(border_tri)
        border_next += [first + (k + 1) % len(segment) for k in range(len(segment))]
        for s, f in zip(segment.tolist(), fraction.tolist()):
            a, b = int(loop[s]), int(loop[(s + 1) % len(loop)])
            t, j = edge_triangle[(a, b)]
            w = np.zeros(3)
            w[j], w[(j + 1) % 3] = 1.0 - f, f
            border_tri.append(t)
            border_bary.append(w)
    border_tri = np.array(border_tri, dtype=np.int64)
    border_bary = np.array(border_bary)

    area = triangle_areas(vertices, triangles)
    count = int(8 * area.sum() / radius ** 2)               # ~5x more than fit at this spacing
    cand_tri = rng.choice(len(triangles), size=count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    cand_bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)

    tri = np.concatenate([border_tri, cand_tri])
    bary = np.concatenate([border_bary, cand_bary])
    points = np.einsum("ij,ijk->ik", bary, vertices[triangles[tri]])
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    neighbours = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                               shape=(len(points), len(points)))
    neighbours = (neighbours + neighbours.T).tocsr()
    n_border = len(border_tri)
    removed = np.zeros(len(points), dtype=bool)
    keep = np.zeros(len(points), dtype=bool)
    keep[:n_border] = True
    for i in range(n_border):
        removed[neighbours.indices[neighbours.indptr[i]:neighbours.indptr[i + 1]]] = True
    indptr, indices = neighbours.indptr, neighbours.indices
    for i in range(n_border, len(points)):                  # greedy dart throwing, random order
        if not removed[i]:
            keep[i] = True
            removed[indices[indptr[i]:indptr[i + 1]]] = True
    following = np.full(len(points), -1, dtype=np.int64)
    following[:n_border] = border_next            # border samples keep their indices
    return tri[keep], bary[keep], following[keep]


def _triangulate_in_map(uv_points, border_next, locator):
    """Delaunay triangles of the points in the flat map that lie on the surface.

    A triangle is kept if its centre and the middles of its edges are on the surface, except for
    edges between neighbouring border samples: those are the new border and may cut a little
    into a hole (the hole's border curves between them).
    """
    triangles = Delaunay(uv_points).simplices
    corners = uv_points[triangles]
    d1, d2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    inside = area > 1e-9 * np.median(area)          # collinear border samples make flat ones
    centre_inside = locator.locate(corners.mean(axis=1))[2]
    inside &= centre_inside
    for j in range(3):
        a, b = triangles[:, j], triangles[:, (j + 1) % 3]
        chord = (border_next[a] == b) | (border_next[b] == a)
        middle_inside = locator.locate(0.5 * (corners[:, j] + corners[:, (j + 1) % 3]))[2]
        inside &= chord | middle_inside
    return triangles[inside]


def remesh_face_region(vertices, triangles, half_open_delta, target_vertices=7000, seed=0,
                       relax_iterations=4):
    """A different, isotropic triangle mesh of the same surface, tied to the source by barycentrics.

    vertices (n, 3): the neutral face region; triangles (T, 3) among them (one open surface);
    half_open_delta (n, 3): added to the neutral to part the lips (e.g. 0.5 * jawOpen).
    Returns (new_vertices (m, 3) on the NEUTRAL surface, new_triangles (F, 3),
    source_triangle (m, 3) source vertex ids of the triangle holding each new vertex,
    barycentric (m, 3) its coordinates there). Deterministic for a given seed.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    posed = vertices + np.asarray(half_open_delta, dtype=np.float64)
    loops = boundary_loops(triangles)
    outer = max(loops, key=lambda loop: np.linalg.norm(np.diff(posed[loop], axis=0), axis=1).sum())
    far = outer[np.argmax(np.linalg.norm(posed[outer] - posed[outer[0]], axis=1))]
    uv = conformal_map(*_capped(posed, triangles, [loop for loop in loops if loop is not outer]),
                       (int(outer[0]), int(far)))[:len(posed)]
    locator = _PlanarLocator(uv, triangles)

    area = triangle_areas(posed, triangles).sum()
    # Maximal Poisson-disk sets hold ~0.7 points per radius^2 of area; one recalibration pass
    # lands the count near the target (the greedy set's density depends a little on the surface).
    radius = np.sqrt(0.7 * area / target_vertices)
    for _ in range(2):
        tri, bary, border_next = _poisson_samples(posed, triangles, loops, radius,
                                                np.random.default_rng(seed))
        radius *= np.sqrt(len(tri) / target_vertices)

    points_uv = np.einsum("ij,ijk->ik", bary, uv[triangles[tri]])
    faces = _triangulate_in_map(points_uv, border_next, locator)
    interior = border_next < 0
    for _ in range(relax_iterations):
        # Move interior points halfway to the mean of their neighbours in the map; a point
        # that would leave the surface stays where it is.
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        adjacency = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                  shape=(len(points_uv),) * 2).tocsr()
        adjacency = ((adjacency + adjacency.T) > 0).astype(np.float64)
        degree = np.asarray(adjacency.sum(axis=1)).ravel()
        mean = (adjacency @ points_uv) / np.maximum(degree, 1)[:, None]
        moved = points_uv.copy()
        moved[interior] = 0.5 * (points_uv[interior] + mean[interior])
        new_tri, new_bary, inside = locator.locate(moved[interior])
        index = np.flatnonzero(interior)[inside]
        points_uv[index], tri[index], bary[index] = moved[index], new_tri[inside], new_bary[inside]
        faces = _triangulate_in_map(points_uv, border_next, locator)

    used = np.unique(faces)                  # a point left on no triangle (rare, at a border) goes
    remap = np.full(len(points_uv), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[faces]
    tri, bary = tri[used], np.clip(bary[used], 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)

    # Same orientation as the source: compare the map's winding of both meshes.
    source_sign = np.sign(_signed_areas(uv, triangles).sum())
    if np.sign(_signed_areas(points_uv[used], faces).sum()) != source_sign:
        faces = faces[:, ::-1]
    source_triangle = triangles[tri]
    return evaluate_at(vertices, source_triangle, bary), faces, source_triangle, bary


def _signed_areas(uv, triangles):
    c = uv[triangles]
    d1, d2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


def evaluate_at(values, source_triangle, barycentric):
    """Per-vertex values (n, k) or (E, n, 3) at barycentric points of source triangles.

    source_triangle (m, 3): the source vertex ids of each point's triangle; barycentric (m, 3).
    Returns (m, k) or (E, m, 3).
    """
    values = np.asarray(values, dtype=np.float64)
    corners = values[..., source_triangle, :]                # (..., m, 3, k)
    return np.einsum("mj,...mjk->...mk", barycentric, corners)


def random_similarity(seed, max_angle_deg=30.0, scale_range=(0.5, 2.0), translation_scale=1.0):
    """(R, s, t): rotation by up to max_angle_deg about a random axis, log-uniform scale, and a
    translation with components uniform in [-translation_scale, translation_scale]."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg))
    rotation = Rotation.from_rotvec(angle * axis).as_matrix()
    scale = float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
    translation = rng.uniform(-translation_scale, translation_scale, size=3)
    return rotation, scale, translation


def apply_similarity(points, R, s, t):
    return s * np.asarray(points, dtype=np.float64) @ np.asarray(R).T + t


def invert_similarity(R, s, t):
    """(R', s', t') with apply_similarity(apply_similarity(p, R, s, t), R', s', t') == p."""
    R_inv = np.asarray(R).T
    return R_inv, 1.0 / s, -(R_inv @ t) / s


def make_case(library_vertices, library_polygons, names, deltas, seed, *, landmarks68=None,
              target_vertices=7000, region_vertex_count=ICT_FACE_VERTEX_COUNT,
              half_open_weight=0.5):
    """A cloning test case with a known answer, from a library whose first
    `region_vertex_count` vertices are the face (the ICT layout).

    library_polygons: (loop_totals, loop_vertices). deltas: (E, n_library, 3) in `names` order
    (must include jawOpen). landmarks68: optional library vertex ids; when given, the case also
    holds the nearest target vertex to each (a landmark pair list for the engine).
    """
    names = list(names)
    if "jawOpen" not in names:
        raise ValueError("the library has no jawOpen expression (needed to part the lips)")
    neutral, triangles = face_region(library_vertices, *library_polygons, region_vertex_count)
    region_deltas = np.asarray(deltas, dtype=np.float64)[:, :region_vertex_count]
    half_open = half_open_weight * region_deltas[names.index("jawOpen")]
    new_vertices, new_triangles, source_triangle, barycentric = remesh_face_region(
        neutral, triangles, half_open, target_vertices=target_vertices, seed=seed)

    diagonal = np.linalg.norm(np.ptp(neutral, axis=0))
    R, s, t = random_similarity(seed, translation_scale=diagonal)
    target = apply_similarity(new_vertices, R, s, t)
    expressions = evaluate_at(neutral[None] + region_deltas, source_triangle, barycentric)
    truth = apply_similarity(expressions, R, s, t) - target
    case = {
        "names": names,
        "target_vertices": target,
        "target_triangles": new_triangles,
        "target_mesh": PolyMesh.from_faces(target, new_triangles),
        "truth_deltas": truth,
        "similarity": (R, s, t),
        "source_triangle": source_triangle,
        "barycentric": barycentric,
        "source_region_triangles": triangles,
    }
    if landmarks68 is not None:
        landmarks68 = np.asarray(landmarks68, dtype=np.int64)
        _, nearest = cKDTree(new_vertices).query(neutral[landmarks68])
        case["source_landmarks"] = landmarks68
        case["target_landmarks"] = nearest
    return case


def relative_error(clone_deltas, truth_deltas, zero_tolerance=1e-6):
    """||clone - truth||_F / ||truth||_F per expression (no offset removed).

    NaN for expressions whose truth is ~0 on the face region (norm below zero_tolerance times
    the largest expression's norm): there is no scale to measure them against.
    """
    clone_deltas = np.asarray(clone_deltas, dtype=np.float64)
    truth_deltas = np.asarray(truth_deltas, dtype=np.float64)
    if clone_deltas.shape != truth_deltas.shape:
        raise ValueError(f"clone deltas {clone_deltas.shape} vs truth {truth_deltas.shape}")
    truth_norm = np.linalg.norm(truth_deltas.reshape(len(truth_deltas), -1), axis=1)
    error_norm = np.linalg.norm((clone_deltas - truth_deltas).reshape(len(truth_deltas), -1), axis=1)
    measurable = truth_norm > zero_tolerance * max(truth_norm.max(initial=0.0), 1e-300)
    return np.where(measurable, error_norm / np.where(measurable, truth_norm, 1.0), np.nan)


def mouth_sides(vertices, triangles, inner_lip_landmarks, band, margin):
    """Label source vertices near the mouth as upper lip (+1), lower lip (-1) or neither (0).

    The mouth is the border loop nearest the inner-lip landmarks; its two ends in x (the mouth
    corners) split it into an upper and a lower half. A vertex within `band` (along the surface)
    of one half belongs to it if the other half is at least `margin` farther: around the mouth
    corners, where both are about as far, the lips legitimately meet and nothing is labelled.
    """
    loops = boundary_loops(triangles)
    centre = vertices[inner_lip_landmarks].mean(axis=0)
    mouth = min(loops, key=lambda loop: np.linalg.norm(vertices[loop].mean(axis=0) - centre))
    x = vertices[mouth, 0]
    i, j = sorted((int(np.argmin(x)), int(np.argmax(x))))
    half_a, half_b = mouth[i:j + 1], np.concatenate([mouth[j:], mouth[:i + 1]])
    upper, lower = (half_a, half_b) if vertices[half_a, 1].mean() > vertices[half_b, 1].mean() \
        else (half_b, half_a)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    graph = sp.coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2).tocsr()
    limit = band + margin
    # beyond `limit` dijkstra gives inf; capping there keeps the comparisons below exact
    d_upper = np.minimum(dijkstra(graph, directed=False, indices=upper, min_only=True,
                                  limit=limit), limit)
    d_lower = np.minimum(dijkstra(graph, directed=False, indices=lower, min_only=True,
                                  limit=limit), limit)
    side = np.zeros(len(vertices), dtype=np.int64)
    side[(d_upper <= band) & (d_lower - d_upper >= margin)] = 1
    side[(d_lower <= band) & (d_upper - d_lower >= margin)] = -1
    return side
