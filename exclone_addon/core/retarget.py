"""Retargeting tracked landmark motion onto an avatar's shape keys (docs/method.md §12).

The avatar's shape keys are sampled at the tracked landmarks' locations on its surface (sparse
blendshapes), mapped into the actor's space by an RBF with a linear term fitted from the avatar's
neutral landmarks to the actor's calibrated neutral, and per frame the weights (0 <= w <= 1) that
best explain the head-motion-free landmark displacements come from bounded least squares.
An optional refinement over a recorded take (Liu et al. 2008) alternates weights and blendshapes.
"""
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.optimize import lsq_linear, nnls

from . import character, data
from .cloning import clone_expressions
from .errors import ExCloneError
from .expression_measures import Openings
from .face_finding import FACEMESH_LANDMARKS
from .mesh import MeshError, PolyMesh, vertex_parts
from .proximity import TriangleSurface


@dataclass
class SurfaceLocations:
    """Points on a mesh: each a barycentric combination of a triangle's three vertices."""
    corners: np.ndarray       # (m, 3) vertex ids
    bary: np.ndarray          # (m, 3) barycentric weights (rows sum to 1)

    @classmethod
    def from_vertices(cls, vertex_ids):
        ids = np.asarray(vertex_ids, dtype=np.int64).ravel()
        return cls(np.repeat(ids[:, None], 3, axis=1), np.tile([1.0, 0.0, 0.0], (len(ids), 1)))

    @classmethod
    def from_triangles(cls, triangles, triangle_ids, bary):
        return cls(np.asarray(triangles)[np.asarray(triangle_ids)], np.asarray(bary, dtype=np.float64))

    def sample(self, values):
        """Per-vertex values (n, 3) or (E, n, 3) -> values at the locations (m, 3) or (E, m, 3)."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 2:
            return np.einsum("mk,mki->mi", self.bary, values[self.corners])
        return np.einsum("mk,emki->emi", self.bary, values[:, self.corners])


def locate_points(points, vertices, triangles):
    """The closest surface locations of `points` (m, 3) on a triangle mesh; returns
    (SurfaceLocations, distances (m,))."""
    triangles = np.asarray(triangles)
    _, tri_ids, dist, bary = TriangleSurface(vertices, triangles).closest(points)
    return SurfaceLocations.from_triangles(triangles, tri_ids, bary), dist


def locate_canonical_face(canonical, avatar, avatar_triangles=None, settings=None, progress=None):
    """Where the tracker's landmarks (the canonical face's vertices) lie on the avatar's surface.

    The cloning engine registers the canonical face onto the avatar (automatic landmarks); each
    registered vertex is then snapped to the closest point of `avatar_triangles`, registered on
    the whole avatar. By default the face is first found on the avatar as Clone finds a
    character's (core.character.found_or_whole: by rendering it, a full body cut to its head
    region), the canonical face registered there with the found face's guide, and each point
    snapped to the head region's part most of them are closest to (its skin): near the lips and
    eyes the closest point is otherwise often on teeth, eyeballs or lashes (on the ICT head 38 of
    468 were).
    Returns (SurfaceLocations in the avatar's numbering, distances of the snap (m,)).
    """
    if avatar_triangles is not None:
        points = _registered(canonical, avatar, None, settings, progress)
        return locate_points(points, avatar.vertices, avatar_triangles)
    face = character.found_or_whole([character.Part("avatar", avatar)])
    head = face.head.mesh
    points = _registered(canonical, head, face.guide, settings, progress)
    triangles = head.triangles()
    first, _ = locate_points(points, head.vertices, triangles)
    located, distances = locate_points(
        points, head.vertices, _part_of_most(len(head.vertices), triangles, first.corners[:, 0]))
    return SurfaceLocations(face.head.own_ids(located.corners), located.bary), distances


def _part_of_most(vertex_count, triangles, vertex_ids):
    """The triangles of the connected part of the mesh that most of `vertex_ids` lie on: the
    located face's skin, not the eyeballs, lashes or teeth beside it."""
    parts = vertex_parts(vertex_count, triangles)
    return triangles[parts[triangles[:, 0]] == np.bincount(parts[vertex_ids]).argmax()]


def _registered(canonical, target, face_guide, settings, progress):
    """(n, 3) the canonical face's vertices registered onto the target PolyMesh."""
    n = len(canonical.vertices)
    return clone_expressions(canonical, np.zeros((1, n, 3)), ["neutral"], target,
                             settings=settings, progress=progress,
                             face_guide=face_guide).registered_source


# Below this fraction of the largest key's motion at the tracked points a key is not read.
UNSEEN_MOTION = 0.01
# The weight solve's optimality tolerance (lsq_linear's default for BVLS).
BVLS_TOLERANCE = 1e-10


@dataclass
class AvatarRig:
    """The avatar's side of retargeting: its shape keys sampled where the tracker's 468 points
    lie on it (sparse blendshapes), and how far each closes the avatar's eyes."""
    names: list
    neutral: np.ndarray        # (468, 3) the located points on the avatar's neutral
    deltas: np.ndarray         # (N, 468, 3) each shape key's displacement there
    locations: SurfaceLocations
    # (N, 2) each key's share of each eye's opening it closes (eye_closures), None: not measured
    closures: np.ndarray = None

    @classmethod
    def from_locations(cls, vertices, deltas, names, locations, triangles=None):
        """The rig of an avatar whose tracker's points are located; with its `triangles`, the
        keys' eye closures are measured too."""
        vertices = np.asarray(vertices, dtype=np.float64)
        deltas = np.asarray(deltas, dtype=np.float64)
        if len(names) == 0 or deltas.ndim != 3 or len(deltas) == 0:
            raise ExCloneError("the avatar has no shape keys to drive")
        if deltas.shape[1:] != vertices.shape or len(names) != len(deltas):
            raise ExCloneError(f"the avatar's shape keys ({len(names)} names, deltas "
                               f"{deltas.shape}) do not match its {len(vertices)} vertices")
        neutral = locations.sample(vertices)
        sparse = locations.sample(deltas)
        motion = np.sqrt((sparse ** 2).sum(axis=2)).max(axis=1)
        size = np.linalg.norm(neutral.max(axis=0) - neutral.min(axis=0))
        if motion.max() <= 1e-6 * size:
            raise ExCloneError("none of the avatar's shape keys moves its face")
        # A key that barely moves the tracked points (a pupil dilating, a point grazing the
        # eyeball) cannot be read from them: solved, it would follow their noise to full
        # weight. It is kept at zero as a key that moves none of them (WeightSolver's ridge).
        sparse[motion < UNSEEN_MOTION * motion.max()] = 0.0
        closures = None if triangles is None else eye_closures(vertices, triangles, deltas,
                                                               locations)
        return cls(list(names), neutral, sparse, locations, closures)

    @classmethod
    def from_arrays(cls, vertices, triangles, deltas, names, progress=None):
        """Locates the tracker's points on the avatar (a registration, seconds) and samples its
        shape keys there. Raises ExCloneError when there are no shape keys or the face does
        not register."""
        if len(names) == 0 or np.asarray(deltas).size == 0:
            raise ExCloneError("the avatar has no shape keys to drive")
        try:
            mesh = PolyMesh.from_faces(vertices, np.asarray(triangles))
            locations, _ = locate_canonical_face(data.canonical_face(), mesh, progress=progress)
        except (MeshError, np.linalg.LinAlgError) as exc:
            raise ExCloneError(f"the tracker's face does not register onto the avatar ({exc})") from exc
        return cls.from_locations(vertices, deltas, names, locations, triangles)


# The eyes in the eye reading's order (core.eyes.SIDES: the subject's right, then left), as
# expression_measures.Openings names them.
READING_EYES = ("eye_right", "eye_left")


def eye_closures(vertices, triangles, deltas, locations):
    """(N, 2) how much of each eye's opening (READING_EYES) each key (deltas (N, n, 3)) closes on
    the avatar: one less the median along the lid of its gap against the gap at rest (1 closed,
    0 as at rest, < 0 wider; the median, as a corner found a little off the opening measures
    skin beyond it that no blink closes), the lids' edges as seen from the front
    (expression_measures.Openings, found from the project's landmarks at the located FaceMesh
    points, on the part of the mesh they are located on: not the eyeballs or lashes of a
    one-mesh avatar); NaN for an eye whose lids are not found. Whatever the keys are named, the
    eye reading can then close the eyes they close (core.eyes.EyeTargets)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    skin = _part_of_most(len(vertices), np.asarray(triangles), locations.corners[:, 0])
    landmarks = {name: int(locations.corners[i, np.argmax(locations.bary[i])])
                 for name, i in FACEMESH_LANDMARKS.items() if name in Openings.NEEDED}
    openings = Openings(vertices, skin, landmarks)
    closures = np.full((len(deltas), len(READING_EYES)), np.nan)
    for k, eye in enumerate(READING_EYES):
        lids = openings.lids.get(eye)
        if lids is not None:
            closures[:, k] = [1.0 - np.median(lids.gaps(vertices + delta) / lids.rest)
                              for delta in deltas]
    return closures


def map_blendshapes(avatar_neutral, avatar_deltas, actor_neutral, kernel="thin_plate_spline",
                    smoothing=1e-3):
    """Sparse avatar blendshapes -> the actor's space (docs/method.md §12).

    avatar_neutral: (m, 3) e'_0; avatar_deltas: (N, m, 3) e'_j - e'_0; actor_neutral: (m, 3) f_1.
    The RBF F with a linear term (degree=1) maps e'_0 onto f_1; the mapped displacement of shape
    j is F(e'_0 + e'_j) - F(e'_0). Returns (N, m, 3).
    A little smoothing: landmarks can land on the same avatar point (e.g. inner-lip points
    snapped to the lip border), and exact interpolation of two targets at one point explodes.
    The smoothing is in the actor's units: the avatar's points are first scaled about their
    centre to the actor's size, so an avatar in metres maps as the same one in centimetres.
    """
    avatar_neutral = np.asarray(avatar_neutral, dtype=np.float64)
    actor_neutral = np.asarray(actor_neutral, dtype=np.float64)
    deltas = np.asarray(avatar_deltas, dtype=np.float64)
    if avatar_neutral.shape != actor_neutral.shape or deltas.shape[1:] != avatar_neutral.shape:
        raise ExCloneError(f"landmark counts differ: avatar neutral {avatar_neutral.shape}, "
                           f"actor neutral {actor_neutral.shape}, avatar shapes {deltas.shape}")
    centre = avatar_neutral.mean(axis=0)
    scale = _spread(actor_neutral) / max(_spread(avatar_neutral), 1e-300)
    rbf = RBFInterpolator(scale * (avatar_neutral - centre), actor_neutral, kernel=kernel,
                          degree=1, smoothing=smoothing)
    base = rbf(scale * (avatar_neutral - centre))
    moved = rbf(scale * (avatar_neutral[None] + deltas - centre).reshape(-1, 3))
    return moved.reshape(deltas.shape) - base[None]


def _spread(points):
    """The points' root mean square distance from their centre."""
    return np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())


class WeightSolver:
    """Per-frame weights 0 <= w <= 1 with sum_i p_i ||d_i - sum_j w_j e_ji||^2 minimal
    (docs/method.md §12).

    point_weights p_i (m,) trust per landmark; axis_weights trust per model axis: a monocular
    tracker sees depth (the face's z) only through perspective and its shape model, so depth
    counts less by default (0.1 was the best of 0.1, 0.25, 0.5, 1 on the closed-loop synthetic
    take of blender_tests/core/test_retarget.py; 1 lost 0.035 of MAE there).

    The matrix is the same every frame: its QR factorisation is computed once, so a frame's
    bounded least squares runs on the small N x N triangle instead of the 3m x N matrix
    (||A w - d||^2 = ||R w - Q^T d||^2 + const). A tiny ridge (relative to the shapes' own
    scale) keeps shapes that do not move any landmark at zero instead of undetermined.
    """

    def __init__(self, blendshapes, names, point_weights=None, axis_weights=(1.0, 1.0, 0.1),
                 ridge=1e-6, scale=None):
        shapes = np.asarray(blendshapes, dtype=np.float64)
        if shapes.ndim != 3 or shapes.shape[2] != 3:
            raise ExCloneError(f"blendshapes must be (N, m, 3), got {shapes.shape}")
        if len(names) != len(shapes):
            raise ExCloneError(f"{len(names)} names for {len(shapes)} blendshapes")
        if len(shapes) == 0:
            raise ExCloneError("no shape keys to solve for")
        m = shapes.shape[1]
        self.names = list(names)
        self.blendshapes = shapes
        pw = np.ones(m) if point_weights is None else np.asarray(point_weights, dtype=np.float64)
        if pw.shape != (m,) or np.any(pw < 0):
            raise ExCloneError(f"point weights must be {m} values >= 0, got shape {pw.shape}")
        self.point_weights = pw
        self.axis_weights = np.asarray(axis_weights, dtype=np.float64)
        self._row_scale = np.sqrt(np.outer(pw, self.axis_weights)).ravel()
        a = shapes.reshape(len(shapes), -1).T * self._row_scale[:, None]    # (3m, N)
        # the ridge is relative to the shapes' mean squared (weighted) norm; `scale` fixes that
        # reference (a refinement keeps its starting one)
        self.ridge = float(ridge)
        self.scale = float(scale) if scale is not None else max(
            float(np.mean(np.einsum("ij,ij->j", a, a))), 1e-300)
        mu = self.ridge * self.scale
        self._q, self._r = np.linalg.qr(np.vstack((a, np.sqrt(mu) * np.eye(len(shapes)))))
        self._q = self._q[: a.shape[0]]          # the ridge rows' right-hand side is zero

    def solve(self, displacement, rows=None, targets=None):
        """displacement: (m, 3) head-motion-free landmarks minus the actor's neutral. rows (k, N)
        and targets (k,): further measurements rows @ w ~ targets (the eyes' lids and gaze,
        core.eyes), weighed by their own scale, in the same bounded solve."""
        d = np.asarray(displacement, dtype=np.float64).reshape(-1) * self._row_scale
        matrix, c = self._r, self._q.T @ d
        if rows is not None:
            matrix, c = np.vstack((matrix, rows)), np.concatenate((c, targets))
        return bounded_weights(matrix, c)

    def solve_take(self, displacements):
        """(T, m, 3) -> (T, N)."""
        return np.array([self.solve(d) for d in displacements])

    def _weighted_sq(self, values):
        """sum over frames/shapes of sum_i p_i sum_axis a_axis values^2, for (T, m, 3)."""
        return float(np.einsum("tmi,m,i->", values ** 2, self.point_weights, self.axis_weights))

    def reconstruction_error(self, displacements, weights):
        """Weighted RMS landmark error of a take's reconstruction (cm if the shapes are in cm)."""
        recon = np.tensordot(weights, self.blendshapes, axes=1)
        norm = len(weights) * self.point_weights.sum() * self.axis_weights.sum()
        return float(np.sqrt(self._weighted_sq(np.asarray(displacements) - recon) / norm))

    def objective(self, displacements, weights):
        """What solve() minimises, summed over a take's frames."""
        recon = np.tensordot(weights, self.blendshapes, axes=1)
        return (self._weighted_sq(np.asarray(displacements) - recon)
                + self.scale * self.ridge * float((weights ** 2).sum()))


def bounded_weights(matrix, c):
    """The weights 0 <= w <= 1 minimising ||matrix w - c||.

    The weights with only w >= 0 (scipy's nnls, about 0.15 ms for the ICT head's 57 keys) are
    the bounded ones too when none exceeds 1 (the unique optimum over the larger set lies in the
    box) and they are optimal to BVLS's tolerance: nnls can stop short along a key the landmarks
    hardly see (0.04 off BVLS's weight on one frame of the rendered turning take). Otherwise
    lsq_linear's BVLS (about 2.5 ms for the 57 keys)."""
    try:
        weights, _ = nnls(matrix, c)
    except RuntimeError:        # out of iterations
        weights = None
    if (weights is not None and weights.max() <= 1.0
            and _nonnegative_optimality(matrix, c, weights) < BVLS_TOLERANCE):
        return weights
    return lsq_linear(matrix, c, bounds=(0.0, 1.0), method="bvls", tol=BVLS_TOLERANCE).x


def _nonnegative_optimality(matrix, c, weights):
    """How far weights >= 0 are from minimising ||matrix w - c|| over w >= 0, as lsq_linear's
    BVLS measures its own answer: the largest gradient where w > 0 and the largest negative one
    where w = 0."""
    gradient = matrix.T @ (matrix @ weights - c)
    return float(np.where(weights > 0, np.abs(gradient), -gradient).max())


@dataclass
class RefinedTake:
    weights: np.ndarray                 # (T, N)
    solver: WeightSolver                # with the refined blendshapes
    errors: list = field(default_factory=list)       # reconstruction RMS after each iteration
    objectives: list = field(default_factory=list)   # the alternation's objective, ditto


def refine_take(solver, displacements, closeness=1.0, iterations=20):
    """Liu et al. 2008 (docs/method.md §12): alternate, `iterations` times, the weights of every frame
    (blendshapes fixed) and the blendshapes (weights fixed).

    The blendshape step minimises sum_t ||d_t - sum_j w_tj e~_j||^2 + lam sum_j ||e~_j - e_j||^2,
    both in the solver's point and axis weights, so a single closed form serves every coordinate
    and the alternation never increases the total objective. lam = closeness * T: the balance
    does not drift with the take's length.
    """
    d = np.asarray(displacements, dtype=np.float64)
    if d.ndim != 3 or d.shape[1:] != solver.blendshapes.shape[1:]:
        raise ExCloneError(f"take displacements {d.shape} do not match the blendshapes "
                           f"{solver.blendshapes.shape[1:]}")
    n_frames, n_shapes = len(d), len(solver.blendshapes)
    initial = solver.blendshapes.reshape(n_shapes, -1)
    data = d.reshape(n_frames, -1)
    lam = closeness * n_frames
    current = solver
    errors, objectives = [], []
    weights = current.solve_take(d)
    for _ in range(iterations):
        gram = weights.T @ weights + lam * np.eye(n_shapes)
        shapes = np.linalg.solve(gram, weights.T @ data + lam * initial).reshape(solver.blendshapes.shape)
        current = WeightSolver(shapes, solver.names, solver.point_weights, solver.axis_weights,
                               solver.ridge, solver.scale)
        weights = current.solve_take(d)
        errors.append(current.reconstruction_error(d, weights))
        objectives.append(current.objective(d, weights)
                          + lam * current._weighted_sq((shapes - solver.blendshapes)))
    return RefinedTake(weights, current, errors, objectives)
