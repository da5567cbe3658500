"""Correspondence between the registered source and the target (docs/method.md §7).

Vertex map (ExClone's default): every target vertex is located on the registered source surface
(triangle + barycentric coordinates). A target triangle whose three corners map plausibly (same
facing, no more than 3x stretched or shrunk, each edge's image measured along the source surface
too) takes the gradient of its image triangle on the source, sampled at exactly its own
resolution: exact for identical faces and much better than averaging source gradients where the
deformation varies inside one target triangle (eyelids, mouth corners). Measured along the
surface, an image that spans a closed seam (its corners on the upper and on the lower lip, which
touch at rest) is seen to be torn: its gradient would pull the target's lip apart when the
mouth opens.

Triangle pairs (the method's), used where the vertex map is not plausible: pairs are found in
both directions so every target triangle in the covered region gets a source triangle: each
target triangle looks up the source surface at several points inside it (the centroid alone
costs accuracy where triangles are long, e.g. eyelids and mouth corners), and each source
triangle's centroid looks up the target surface. A pair counts only if the two triangles
face the same way (normals within 90 degrees, so the upper lip never takes the lower lip's
gradient) and are closer than a threshold. The result is a weighted pair list.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from .mesh import corner_normals
from .proximity import interpolate

# Barycentric sample points inside a triangle: the centroid and one towards each corner.
SAMPLES = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], dtype=float)
SAMPLES /= SAMPLES.sum(axis=1, keepdims=True)
# A target triangle whose samples lie within this many source edge lengths of its centroid
# is looked up at its centroid alone (which then weighs like all the samples).
SMALL_TRIANGLE = 0.25
# Paths along the source are found this many (start, vertex) distances at a time.
GRAPH_CELLS = 1 << 22


@dataclass
class Correspondence:
    target_triangles: np.ndarray    # (m,) target triangle index of each pair
    source_triangles: np.ndarray    # (m,) source triangle index of each pair
    weights: np.ndarray             # (m,)

    def matrix(self, n_target, n_source):
        """Sparse (n_target x n_source) of the pair weights (duplicates summed)."""
        return sp.csr_matrix((self.weights, (self.target_triangles, self.source_triangles)),
                             shape=(n_target, n_source))


def _lookups(origin, ids, other, samples):
    """For sample points inside the `origin` Surface's triangles `ids`: (index into ids, `other`
    triangle, distance, whether the two face the same way) of each sample's closest point."""
    corners = origin.vertices[origin.triangles[ids]]                    # (m, 3, 3)
    points = np.einsum("sk,tkd->tsd", samples, corners).reshape(-1, 3)  # (m*k, 3)
    _, tri, dist, _ = other.closest(points)
    owner = np.repeat(np.arange(len(ids)), len(samples))
    facing = np.einsum("ij,ij->i", origin.triangle_normals[ids][owner], other.triangle_normals[tri])
    return owner, tri, dist, facing > 0


def _matches(origin, ids, other, samples, max_distance):
    """(index into ids, `other` triangle) of each valid match of _lookups (closer than
    max_distance, facing the same way)."""
    owner, tri, dist, facing = _lookups(origin, ids, other, samples)
    ok = (dist < max_distance) & facing
    return owner[ok], tri[ok]


def _target_matches(source, target, ids, max_distance):
    """_matches of the target triangles `ids` on the source, and each match's weight: the
    centroid first; the other SAMPLES only in the triangles SMALL_TRIANGLE source edges across
    or more (in a smaller one they land where the centroid does: the centroid weighs for all)
    whose centroid is near enough that one of them may match (a sample lies at most `reach`
    from the centroid: beyond max_distance + reach none can)."""
    _, c_to, c_dist, facing = _lookups(target, ids, source, SAMPLES[:1])
    c_from = np.flatnonzero((c_dist < max_distance) & facing)
    corners = target.vertices[target.triangles[ids]]
    # a sample's weights differ from the centroid's by d (summing to 0): it lies at most
    # |d|_1 times the furthest corner's distance from the centroid
    reach = np.linalg.norm(corners - corners.mean(axis=1)[:, None], axis=2).max(axis=1) * np.abs(
        SAMPLES[1:] - SAMPLES[0]).sum(axis=1).max()
    large = reach >= SMALL_TRIANGLE * source.mean_edge_length
    split = np.flatnonzero(large & (c_dist < max_distance + reach))
    s_from, s_to = _matches(target, ids[split], source, SAMPLES[1:], max_distance)
    weights = np.where(large[c_from], 1.0, len(SAMPLES)) / len(SAMPLES)
    return (np.r_[c_from, split[s_from]], np.r_[c_to[c_from], s_to],
            np.r_[weights, np.full(len(s_from), 1.0 / len(SAMPLES))])


