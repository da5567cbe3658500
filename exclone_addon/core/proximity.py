"""Closest points on triangle surfaces (cKDTree over centroids + exact point-triangle distance)."""
import numpy as np
from scipy.spatial import cKDTree


def closest_points_on_triangles(points, a, b, c):
    """Closest point on triangle (a, b, c) to each point, all (m, 3); returns (closest, bary (m, 3)).

    Ericson, Real-Time Collision Detection, 5.1.5, vectorised over the rows.
    """
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = points - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = points - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in = vb / denom
        w_in = vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    bary = np.stack([1 - v_in - w_in, v_in, w_in], axis=1)
    # Ericson's region tests in reverse priority (A, B, AB, C, AC, BC win in that order), so
    # that the last assignment is the one his early-outs would return.
    regions = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([0 * t_bc, 1 - t_bc, t_bc], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t_ac, 0 * t_ac, t_ac], 1)),
        ((d6 >= 0) & (d5 <= d6), np.tile([0.0, 0.0, 1.0], (len(points), 1))),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t_ab, t_ab, 0 * t_ab], 1)),
        ((d3 >= 0) & (d4 <= d3), np.tile([0.0, 1.0, 0.0], (len(points), 1))),
        ((d1 <= 0) & (d2 <= 0), np.tile([1.0, 0.0, 0.0], (len(points), 1))),
    ]
    for mask, value in regions:
        bary[mask] = value[mask]
    bad = ~np.all(np.isfinite(bary), axis=1)          # degenerate triangle: take corner a
    bary[bad] = [1.0, 0.0, 0.0]
    closest = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return closest, bary


class TriangleSurface:
    """A triangle set that answers closest-point queries.

    Candidates are the k triangles with the nearest centroids (exact for reasonably uniform
    meshes; k grows the safety margin).
    """

    def __init__(self, vertices, triangles, k=12):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles)
        self.k = min(k, len(self.triangles))
        self.tree = cKDTree(self.vertices[self.triangles].mean(axis=1))

    def closest(self, points, chunk=20000):
        """Returns (closest points (m,3), triangle ids (m,), distances (m,), barycentric (m,3))."""
        points = np.asarray(points, dtype=np.float64)
        if len(points) > chunk:   # bounded memory: k candidates per point add up
            parts = [self.closest(points[i:i + chunk], chunk) for i in range(0, len(points), chunk)]
            return tuple(np.concatenate(p) for p in zip(*parts))
        m = len(points)
        if m == 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3))
        # threads only pay off for large queries; small ones lose more to the pool's start-up
        _, cand = self.tree.query(points, k=self.k, workers=-1 if m > 5000 else 1)
        cand = cand.reshape(m, -1)
        tri = self.triangles[cand.ravel()]
        rep = np.repeat(points, cand.shape[1], axis=0)
        v = self.vertices
        pts, bary = closest_points_on_triangles(rep, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
        dist = np.linalg.norm(pts - rep, axis=1).reshape(m, -1)
        best = np.argmin(dist, axis=1)
        rows = np.arange(m) * cand.shape[1] + best
        return pts[rows], cand[np.arange(m), best], dist[np.arange(m), best], bary[rows]


def interpolate(values, triangles, triangle_ids, bary):
    """Per-vertex values (n, ...) evaluated at barycentric locations on triangles."""
    corners = triangles[triangle_ids]                               # (m, 3)
    v = values[corners]                                             # (m, 3, ...)
    weights = bary.reshape(bary.shape + (1,) * (v.ndim - 2))
    return (weights * v).sum(axis=1)


class SegmentSet:
    """Line segments (e.g. a mesh's open border edges) that answer closest-point queries."""

    def __init__(self, vertices, edges, k=8):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.edges = np.asarray(edges)
        self.k = min(k, len(self.edges))
        self.tree = cKDTree(self.vertices[self.edges].mean(axis=1)) if len(self.edges) else None

    def closest(self, points):
        """Returns (closest points (m,3), edge ids (m,), distances (m,), weight of the 2nd end (m,))."""
        points = np.asarray(points, dtype=np.float64)
        m = len(points)
        if self.tree is None:
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
