"""Rigid and non-rigid registration of the source face onto the target (docs/method.md §6).

The non-rigid fit minimises, over the deformed source x,

    w_S E_smooth + w_I E_identity + E_rest + w_C (E_closest + E_target + E_border) [+ E_landmarks]

Each energy term below is a function returning its normal-equation contribution (A, b) (the
term is x^T A x - 2 b^T x + const, one A for x, y and z). w_C ramps up over the schedule's steps
and the closest points are found again at each step. Landmarks are either eliminated from the
unknowns (hard: user-placed ones) or pinned by a soft term (automatic ones). The normal matrix
keeps its sparsity pattern from step to step, so its fill-reducing ordering is computed once.
"""
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from . import deformation
from .errors import ExCloneError
from .proximity import interpolate

# Closest-point weights per step after the landmark-only solve; w_S = 1, w_I = 0.001 (the thesis').
PRESETS = {
    "fast": (1.0, 10.0, 100.0),
    "balanced": (1.0, 5.0, 20.0, 100.0, 500.0),
    "precise": (1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0),
}


@dataclass
class Schedule:
    closest_weights: tuple = PRESETS["balanced"]
    smooth_weight: float = 1.0
    identity_weight: float = 0.001
    max_distance: float = 0.05        # closest points further than this x target diagonal are ignored
    border_distance: float = 0.015    # open borders match borders closer than this x target diagonal
    # None: landmarks are hard constraints (user-placed ones). A number: soft, with this weight
    # per landmark against a closest-point weight of 1 per vertex (automatic ones, which can be
    # off by a few percent and must not pin the fit to their error).
    landmark_weight: float = None

    @classmethod
    def preset(cls, name):
        if name not in PRESETS:
            raise ExCloneError(f"unknown registration preset {name!r}; use one of: "
                               + ", ".join(PRESETS))
        return cls(closest_weights=PRESETS[name])


@dataclass
class Registration:
    vertices: np.ndarray              # (n_source, 3) registered source, in target coordinates
    mean_distance: float              # mean distance to the target surface where the two overlap
    valid_fraction: float             # share of region vertices in the overlap (valid closest point)
    history: list = field(default_factory=list)   # mean distance before each w_C step, and at the end
    # (before each step: over all region vertices with a valid closest point of that step)
    surface: object = None            # surface.Surface of the registered source region


