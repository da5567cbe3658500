"""Per-frame 3D face fit to 2D landmarks: a point distribution model with head pose.

A constrained local model (docs/method.md §11) with a neural landmark detector
as the local expert: the 468 FaceMesh points of a frame are explained by a rigid head pose
(rotation, translation; a perspective camera) and a 3D shape mean + sum_j b_j mode_j, with the
prior beta * sum_j b_j^2 / lambda_j. Robust per-point weights keep occluded or wrong points from
dragging the fit. Neutral calibration adapts the model's mean to the actor's face; a One Euro
filter removes jitter; Kabsch removes head motion against the neutral.

With three columns the points carry FaceMesh's depth (relative to the face, in pixels at the
image's scale) as a further observation: with a model of the located points, 2D points alone read
the head's pitch at 0.77-0.78 of its size on rendered takes (FaceMesh's 2D points slide as the
head turns; the true points' projections give 1.00), with the depth 0.85-0.87. A model that knows
the slide (ShapeModel.pose_offsets, learnt from FaceMesh: core.tracker_model) reads it at
0.99-1.05 from the 2D points alone.

Scale is not a separate pose parameter: from one perspective view a bigger face further away
looks the same, so the actor's size goes into the calibrated neutral and distance into depth.

Camera coordinates follow OpenCV: x right, y down, z forward (into the scene); pixels (u, v).
"""
import functools
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.transform import Rotation

from .registration import similarity_transform
from .errors import ExCloneError
from .mesh import outward_sign, vertex_normals

# A point whose surface faces the camera at less than this cosine (60 deg) counts less, down to
# nothing at the silhouette: FaceMesh's points there slide over the surface as the head turns
# (on a rendered turning take their error varies with the pose by 2.7 px median facing away,
# 1.6 px facing the camera).
FACING_COSINE = 0.5

# The features of the head's turn that a point's slide is linear in (ShapeModel.pose_features):
# the monomials x^a y^b of the direction to the camera in the model's axes (frontal: +Z) up to
# this degree (on the rendered takes, FaceMesh's points less the learnt model's, at the true pose:
# 1.42 px median with degree 2, 1.37 with 3).
POSE_DEGREE = 3
POSE_FEATURES = tuple((a, total - a) for total in range(1, POSE_DEGREE + 1)
                      for a in range(total, -1, -1))
_POWERS_X, _POWERS_Y = np.array(POSE_FEATURES).T

# Model (canonical face: +Y up, looking along +Z) seen frontally by the camera: turned half a
# turn about x, so the model's up is the image's up and its face looks into the camera.
FRONTAL = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))


@dataclass
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_image_size(cls, width, height, fx=None, fy=None, cx=None, cy=None):
        """Pinhole intrinsics; missing values default to f = max(w, h), centre of the image."""
        if width <= 0 or height <= 0:
            raise ExCloneError(f"image size must be positive, got {width} x {height}")
        f = float(max(width, height))
        return cls(float(fx if fx is not None else f), float(fy if fy is not None else (fx or f)),
                   float(cx if cx is not None else width / 2.0),
                   float(cy if cy is not None else height / 2.0))

    def project(self, points):
        """Camera-space points (n, 3) -> pixels (n, 2)."""
        z = points[:, 2]
        return np.column_stack((self.fx * points[:, 0] / z + self.cx,
                                self.fy * points[:, 1] / z + self.cy))

    def jacobian(self, points):
        """d project / d point for camera-space points (n, 3): (n, 2, 3)."""
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        jac = np.zeros((len(points), 2, 3))
        jac[:, 0, 0] = self.fx / z
        jac[:, 0, 2] = -self.fx * x / (z * z)
        jac[:, 1, 1] = self.fy / z
        jac[:, 1, 2] = -self.fy * y / (z * z)
        return jac