def source_matches(source, target, max_distance):
    """(source triangle, target triangle) of each source triangle whose centroid matches on the
    target (_matches): the pairs' second direction, which needs no vertex map."""
    return _matches(source, np.arange(len(source.triangles)), target, SAMPLES[:1], max_distance)


def triangle_correspondence(source, target, max_distance, wanted=None, from_source=None):
    """Weighted triangle pairs between a registered source Surface and the target Surface (same
    space). wanted: optional (T_target,) mask of the target triangles that need pairs (default:
    all). from_source: source_matches of the two if already found."""
    wanted = np.ones(len(target.triangles), dtype=bool) if wanted is None else wanted
    ids = np.flatnonzero(wanted)
    t_from, s_to, t_weights = _target_matches(source, target, ids, max_distance)
    t_from = ids[t_from]
    s_from, t_to = source_matches(source, target, max_distance) if from_source is None \
        else from_source
    keep = wanted[t_to]
    s_from, t_to = s_from[keep], t_to[keep]
    # each target sample carries 1/k of its triangle; a source centroid weighs like one sample
    weights = np.r_[t_weights, np.full(len(s_from), 1.0 / len(SAMPLES))]
    return Correspondence(np.r_[t_from, t_to], np.r_[s_to, s_from], weights)


@dataclass
class VertexMap:
    triangle: np.ndarray     # (n,) source triangle under each target vertex (-1 if none)
    bary: np.ndarray         # (n, 3) barycentric coordinates in it
    valid: np.ndarray        # (n,) bool

    def sample(self, values, source_triangles, ids=None):
        """Per-source-vertex values (n_s, ...) at the mapped target vertices `ids` (default: valid)."""
        ids = np.flatnonzero(self.valid) if ids is None else ids
        return interpolate(values, source_triangles, self.triangle[ids], self.bary[ids])


def map_vertices(source, target, max_distance):
    """Locate the target Surface's vertices on the registered source Surface. A vertex maps if
    the closest source point is nearer than max_distance and faces the same way."""
    n = len(target.vertices)
    triangle = np.full(n, -1)
    bary = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    ids = target.used
    _, tri, dist, b = source.closest(target.vertices[ids])
    facing = np.einsum("ij,ij->i", source.triangle_normals[tri], target.vertex_normals[ids])
    triangle[ids], bary[ids], valid[ids] = tri, b, (dist < max_distance) & (facing > 0)
    return VertexMap(triangle, bary, valid)


def mapped_triangles(vertex_map, source, target, stretch=3.0):
    """Target triangles whose corners' images on the source form a plausible triangle: same
    facing, edges and area within `stretch` (squared for the area) of the target's own, each
    edge's image measured along the source surface (_apart_along): where two sides of a seam
    touch (closed lips, closed lids), corners on either side have images a hair apart in space
    but far apart on the source, and such an image tears apart when the seam opens."""
    tris = target.triangles
    ok = vertex_map.valid[tris].all(axis=1)
    image = np.zeros(tris.shape + (3,))
    image[ok] = vertex_map.sample(source.vertices, source.triangles,
                                  tris[ok].ravel()).reshape(-1, 3, 3)
    own = target.vertices[tris]
    lengths = _edge_lengths(own)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = _edge_lengths(image) / lengths
    ok &= np.all((ratio > 1 / stretch) & (ratio < stretch), axis=1)
    image_n, own_n = corner_normals(image, normalize=False), corner_normals(own, normalize=False)
    ok &= source.sign * target.sign * np.einsum("ij,ij->i", image_n, own_n) > 0
    # corners that land in a line make a flat image even when no edge shrank
    with np.errstate(divide="ignore", invalid="ignore"):
        area_ratio = np.linalg.norm(image_n, axis=1) / np.linalg.norm(own_n, axis=1)
    ok &= (area_ratio > 1 / stretch ** 2) & (area_ratio < stretch ** 2)
    ok[ok] = ~_apart_along(vertex_map, source, target.vertices, tris[ok], image[ok],
                           stretch * lengths[ok]).any(axis=1)
    return ok


