"""Deformation gradients of triangle meshes as sparse linear operators.

For triangle j with corners (v1, v2, v3) deformed to (v1', v2', v3'), the gradient Q_j solves
Q_j V_j = V_j'. Two forms (docs/method.md §5):

- reduced (the thesis' contribution, the default): V = [v2-v1, v3-v1] (3x2), V = Q R (thin QR),
  V^+ = R^-1 Q^T, Q_j = [v2'-v1', v3'-v1'] V^+. Linear in the three deformed vertices only, so the
  unknowns are the vertices alone. Q_j ignores the normal direction (it maps it to 0).
- augmented (Sumner & Popovic 2004): a 4th vertex v4 = v1 + n / sqrt(|n|) per triangle makes V
  3x3 and invertible; the 4th vertices become extra unknowns (columns n_vertices + j).

Layout: an operator G maps unknowns X (N, 3) to G @ X (3T, 3) with (G @ X)[3j + c, r] = Q_j[r, c],
i.e. the gradients stacked transposed, one 3x3 block per triangle; the same G serves x, y and z.
"""
import numpy as np
import scipy.sparse as sp

from .errors import ExCloneError
from .mesh import triangle_normals

REDUCED = "reduced"
AUGMENTED = "augmented"
FORMULATIONS = (REDUCED, AUGMENTED)


def checked_formulation(name):
    """The formulation `name`, or ExCloneError naming the valid ones."""
    if name not in FORMULATIONS:
        raise ExCloneError(f"unknown formulation {name!r}; use one of: {', '.join(FORMULATIONS)}")
    return name

# Corner weights of the edge matrices: E = corners^T @ B, i.e. edges v2-v1, v3-v1 (and v4-v1).
_EDGES_3 = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
_EDGES_4 = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def corner_edges(corners):
    """(v2 - v1, v3 - v1), each (..., 3), of triangles given as corners (..., 3, 3)."""
    return corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]


def _fourth_corner(corners):
    """Sumner's 4th vertex for triangles given as corners (..., 3, 3): v1 + n / sqrt(|n|)."""
    return corners[..., 0, :] + fourth_offsets(*corner_edges(corners))


def fourth_offsets(first_edges, second_edges, axis=-1):
    """v4 - v1 of Sumner's 4th vertex from triangles' edges v2 - v1 and v3 - v1 (xyz along
    `axis`): n / sqrt(|n|) with n = first x second; 0 where the triangle is degenerate."""
    # each coordinate contiguous: the products below run several times faster than on strides
    a = np.ascontiguousarray(np.moveaxis(first_edges, axis, 0))
    b = np.ascontiguousarray(np.moveaxis(second_edges, axis, 0))
    n = np.empty(np.broadcast_shapes(a.shape, b.shape))
    scratch = np.empty(n.shape[1:])
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):     # the cross product
        np.multiply(a[i], b[j], out=n[k])
        n[k] -= np.multiply(a[j], b[i], out=scratch)
    root = np.multiply(n[0], n[0])                              # sqrt(|n|)
    root += np.multiply(n[1], n[1], out=scratch)
    root += np.multiply(n[2], n[2], out=scratch)
    np.sqrt(np.sqrt(root, out=root), out=root)
    np.divide(n, root, out=n, where=root > 0)
    np.copyto(n, 0.0, where=root == 0)
    return np.moveaxis(n, 0, axis)


def fourth_vertices(vertices, triangles):
    """Sumner's 4th vertex per triangle: v1 + n / sqrt(|n|), n the unnormalised normal."""
    return _fourth_corner(vertices[triangles])


def _augmented_edges(corners):
    """(..., 3, 3) edge matrices [v2-v1, v3-v1, v4-v1] as columns."""
    return np.stack([*corner_edges(corners), _fourth_corner(corners) - corners[..., 0, :]],
                    axis=-1)


def edge_pseudo_inverses(vertices, triangles, rel_eps=1e-10):
    """V^+ = R^-1 Q^T of every triangle's 3x2 edge matrix, (T, 2, 3); zeros for degenerate ones.

    Returns (pinv, ok) where ok marks the triangles whose QR is well conditioned.
    """
    v = vertices[triangles]
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]], axis=2)    # (T, 3, 2)
    q, r = np.linalg.qr(edges)                                          # (T,3,2), (T,2,2)
    scale = np.abs(r[:, 0, 0]) + np.abs(r[:, 1, 1]) + np.abs(r[:, 0, 1])
    ok = (np.abs(r[:, 0, 0]) > rel_eps * scale) & (np.abs(r[:, 1, 1]) > rel_eps * scale) & (scale > 0)
    r_safe = np.where(ok[:, None, None], r, np.eye(2))
    pinv = np.linalg.solve(r_safe, np.swapaxes(q, 1, 2))                # R^-1 Q^T
    pinv[~ok] = 0.0
    return pinv, ok


def augmented_inverses(vertices, triangles, rel_eps=1e-10):
    """V^-1 of every triangle's 3x3 edge matrix with the 4th vertex, (T, 3, 3); zeros if degenerate."""
    return _inverses(_augmented_edges(vertices[triangles]), rel_eps)


def _inverses(edges, rel_eps=1e-10):
    det = np.linalg.det(edges)
    scale = np.linalg.norm(edges, axis=(-2, -1)) ** 3
    ok = np.abs(det) > rel_eps * np.maximum(scale, 1e-300)
    inv = np.linalg.inv(np.where(ok[..., None, None], edges, np.eye(3)))
    inv[~ok] = 0.0
    return inv, ok


