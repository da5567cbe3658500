"""The source's own shape space fitted to the target: where the registration starts.

A source that ships modes of how its neutral varies between faces (the bundled library: the ICT
identity model's first modes) is first made the face of that space nearest the target, its
similarity refined with it; the non-rigid registration then starts from that face rather than
from the rigidly aligned neutral. The registration stops in the minimum its first steps lead to
(docs/method.md §6), and from a face of the target's proportions that is the right one: on new ICT
identities the source's points land 0.07-0.19% of the diagonal from their true places on average
against 0.53-1.80% from the neutral. A face the space does not make (its weights implausible) is
left to start from the neutral.

The fit is Gauss-Newton on point-to-plane distances to the target's closest points (a small share
of the point-to-point distance keeps sliding bounded), the similarity linearised beside the modes'
weights, the weights a priori standard normal and bounded (lsq_linear).
"""
import numpy as np
from scipy.optimize import lsq_linear
from scipy.stats import chi2
from scipy.spatial.transform import Rotation

from .proximity import interpolate
from .registration import Schedule, closest_valid_points

# What the modes leave unexplained of a face, x the target's diagonal: the prior's scale (a
# weight's standard deviation is 1).
UNEXPLAINED = 0.01
# The weights' bound, in standard deviations.
WEIGHT_BOUND = 3.0
# A face the space calls plausible: its weights' squared norm within this quantile of the
# chi-square distribution of k standard normal weights. A face beyond it (a stylised head, a
# low-poly one) is not one of the space's faces, and its nearest face only misleads the start.
PLAUSIBLE = 0.999
# The point-to-point share beside the point-to-plane distance.
ALONG_SURFACE = 0.05
# Gauss-Newton steps (it settles in 3-5), and the largest move of a point (x diagonal) below
# which it stops.
STEPS = 8
SETTLED = 1e-5
# Points the fit reads (evenly over the region's vertices): enough for 30 modes and a similarity.
SAMPLE = 2000


def fit_shape_space(aligned, target, modes, max_distance):
    """The face of the source's shape space nearest the target Surface, and the similarity that
    places it.

    aligned: the source Surface in the target's frame (the rigid alignment); modes: (k, n, 3)
    in the aligned frame (the source's modes rotated and scaled with it); max_distance: the
    closest points' cut-off (x the target's diagonal).
    Returns (R, s, t, weights, face): the similarity to apply on top of the aligned source, the
    modes' weights (k,), and the face's vertices (n, 3) (the moved neutral plus the weighted
    modes, moved).
    """
    diagonal = target.diagonal
    # border points match the target's border as the registration's do
    border_distance = Schedule().border_distance * diagonal
    ids = aligned.used[::max(1, len(aligned.used) // SAMPLE)]
    # never changed in place (each step makes new arrays): no copies
    neutral, modes = aligned.vertices, np.asarray(modes, dtype=np.float64)
    k = len(modes)
    weights = np.zeros(k)
    total_r, total_s, total_t = np.eye(3), 1.0, np.zeros(3)
    face = neutral
    for _ in range(STEPS):
        step, centre = _gauss_newton_step(aligned.moved(face), ids, target, modes, weights,
                                          max_distance * diagonal, border_distance)
        if step is None:
            break
        weights = weights + step[:k]
        r = Rotation.from_rotvec(step[k:k + 3]).as_matrix()
        s = 1.0 + step[k + 6]
        t = centre + step[k + 3:k + 6] - s * r @ centre
        neutral, modes = neutral @ r.T * s + t, modes @ r.T * s
        total_r, total_s, total_t = r @ total_r, s * total_s, s * (r @ total_t) + t
        moved, face = face, neutral + np.tensordot(weights, modes, 1)
        if np.abs(face[ids] - moved[ids]).max() < SETTLED * diagonal:
            break
    return total_r, total_s, total_t, weights, face


def plausible(weights):
    """Whether the fitted weights make a face of the space (PLAUSIBLE)."""
    return bool(np.sum(np.square(weights)) <= chi2.ppf(PLAUSIBLE, len(weights)))


def _gauss_newton_step(face, ids, target, modes, weights, max_distance, border_distance):
    """One step of (weights, rotation vector, translation, scale - 1) about the face's centre,
    or (None, None) if too few points found the target."""
    closest, valid, _ = closest_valid_points(face.vertices[ids], face.vertex_normals[ids],
                                             face.on_border[ids], target, max_distance,
                                             border_distance)
    if valid.sum() < 3 * len(modes):
        return None, None
    points, closest = face.vertices[ids[valid]], closest[valid]
    _, triangle, _, barycentric = target.closest(closest)
    normals = interpolate(target.vertex_normals, target.triangles, triangle, barycentric)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centre = points.mean(axis=0)
    columns = _motion_columns(modes[:, ids[valid]], points - centre)      # (c, m, 3)
    residual = closest - points
    rows = np.vstack([np.einsum("cmj,mj->mc", columns, normals),
                      ALONG_SURFACE * columns.reshape(len(columns), -1).T])
    rhs = np.concatenate([np.einsum("mj,mj->m", residual, normals),
                          ALONG_SURFACE * residual.ravel()])
    # the prior: each weight standard normal, the residual's scale UNEXPLAINED
    k = len(modes)
    prior = np.zeros((k, len(columns)))
    prior[:, :k] = np.eye(k) * UNEXPLAINED * target.diagonal
    rows = np.vstack([rows, prior])
    rhs = np.concatenate([rhs, -UNEXPLAINED * target.diagonal * weights])
    lower = np.full(len(columns), -np.inf)
    upper = np.full(len(columns), np.inf)
    lower[:k], upper[:k] = -WEIGHT_BOUND - weights, WEIGHT_BOUND - weights
    # the same problem on the rows' small triangular factor (bounded-variable least squares)
    q, r = np.linalg.qr(rows)
    return lsq_linear(r, q.T @ rhs, bounds=(lower, upper), method="bvls").x, centre


def _motion_columns(modes, offsets):
    """How the points move per unit of each unknown: the modes, a rotation about each axis
    (w x offset), a translation along each axis, and a scaling about the centre."""
    m = len(offsets)
    rotations = np.stack([np.cross(axis, offsets) for axis in np.eye(3)])
    translations = np.broadcast_to(np.eye(3)[:, None, :], (3, m, 3))
    return np.concatenate([modes, rotations, translations, offsets[None]])