@dataclass
class ShapeModel:
    """Point distribution model: shape(b) = mean + sum_j b_j modes[j]; Var(b_j) = eigenvalues[j]."""
    mean: np.ndarray          # (n, 3)
    modes: np.ndarray         # (K, n, 3), orthonormal as (K, 3n) rows
    eigenvalues: np.ndarray   # (K,)
    triangles: np.ndarray = None   # (T, 3) the points' surface (for which way each faces), if known
    # How each point slides with the head's turn: offsets (F, n, 3) linear in POSE_FEATURES of
    # the direction from pose_centre (3,) to the camera; None: no slide.
    pose_offsets: np.ndarray = None
    pose_centre: np.ndarray = None
    # How the image model's points move with each mode (K, n, 3), where that differs from the
    # modes (what the fit compares with the image; shape() stays the modes); None: as the modes.
    seen_modes: np.ndarray = None

    @classmethod
    def from_displacements(cls, mean, displacements, energy=0.9999, max_modes=60,
                           weight_second_moment=1.0 / 3.0, triangles=None, seen=None):
        """PCA about the mean of example displacements (E, n, 3) (e.g. expressions at the landmarks).

        The examples are variations about the mean (a neutral face), so the PCA is not centred.
        They are taken as blendshapes each used independently with weights of second moment
        `weight_second_moment` (1/3: uniform in 0..1), so the covariance is that times
        sum_e d_e d_e^T (not divided by E: a face uses many shapes at once).
        Keeps the leading modes that explain `energy` of the variation. seen (E, n, 3): how the
        image model's points move with each example; each mode is seen as the same combination
        of them (seen_modes).
        """
        mean = np.asarray(mean, dtype=np.float64)
        d = np.asarray(displacements, dtype=np.float64).reshape(len(displacements), -1)
        if d.shape[1] != mean.size:
            raise ExCloneError(f"displacements have {d.shape[1] // 3} points, the mean has {len(mean)}")
        u, s, vt = np.linalg.svd(d, full_matrices=False)
        variance = weight_second_moment * s ** 2
        if variance.sum() <= 0:
            raise ExCloneError("the example shapes do not move any landmark")
        explained = np.cumsum(variance) / variance.sum()
        k = min(int(np.searchsorted(explained, energy)) + 1, max_modes, len(s))
        seen_modes = None
        if seen is not None:
            # mode j is sum_e u_ej / s_j d_e: the same combination of the seen motion
            seen_flat = np.asarray(seen, dtype=np.float64).reshape(d.shape)
            seen_modes = ((u[:, :k] / s[:k]).T @ seen_flat).reshape(k, -1, 3)
        return cls(mean, vt[:k].reshape(k, -1, 3), variance[:k], triangles, seen_modes=seen_modes)

    def shape(self, params):
        return self.mean + np.tensordot(params, self.modes, axes=1)

    def with_mean(self, mean, modes=None):
        """The same model about another mean (e.g. the actor's calibrated neutral), with its
        first `modes` modes (all by default)."""
        k = len(self.eigenvalues) if modes is None else modes
        seen = None if self.seen_modes is None else self.seen_modes[:k]
        return replace(self, mean=mean, modes=self.modes[:k], eigenvalues=self.eigenvalues[:k],
                       seen_modes=seen)

    @staticmethod
    def camera_offsets(rotation, translation, centre):
        """(3,) or (T, 3) where the camera is from centre (3,), in the model's axes, for a pose
        or poses (model -> camera): a scipy Rotation and translation (3,) or (T, 3)."""
        return -rotation.inv().apply(translation) - centre

    @staticmethod
    def pose_features(directions):
        """(T, F) POSE_FEATURES of directions to the camera (T, 3) in the model's axes."""
        v = np.asarray(directions, dtype=np.float64)
        v = v / np.linalg.norm(v, axis=1, keepdims=True)
        return v[:, :1] ** _POWERS_X * v[:, 1:2] ** _POWERS_Y

    def pose_offset(self, rotation, translation, jacobian=False):
        """(n, 3) each point's slide at a pose (model -> camera), in model space; None without
        a slide model. With jacobian: (slide, its derivative (n, 3, 6) by [omega, t], omega
        turning on the left as in ShapeFitter)."""
        if self.pose_offsets is None:
            return None
        r_t = rotation.as_matrix().T
        to_camera = self.camera_offsets(rotation, translation, self.pose_centre)
        length = np.linalg.norm(to_camera)
        v = to_camera / length
        x, y = v[0], v[1]
        features = self.pose_features(v[None])[0]
        offsets = self.pose_offsets.reshape(len(features), -1)       # (F, 3n)
        if not jacobian:
            return (features @ offsets).reshape(-1, 3)
        # d features / d v (F, 3); d v / d to_camera; d to_camera / d [omega, t]: turning by
        # exp(w) adds -R^T [t]x w, moving by dt adds -R^T dt
        by_v = np.zeros((len(features), 3))
        by_v[:, 0] = _POWERS_X * x ** np.maximum(_POWERS_X - 1, 0) * y ** _POWERS_Y
        by_v[:, 1] = _POWERS_Y * x ** _POWERS_X * y ** np.maximum(_POWERS_Y - 1, 0)
        by_direction = by_v @ (np.eye(3) - np.outer(v, v)) / length
        by_pose = np.hstack((-r_t @ skew_rows(translation[None])[0], -r_t))     # (3, 6)
        # the slide and its derivative in one (7, F) @ (F, 3n) product
        both = np.vstack((features, (by_direction @ by_pose).T)) @ offsets
        return both[0].reshape(-1, 3), both[1:].reshape(6, -1, 3).transpose(1, 2, 0)

    def facing(self, shape, rotation, translation):
        """(n,) cosine between each point's outward normal and the direction to the camera
        for a shape (n, 3) at a pose; None without triangles."""
        if self.triangles is None:
            return None
        normals = self._winding_sign * vertex_normals(shape, self.triangles)
        points = rotation.apply(shape) + translation
        return -np.einsum("ij,ij->i", rotation.apply(normals), points) / np.linalg.norm(points, axis=1)

    @functools.cached_property
    def _winding_sign(self):
        # outward_sign on the mean: a face's expressions and slides do not turn its triangles
        # inside out, so the sign is found once (it took a fifth of a warm-started fit)
        return outward_sign(self.mean, self.triangles)

    def point_variance(self):
        """(n,) expected squared displacement of each point under the prior."""
        return np.einsum("k,kni->n", self.eigenvalues, self.modes ** 2)

    def rigid_weights(self):
        """(n,) weights favouring points that expressions hardly move (for head-pose alignment)."""
        var = self.point_variance()
        return 1.0 / (var + 0.1 * np.median(var) + 1e-12)


