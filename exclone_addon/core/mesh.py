"""Polygon meshes as plain arrays: OBJ I/O, triangulation, normals, parts.

A mesh is (vertices, loop_totals, loop_vertices), Blender's own layout: polygon p uses
loop_vertices[start[p]:start[p] + loop_totals[p]]. Everything downstream works on the triangles
`triangulate` makes, and results go back in the original vertex order (triangulation never adds
or reorders vertices).
"""
import re
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import ExCloneError


class MeshError(ExCloneError):
    """Input that is not a usable mesh."""


@dataclass
class PolyMesh:
    vertices: np.ndarray        # (n, 3) float64
    loop_totals: np.ndarray     # (P,) int: corners per polygon
    loop_vertices: np.ndarray   # (L,) int: vertex index per corner

    @classmethod
    def from_faces(cls, vertices, faces):
        """faces: a (P, k) array or a list of vertex-index sequences."""
        if isinstance(faces, np.ndarray) and faces.ndim == 2:     # one size: no loop per face
            return cls(np.asarray(vertices, dtype=np.float64),
                       np.full(len(faces), faces.shape[1], dtype=np.int64),
                       faces.astype(np.int64).ravel())
        faces = [np.asarray(f, dtype=np.int64) for f in faces]
        totals = np.array([len(f) for f in faces], dtype=np.int64)
        loops = np.concatenate(faces) if faces else np.zeros(0, np.int64)
        return cls(np.asarray(vertices, dtype=np.float64), totals, loops)

    def triangles(self):
        return triangulate(self.loop_totals, self.loop_vertices, self.vertices)

    def faces(self):
        if len(self.loop_totals) == 0:
            return []
        return np.split(self.loop_vertices, np.cumsum(self.loop_totals)[:-1])


def triangulate(loop_totals, loop_vertices, vertices=None):
    """Triangles of every polygon, polygon by polygon in its winding; returns (T, 3) int64.

    Triangles and quads are fanned from their first corner. Polygons of five corners or more are
    fanned too without `vertices`; with them, they are cut ear by ear in their own plane, so a
    concave one (a cap closing a neck, a few faces merged) is covered without triangles that
    fold outside it."""
    totals = np.asarray(loop_totals, dtype=np.int64)
    loops = np.asarray(loop_vertices, dtype=np.int64)
    if np.any(totals < 3):
        raise MeshError("mesh has a polygon with fewer than 3 corners")
    starts = np.concatenate([[0], np.cumsum(totals)[:-1]])
    fans = totals - 2
    poly = np.repeat(np.arange(len(totals)), fans)
    k = np.arange(fans.sum()) - np.repeat(np.cumsum(fans) - fans, fans)
    first = starts[poly]
    triangles = np.stack([loops[first], loops[first + k + 1], loops[first + k + 2]], axis=1)
    if vertices is not None:
        rows = np.cumsum(fans) - fans               # each polygon's first triangle
        for p in np.flatnonzero(totals > 4):
            corners = loops[starts[p]:starts[p] + totals[p]]
            triangles[rows[p]:rows[p] + fans[p]] = corners[_ears(np.asarray(vertices)[corners])]
    return triangles


def _ears(points):
    """(k - 2, 3) corner numbers of the triangles that cut the polygon `points` (k, 3) ear by
    ear (each triangle in the polygon's winding), projected onto its own plane (Newell's
    normal). Where no ear is left (a polygon that crosses itself in that plane) the rest is
    fanned."""
    normal = np.cross(points, np.roll(points, -1, axis=0)).sum(axis=0)
    axis_u = np.cross(normal, np.eye(3)[np.argmin(np.abs(normal))])
    axis_v = np.cross(normal, axis_u)
    flat = points @ np.stack([axis_u, axis_v], axis=1)
    # the winding in that plane: the sign of the shoelace area (numpy 2 has no 2-D np.cross)
    sign = 1.0 if _turn(np.zeros(2), flat, np.roll(flat, -1, axis=0)).sum() >= 0 else -1.0
    left, ears = list(range(len(points))), []
    while len(left) > 3:
        ear = next((j for j in range(len(left)) if _is_ear(flat, left, j, sign)), None)
        if ear is None:
            break
        ears.append((left[ear - 1], left[ear], left[(ear + 1) % len(left)]))
        del left[ear]
    ears += [(left[0], left[i], left[i + 1]) for i in range(1, len(left) - 1)]
    return np.array(ears, dtype=np.int64)


