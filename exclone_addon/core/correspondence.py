"""Correspondence between the registered source and the target (docs/method.md §7).

Vertex map (ExClone's default): every target vertex is located on the registered source surface
(triangle + barycentric coordinates). A target triangle whose three corners map plausibly (same
facing, no more than 3x stretched or shrunk) takes the gradient of its image triangle on the
source, sampled at exactly its own resolution: exact for identical faces and much better than
averaging source gradients where the deformation varies inside one target triangle (eyelids,
mouth corners).

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

from .mesh import corner_normals
from .proximity import interpolate

# Barycentric sample points inside a triangle: the centroid and one towards each corner.
SAMPLES = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], dtype=float)
SAMPLES /= SAMPLES.sum(axis=1, keepdims=True)
# A target triangle whose samples lie within this many source edge lengths of its centroid
# is looked up at its centroid alone (which then weighs like all the samples).
SMALL_TRIANGLE = 0.25


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


def triangle_correspondence(source, target, max_distance, wanted=None):
    """Weighted triangle pairs between a registered source Surface and the target Surface (same
    space). wanted: optional (T_target,) mask of the target triangles that need pairs (default:
    all)."""
    wanted = np.ones(len(target.triangles), dtype=bool) if wanted is None else wanted
    ids = np.flatnonzero(wanted)
    t_from, s_to, t_weights = _target_matches(source, target, ids, max_distance)
    t_from = ids[t_from]
    s_from, t_to = _matches(source, np.arange(len(source.triangles)), target, SAMPLES[:1],
                            max_distance)
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
    facing, edges and area within `stretch` (squared for the area) of the target's own."""
    tris = target.triangles
    ok = vertex_map.valid[tris].all(axis=1)
    image = np.zeros(tris.shape + (3,))
    image[ok] = vertex_map.sample(source.vertices, source.triangles,
                                  tris[ok].ravel()).reshape(-1, 3, 3)
    own = target.vertices[tris]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = _edge_lengths(image) / _edge_lengths(own)
    ok &= np.all((ratio > 1 / stretch) & (ratio < stretch), axis=1)
    image_n, own_n = corner_normals(image, normalize=False), corner_normals(own, normalize=False)
    ok &= source.sign * target.sign * np.einsum("ij,ij->i", image_n, own_n) > 0
    # corners that land in a line make a flat image even when no edge shrank
    with np.errstate(divide="ignore", invalid="ignore"):
        area_ratio = np.linalg.norm(image_n, axis=1) / np.linalg.norm(own_n, axis=1)
    ok &= (area_ratio > 1 / stretch ** 2) & (area_ratio < stretch ** 2)
    return ok


def _edge_lengths(corners):
    """(T, 3) lengths of the edges v1v2, v2v3, v3v1 of triangles given as corners (T, 3, 3)."""
    return np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)