def expression_shape_model(canonical_vertices, located_neutral, located_deltas, **pca_options):
    """The tracker's shape model: mean = the canonical face, modes = PCA of a head's expressions.

    located_neutral (n, 3) and located_deltas (E, n, 3): a head's neutral and expression
    displacements sampled where the canonical face's points lie on it (e.g. the ICT library
    sampled at retarget.locate_canonical_face's locations). The displacements are brought into
    the canonical face's frame and scale by the similarity that aligns the two neutrals.
    """
    canonical = np.asarray(canonical_vertices, dtype=np.float64)
    rot, scale, _ = similarity_transform(np.asarray(located_neutral, dtype=np.float64), canonical)
    deltas = scale * np.asarray(located_deltas, dtype=np.float64) @ rot.T
    return ShapeModel.from_displacements(canonical, deltas, **pca_options)


@dataclass
class FitResult:
    rotation: Rotation        # model -> camera
    translation: np.ndarray   # (3,) camera space
    params: np.ndarray        # (K,) shape parameters b
    shape: np.ndarray         # (n, 3) model-space shape mean + modes . b (head-pose free)
    points2d: np.ndarray      # (n, 2) fitted points in pixels
    residuals: np.ndarray     # (n,) pixel distance fitted - observed
    weights: np.ndarray       # (n,) robust weights in [0, 1] (0: treated as an outlier)
    iterations: int
    scale_px: float           # robust residual scale (pixels)
    pose_offset: np.ndarray = None   # (n, 3) the points' slide at this pose (model space), if modelled
    # (K, K) the shape parameters' block of the last step's normal matrix (prior included): what
    # further observations of the shape add to at this pose (core.material_points)
    shape_normal: np.ndarray = None
    # the parameters of the model's seen modes at this pose (what placed it), when it has them
    seen_params: np.ndarray = None

    def camera_points(self):
        """(n, 3) the fitted points in camera space (with their slide)."""
        shape = self.shape if self.pose_offset is None else self.shape + self.pose_offset
        return self.rotation.apply(shape) + self.translation


@dataclass
class FitStart:
    """Where a fit starts and its first linearisation there (ShapeFitter.start_from)."""
    rotation: Rotation
    translation: np.ndarray
    params: np.ndarray              # (K,) the seen modes' parameters when the model has them
    facing: np.ndarray              # (n,) each point's weight for its facing (None: no triangles)
    points: np.ndarray              # (n, 3) camera space
    jacobian: np.ndarray            # (2n, 6 + K)
    depth_jacobian: np.ndarray      # (n, 6 + K), None without a depth weight


