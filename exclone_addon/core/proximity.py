"""Closest points on triangle surfaces (cKDTree over centroids + exact point-triangle distance)."""
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree

from .errors import ExCloneError

# Closest-point queries are answered this many points at a time: a chunk's candidates (k per
# point) stay in cache (20,000 at a time took 20% more CPU on a 50k-vertex target), and what a
# chunk thread frees stays with its own allocator arena, out of the main thread's reach: at
# 8,192 the 50k clone's peak grew 394 -> 469 MiB with two chunk threads, at 2,048 to 409 MiB,
# for 4% more CPU in the query (the same results).
POINTS_PER_CHUNK = 2048
# Triangles per KD-tree leaf: a query for k = 12 candidates ends in fewer leaves than with
# scipy's 16 (10% less CPU for a 50k-vertex head's points on a 9k-vertex face, 1% more for
# the face's on the head; the same candidates).
LEAF_SIZE = 24
# Queries of more points than this are answered in chunks, this many at once, each on a thread.
PARALLEL_POINTS = 5000
CHUNK_THREADS = 2


def components_dot(x, y):
    """Row-wise dot product of component-first arrays (3, ...): a product per coordinate, several
    times faster than a sum over a strided axis of 3."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _closest_weights(ap, ab, ac, ab_ab, ab_ac, ac_ac):
    """Weights (v, w) of the closest point a + v ab + w ac on triangles (a, b, c) to points p.

    Ericson, Real-Time Collision Detection, 5.1.5, vectorised: ap = p - a, ab, ac component
    first (3, ...); ab_ab, ab_ac, ac_ac the edges' dot products, so two dot products per pair.
    """
    d1, d2 = components_dot(ab, ap), components_dot(ac, ap)
    d3, d4 = d1 - ab_ab, d2 - ab_ac          # the same against b (bp = ap - ab)
    d5, d6 = d1 - ab_ac, d2 - ac_ac          # and against c
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        t_ab = d1 / ab_ab
        t_ac = d2 / ac_ac
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # Ericson's region tests in reverse priority (A, B, AB, C, AC, BC win in that order), so
    # that the last assignment is the one his early-outs would return.
    for mask, region_v, region_w in (
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1 - t_bc, t_bc),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, t_ac),
        ((d6 >= 0) & (d5 <= d6), 0.0, 1.0),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), t_ab, 0.0),
        ((d3 >= 0) & (d4 <= d3), 1.0, 0.0),
        ((d1 <= 0) & (d2 <= 0), 0.0, 0.0),
    ):
        np.copyto(v, region_v, where=mask)
        np.copyto(w, region_w, where=mask)
    bad = ~(np.isfinite(v) & np.isfinite(w))       # degenerate triangle: take corner a
    v[bad] = 0.0
    w[bad] = 0.0
    return v, w


def closest_points_on_triangles(points, a, b, c):
    """Closest point on triangle (a, b, c) to each point, all (m, 3); returns (closest, bary (m, 3))."""
    a, ab, ac = (np.asarray(x, dtype=np.float64).T for x in (a, b - a, c - a))
    ap = np.asarray(points, dtype=np.float64).T - a
    v, w = _closest_weights(ap, ab, ac, components_dot(ab, ab), components_dot(ab, ac),
                            components_dot(ac, ac))
    closest = (a + v * ab + w * ac).T
    return closest, np.stack([1 - v - w, v, w], axis=1)


class TriangleSurface:
    """A triangle set that answers closest-point queries.

    Candidates are the k triangles with the nearest centroids (exact for reasonably uniform
    meshes; k grows the safety margin).
    """

    def __init__(self, vertices, triangles, k=12):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles)
        if len(self.triangles) == 0:
            raise ExCloneError("no surface to search: the mesh region has no triangles")
        self.k = min(k, len(self.triangles))
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        self.tree = cKDTree((a + b + c) / 3, leafsize=LEAF_SIZE)
        # per triangle, component first: corner a, edges ab and ac, and their dot products
        self._a, self._ab, self._ac = (np.ascontiguousarray(x.T) for x in (a, b - a, c - a))
        self._dots = (components_dot(self._ab, self._ab), components_dot(self._ab, self._ac),
                      components_dot(self._ac, self._ac))

    def closest(self, points):
        """Returns (closest points (m,3), triangle ids (m,), distances (m,), barycentric (m,3))."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        # threads only pay off for large queries; small ones lose more to the pool's start-up
        if len(points) <= PARALLEL_POINTS:
            return self._closest(points)
        # equal chunks, two at a time, each wholly on one thread (numpy and the KD-tree release
        # the GIL): both cores for the exact distances too, not only for the KD-tree's search
        chunks = np.array_split(points, max(CHUNK_THREADS, -(-len(points) // POINTS_PER_CHUNK)))
        with ThreadPoolExecutor(max_workers=CHUNK_THREADS) as pool:
            parts = list(pool.map(self._closest, chunks))
        return tuple(np.concatenate(part) for part in zip(*parts))

    def _closest(self, points):
        """closest() of one chunk of points."""
        m = len(points)
        if m == 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3))
        _, cand = self.tree.query(points, k=self.k)
        cand = cand.reshape(m, -1)                                    # (m, k) candidates
        ap = np.ascontiguousarray(points.T)[:, :, None] - self._a.take(cand, axis=1)  # (3, m, k)
        ab, ac = self._ab.take(cand, axis=1), self._ac.take(cand, axis=1)
        v, w = _closest_weights(ap, ab, ac, *(d[cand] for d in self._dots))
        offset = ap - v * ab - w * ac                                 # closest point -> point
        squared = components_dot(offset, offset)
        best = np.argmin(squared, axis=1)
        rows = np.arange(m)
        v, w = v[rows, best], w[rows, best]
        return (points - offset[:, rows, best].T, cand[rows, best], np.sqrt(squared[rows, best]),
                np.stack([1 - v - w, v, w], axis=1))


def interpolate(values, triangles, triangle_ids, bary):
    """Per-vertex values (n, ...) evaluated at barycentric locations on triangles."""
    corners = triangles[triangle_ids]                               # (m, 3)
    weights = bary.reshape(bary.shape + (1,) * (np.ndim(values) - 1))
    # corner by corner, summed in the order a sum over the corners takes (the same values), at
    # half the CPU of gathering (m, 3, ...) first
    return (weights[:, 0] * values[corners[:, 0]] + weights[:, 1] * values[corners[:, 1]]
            + weights[:, 2] * values[corners[:, 2]])


class SegmentSet:
    """Line segments (e.g. a mesh's open border edges) that answer closest-point queries."""

    def __init__(self, vertices, edges, k=8):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.edges = np.asarray(edges)
        self.k = min(k, len(self.edges))
        self.tree = cKDTree(self.vertices[self.edges].mean(axis=1)) if len(self.edges) else None

    def closest(self, points):
        """Returns (closest points (m,3), edge ids (m,), distances (m,), weight of the 2nd end (m,))."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = len(points)
        if self.tree is None or m == 0:    # no segments (a closed mesh) or nothing to look up
            return np.zeros((m, 3)), np.full(m, -1), np.full(m, np.inf), np.zeros(m)
        _, cand = self.tree.query(points, k=self.k)
        cand = cand.reshape(m, -1)
        a = self.vertices[self.edges[cand, 0]]
        b = self.vertices[self.edges[cand, 1]]
        ab = b - a
        length2 = np.einsum("ijk,ijk->ij", ab, ab)
        t = np.einsum("ijk,ijk->ij", points[:, None] - a, ab) / np.where(length2 > 0, length2, 1.0)
        t = np.clip(t, 0.0, 1.0)
        pts = a + t[..., None] * ab
        dist = np.linalg.norm(pts - points[:, None], axis=2)
        best = np.argmin(dist, axis=1)
        rows = np.arange(m)
        return pts[rows, best], cand[rows, best], dist[rows, best], t[rows, best]
