"""Non-rigid registration of the source face onto the target (METHOD.md, "Registration").

min over the deformed source of w_S E_smooth + w_I E_identity + w_C E_closest, with the landmark
vertices fixed at their target positions (eliminated from the unknowns). Solved as sparse normal
equations per coordinate; w_C ramps up over the steps and closest points are recomputed each step.
The normal matrix changes only on its diagonal between steps, so its fill-reducing ordering is
computed once and reused (the symbolic part of the factorisation).
"""
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation
from scipy.sparse.linalg import splu

from . import deformation
from .mesh import boundary_edges, diagonal, triangle_areas, vertex_normals
from .proximity import SegmentSet, TriangleSurface, interpolate

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
            raise ValueError(f"unknown preset {name!r}; use one of {sorted(PRESETS)}")
        return cls(closest_weights=PRESETS[name])


@dataclass
class Registration:
    vertices: np.ndarray              # (n_source, 3) registered source, in target coordinates
    mean_distance: float              # mean distance to the target surface where the two overlap
    valid_fraction: float             # share of region vertices in the overlap (valid closest point)
    history: list = field(default_factory=list)   # mean distance before each w_C step, and at the end
    # (before each step: over all region vertices with a valid closest point of that step)


class ReusedOrderingSolver:
    """Repeated sparse SPD solves with one fill-reducing ordering (computed on first use)."""

    def __init__(self):
        self.perm = None

    def solve(self, matrix, rhs):
        matrix = sp.csc_matrix(matrix)
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


def closest_valid_points(points, normals, on_border, surface, surface_normals, border,
                         border_edges, max_distance, border_distance):
    """Closest target points for source points.

    Interior source points take the closest surface point whose normal is within 90 degrees,
    not further than max_distance and not on the target's open border. Source points on their
    own open border (eye, mouth, outer edge) take the closest point on the target's border
    edges instead, if it is nearer than border_distance: borders match borders, so eyelid
    margins and lips do not slide. Returns (closest points, valid, distances).
    """
    closest, tri, dist, bary = surface.closest(points)
    n_target = interpolate(surface_normals, surface.triangles, tri, bary)
    valid = (np.einsum("ij,ij->i", n_target, normals) > 0) & (dist < max_distance)
    valid &= ~border[surface.triangles[tri]].any(axis=1)
    if on_border.any():
        b_closest, _, b_dist, _ = border_edges.closest(points[on_border])
        closest[on_border] = b_closest
        dist = dist.copy()
        dist[on_border] = b_dist
        valid[on_border] = b_dist < border_distance
    return closest, valid, dist


def similarity_transform(source_points, target_points):
    """Least-squares similarity (R, s, t) with target ~ s R source + t."""
    src_c, dst_c = source_points.mean(axis=0), target_points.mean(axis=0)
    a, b = source_points - src_c, target_points - dst_c
    rotation, _ = Rotation.align_vectors(b, a)
    r = rotation.as_matrix()
    s = float(np.einsum("ij,ij->", b, a @ r.T) / max(np.einsum("ij,ij->", a, a), 1e-300))
    return r, s, dst_c - s * r @ src_c