def skew_rows(v):
    """Cross-product matrices [v]x for each row of v: (n, 3) -> (n, 3, 3)."""
    skew = np.zeros((len(v), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -v[:, 2], v[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = v[:, 2], -v[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -v[:, 1], v[:, 0]
    return skew


def by_model_point(jacobians, matrix):
    """(n, 2, 3) d pixels / d camera-space point times a rotation matrix (model -> camera): d
    pixels / d model point, as one (2n, 3) @ (3, 3) product (a stack of n small products took
    five times as long)."""
    return (jacobians.reshape(-1, 3) @ matrix).reshape(jacobians.shape)


def tukey_weights(r, c):
    """Tukey biweight: (1 - (r/c)^2)^2 inside c, 0 beyond."""
    u = np.clip(r / c, 0.0, 1.0)
    return (1.0 - u * u) ** 2


# Tukey's cut-off in robust standard deviations (robust_sigma): 95% efficiency on normal residuals
TUKEY_CUTOFF = 4.685


def robust_sigma(residuals, floor=0.0, axis=None):
    """A normal spread's standard deviation read from absolute residuals: 1.4826 x their median
    (along axis), at least floor."""
    return np.maximum(1.4826 * np.median(residuals, axis=axis), floor)


def huber_weights(r, k):
    return np.minimum(1.0, k / np.maximum(r, 1e-12))


class ShapeFitter:
    """Fits head pose + shape parameters to 2D points by robust Gauss-Newton (IRLS).

    Minimises sum_i w_i ||project(R (mean + M b)_i + t) - p_i||^2 + beta sum_j b_j^2 / lambda_j.
    With points (n, 3), depth_weight * sum_i w_i (d_i - z_i)^2 joins it: d_i the fitted point's
    depth relative to the face, in pixels (f / t_z times its camera depth less the weighted mean),
    z_i the observed relative depth less its weighted mean (FaceMesh's z: what matters is the
    shape of the depth, its offset is free). depth_weight 0.1: the depth is the image model's
    inference, not seen in the image; of 1.0, 0.3 and 0.1 on the rendered takes, 0.1 keeps the
    expressions' accuracy (1.0 and 0.3 cost up to 0.06 of correlation) and most of the pose's
    gain.
    With the model's triangles, each point's weight is scaled by how squarely it faces the
    camera at the starting pose (FACING_COSINE).
    Robust weights w_i come from the point residuals: Huber while the pose is still being found
    (convex, safe from a poor start), Tukey's biweight after (rejects wrong points outright); the
    residual scale is the median absolute residual (robust to 50% outliers), at least
    `min_scale_px`. Rotation updates are on the manifold (R <- exp(w) R), so no parametrisation
    singularities. A plain Levenberg damping guards the first iterations.
    """

    def __init__(self, model, camera, beta=1.0, min_scale_px=0.5, max_iterations=30,
                 tolerance_px=1e-3, depth_weight=0.1):
        self.model = model
        self.depth_weight = float(depth_weight)
        self.camera = camera
        self.beta = float(beta)
        self.min_scale_px = float(min_scale_px)
        self.max_iterations = int(max_iterations)
        self.tolerance_px = float(tolerance_px)
        k = len(model.eigenvalues)
        self._prior = np.zeros(6 + k)
        self._prior[6:] = self.beta / model.eigenvalues
        # the points are compared with the image as the image model sees them move
        seen = model.modes if model.seen_modes is None else model.seen_modes
        self._modes_flat = seen.reshape(k, 3 * len(model.mean))   # (K, 3n)
        self._point_modes = np.ascontiguousarray(seen.transpose(1, 2, 0))   # (n, 3, K)
        self._located_modes = np.ascontiguousarray(model.modes.transpose(1, 2, 0))

    def initial_pose(self, points2d, weights):
        """A frontal-facing start: 2D similarity of the mean's (x, -y) onto the points."""
        mean = self.model.mean
        src = np.column_stack((mean[:, 0], -mean[:, 1]))            # image axes: y down
        w = weights / weights.sum()
        sc, dc = w @ src, w @ points2d
        a, b = src - sc, points2d - dc
        # closed-form 2D Procrustes: angle and scale
        num = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        den = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
        angle = math.atan2(num, den)
        scale = math.hypot(num, den) / max(np.sum(w * (a * a).sum(axis=1)), 1e-300)
        f = 0.5 * (self.camera.fx + self.camera.fy)
        depth = f / max(scale, 1e-12)
        rotation = Rotation.from_rotvec([0.0, 0.0, angle]) * FRONTAL
        # the model centre's image must land on the points' centre
        centre3 = rotation.apply(w @ mean)
        tx = (dc[0] - self.camera.cx) * depth / self.camera.fx - centre3[0]
        ty = (dc[1] - self.camera.cy) * depth / self.camera.fy - centre3[1]
        return rotation, np.array([tx, ty, depth - centre3[2]])

    def start_from(self, previous):
        """FitStart: what a fit warm-started from `previous` (a FitResult: its pose and shape
        parameters) computes before it reads the points, so that a live step can compute it
        while the image model is still finding them."""
        rotation, t = previous.rotation, previous.translation.copy()
        b = (previous.params if previous.seen_params is None else previous.seen_params).copy()
        return self._start(rotation, t, b)

    def _start(self, rotation, t, b):
        shape = self.model.mean + (b @ self._modes_flat).reshape(-1, 3)
        facing = self.model.facing(shape, rotation, t)
        facing = None if facing is None else np.clip(facing / FACING_COSINE, 0.0, 1.0)
        return FitStart(rotation, t, b, facing,
                        *self._linearised(rotation, t, b, self.depth_weight > 0, shape))

    def _linearised(self, rotation, t, b, with_depth, shape=None):
        """(camera-space points y (n, 3), d pixels / d [omega, t, b], d depth / d [omega, t, b]
        or None) of the model at a pose and shape parameters (shape: its points without the
        slide, when known)."""
        if shape is None:
            shape = self.model.mean + (b @ self._modes_flat).reshape(-1, 3)
        slide = self.model.pose_offset(rotation, t, jacobian=True)
        if slide is not None:
            shape = shape + slide[0]
        y = rotation.apply(shape) + t
        return (y, *self._jacobians(y, t, rotation, None if slide is None else slide[1],
                                    with_depth=with_depth))

    def fit(self, points2d, weights=None, previous=None):
        """Fit one frame. points2d: (n, 2) pixels, or (n, 3) with each point's relative depth
        (pixels; non-finite: none); weights: optional (n,) confidences; previous: the last
        frame's FitResult (warm start), or start_from's FitStart of it."""
        p, conf, depth = self._checked_points(points2d, weights)
        if previous is None:
            start = self._start(*self.initial_pose(p, conf), np.zeros(len(self.model.eigenvalues)))
            huber_iterations = 4
        else:
            start = previous if isinstance(previous, FitStart) else self.start_from(previous)
            huber_iterations = 0
        rotation, t, b = start.rotation, start.translation, start.params
        if start.facing is not None:
            conf = conf * start.facing
        damping = 1e-3
        robust = conf.copy()
        scale_px = self.min_scale_px
        iteration = 0
        for iteration in range(1, self.max_iterations + 1):
            if iteration == 1:
                y, jac, depth_jac = start.points, start.jacobian, start.depth_jacobian
            else:
                y, jac, depth_jac = self._linearised(rotation, t, b, depth is not None)
            diff = self.camera.project(y) - p
            robust, scale_px = self._robust_weights(diff, conf, huber=iteration <= huber_iterations)
            depth_rows = None if depth is None else self._depth_rows(y, t, depth_jac, depth, robust)
            step, normal = self._gauss_newton_step(jac, diff, robust, b, damping, depth_rows)
            rotation = Rotation.from_rotvec(step[:3]) * rotation
            t = t + step[3:6]
            b = b + step[6:]
            damping = max(damping * 0.3, 1e-9)
            # converged when no point moves by more than the tolerance
            moved = np.abs(jac @ step).max()
            if moved < self.tolerance_px and iteration > huber_iterations:
                break
        slide = self.model.pose_offset(rotation, t)
        seen_params, shape_normal = None, normal[6:, 6:]
        if self.model.seen_modes is not None:
            seen_params = b
            b, shape_normal = self._located_params(p, robust, rotation, t, b, slide)
        shape = self.model.shape(b)
        placed = shape if slide is None else shape + slide
        proj = self.camera.project(rotation.apply(placed) + t)
        dist = np.linalg.norm(proj - p, axis=1)
        return FitResult(rotation, t, b, shape, proj, dist, robust, iteration, scale_px, slide,
                         shape_normal, seen_params)

    def _located_params(self, p, robust, rotation, t, params, slide):
        """(The modes' own parameters at a pose the seen modes found, their normal matrix): one
        Gauss-Newton step on the parameters alone from the seen modes' (the pose fixed, the
        projection is almost linear in them: a second step moves no point by more than 0.002
        cm), the points weighed as the pose's fit left them."""
        shape = self.model.shape(params)
        y = rotation.apply(shape if slide is None else shape + slide) + t
        diff = self.camera.project(y) - p
        jac = by_model_point(self.camera.jacobian(y), rotation.as_matrix()) @ self._located_modes
        root = np.sqrt(np.repeat(robust, 2))
        weighted = jac.reshape(len(root), -1) * root[:, None]
        normal = weighted.T @ weighted
        normal.flat[::len(normal) + 1] += self._prior[6:]
        gradient = weighted.T @ (root * diff.reshape(-1)) + self._prior[6:] * params
        return params - cho_solve(cho_factor(normal, check_finite=False), gradient,
                                  check_finite=False), normal

    def _checked_points(self, points2d, weights):
        """(points (n, 2), confidences, depths (n,) or None): non-finite points get confidence 0
        (and a placeholder 0); depths only with a third column and a depth weight (a
        non-finite depth: NaN, left out of the depth rows)."""
        n = len(self.model.mean)
        p = np.asarray(points2d, dtype=np.float64)
        if p.ndim != 2 or p.shape[0] != n or p.shape[1] not in (2, 3):
            raise ExCloneError(f"expected {n} 2D points, got an array of shape {p.shape}")
        depth = p[:, 2] if p.shape[1] == 3 and self.depth_weight > 0 else None
        p = p[:, :2]
        conf = np.ones(n) if weights is None else np.clip(np.asarray(weights, float), 0.0, None)
        finite = np.all(np.isfinite(p), axis=1)
        conf = np.where(finite, conf, 0.0)
        p = np.where(finite[:, None], p, 0.0)
        if np.count_nonzero(conf) < 6:
            raise ExCloneError("fewer than 6 usable points: cannot fit a head pose")
        if depth is not None and np.count_nonzero(np.isfinite(depth) & (conf > 0)) < 6:
            depth = None
        return p, conf, depth

    def _robust_weights(self, diff, conf, huber):
        """(per-point weights, robust residual scale in pixels) from the residuals (n, 2)."""
        dist = np.sqrt((diff * diff).sum(axis=1))
        scale_px = robust_sigma(dist[conf > 0], self.min_scale_px)
        robust = conf * tukey_weights(dist, TUKEY_CUTOFF * scale_px)
        if huber or np.count_nonzero(robust) < 6:
            # Huber never rejects a point: safe while the pose is still far off
            robust = conf * huber_weights(dist, 1.345 * scale_px)
        return robust, scale_px

    def _jacobians(self, y, t, rotation, slide_jacobian=None, with_depth=False):
        """(d pixels / d [omega, t, b] (2n, 6 + K), d camera depth / d [omega, t, b] (n, 6 + K),
        None unless with_depth) at camera-space points y; slide_jacobian (n, 3, 6): the
        model-space slide's own change with the pose. The modes' columns are the projection's
        Jacobian brought into the model's axes times the modes: (n, 2, 3) @ (n, 3, K) instead of
        turning all K modes each iteration."""
        n = len(self.model.mean)
        matrix = rotation.as_matrix()
        # omega perturbs on the left: y = exp(w) R x + t
        pose = np.empty((n, 3, 6))
        pose[:, :, :3] = -skew_rows(y - t)
        pose[:, :, 3:] = np.eye(3)
        if slide_jacobian is not None:
            # R @ each point's (3, 6) block, as one (6n, 3) @ (3, 3) product
            turned = slide_jacobian.transpose(2, 0, 1).reshape(-1, 3) @ matrix.T
            pose += turned.reshape(6, n, 3).transpose(1, 2, 0)
        projection = self.camera.jacobian(y)
        jac = np.empty((n, 2, 6 + self._point_modes.shape[2]))
        jac[:, :, :6] = projection @ pose
        jac[:, :, 6:] = by_model_point(projection, matrix) @ self._point_modes
        depth_jac = np.hstack((pose[:, 2], matrix[2] @ self._point_modes)) if with_depth else None
        return jac.reshape(2 * n, -1), depth_jac

    def _depth_rows(self, y, t, depth_jacobian, depth, robust):
        """(jacobian (n, 6 + K), residuals (n,), weights (n,)) of the relative depths: each
        point's depth in pixels (f / t_z times its camera depth) less the weighted mean, against
        the observed less theirs. The same robust weights as the 2D points. depth_jacobian
        (n, 6 + K): d (camera depth) / d [omega, t, b]."""
        w = np.where(np.isfinite(depth), robust, 0.0) * self.depth_weight
        share = w / max(w.sum(), 1e-300)
        f, tz = 0.5 * (self.camera.fx + self.camera.fy), t[2]
        relative = y[:, 2] - share @ y[:, 2]
        observed = np.where(np.isfinite(depth), depth, 0.0)
        residuals = f * relative / tz - (observed - share @ observed)
        jy = depth_jacobian
        jac = f / tz * (jy - share @ jy)
        jac[:, 5] -= f * relative / tz ** 2       # the pixel scale f / t_z changes with t_z
        return jac, residuals - share @ residuals, w

    def _gauss_newton_step(self, jac, diff, robust, params, damping, depth_rows=None):
        """(The damped, prior-regularised weighted Gauss-Newton step in [omega, t, b], its normal
        matrix)."""
        # J^T W J as (W^1/2 J)^T (W^1/2 J): one symmetric product
        root = np.sqrt(np.repeat(robust, 2))
        weighted = jac * root[:, None]
        h = weighted.T @ weighted
        g = weighted.T @ (root * diff.reshape(-1))
        if depth_rows is not None:
            depth_jac, depth_res, depth_w = depth_rows
            h += (depth_jac.T * depth_w) @ depth_jac
            g += (depth_jac.T * depth_w) @ depth_res
        h.flat[::len(h) + 1] += self._prior + damping * h.diagonal()
        g[6:] += self._prior[6:] * params
        return -cho_solve(cho_factor(h, check_finite=False), g, check_finite=False), h


def calibrate_neutral(fitter, frames, rounds=5, stiffness=1.0):
    """Adapt the shape model to the actor from frames of a held neutral face (the calibrated
    neutral f_1 of docs/method.md §11).

    The canonical mean is not the actor's face; left alone, the shape modes would absorb the
    difference in every frame. Each point gets a 3D offset, shared by all calibration frames,
    that best explains its observed positions given each frame's pose (a small bundle
    adjustment: in-plane offsets come from any frame, depth offsets from frames where the head
    turns). `stiffness` (per unit squared offset, relative to one pixel squared) keeps the offsets
    the frames do not constrain near the model. Poses and offsets alternate for `rounds`.
    Frames (F, n, 2), or (F, n, 3) with depths (used by the fits, as ShapeFitter.fit does).
    Returns (neutral shape (n, 3), ShapeFitter whose model mean is that neutral, fits of the frames).
    """
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 3 or len(frames) == 0:
        raise ExCloneError("neutral calibration needs at least one frame of points")
    cam = fitter.camera
    model = fitter.model

    def with_mean(mean, modes=True):
        # the face is held neutral: while calibrating, poses are fitted rigidly (no modes), so
        # the whole difference between actor and model goes into the offsets
        return ShapeFitter(model.with_mean(mean, None if modes else 0), cam,
                           beta=fitter.beta, min_scale_px=fitter.min_scale_px,
                           max_iterations=fitter.max_iterations, tolerance_px=fitter.tolerance_px,
                           depth_weight=fitter.depth_weight)

    neutral = model.mean.copy()
    for _ in range(rounds):
        fits = _fit_frames(with_mean(neutral, modes=False), frames)
        neutral = neutral + _neutral_offsets(cam, frames[..., :2], fits, fitter.min_scale_px,
                                             stiffness)
    current = with_mean(neutral)
    return neutral, current, _fit_frames(current, frames)


def _fit_frames(fitter, frames):
    """The fits of consecutive frames, each warm-started from the one before."""
    fits, previous = [], None
    for points in frames:
        previous = fitter.fit(points, previous=previous)
        fits.append(previous)
    return fits


def _neutral_offsets(cam, frames, fits, min_scale_px, stiffness):
    """(n, 3) the per-point offsets of the model that best explain all frames given their fits."""
    jacobians, residuals = [], []
    for points, fit in zip(frames, fits):
        y = fit.camera_points()
        jacobians.append(cam.jacobian(y) @ fit.rotation.as_matrix())   # d proj / d offset
        residuals.append(points - cam.project(y))
    jac, res = np.array(jacobians), np.array(residuals)      # (F, n, 2, 3), (F, n, 2)
    # The fit's robust weights would keep rejecting exactly the points where the actor
    # differs most from the model. The actor's difference is the same in every frame and a
    # wrong detection is not: weigh each point's frames by their distance to its median.
    spread = np.linalg.norm(res - np.median(res, axis=0), axis=2)       # (F, n)
    w = tukey_weights(spread, TUKEY_CUTOFF * robust_sigma(spread, min_scale_px, axis=0))
    normal = np.einsum("fnki,fnkj,fn->nij", jac, jac, w) + stiffness * np.eye(3)
    rhs = np.einsum("fnki,fnk,fn->ni", jac, res, w)
    return np.linalg.solve(normal, rhs[..., None])[..., 0]


class OneEuroFilter:
    """The One Euro filter (Casiez, Roussel, Vogel, CHI 2012) on arrays of any shape.

    An adaptive low-pass: the cut-off rises with speed, so slow jitter is smoothed strongly while
    fast motion passes with little lag. min_cutoff (Hz) sets the jitter removal at rest; beta the
    speed adaptation; d_cutoff (Hz) smooths the speed estimate.
    """

    def __init__(self, min_cutoff=1.0, beta=0.05, d_cutoff=1.0):
        self.min_cutoff = float(min_cutoff)
        self.beta = float(beta)
        self.d_cutoff = float(d_cutoff)
        self.reset()

    def reset(self):
        self._x = None
        self._dx = None
        self._t = None

    @staticmethod
    def _alpha(cutoff, dt):
        tau = 1.0 / (2.0 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / dt)

    def __call__(self, value, timestamp):
        """Filter `value` observed at `timestamp` (seconds); returns the filtered value."""
        x = np.asarray(value, dtype=np.float64)
        if self._x is None:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), float(timestamp)
            return x.copy()
        dt = float(timestamp) - self._t
        if dt <= 0:
            return self._x.copy()
        self._t = float(timestamp)
        dx = (x - self._x) / dt
        a_d = self._alpha(self.d_cutoff, dt)
        self._dx = self._dx + a_d * (dx - self._dx)
        cutoff = self.min_cutoff + self.beta * np.abs(self._dx)
        self._x = self._x + self._alpha(cutoff, dt) * (x - self._x)
        return self._x.copy()


class RotationFilter:
    """One Euro filtering of a rotation, on its rotation vector relative to the first one seen
    (continuous, no wrap-around, for the head turns a face tracker sees)."""

    def __init__(self, min_cutoff=1.0, beta=0.5, d_cutoff=1.0):
        self._filter = OneEuroFilter(min_cutoff, beta, d_cutoff)
        self._reference = None

    def __call__(self, rotation, timestamp):
        if self._reference is None:
            self._reference = rotation
            self._filter(np.zeros(3), timestamp)
            return rotation
        rel = (rotation * self._reference.inv()).as_rotvec()
        out = self._filter(rel, timestamp)
        return Rotation.from_rotvec(out) * self._reference


def remove_head_motion(shape3d, neutral, weights=None):
    """Rigidly align a frame's 3D shape onto the neutral (weighted Kabsch, no reflection).

    Returns (aligned shape (n, 3), head rotation): aligned - neutral is the head-pose free
    expression displacement; the rotation turns the neutral's orientation into the frame's.
    """
    shape3d = np.asarray(shape3d, dtype=np.float64)
    neutral = np.asarray(neutral, dtype=np.float64)
    if shape3d.shape != neutral.shape:
        raise ExCloneError(f"shape {shape3d.shape} and neutral {neutral.shape} differ")
    w = np.ones(len(neutral)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, cn = w @ shape3d, w @ neutral
    # align_vectors returns a proper rotation (the reflection fix of Kabsch) for weighted pairs
    rotation, _ = Rotation.align_vectors(shape3d - cs, neutral - cn, weights=w)
    aligned = rotation.inv().apply(shape3d - cs) + cn
    return aligned, rotation