def _is_ear(flat, left, j, sign):
    """Whether corner left[j] of the polygon left (ids into flat (k, 2)) is convex and its
    triangle with its two neighbours holds no other corner."""
    a, b, c = flat[left[j - 1]], flat[left[j]], flat[left[(j + 1) % len(left)]]
    if sign * _turn(a, b, c) <= 0:
        return False
    others = flat[[i for i in left if i not in (left[j - 1], left[j], left[(j + 1) % len(left)])]]
    inside = (sign * _turn(a, b, others) >= 0) & (sign * _turn(b, c, others) >= 0) \
        & (sign * _turn(c, a, others) >= 0)
    return not inside.any()


def _turn(a, b, c):
    """z of (b - a) x (c - a): positive where a, b, c turn counter-clockwise."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) \
        - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def read_obj(path, faces=True):
    """Vertices and polygons of a Wavefront OBJ (all groups and objects merged, file order kept);
    faces=False reads the vertices only (no polygons, face lines not looked at).
    MeshError naming the file and line for anything that is not a vertex or face it can read."""
    try:
        with open(path, "r", encoding="utf-8", errors="replace") as fh:
            lines = fh.read().split("\n")      # the lines of iterating the file (newlines unified)
    except OSError as exc:
        raise MeshError(f"cannot read {path}: {exc.strerror}") from exc
    try:
        mesh = _obj_in_bulk(lines, faces)
    except (ValueError, OverflowError):        # a word that is no number, an id past int64
        mesh = None
    if mesh is None:                           # anything unusual: line by line, naming the line
        mesh = _obj_line_by_line(path, lines, faces)
    if len(mesh.loop_vertices) and not (0 <= mesh.loop_vertices.min()
                                        and mesh.loop_vertices.max() < len(mesh.vertices)):
        raise MeshError(f"{path}: a face refers to a vertex that does not exist")
    return mesh


# Lines the bulk reading takes: printable ASCII, where numpy's and Python's word splitting agree
# (spaces and tabs only) and numpy's number parsing is Python's float()/int() (others go line
# by line, which takes any text).
_PLAIN_TEXT = re.compile(r"[ -~\t\n]*")
# face lines with their a/b/c forms cut to a: "f" and signed whole numbers of up to 18 digits
_PLAIN_FACES = re.compile(r"(?:f(?:[ \t]+[+-]?\d{1,18})*[ \t]*(?:\n|$))*")


def _obj_in_bulk(lines, faces):
    """read_obj's mesh with numpy parsing all vertex lines at once and all face lines at once,
    face ids 0-based; None (or ValueError) for lines it cannot read exactly as line by line."""
    vertex_lines = [line for line in lines if line.startswith("v ")]
    if not _PLAIN_TEXT.fullmatch("\n".join(vertex_lines)):
        return None
    vertices = (np.loadtxt(vertex_lines, usecols=(1, 2, 3), comments=None, ndmin=2)
                if vertex_lines else np.zeros((0, 3)))
    face_lines = [line for line in lines if line.startswith("f ")] if faces else []
    polygons = _faces_in_bulk("\n".join(face_lines), len(face_lines))
    if polygons is None:
        return None
    totals, ids = polygons
    # OBJ indices are 1-based; negatives count back from the end (out of range: read_obj says so)
    return PolyMesh(vertices, totals, np.where(ids < 0, ids + len(vertices), ids - 1))


def _faces_in_bulk(block, count):
    """(corners per face line, their vertex ids as written) of `count` face lines joined by
    newlines, or None if a line is not plain (see _PLAIN_FACES)."""
    if not count:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not _PLAIN_TEXT.fullmatch(block) or re.search(r"(?:^|[ \t\n])/", block):
        return None
    block = re.sub(r"/[^ \t\n]*", "", block)             # a/b/c -> a
    if not _PLAIN_FACES.fullmatch(block):
        return None
    codes = np.frombuffer(block.encode("ascii"), dtype=np.uint8)
    blank = np.isin(codes, (ord(" "), ord("\t"), ord("\n")))
    word_starts = ~blank & np.append(True, blank[:-1])
    words = np.bincount(np.cumsum(codes == ord("\n"))[word_starts], minlength=count)
    ids = np.fromstring(block.replace("f", " "), dtype=np.int64, sep=" ")
    totals = words - 1                                   # the line's own "f" is no corner
    return (totals, ids) if len(ids) == totals.sum() else None


def _obj_line_by_line(path, lines, faces):
    """read_obj's mesh read one line at a time: MeshError at the first malformed line."""
    vertices, polygons = [], []
    for number, line in enumerate(lines, 1):
        if line.startswith("v "):
            vertices.append(_obj_numbers(line, float, f"{path}, line {number}"))
        elif faces and line.startswith("f "):
            polygons.append(_obj_numbers(line, int, f"{path}, line {number}"))
    verts = np.array(vertices, dtype=np.float64).reshape(-1, 3)
    n = len(verts)
    fixed = []
    for f in polygons:
        # OBJ indices are 1-based; negatives count back from the end
        idx = [i + n if i < 0 else i - 1 for i in f]
        if any(i < 0 or i >= n for i in idx):
            raise MeshError(f"{path}: a face refers to a vertex that does not exist")
        fixed.append(np.array(idx, dtype=np.int64))
    return PolyMesh.from_faces(verts, fixed)