def similarity_icp(source_points, source_normals, target_vertices, target_triangles,
                   target_normal_sign=1.0, max_distance=np.inf, iterations=100, sample=2000,
                   tolerance=1e-3):
    """Refine a rough alignment of the source points to the target surface by a similarity.

    Each iteration pairs (up to `sample` of) the source points with their closest target points
    (normals within 90 degrees, within max_distance, the worst 10% trimmed) and solves the
    least-squares similarity; it stops when the mean distance improves by less than `tolerance`
    (relative). Returns (R, s, t) to apply on top of the current positions.
    """
    surface = TriangleSurface(target_vertices, target_triangles)
    normals_t = target_normal_sign * vertex_normals(target_vertices, target_triangles)
    total_r, total_s, total_t = np.eye(3), 1.0, np.zeros(3)
    step = max(1, len(source_points) // sample)
    points, normals = source_points[::step].copy(), source_normals[::step].copy()
    previous = np.inf
    for _ in range(iterations):
        closest, tri, dist, bary = surface.closest(points)
        facing = np.einsum("ij,ij->i", interpolate(normals_t, target_triangles, tri, bary), normals)
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


def register(source_vertices, source_triangles, target_vertices, target_triangles,
             landmark_ids, landmark_positions, *, formulation=deformation.REDUCED,
             schedule=None, source_normal_sign=1.0, target_normal_sign=1.0, progress=None):
    """Deform the source (already aligned to the target's frame) onto the target surface.

    source_triangles: the source region to register (other source vertices just follow the
    solution as unconstrained unknowns; vertices on no triangle stay where they are).
    landmark_ids: source vertex ids fixed at landmark_positions (target coordinates).
    *_normal_sign: +1 or -1 so that both meshes' normals point out of the face.
    """
    schedule = schedule or Schedule()
    # Work in units of the source's mean edge length: the gradient terms are unitless, so
    # this keeps the weights' meaning the same for any mesh scale and density.
    edges = source_vertices[source_triangles[:, [1, 2, 0]]] - source_vertices[source_triangles]
    unit = float(np.linalg.norm(edges, axis=2).mean())
    source_vertices = source_vertices / unit
    target_vertices = target_vertices / unit
    landmark_positions = np.asarray(landmark_positions) / unit
    n = len(source_vertices)
    t = len(source_triangles)
    diag = diagonal(target_vertices, np.unique(target_triangles))
    region = np.unique(source_triangles)

    grad, _ = deformation.gradient_operator(source_vertices, source_triangles, formulation)
    difference = deformation.neighbour_difference(source_triangles)
    smooth = difference @ grad
    # E_S = || D (G x + C) ||^2 with C the normal completion, so the rest shape costs nothing
    smooth_rhs = -(difference @ deformation.normal_completion(source_vertices, source_triangles,
                                                                formulation))
    n_unknowns = grad.shape[1]
    rest = deformation.unknowns_of(source_vertices, source_triangles, formulation)
    identity_rhs = deformation.stacked_identity(t)

    # Vertices not in the region get a tiny pull to where they are, so the system stays
    # definite; landmark vertices are eliminated.
    outside = np.ones(n_unknowns, dtype=bool)
    outside[region] = False
    if formulation == deformation.AUGMENTED:
        outside[n:] = False
    hard = np.zeros(n_unknowns, dtype=bool)
    hard[landmark_ids] = True
    nothing = np.zeros(n_unknowns, dtype=bool)
    x = rest.copy()
    x[landmark_ids] = landmark_positions
    landmark_targets = np.zeros((n_unknowns, 3))
    landmark_targets[landmark_ids] = landmark_positions

    base = (schedule.smooth_weight * (smooth.T @ smooth)
            + schedule.identity_weight * (grad.T @ grad)
            + sp.diags(outside.astype(float))).tocsr()
    base_rhs = (schedule.smooth_weight * (smooth.T @ smooth_rhs)
                + schedule.identity_weight * (grad.T @ identity_rhs) + outside[:, None] * rest)

    surface = TriangleSurface(target_vertices, target_triangles)
    target_normals = target_normal_sign * vertex_normals(target_vertices, target_triangles)
    target_edges = boundary_edges(target_triangles)
    target_border_ids = np.unique(target_edges)
    border = np.zeros(len(target_vertices), dtype=bool)
    border[target_border_ids] = True
    source_border_edges = boundary_edges(source_triangles)
    source_border = np.zeros(n, dtype=bool)
    source_border[source_border_edges.ravel()] = True
    target_border_edges = SegmentSet(target_vertices, target_edges)
    # Target points pull the source too (symmetric closest points): without it the source can
    # settle on part of the target and leave the rest uncovered. Each target vertex weighs its
    # share of the surface in units of a source vertex's share, so density does not matter.
    target_ids = np.setdiff1d(np.unique(target_triangles), target_border_ids)
    source_area = _vertex_areas(source_vertices, source_triangles)[region].mean()
    target_share = _vertex_areas(target_vertices, target_triangles)[target_ids] / source_area
    # border vertices weigh their share of the border's length in source edge lengths (= 1)
    target_border_share = _border_lengths(target_vertices, target_edges)[target_border_ids]
    solver = ReusedOrderingSolver()
    history = []
    # the landmark-only solve starts a fit from hard landmarks; soft ones start from the surfaces
    steps = ((0.0,) if schedule.landmark_weight is None else ()) + tuple(schedule.closest_weights)
    valid = np.zeros(n, dtype=bool)
    with ThreadPoolExecutor(max_workers=1) as pool:
        for k, w_c in enumerate(steps):
            if progress:
                progress(k / len(steps), f"registration step {k + 1}/{len(steps)}")
            data = np.zeros(n_unknowns)
            rhs = base_rhs.copy()
            if w_c > 0:
                normals = source_normal_sign * vertex_normals(x[:n], source_triangles)
                # the target-to-source pull is computed beside the source-to-target closest points
                # (numpy and the KD-tree release the GIL, so the two use both cores)
                pull_job = pool.submit(_target_pull, x[:n], source_triangles, normals,
                                       source_border, target_vertices[target_ids],
                                       target_normals[target_ids], target_share,
                                       schedule.max_distance * diag, n_unknowns)
                closest, valid_region, distance = closest_valid_points(
                    x[region], normals[region], source_border[region], surface, target_normals,
                    border, target_border_edges, schedule.max_distance * diag,
                    schedule.border_distance * diag)
                valid = np.zeros(n, dtype=bool)
                valid[region[valid_region]] = True
                targets = np.zeros((n_unknowns, 3))
                targets[region] = closest
                data[:n] = w_c * valid
                rhs += data[:, None] * targets
                history.append(float(distance.mean()) * unit)
                border_pull, border_rhs = _border_pull(x[:n], source_border_edges,
                                                       target_vertices[target_border_ids],
                                                       target_border_share,
                                                       schedule.border_distance * diag, n_unknowns)
                pull, pull_rhs = pull_job.result()
                pull = pull + border_pull
                pull_rhs = pull_rhs + border_rhs
                matrix = (base + sp.diags(data) + w_c * pull).tocsr()
                rhs += w_c * pull_rhs
            else:
                matrix = base
            released = schedule.landmark_weight is not None
            fixed = nothing if released else hard
            if released:
                pin = np.where(hard, schedule.landmark_weight * max(w_c, 1.0), 0.0)
                matrix = matrix + sp.diags(pin)
                rhs = rhs + pin[:, None] * landmark_targets
            if not fixed.any():
                x = solver.solve(matrix, rhs)
                continue
            free = ~fixed
            matrix = sp.csr_matrix(matrix)
            x[free] = solver.solve(matrix[free][:, free],
                                   rhs[free] - matrix[free][:, fixed] @ x[fixed])
    # The fit error counts where the surfaces overlap: source parts that reach past the target
    # (a neck below a head's cut) have no closest point to be measured against.
    normals = source_normal_sign * vertex_normals(x[:n], source_triangles)
    _, overlap, distances = closest_valid_points(
        x[region], normals[region], source_border[region], surface, target_normals, border,
        target_border_edges, schedule.max_distance * diag, schedule.border_distance * diag)
    mean_distance = float(distances[overlap].mean()) if overlap.any() else float(distances.mean())
    history.append(mean_distance * unit)
    return Registration(
        vertices=x[:n] * unit,
        mean_distance=mean_distance * unit,
        valid_fraction=float(overlap.mean()) if len(region) else 0.0,
        history=history,
    )


def _vertex_areas(vertices, triangles):
    """A third of the area of every triangle around each vertex."""
    third = triangle_areas(vertices, triangles) / 3
    return np.bincount(triangles.ravel(), np.repeat(third, 3), minlength=len(vertices))


def _target_pull(source, source_triangles, source_normals, source_border, points, point_normals,
                 weights, max_distance, n_unknowns):
    """Normal-equation terms (B^T W B, B^T W p) pulling the source surface onto target points.

    B picks, for each target point, the barycentric combination of the source triangle closest
    to it; points that land on the source's open border, face the other way or are too far are
    left out (the target may extend past the source, e.g. the back of a head).
    """
    surface = TriangleSurface(source, source_triangles)
    _, tri, dist, bary = surface.closest(points)
    corners = source_triangles[tri]
    facing = np.einsum("ij,ij->i", interpolate(source_normals, source_triangles, tri, bary),
                       point_normals)
    ok = (dist < max_distance) & (facing > 0) & ~source_border[corners].any(axis=1)
    rows = np.repeat(np.flatnonzero(ok), 3)
    b = sp.csr_matrix((bary[ok].ravel(), (rows, corners[ok].ravel())),
                      shape=(len(points), n_unknowns))
    w = sp.diags(np.where(ok, weights, 0.0))
    return (b.T @ w @ b), b.T @ (w @ points)


def _border_lengths(vertices, edges):
    """Half the length of the border edges at each vertex."""
    length = np.linalg.norm(vertices[edges[:, 1]] - vertices[edges[:, 0]], axis=1) / 2
    return np.bincount(edges.ravel(), np.repeat(length, 2), minlength=len(vertices))


def _border_pull(source, source_border_edges, points, weights, max_distance, n_unknowns):
    """Like _target_pull, for the target's border vertices onto the source's border edges."""
    segments = SegmentSet(source, source_border_edges)
    _, edge, dist, t = segments.closest(points)
    ok = dist < max_distance
    ends = source_border_edges[edge[ok]]
    rows = np.repeat(np.flatnonzero(ok), 2)
    b = sp.csr_matrix((np.stack([1 - t[ok], t[ok]], axis=1).ravel(), (rows, ends.ravel())),
                      shape=(len(points), n_unknowns))
    w = sp.diags(np.where(ok, weights, 0.0))
    return (b.T @ w @ b), b.T @ (w @ points)