class ReusedOrderingSolver:
    """Repeated sparse SPD solves with one fill-reducing ordering (computed on first use)."""

    def __init__(self):
        self.perm = None

    def solve(self, matrix, rhs):
        try:
            return self._solve(sp.csc_matrix(matrix), rhs)
        except RuntimeError as exc:       # SuperLU: "Factor is exactly singular"
            raise ExCloneError("the registration's equations have no unique solution (the source "
                               "mesh has triangles too thin to deform); clean up the mesh") from exc

    def _solve(self, matrix, rhs):
        if self.perm is None:
            lu = splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
            # perm_c[i] is the new position of column i; the order to apply is its inverse
            self.perm = np.argsort(lu.perm_c)
            return lu.solve(rhs)
        p = self.perm
        inv = np.empty_like(p)
        inv[p] = np.arange(len(p))
        permuted = sp.csc_matrix(matrix[p][:, p])
        lu = splu(permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
        return lu.solve(rhs[p])[inv]


# ------------------------------------------------------------------------------ rigid alignment

def similarity_transform(source_points, target_points):
    """Least-squares similarity (R, s, t) with target ~ s R source + t.

    ExCloneError if no rotation can be read from the pairs: either point set lies on one line
    or at one point, or the pairs cross each other so that no rotation fits them better than
    another (their cross-covariance has rank 1).
    """
    for points, what in ((source_points, "source"), (target_points, "target")):
        if not _spans_a_plane(points):
            raise ExCloneError(f"cannot align the faces: the {what} points lie on one line or at "
                               "one point; landmarks must be spread over the face")
    src_c, dst_c = source_points.mean(axis=0), target_points.mean(axis=0)
    a, b = source_points - src_c, target_points - dst_c
    if not _spans_a_plane(b.T @ a, centred=True):
        raise ExCloneError("cannot align the faces: the point pairs fix no rotation (they pair "
                           "points that do not correspond); check the landmarks")
    rotation, _ = Rotation.align_vectors(b, a)
    r = rotation.as_matrix()
    s = float(np.einsum("ij,ij->", b, a @ r.T) / np.einsum("ij,ij->", a, a))
    return r, s, dst_c - s * r @ src_c


def _spans_a_plane(points, centred=False):
    """Whether the points (k, 3) reach out in two directions at least, relative to their own
    size and (unless centred) their distance from the origin: rank 2 at least."""
    if len(points) < 2 or (len(points) < 3 and not centred):
        return False
    spread = points if centred else points - points.mean(axis=0)
    extent = np.linalg.svd(spread, compute_uv=False)
    return bool(extent[1] > 1e-9 * max(extent[0], 0.0 if centred else np.abs(points).max()))


def similarity_icp(source_points, source_normals, target, max_distance=np.inf, iterations=100,
                   sample=2000, tolerance=1e-3):
    """Refine a rough alignment of the source points to the target Surface by a similarity.

    Each iteration pairs (up to `sample` of) the source points with their closest target points
    (normals within 90 degrees, within max_distance, the worst 10% trimmed) and solves the
    least-squares similarity; it stops when the mean distance improves by less than `tolerance`
    (relative). Returns (R, s, t) to apply on top of the current positions.
    """
    total_r, total_s, total_t = np.eye(3), 1.0, np.zeros(3)
    step = max(1, len(source_points) // sample)
    points, normals = source_points[::step].copy(), source_normals[::step].copy()
    previous = np.inf
    for _ in range(iterations):
        closest, tri, dist, bary = target.closest(points)
        facing = np.einsum("ij,ij->i", interpolate(target.vertex_normals, target.triangles, tri,
                                                   bary), normals)
        ok = (facing > 0) & (dist < max_distance)
        if ok.sum() < 10:
            break
        ok &= dist <= np.quantile(dist[ok], 0.9)
        mean = dist[ok].mean()
        if mean > previous * (1 - tolerance):
            break
        previous = mean
        r, s, t = similarity_transform(points[ok], closest[ok])
        points = points @ r.T * s + t
        normals = normals @ r.T
        total_r, total_s, total_t = r @ total_r, s * total_s, s * (r @ total_t) + t
    return total_r, total_s, total_t


# ------------------------------------------------------------------------------ closest points

def closest_valid_points(points, normals, on_border, target, max_distance, border_distance):
    """Closest points on the target Surface for source points (their outward normals, and
    whether each is on the source's open border).

    Interior source points take the closest surface point whose normal is within 90 degrees,
    not further than max_distance and not on the target's open border. Source points on their
    own open border (eye, mouth, outer edge) take the closest point on the target's border
    edges instead, if it is nearer than border_distance: borders match borders, so eyelid
    margins and lips do not slide. Returns (closest points, valid, distances).
    """
    closest, tri, dist, bary = target.closest(points)
    n_target = interpolate(target.vertex_normals, target.triangles, tri, bary)
    valid = (np.einsum("ij,ij->i", n_target, normals) > 0) & (dist < max_distance)
    valid &= ~target.on_border[target.triangles[tri]].any(axis=1)
    if on_border.any():
        b_closest, _, b_dist, _ = target.border_search.closest(points[on_border])
        closest[on_border] = b_closest
        dist = dist.copy()
        dist[on_border] = b_dist
        valid[on_border] = b_dist < border_distance
    return closest, valid, dist


def _source_to_target(fitted, target, schedule):
    """closest_valid_points of the fitted source region's vertices."""
    region = fitted.used
    return closest_valid_points(fitted.vertices[region], fitted.vertex_normals[region],
                                fitted.on_border[region], target,
                                schedule.max_distance * target.diagonal,
                                schedule.border_distance * target.diagonal)


# ------------------------------------------------------------------------------ energy terms

def smoothness_term(source, grad, formulation):
    """E_smooth = ||D (G x + C)||^2: every triangle's gradient like its edge neighbours' (D the
    neighbour difference; C the normal completion, so the rest shape costs nothing)."""
    difference = deformation.neighbour_difference(source.triangles)
    smooth = difference @ grad
    completion = deformation.normal_completion(source.vertices, source.triangles, formulation)
    return smooth.T @ smooth, smooth.T @ -(difference @ completion)


def identity_term(source, grad):
    """E_identity = ||G x - I||^2: every triangle's gradient near the identity."""
    return grad.T @ grad, grad.T @ deformation.stacked_identity(len(source.triangles))


def rest_term(source, rest):
    """E_rest: vertices on no region triangle are held where they are (a tiny pull that keeps
    the system definite; they take no part in the fit)."""
    outside = np.zeros(len(rest))
    outside[:len(source.vertices)] = 1.0          # 4th vertices (augmented) are all on the region
    outside[source.used] = 0.0
    return sp.diags(outside), outside[:, None] * rest


def closest_point_term(fitted, target, schedule, n_unknowns):
    """E_closest = sum over region vertices with a valid closest target point of ||x_i - c_i||^2.
    Also returns the mean distance of all region vertices to their closest points."""
    closest, valid, distance = _source_to_target(fitted, target, schedule)
    weight = np.zeros(n_unknowns)
    weight[fitted.used[valid]] = 1.0
    points = np.zeros((n_unknowns, 3))
    points[fitted.used] = closest
    return (sp.diags(weight), weight[:, None] * points), float(distance.mean())


def target_pull_term(fitted, pulling, max_distance, n_unknowns):
    """E_target = sum over target points p of w_p ||B_p x - p||^2, B_p the barycentric point of
    the fitted source surface closest to p (symmetric closest points: without it the source can
    settle on part of the target and leave the rest uncovered). Points that land on the source's
    open border, face the other way or are further than max_distance are left out (the target
    may extend past the source, e.g. the back of a head). pulling: (points, normals, weights)."""
    points, normals, weights = pulling
    _, tri, dist, bary = fitted.closest(points)
    corners = fitted.triangles[tri]
    facing = np.einsum("ij,ij->i", interpolate(fitted.vertex_normals, fitted.triangles, tri, bary),
                       normals)
    ok = (dist < max_distance) & (facing > 0) & ~fitted.on_border[corners].any(axis=1)
    rows = np.repeat(np.flatnonzero(ok), 3)
    b = sp.csr_matrix((bary[ok].ravel(), (rows, corners[ok].ravel())),
                      shape=(len(points), n_unknowns))
    return _weighted_normal_equations(b, np.where(ok, weights, 0.0), points)


def border_pull_term(fitted, pulling, max_distance, n_unknowns):
    """E_border: like E_target, for the target's border vertices onto the fitted source's
    border edges (borders match borders). pulling: (points, weights)."""
    points, weights = pulling
    _, edge, dist, t = fitted.border_search.closest(points)
    ok = dist < max_distance
    ends = fitted.border_edges[edge[ok]]
    rows = np.repeat(np.flatnonzero(ok), 2)
    b = sp.csr_matrix((np.stack([1 - t[ok], t[ok]], axis=1).ravel(), (rows, ends.ravel())),
                      shape=(len(points), n_unknowns))
    return _weighted_normal_equations(b, np.where(ok, weights, 0.0), points)


def landmark_term(landmark_ids, landmark_positions, n_unknowns):
    """E_landmarks = sum ||x_l - p_l||^2: soft landmarks, pinned to their target positions."""
    pin = np.zeros(n_unknowns)
    pin[landmark_ids] = 1.0
    positions = np.zeros((n_unknowns, 3))
    positions[landmark_ids] = landmark_positions
    return sp.diags(pin), pin[:, None] * positions


def _weighted_normal_equations(b, weights, points):
    """(B^T W B, B^T W p) of sum_p w_p ||B_p x - p||^2."""
    w = sp.diags(weights)
    return b.T @ w @ b, b.T @ (w @ points)


def _weighted_sum(*weighted_terms):
    """sum of w * (A, b) over (w, (A, b)) pairs."""
    matrix = sum(w * term[0] for w, term in weighted_terms)
    rhs = sum(w * term[1] for w, term in weighted_terms)
    return matrix, rhs


def _solve_with_fixed(solver, matrix, rhs, x, fixed_ids):
    """x with the unknowns fixed_ids kept as they are (hard landmarks, eliminated) and the
    others solved."""
    free = np.ones(len(x), dtype=bool)
    free[fixed_ids] = False
    matrix = sp.csr_matrix(matrix)
    x = x.copy()
    x[free] = solver.solve(matrix[free][:, free], rhs[free] - matrix[free][:, ~free] @ x[~free])
    return x


# ------------------------------------------------------------------------------ the schedule

def register(source, target, landmark_ids, landmark_positions, *, formulation=deformation.REDUCED,
             schedule=None, progress=None):
    """Deform the source (a surface.Surface already aligned to the target's frame, its triangles
    the region to register) onto the target Surface; returns a Registration.

    Source vertices on no region triangle stay where they are. landmark_ids: source vertex ids
    that go to landmark_positions (target coordinates), hard or soft as the schedule says.
    """
    schedule = schedule or Schedule()
    _check_registrable(source, target)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # the target's pulling points are found beside the source's own terms (numpy releases
        # the GIL); the pool then computes each step's target pull beside its closest points
        pulling_job = pool.submit(_pulling_points, source, target)
        grad, _ = deformation.gradient_operator(source.vertices, source.triangles, formulation)
        rest = deformation.unknowns_of(source.vertices, source.triangles, formulation)
        # The gradient terms are unitless, the point terms squared lengths: weighting the former
        # by the squared mean edge length measures distances in source edges, which keeps the
        # weights' meaning the same for any mesh scale and density.
        unit2 = source.mean_edge_length ** 2
        base = _weighted_sum(
            (schedule.smooth_weight * unit2, smoothness_term(source, grad, formulation)),
            (schedule.identity_weight * unit2, identity_term(source, grad)),
            (1.0, rest_term(source, rest)))
        pins = landmark_term(landmark_ids, landmark_positions, len(rest))
        pulling, coarse_pulling, border_pulling = pulling_job.result()
        x = rest.copy()
        x[landmark_ids] = landmark_positions
        solver, history = ReusedOrderingSolver(), []
        # the landmark-only solve starts a fit from hard landmarks; soft ones start from the
        # surfaces
        steps = ((0.0,) if schedule.landmark_weight is None else ()) + tuple(
            schedule.closest_weights)
        for k, w_c in enumerate(steps):
            if progress:
                progress(k / len(steps), f"registration step {k + 1}/{len(steps)}")
            matrix, rhs = base
            if w_c > 0:
                # the steps before the last only bring the fit near: the coarse pull does that
                last = k == len(steps) - 1
                fit_terms, distance = _fit_terms(source.moved(x[:len(source.vertices)]), target,
                                                 pulling if last else coarse_pulling,
                                                 border_pulling, schedule, len(x), pool)
                history.append(distance)
                matrix, rhs = _weighted_sum((1.0, (matrix, rhs)), (w_c, fit_terms))
            if schedule.landmark_weight is None:
                x = _solve_with_fixed(solver, matrix, rhs, x, landmark_ids)
            else:
                pin = schedule.landmark_weight * max(w_c, 1.0)
                x = solver.solve(*_weighted_sum((1.0, (matrix, rhs)), (pin, pins)))
    return _registration(source.moved(x[:len(source.vertices)]), target, schedule, history)


def _check_registrable(source, target):
    if len(source.triangles) == 0 or len(target.triangles) == 0:
        raise ExCloneError("nothing to register: the landmarks lie on no face of the "
                           f"{'source' if len(source.triangles) == 0 else 'target'} mesh")
    if not source.mean_edge_length > 0 or not target.diagonal > 0:
        raise ExCloneError("nothing to register: the face has no extent")


def _pulling_points(source, target):
    """The target points that pull the source, with their weights: interior vertices weigh
    their share of the surface in units of a source vertex's share, border vertices their share
    of the border's length in source edge lengths (so density does not matter). Returns
    (interior, the interior for the steps before the last, border): a target with more interior
    vertices than the source region has pulls there through one per PULL_CELL source edges."""
    interior = np.setdiff1d(target.used, target.border_ids)
    share = target.vertex_areas[interior] / source.vertex_areas[source.used].mean()
    border = target.border_ids
    pulling = (target.vertices[interior], target.vertex_normals[interior], share)
    coarse = pulling if len(interior) <= len(source.used) else \
        _one_per_cell(*pulling, PULL_CELL * source.mean_edge_length)
    return (pulling, coarse,
            (target.vertices[border], target.border_lengths[border] / source.mean_edge_length))


# Grid cell of the coarse target pull, in source edge lengths: one target vertex per cell,
# carrying the whole cell's weight, so the closest-point queries of the steps before the last
# follow the source's density, not the target's (a 50k-vertex head pulls through 16,058 of its
# 49,908 interior vertices; all of them pull in the last step, which decides the fit).
PULL_CELL = 1.0


def _one_per_cell(points, normals, weights, cell):
    """(points, normals, weights) with one point per grid cell `cell` wide (the first in it),
    weighing what the cell's points weighed together: the pull's total and where it acts stay
    as they were, to within a cell. Points facing other octants keep apart (closed lips or lids
    share a cell, and each must pull its own side)."""
    cells = np.floor(points / cell).astype(np.int64)
    cells -= cells.min(axis=0)
    # one number per (cell, octant), in the order of the rows (cell, octant): a tenth of the
    # CPU of np.unique over rows (0.007 s against 0.075 on a 50k-vertex head), same groups
    keys = np.ravel_multi_index((*cells.T, *(normals > 0).T), (*(cells.max(axis=0) + 1), 2, 2, 2))
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return points[first], normals[first], np.bincount(inverse.ravel(), weights)


def _fit_terms(fitted, target, pulling, border_pulling, schedule, n_unknowns, pool):
    """E_closest + E_target + E_border at the current fit, and the mean closest-point distance."""
    _ = fitted.vertex_normals       # computed once, before both threads read them
    # the target-to-source pull is computed beside the source-to-target closest points (numpy
    # and the KD-tree release the GIL, so the two use both cores)
    pull_job = pool.submit(target_pull_term, fitted, pulling,
                           schedule.max_distance * target.diagonal, n_unknowns)
    closest, distance = closest_point_term(fitted, target, schedule, n_unknowns)
    border = border_pull_term(fitted, border_pulling, schedule.border_distance * target.diagonal,
                              n_unknowns)
    return _weighted_sum((1.0, closest), (1.0, pull_job.result()), (1.0, border)), distance


def _registration(registered, target, schedule, history):
    """The Registration of the final fit (history: the mean distances before each step). Its
    error counts where the surfaces overlap: source parts that reach past the target (a neck
    below a head's cut) have no closest point to be measured against."""
    if not np.all(np.isfinite(registered.vertices)):
        raise ExCloneError("registration produced invalid values; check the meshes and landmarks")
    _, overlap, distances = _source_to_target(registered, target, schedule)
    mean_distance = float(distances[overlap].mean()) if overlap.any() else float(distances.mean())
    return Registration(registered.vertices, mean_distance, float(overlap.mean()),
                        history + [mean_distance], registered)