def _apart_along(vertex_map, source, target_vertices, triangles, image, limit):
    """(T, 3) True where the images of the edges v1v2, v2v3, v3v1 of target triangles (T, 3)
    (their corners' images `image` (T, 3, 3)) lie surely `limit` (T, 3) or further apart along
    the source surface. Images in source triangles that share a corner are near; the others are
    bounded by _path_bound, from below where they may be far, so near images are never taken
    for far ones, and two sides of a seam (a long way round) are told apart."""
    ends = np.sort(np.stack([triangles, triangles[:, [1, 2, 0]]], axis=-1).reshape(-1, 2), axis=1)
    n = len(vertex_map.triangle)
    keys, edge_of = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
    edges = np.column_stack([keys // n, keys % n])
    points = np.zeros((vertex_map.triangle.shape[0], 3))
    points[triangles.ravel()] = image.reshape(-1, 3)
    reach = np.full(len(edges), np.inf)
    np.minimum.at(reach, edge_of, limit.ravel())
    corners = source.triangles[vertex_map.triangle[edges]]                      # (k, 2, 3)
    apart = np.flatnonzero(~_touching(corners[:, 0], corners[:, 1]))
    far = np.zeros(len(edges), dtype=bool)
    if len(apart):
        far[apart] = _path_bound(source, corners[apart], points[edges[apart]], reach[apart],
                                 target_vertices[edges[apart]]) >= reach[apart]
    return far[edge_of].reshape(-1, 3)


def _touching(first, second):
    """(k,) True where source triangles of corners first (k, 3) and second (k, 3) share one."""
    return (first[:, :, None] == second[:, None, :]).any(axis=(1, 2))


def _path_bound(source, corners, points, reach, ends):
    """(k,) a bound of the path along the source between two points (points (k, 2, 3), in the
    source triangles of corners (k, 2, 3), the images of target edges ends (k, 2, 3)) that tells
    whether it is `reach` (k,) or longer: where it is surely shorter, a length above the path (a
    chain of short steps), else one below it, the least over corner pairs (u, v) of the path
    along the source's edges from u to v less |a - u| and |b - v| (inf where that is `reach` or
    more for certain: the search goes no further than needed)."""
    used, graph = _edge_graph(source)
    vertices, corners = source.vertices[used], np.searchsorted(used, corners)
    offsets = np.linalg.norm(vertices[corners] - points[:, :, None], axis=3)      # (k, 2, 3)
    detour = offsets[:, 0, :, None] + offsets[:, 1, None, :]                      # (k, 3, 3)
    bound = (_short_paths(graph, vertices, corners[:, 0], corners[:, 1]) - detour).min(axis=(1, 2))
    rest = np.flatnonzero(bound >= reach)
    chain = _chain_length(source, used, graph, ends[rest], corners[rest], points[rest])
    bound[rest] = chain
    rest = rest[chain >= reach[rest]]
    # the rest by Dijkstra from the first image's nearest corner, nearest searches first, so
    # each batch looks no further than its own pairs need
    start = corners[rest, 0, np.argmin(offsets[rest, 0], axis=1)]
    needed = reach[rest] + offsets[rest, 0].min(axis=1) + offsets[rest, 1].max(axis=1)
    order = np.argsort(needed)
    rows = max(1, GRAPH_CELLS // len(vertices))       # bounded memory: rows x vertices
    for batch in np.array_split(order, -(-len(order) // rows)) if len(order) else ():
        starts, slot = np.unique(start[batch], return_inverse=True)
        near = dijkstra(graph, indices=starts, limit=float(needed[batch].max()))
        along = near[slot.ravel()[:, None], corners[rest[batch], 1]]                  # (b, 3)
        bound[rest[batch]] = (along - offsets[rest[batch], 0].min(axis=1)[:, None]
                              - offsets[rest[batch], 1]).min(axis=1)
    return bound


def _edge_graph(source):
    """(the source surface's vertex ids (m,), sparse (m x m) of its edges' lengths, numbered
    0..m-1 in that order)."""
    used = source.used
    triangles, vertices = np.searchsorted(used, source.triangles), source.vertices[used]
    graph = sp.csr_matrix((np.ones(6 * len(triangles)), (
        triangles[:, [0, 1, 2, 1, 2, 0]].ravel(), triangles[:, [1, 2, 0, 0, 1, 2]].ravel())),
        shape=(len(used), len(used)))
    graph.sum_duplicates()
    graph.data = np.linalg.norm(
        vertices[graph.indices] - vertices[np.repeat(np.arange(len(used)), np.diff(graph.indptr))],
        axis=1)
    return used, graph


def _short_paths(graph, vertices, first, second):
    """(k, 3, 3) the path along the graph's edges from each of the corners first (k, 3) to each
    of second (k, 3): 0 for the same vertex, through one edge or two, else inf."""
    first, second = np.repeat(first, 3, axis=1).ravel(), np.tile(second, 3).ravel()
    step = np.asarray(graph[first, second]).ravel()
    short = np.where(first == second, 0.0, np.where(step > 0, step, np.inf))
    via = graph[first].multiply(graph[second] > 0).tocoo()           # (pair, shared neighbour)
    np.minimum.at(short, via.row, via.data + np.linalg.norm(
        vertices[via.col] - vertices[second[via.row]], axis=1))
    return short.reshape(-1, 3, 3)


def _chain_length(source, used, graph, ends, corners, points):
    """(k,) the length of a path along the source from each image a to b (points (k, 2, 3) in
    the triangles of corners (k, 2, 3), local numbering of _edge_graph) through the closest
    source points of the target edge ends (k, 2, 3) at about one source edge length apart: each
    step straight within a triangle or via the corners, one or two edges apart (inf if not)."""
    length, vertices = np.full(len(ends), np.inf), source.vertices[used]
    pieces = np.ceil(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1) / source.mean_edge_length)
    pieces = np.maximum(pieces, 2).astype(np.int64)
    for count in np.unique(pieces):
        ids = np.flatnonzero(pieces == count)
        share = np.linspace(0.0, 1.0, count + 1)[1:-1]
        inner = ends[ids, :1] + share[None, :, None] * (ends[ids, 1:] - ends[ids, :1])
        met, triangle = source.closest(inner.reshape(-1, 3))[:2]
        chain = np.concatenate([points[ids, :1], met.reshape(len(ids), -1, 3), points[ids, 1:]],
                               axis=1).reshape(-1, 3)
        on = np.concatenate([corners[ids, :1], np.searchsorted(used, source.triangles[
            triangle]).reshape(len(ids), -1, 3), corners[ids, 1:]], axis=1).reshape(-1, 3)
        here, there = np.arange(len(on)) % (count + 1) < count, np.arange(len(on)) % (count + 1) > 0
        off_a = np.linalg.norm(vertices[on[here]] - chain[here, None], axis=2)
        off_b = np.linalg.norm(vertices[on[there]] - chain[there, None], axis=2)
        steps = (_short_paths(graph, vertices, on[here], on[there])
                 + off_a[:, :, None] + off_b[:, None, :]).min(axis=(1, 2))
        same = (on[here] == on[there]).all(axis=1)
        steps[same] = np.linalg.norm(chain[here][same] - chain[there][same], axis=1)
        length[ids] = steps.reshape(len(ids), count).sum(axis=1)
    return length


def _edge_lengths(corners):
    """(T, 3) lengths of the edges v1v2, v2v3, v3v1 of triangles given as corners (T, 3, 3)."""
    return np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)