def gradient_operator(vertices, triangles, formulation=REDUCED):
    """Sparse G (3T x N) of the rest shape `vertices`; N = n (reduced) or n + T (augmented).

    Returns (G, ok): ok marks non-degenerate triangles (degenerate ones get all-zero rows, so they
    neither pull nor produce NaNs).
    """
    n, t = len(vertices), len(triangles)
    if checked_formulation(formulation) == REDUCED:
        pinv, ok = edge_pseudo_inverses(vertices, triangles)
        coeff = _EDGES_3 @ pinv                                        # (T, 3 corners, 3 columns)
        cols = triangles
        n_unknowns = n
    else:
        inv, ok = augmented_inverses(vertices, triangles)
        coeff = _EDGES_4 @ inv                                         # (T, 4 corners, 3 columns)
        cols = np.concatenate([triangles, n + np.arange(t)[:, None]], axis=1)
        n_unknowns = n + t
    return _stacked_operator(coeff, cols, n_unknowns), ok


def _stacked_operator(coeff, columns, n_unknowns):
    """Sparse (3T x n_unknowns) in G's layout: row 3j + c holds coeff[j, i, c] (T, corners, 3)
    in column columns[j, i] (T, corners)."""
    t, corners = columns.shape
    rows = 3 * np.arange(t)[:, None, None] + np.arange(3)[None, None, :]   # (T, 1, 3)
    rows = np.broadcast_to(rows, (t, corners, 3))
    cols = np.broadcast_to(columns[:, :, None], (t, corners, 3))
    return sp.csr_matrix((coeff.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * t, n_unknowns))


def unknowns_of(vertices, triangles, formulation=REDUCED):
    """The rest-shape unknowns of a formulation: vertices, plus the 4th vertices if augmented."""
    if checked_formulation(formulation) == AUGMENTED:
        return np.concatenate([vertices, fourth_vertices(vertices, triangles)])
    return vertices


def corner_gradients(rest_corners, deformed_corners):
    """Sumner's full 3x3 gradients taking triangles `rest_corners` (T, 3, 3) to each of
    `deformed_corners` (E, T, 3, 3); returns (E, T, 3, 3), zeros for degenerate rest triangles.

    Used for the SOURCE of a transfer: the full gradient also says how the normal direction
    moves, which matters when the target triangle is tilted relative to the source one.
    """
    return deformed_gradients(corner_inverses(rest_corners), deformed_corners)


def corner_inverses(rest_corners):
    """(T, 3, 3) the inverses of rest triangles' (T, 3, 3) edge matrices with the 4th vertex,
    zeros for degenerate ones: corner_gradients' rest share, kept where many deformations of one
    rest shape come one after another."""
    return _inverses(_augmented_edges(rest_corners))[0]


def deformed_gradients(inverses, deformed_corners):
    """corner_gradients from the rest triangles' corner_inverses (T, 3, 3) to each of
    `deformed_corners` (E, T, 3, 3)."""
    return _augmented_edges(deformed_corners) @ inverses


def corner_gradient_operators(rest_vertices, triangles):
    """corner_gradients from the rest triangles of `rest_vertices` (n, 3), split for many
    deformations at once into two sparse operators in G's layout (the gradient is linear in the
    deformed edges, and in the deformed 4th vertex's offset, which itself is not linear):

    - edges (3T x n): applied to the deformed vertices (n, 3), the share of the two edges;
    - normal (3T x T): applied to fourth_offsets of the deformed triangles (T, 3), the rest.
    Zeros for degenerate rest triangles, as corner_gradients."""
    inv, _ = _inverses(_augmented_edges(rest_vertices[triangles]))
    t = len(triangles)
    edges = _stacked_operator(_EDGES_3 @ inv[:, :2, :], triangles, len(rest_vertices))
    normal = _stacked_operator(inv[:, 2:, :], np.arange(t)[:, None], t)
    return edges, normal


def stacked_identity(n_triangles):
    """Right-hand side (3T, 3) meaning 'identity gradient' on every triangle, in G's layout."""
    return np.tile(np.eye(3), (n_triangles, 1))


def stack_gradients(gradients):
    """(..., T, 3, 3) gradients -> (..., 3T, 3) in G's layout (each block transposed)."""
    g = np.swapaxes(np.asarray(gradients), -1, -2)
    return g.reshape(g.shape[:-3] + (-1, 3))


def triangle_adjacency(triangles):
    """Sparse (T x T) 0/1 matrix of triangles sharing an edge."""
    t = len(triangles)
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(t), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    e, o = edges[order], owner[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    # every pair of triangles on the same edge (also non-manifold fans: consecutive pairs suffice
    # to connect them, which is all a smoothness term needs)
    a, b = o[:-1][same], o[1:][same]
    keep = a != b
    a, b = a[keep], b[keep]
    adj = sp.csr_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(t, t))
    adj.data[:] = 1.0
    return adj


def neighbour_difference(triangles):
    """D (3T x 3T): each triangle's 3x3 block minus the mean of its edge neighbours' (0 if none)."""
    adj = triangle_adjacency(triangles)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    mean = sp.diags(np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)) @ adj
    has_neighbours = sp.diags((deg > 0).astype(float))
    return sp.kron(has_neighbours - mean, sp.eye(3), format="csr")


def normal_completion(vertices, triangles, formulation=REDUCED):
    """Constant (3T, 3) to add to G @ X so that the rest shape has identity gradients.

    A reduced gradient at rest is the projector onto its triangle's plane, not I; adding the rest
    normal's projector n n^T makes it I again (the first-order completion of the dropped normal
    direction). Without it a smoothness term would pull every triangle towards its neighbours'
    plane, i.e. flatten the face. The augmented form is already I at rest: zeros.
    """
    if checked_formulation(formulation) == AUGMENTED:
        return np.zeros((3 * len(triangles), 3))
    n = triangle_normals(vertices, triangles)
    return stack_gradients(n[:, :, None] * n[:, None, :])
