"""Correspondence between the registered source and the target.

Vertex map (ExClone's default): every target vertex is located on the registered source surface
(triangle + barycentric coordinates). A target triangle whose three corners map plausibly (same
facing, no more than 3x stretched or shrunk) takes the gradient of its image triangle on the
source, sampled at exactly its own resolution: exact for identical faces and much better than
averaging source gradients where the deformation varies inside one target triangle (eyelids,
mouth corners).

Triangle pairs (the method's, METHOD.md), used where the vertex map is not plausible: pairs are
found in both directions so every target triangle in the covered region gets a source
triangle: each target triangle looks up the source surface at several points inside it (the
centroid alone costs accuracy where triangles are long, e.g. eyelids and mouth corners), and each
source triangle's centroid looks up the target surface. A pair counts only if the two triangles
face the same way (normals within 90 degrees, so the upper lip never takes the lower lip's
gradient) and are closer than a threshold. The result is a weighted pair list.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .mesh import triangle_normals
from .proximity import TriangleSurface, interpolate

# Barycentric sample points inside a triangle: the centroid and one towards each corner.
SAMPLES = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], dtype=float)
SAMPLES /= SAMPLES.sum(axis=1, keepdims=True)


@dataclass
class Correspondence:
    target_triangles: np.ndarray    # (m,) target triangle index of each pair
    source_triangles: np.ndarray    # (m,) source triangle index of each pair
    weights: np.ndarray             # (m,)

    def matrix(self, n_target, n_source):
        """Sparse (n_target x n_source) of the pair weights (duplicates summed)."""
        return sp.csr_matrix((self.weights, (self.target_triangles, self.source_triangles)),
                             shape=(n_target, n_source))



def _matches(from_vertices, from_tris, from_normals, to_surface, to_normals, samples, max_distance):
    """For sample points inside each `from` triangle: (from index, to index) of valid matches."""
    k = len(samples)
    corners = from_vertices[from_tris]                                  # (T, 3, 3)
    points = np.einsum("sk,tkd->tsd", samples, corners).reshape(-1, 3)  # (T*k, 3)
    _, tri, dist, _ = to_surface.closest(points)
    owner = np.repeat(np.arange(len(from_tris)), k)
    ok = (dist < max_distance) & (np.einsum("ij,ij->i", from_normals[owner], to_normals[tri]) > 0)
    return owner[ok], tri[ok]


def triangle_correspondence(source_vertices, source_triangles, target_vertices, target_triangles,
                            max_distance, source_normal_sign=1.0, target_normal_sign=1.0,
                            wanted=None):
    """Weighted triangle pairs between a registered source and the target (same space).

    wanted: optional (T_target,) mask of the target triangles that need pairs (default: all).
    """
    wanted = np.ones(len(target_triangles), dtype=bool) if wanted is None else wanted
    src_n = source_normal_sign * triangle_normals(source_vertices, source_triangles)
    tgt_n = target_normal_sign * triangle_normals(target_vertices, target_triangles)
    src_surface = TriangleSurface(source_vertices, source_triangles)
    tgt_surface = TriangleSurface(target_vertices, target_triangles)
    ids = np.flatnonzero(wanted)
    t_from, s_to = _matches(target_vertices, target_triangles[ids], tgt_n[ids], src_surface, src_n,
                            SAMPLES, max_distance)
    t_from = ids[t_from]
    s_from, t_to = _matches(source_vertices, source_triangles, src_n, tgt_surface, tgt_n,
                            SAMPLES[:1], max_distance)
    keep = wanted[t_to]
    s_from, t_to = s_from[keep], t_to[keep]
    # each target sample carries 1/k of its triangle; a source centroid weighs like one sample
    weights = np.r_[np.full(len(t_from), 1.0 / len(SAMPLES)), np.full(len(s_from), 1.0 / len(SAMPLES))]
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


def map_vertices(source_vertices, source_triangles, target_vertices, target_normals, target_ids,
                 max_distance, source_normal_sign=1.0):
    """Locate target vertices `target_ids` on the registered source surface.

    target_normals: (n, 3) outward target vertex normals. A vertex maps if the closest source
    point is nearer than max_distance and faces the same way.
    """
    n = len(target_vertices)
    triangle = np.full(n, -1)
    bary = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    surface = TriangleSurface(source_vertices, source_triangles)
    _, tri, dist, b = surface.closest(target_vertices[target_ids])
    src_n = source_normal_sign * triangle_normals(source_vertices, source_triangles)[tri]
    ok = (dist < max_distance) & (np.einsum("ij,ij->i", src_n, target_normals[target_ids]) > 0)
    triangle[target_ids], bary[target_ids], valid[target_ids] = tri, b, ok
    return VertexMap(triangle, bary, valid)


def mapped_triangles(vertex_map, source_vertices, source_triangles, target_vertices,
                     target_triangles, source_normal_sign=1.0, target_normal_sign=1.0, stretch=3.0):
    """Target triangles whose corners' images on the source form a plausible triangle: same
    facing, edges and area within `stretch` (squared for the area) of the target's own."""
    ok = vertex_map.valid[target_triangles].all(axis=1)
    corners = np.zeros(target_triangles.shape + (3,))
    ids = target_triangles[ok]
    corners[ok] = vertex_map.sample(source_vertices, source_triangles, ids.ravel()).reshape(-1, 3, 3)
    image_edges = np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)
    own = target_vertices[target_triangles]
    own_edges = np.linalg.norm(own[:, [1, 2, 0]] - own, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = image_edges / own_edges
    ok &= np.all((ratio > 1 / stretch) & (ratio < stretch), axis=1)
    image_n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    own_n = np.cross(own[:, 1] - own[:, 0], own[:, 2] - own[:, 0])
    ok &= source_normal_sign * target_normal_sign * np.einsum("ij,ij->i", image_n, own_n) > 0
    # corners that land in a line make a flat image even when no edge shrank
    with np.errstate(divide="ignore", invalid="ignore"):
        area_ratio = np.linalg.norm(image_n, axis=1) / np.linalg.norm(own_n, axis=1)
    ok &= (area_ratio > 1 / stretch ** 2) & (area_ratio < stretch ** 2)
    return ok