def _obj_numbers(line, kind, where):
    """A vertex line's three coordinates (kind float; more, e.g. a colour, are ignored) or a
    face line's vertex indices (kind int)."""
    tokens = line.split()[1:]
    try:
        if kind is float:
            numbers = [float(tok) for tok in tokens[:3]] if len(tokens) >= 3 else None
        else:
            numbers = [int(tok.split("/")[0]) for tok in tokens]
    except ValueError:
        numbers = None
    if numbers is None:
        what = "vertex" if kind is float else "face"
        raise MeshError(f"{where}: malformed {what} line {line.strip()[:40]!r}")
    return numbers


def write_obj(path, mesh, header=None):
    with open(path, "w", encoding="utf-8") as fh:
        if header:
            fh.write("".join(f"# {line}\n" for line in header.splitlines()))
        np.savetxt(fh, mesh.vertices, fmt="v %.7g %.7g %.7g")
        for face in mesh.faces():
            fh.write("f " + " ".join(str(i + 1) for i in face) + "\n")


# Vertices closer than this (x the bounding-box diagonal) are one point (docs/method.md §2).
WELD_TOLERANCE = 1e-6


def welded(mesh):
    """(the mesh with its split copies joined, (n,) welded vertex id of every original vertex).

    Exporters split vertices where the UV map is cut (glTF, FBX), or give every polygon its own:
    the copies lie within WELD_TOLERANCE of the diagonal of each other, on open border edges
    that are also there twice (the two sides of the cut). Those copies become one vertex, the
    first of them in the original order, so welded vertices keep the originals' order and a mesh
    without such copies comes back as it is, with the identity map. Separate parts that only
    touch (eyelashes planted on a lid) are not a cut and stay apart."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    n = len(vertices)
    if n == 0 or not np.all(np.isfinite(vertices)):       # check_mesh says what is wrong
        return mesh, np.arange(n)
    pairs = cKDTree(vertices).query_pairs(WELD_TOLERANCE * diagonal(vertices),
                                          output_type="ndarray")
    if len(pairs):
        on_cut = _on_cut_edges(n, pairs, boundary_edges(mesh.triangles()))
        pairs = pairs[on_cut[pairs[:, 0]] & on_cut[pairs[:, 1]]]
    if not len(pairs):
        return mesh, np.arange(n)
    groups = _groups(n, pairs)
    representatives = np.sort(np.unique(groups, return_index=True)[1])    # each group's first
    # groups numbered in the order of their first vertex: welded order is the original order
    number = np.empty(len(representatives), dtype=np.int64)
    number[groups[representatives]] = np.arange(len(representatives))
    index = number[groups]
    loops = index[np.asarray(mesh.loop_vertices, dtype=np.int64)]
    return PolyMesh(vertices[representatives], np.asarray(mesh.loop_totals), loops), index


def _groups(n, pairs):
    """(n,) a label per vertex: vertices joined by the pairs (chains too) share one."""
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _on_cut_edges(n, pairs, border):
    """(n,) True on the vertices of an open border edge that lies twice at one place (pairs:
    the vertices at one place; border: the (k, 2) open border edges)."""
    place = _groups(n, pairs)
    ends = np.sort(place[border], axis=1)
    keys = ends[:, 0] * n + ends[:, 1]                # one integer per place of an edge
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    twice = (counts[inverse] > 1) & (ends[:, 0] != ends[:, 1])
    mask = np.zeros(n, dtype=bool)
    mask[border[twice].ravel()] = True
    return mask


def corner_normals(corners, normalize=True):
    """Normals of triangles given as corners (..., 3, 3): (v2 - v1) x (v3 - v1), so the
    unnormalised ones have length 2 * area. Degenerate ones stay 0."""
    n = np.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])
    if normalize:
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    return n


def triangle_normals(vertices, triangles, normalize=True):
    """Per-triangle normals of a mesh (corner_normals of its triangles)."""
    return corner_normals(vertices[triangles], normalize)


def vertex_normals(vertices, triangles):
    """Area-weighted vertex normals; vertices on no (non-degenerate) triangle get 0."""
    fn = np.repeat(triangle_normals(vertices, triangles, normalize=False), 3, axis=0)
    corners = triangles.ravel()
    n = np.stack([np.bincount(corners, fn[:, c], minlength=len(vertices)) for c in range(3)],
                 axis=1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def outward_sign(vertices, triangles):
    """+1 if the triangles' winding makes normals point out of the face, else -1.

    Normals of a head or of a face shell point away from the enclosed side: the area-weighted
    sum of n . (p - centre) is positive when they point out (+1 for no triangles at all).
    """
    if len(triangles) == 0:
        return 1.0
    n = triangle_normals(vertices, triangles, normalize=False)
    centroids = vertices[triangles].mean(axis=1)
    centre = centroids.mean(axis=0)
    return 1.0 if np.einsum("ij,ij->", n, centroids - centre) >= 0 else -1.0


def triangle_areas(vertices, triangles):
    return 0.5 * np.linalg.norm(triangle_normals(vertices, triangles, normalize=False), axis=1)


def vertex_adjacency(n_vertices, triangles):
    """Symmetric sparse vertex-vertex adjacency (edges of the triangles)."""
    i = triangles[:, [0, 1, 2, 1, 2, 0]].ravel()
    j = triangles[:, [1, 2, 0, 0, 1, 2]].ravel()
    return sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices))


def vertex_parts(n_vertices, triangles):
    """Connected part label of every vertex (an unreferenced vertex is a part of its own)."""
    _, labels = connected_components(vertex_adjacency(n_vertices, triangles), directed=False)
    return labels


def unique_edges(triangles, times=None):
    """The triangles' edges (k, 2), each once, lower corner first, in np.unique(axis=0)'s order;
    times: only the edges used by that many triangles (1: the open borders)."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
    size = int(edges.max()) + 1 if len(edges) else 1
    # one integer per edge (row-major, so the order is np.unique(axis=0)'s, several times faster)
    keys, counts = np.unique(edges[:, 0] * size + edges[:, 1], return_counts=True)
    if times is not None:
        keys = keys[counts == times]
    return np.stack([keys // size, keys % size], axis=1).astype(triangles.dtype)


def boundary_edges(triangles):
    """Edges (k, 2) used by exactly one triangle: the open borders."""
    return unique_edges(triangles, times=1)


def boundary_vertices(triangles):
    return np.unique(boundary_edges(triangles))


def valid_triangles(vertices, triangles, rel_eps=1e-12):
    """Triangles with three distinct corners and a non-negligible area."""
    distinct = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) \
        & (triangles[:, 0] != triangles[:, 2])
    scale = np.ptp(vertices, axis=0).max() if len(vertices) else 0.0
    area = triangle_areas(vertices, triangles)
    return distinct & (area > rel_eps * max(scale, 1e-30) ** 2)


def diagonal(vertices, ids=None):
    """Length of the bounding-box diagonal of the vertices (of `ids` only, if given): the one
    scale every relative tolerance and figure in ExClone is measured against."""
    points = vertices if ids is None else vertices[ids]
    return float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0


def checked_triangles(mesh, what="mesh"):
    """(vertices as float64, its valid triangles) of a PolyMesh; MeshError with a user-facing
    message if the pipeline cannot use it."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = mesh.triangles()
    check_mesh(vertices, triangles, what)
    return vertices, triangles[valid_triangles(vertices, triangles)]


def check_mesh(vertices, triangles, what="mesh"):
    """Raise MeshError with a user-facing message for meshes the pipeline cannot use."""
    if len(vertices) == 0 or len(triangles) == 0:
        raise MeshError(f"{what} is empty (no vertices or no faces)")
    if not np.all(np.isfinite(vertices)):
        raise MeshError(f"{what} has vertices with NaN or infinite coordinates")
    if not valid_triangles(vertices, triangles).any():
        raise MeshError(f"{what} is degenerate: every face has zero area")
    extent = np.ptp(vertices[np.unique(triangles)], axis=0)
    if np.sort(extent)[1] <= 1e-9 * extent.max():
        raise MeshError(f"{what} is degenerate: it has no extent in two directions")
    if not 1e-30 < extent.max() < 1e30:     # squared areas (lengths^4) must stay finite
        raise MeshError(f"{what} measures {extent.max():.3g} across, too large or too small to "
                        "compute with; scale it to everyday units")
