"""A mesh prepared once for the pipeline's surface questions (docs/method.md §2).

Landmarks, rigid alignment, registration, correspondence and the parts that follow all ask the
same things of a mesh: which way is out, its outward normals, the closest point on it, its
connected parts, its size and its open borders. A Surface answers each on first use and keeps
the answer, so a fit builds every one of them once per mesh and state, and its steps pass the
Surface on instead of loose arrays.
"""
from functools import cached_property

import numpy as np

from . import mesh
from .proximity import SegmentSet, TriangleSurface


# what depends on the triangles alone, not on where the vertices are, and every moved copy uses
_TOPOLOGY = ("used", "border_edges", "border_ids", "on_border")


class Surface:
    """Vertices (all of a mesh's, in its order) and the triangles that make the surface (its
    valid ones, or a region of them); vertices on no triangle are carried but not part of it."""

    def __init__(self, vertices, triangles, sign=None):
        """sign: the outward sign if already known (see `moved`); found from the winding if None."""
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if sign is not None:
            self.__dict__["sign"] = float(sign)

    def moved(self, vertices):
        """The same triangles on new vertex positions (a deformed or re-aligned copy). The
        outward sign and what depends on the triangles alone (parts, borders) are carried:
        moving a surface neither turns it inside out nor changes its connections."""
        moved = Surface(vertices, self.triangles, self.sign)
        for name in _TOPOLOGY:      # found once here, shared by every copy
            moved.__dict__[name] = getattr(self, name)
        if "parts" in self.__dict__:
            moved.__dict__["parts"] = self.parts
        return moved

    def parts_holding(self, ids):
        """The Surface of the connected parts that hold any of the vertices `ids` (this one if
        that is all of it)."""
        keep = np.isin(self.parts, self.parts[np.asarray(ids, dtype=np.int64)])
        kept = keep[self.triangles[:, 0]]
        return self if kept.all() else Surface(self.vertices, self.triangles[kept])

    @cached_property
    def used(self):
        """Ids of the vertices on the surface (sorted)."""
        return np.unique(self.triangles)

    @cached_property
    def sign(self):
        """+1 if the winding's normals point out of the face, else -1 (mesh.outward_sign)."""
        return mesh.outward_sign(self.vertices, self.triangles)

    @cached_property
    def vertex_normals(self):
        """(n, 3) outward unit vertex normals (0 on vertices off the surface)."""
        return self.sign * mesh.vertex_normals(self.vertices, self.triangles)

    @cached_property
    def triangle_normals(self):
        """(T, 3) outward unit triangle normals."""
        return self.sign * mesh.triangle_normals(self.vertices, self.triangles)

    @cached_property
    def search(self):
        """The closest-point search structure (proximity.TriangleSurface)."""
        return TriangleSurface(self.vertices, self.triangles)

    def closest(self, points):
        """(closest points, triangle ids, distances, barycentric coordinates) on the surface."""
        return self.search.closest(points)

    @cached_property
    def parts(self):
        """(n,) connected part label of every vertex."""
        return mesh.vertex_parts(len(self.vertices), self.triangles)

    @cached_property
    def diagonal(self):
        """Bounding-box diagonal of the surface's vertices (mesh.diagonal)."""
        return mesh.diagonal(self.vertices, self.used)

    @cached_property
    def border_edges(self):
        """(k, 2) open border edges (used by one triangle only)."""
        return mesh.boundary_edges(self.triangles)

    @cached_property
    def border_ids(self):
        """Ids of the vertices on an open border (sorted)."""
        return np.unique(self.border_edges)

    @cached_property
    def on_border(self):
        """(n,) True on the vertices of an open border."""
        mask = np.zeros(len(self.vertices), dtype=bool)
        mask[self.border_ids] = True
        return mask

    @cached_property
    def border_search(self):
        """The closest-point search over the open border edges (proximity.SegmentSet)."""
        return SegmentSet(self.vertices, self.border_edges)

    @cached_property
    def vertex_areas(self):
        """(n,) a third of the area of every triangle around each vertex."""
        third = mesh.triangle_areas(self.vertices, self.triangles) / 3
        return np.bincount(self.triangles.ravel(), np.repeat(third, 3),
                           minlength=len(self.vertices))

    @cached_property
    def border_lengths(self):
        """(n,) half the length of the border edges at each vertex."""
        edges = self.border_edges
        half = np.linalg.norm(self.vertices[edges[:, 1]] - self.vertices[edges[:, 0]], axis=1) / 2
        return np.bincount(edges.ravel(), np.repeat(half, 2), minlength=len(self.vertices))

    @cached_property
    def mean_edge_length(self):
        """Mean length of the triangles' edges: the mesh's own unit of length."""
        edges = self.vertices[self.triangles[:, [1, 2, 0]]] - self.vertices[self.triangles]
        return float(np.linalg.norm(edges, axis=2).mean()) if len(edges) else 0.0
