"""The tracker's 3D shape model: the file that ships it (build and read) and the model built from it.

The model's points are FaceMesh's 468 (its order). Where they lie on the bundled ICT face's skin
is a registration of MediaPipe's canonical face (about 5 s); the located points carry the ICT
library's expressions (docs/method.md §11) and are where retargeting samples an avatar made on
ICT's topology. FaceMesh does not report those points, though: its points sit a little apart
and slide over the face as the head turns. So the shipped model is learnt from what FaceMesh
reports on ICT heads rendered with known expressions and head turns (learn_tracker_model): its
neutral and each point's slide with the turn; the modes are the located points' expression
motion, which the fit sees partly as FaceMesh's points move with each expression.
The same renders, read by the iris model, teach how the eyes' frontal reading still slides with
the head's turn (learn_eye_slide, core.eyes.EyeSlide).
What the fit still reads wrongly of the head's turn on those renders, where it is linear in what
the fit reports, is learnt too and taken out of the reported rotation (learn_pose_bias).
data/tracker_model.npz ships both the locations and the learnt arrays (written by
scripts/make_tracker_model.py, which renders in background Blender); loading it is a small PCA.
"""
import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from . import data
from .eyes import READING_MEASURES, EyeGeometry, EyeReading, EyeSlide, reading_measures
from .library import load_library
from .retarget import SurfaceLocations, locate_canonical_face
from .registration import similarity_transform
from .tracking import (POSE_FEATURES, TUKEY_CUTOFF, ShapeFitter, ShapeModel, calibrate_neutral,
                       expression_shape_model, robust_sigma, tukey_weights)

TRACKER_MODEL_VERSION = 4
REMEDY = "run scripts/make_tracker_model.py"


# -- build time -------------------------------------------------------------------------------------

def locate_tracker_landmarks(library=None, progress=None):
    """Where the canonical face's 468 points lie on the bundled ICT face's skin (a registration)."""
    library = library or load_library()
    triangles = library.mesh.triangles()
    start, stop = library.parts["face"]      # ICT's skin, as its README defines it
    skin = triangles[np.all((triangles >= start) & (triangles < stop), axis=1)]
    locations, _ = locate_canonical_face(data.canonical_face(), library.mesh, skin,
                                         progress=progress)
    return locations


@dataclass
class TrainingFrames:
    """One rendered head's frames: FaceMesh's points and the known truth."""
    points: np.ndarray          # (T, 468, 3) FaceMesh's points (pixels; NaN: no face found)
    weights: np.ndarray         # (T, E) the library's expression weights
    rotations: object           # scipy Rotation (T,): the head (library axes) -> camera
    translations: np.ndarray    # (T, 3) where the library's origin is in camera space
    neutral: np.ndarray         # (468, 3) the located points on this head's neutral
    # (T, 2, READING_MEASURES) the iris model's reading of each frame's eyes (core.eyes.read_eyes:
    # eyes.reading_measures; NaN: none), or None
    eyes: np.ndarray = None


LEARNED_ARRAYS = ("mean", "deltas", "seen_deltas", "pose_offsets", "pose_centre",
                  "eye_pose_offsets", "pose_bias")
# How far the learnt model may stray from the located points where the frames say little, as
# pixel^2 per cm^2 of difference (a pixel is about 0.08 cm on the training renders): the neutral's
# offsets, the expressions' point motion (from the located motion) and the turn's slide.
OFFSET_PRIOR = 1.0
# A point's depth offset and its slide linear in the turn move its image alike (to first order):
# the depth offset is held near the located surface, so that the turn's effect is the slide's.
OFFSET_DEPTH_PRIOR = 1000.0
MOTION_PRIOR = 20.0
SLIDE_PRIOR = 5.0
# The fit sees each mode move FaceMesh's points this share of the way from the located motion to
# FaceMesh's learnt motion (ShapeModel.seen_modes): what the located motion leaves unexplained
# of FaceMesh's response (a sneer moves its nose points alike, as if the head pitched) otherwise
# goes into the head's pose. On the rendered takes' fits (rotation error median / max, degrees,
# unfiltered): moving 1.40 / 3.14 -> 1.32 / 2.74, the head still 0.75 / 2.93 -> 0.74 / 2.10; 0.3,
# 0.6 and 0.8 do less for the moving take or cost identity 7 more, all of it (1.0): 1.94 / 3.11
# (docs/method.md §11).
SEEN_SHARE = 0.45
# The eyes' slide is learnt from the frames whose keys leave the eyes alone (their names start
# with this): a closing lid or a turned eye is not what the turn does to a neutral one.
EYE_KEY_PREFIX = "eye"
# Keeps what the frames do not separate (a key's effect on the lids from the turn's) near zero,
# per unit squared coefficient against the readings' squared residuals (eye widths^2; the
# readings' noise is about 0.01 widths a frame).
EYE_SLIDE_PRIOR = 1e-2
# The ridge penalty of the rotation's learnt bias (learn_pose_bias), per frame and relative to each
# feature's variance: chosen by leaving each training head out in turn (the bias learnt from the
# other 7, the rotation error's median / 95th percentile on the one left out, degrees: none 1.76;
# 0.01 1.69 / 3.58, 0.1 1.66 / 3.49, 0.3 1.65 / 3.50, 1.0 1.64 / 3.55).
POSE_BIAS_RIDGE = 0.3


def _training_axes(frames):
    """(the heads' mean located neutral (n, 3), its similarity (rot, scale, shift) onto the
    canonical face, its centre): the frame the learnt slides are measured in."""
    mean_neutral = np.mean([f.neutral for f in frames], axis=0)
    return (mean_neutral, similarity_transform(mean_neutral, data.canonical_face().vertices),
            mean_neutral.mean(axis=0))


def learn_tracker_model(locations, frames, library, camera, rounds=2):
    """The tracker's model learnt from what FaceMesh reports on rendered heads (docs/method.md
    §11): each point p of a frame, in the library's axes, is the located point on that head's
    neutral L plus the head's own offset o_h (what calibration finds for an actor), the
    expressions' motion sum_e w_e D_e and a slide with the head's turn sum_f phi_f(v) A_f
    (ShapeModel.pose_features of the direction v to the camera). Every observed pixel is a
    linear equation in (o, D, A) (the point lies on the pixel's ray, divided by its depth:
    residuals in pixels), solved per point by least squares with the priors above; a second
    round weighs each observation by its residual (Tukey: a frame FaceMesh misread counts for
    nothing). Returns a dict of arrays in the canonical face's axes and units
    (write_tracker_model): the mean (the heads' mean neutral with their mean offset), the
    expressions' located motion, FaceMesh's own motion D (TrackerModel.from_learned), the slide
    A and the centre it is measured from.
    """
    located_deltas = locations.sample(library.deltas)                  # (E, n, 3)
    mean_neutral, (rot, scale, shift), centre = _training_axes(frames)
    n, heads, count = len(mean_neutral), len(frames), len(library.deltas)
    size = heads + count + len(POSE_FEATURES)
    prior = np.repeat(np.concatenate([np.full(heads, OFFSET_PRIOR), np.full(count, MOTION_PRIOR),
                                      np.full(len(POSE_FEATURES), SLIDE_PRIOR)]), 3)
    prior[2:3 * heads:3] = OFFSET_DEPTH_PRIOR
    target = np.zeros((n, size, 3))
    target[:, heads:heads + count] = located_deltas.transpose(1, 0, 2)
    systems = [_LinearRays(part, h, heads, camera, centre, rot) for h, part in enumerate(frames)]
    solved = target
    for round_ in range(rounds):
        gram = np.diag(prior)[None] + sum(system.gram(solved, robust=round_ > 0) for system in systems)
        rhs = prior * target.reshape(n, -1) + sum(system.rhs() for system in systems)
        solved = np.linalg.solve(gram, rhs[..., None])[..., 0].reshape(n, size, 3)
    offsets = solved[:, :heads].mean(axis=1)
    slide = solved[:, heads + count:].transpose(1, 0, 2)
    to_model = scale * rot.T      # row vectors: x @ (s R)^T
    seen = solved[:, heads:heads + count].transpose(1, 0, 2)
    return dict(mean=(mean_neutral + offsets) @ to_model + shift, deltas=located_deltas @ to_model,
                seen_deltas=seen @ to_model, pose_offsets=slide @ to_model,
                pose_centre=centre @ to_model + shift)


def learn_eye_slide(frames, names, camera, rounds=2):
    """(F, 2, READING_MEASURES) the eyes' slide (core.eyes.EyeSlide's offsets, about the centre
    and in the axes of learn_tracker_model's pose_offsets) from the frames' eye readings: each
    frame's reading is brought frontal by the true pose (EyeGeometry on the head's located
    neutral; the irises' centres the head's median frontal iris), and each measure is fitted by
    least squares as the head's own value, the frame's keys' linear effect and the slide linear
    in ShapeModel.pose_features; a second round weighs each frame by its residual (Tukey: a
    frame the iris model misread counts for nothing). Frames wearing eye keys are left out."""
    _, (rot, _, _), centre = _training_axes(frames)
    eye_keys = np.array([name.startswith(EYE_KEY_PREFIX) for name in names])
    heads, columns, values = len(frames), [], []
    for h, part in enumerate(frames):
        used = np.flatnonzero(np.all(np.isfinite(part.eyes), axis=(1, 2))
                              & ~np.any(part.weights[:, eye_keys] > 0, axis=1))
        geometry = EyeGeometry(part.neutral, camera)
        readings = [EyeReading.from_measures(part.eyes[k]) for k in used]
        ahead = [geometry.frontal(r, part.rotations[k], part.translations[k])
                 for r, k in zip(readings, used)]
        centres = np.median([r.iris for r in ahead], axis=0)
        values += [reading_measures(geometry.frontal(r, part.rotations[k], part.translations[k],
                                                     centres)).reshape(-1)
                   for r, k in zip(readings, used)]
        to_camera = ShapeModel.camera_offsets(part.rotations[used], part.translations[used],
                                              centre) @ rot.T
        which = np.zeros((len(used), heads))
        which[:, h] = 1.0
        columns.append(np.column_stack((which, part.weights[used][:, ~eye_keys],
                                        ShapeModel.pose_features(to_camera))))
    design, values = np.vstack(columns), np.array(values)            # (T, U), (T, 2 * M)
    size = design.shape[1]
    prior = np.sqrt(EYE_SLIDE_PRIOR) * np.eye(size)[heads:]
    weights = np.ones(values.shape)
    for _ in range(rounds):
        solved = np.column_stack([np.linalg.lstsq(
            np.vstack((design * np.sqrt(w)[:, None], prior)),
            np.concatenate((value * np.sqrt(w), np.zeros(len(prior)))), rcond=None)[0]
            for value, w in zip(values.T, weights.T)])
        residual = np.abs(values - design @ solved)
        weights = tukey_weights(residual, TUKEY_CUTOFF * robust_sigma(residual, axis=0))
    return solved[size - len(POSE_FEATURES):].reshape(len(POSE_FEATURES), 2, READING_MEASURES)
def pose_bias_features(model, params, rotation, translation):
    """(K + F,) what the rotation's learnt bias is linear in: a fit's shape parameters and its
    pose's features (ShapeModel.pose_features of the direction to the camera, as the slide)."""
    to_camera = ShapeModel.camera_offsets(rotation, translation, model.pose_centre)
    return np.concatenate((params, ShapeModel.pose_features(to_camera[None])[0]))


def learn_pose_bias(tracker, frames, camera, ridge=POSE_BIAS_RIDGE):
    """(3, K + F) the fit's rotation error (a rotation vector in the head's axes) linear in
    pose_bias_features, learnt from the training renders (TrainingFrames, docs/method.md §11):
    each head calibrated on its neutral frames as a session does, each frame fitted afresh by the
    calibrated tracker (a TrackerModel: the model as shipped), its error against the known turn
    (the head's axes in the model's are what best aligns the neutral frames' fits); ridge
    regression with an intercept (penalty `ridge`, POSE_BIAS_RIDGE). What a fit reads wrongly
    for the expressions' look in FaceMesh's points (a sneer or a pucker read as a pitch) and for
    the slide the model leaves, as far as that is common to the heads."""
    rows, errors = [], []
    for part in frames:
        found = np.all(np.isfinite(part.points[..., :2]), axis=(1, 2))
        neutral = np.flatnonzero(found & ~np.any(part.weights, axis=1))
        fitter = ShapeFitter(tracker.shape_model, camera, depth_weight=tracker.depth_weight)
        _, actor, fits = calibrate_neutral(fitter, part.points[neutral])
        to_library = (part.rotations[neutral].inv()
                      * Rotation.concatenate([fit.rotation for fit in fits])).mean()
        for k in np.flatnonzero(found):
            fit = actor.fit(part.points[k])
            rows.append(pose_bias_features(actor.model, fit.params, fit.rotation, fit.translation))
            errors.append(((part.rotations[k] * to_library).inv() * fit.rotation).as_rotvec())
    x = np.column_stack((rows, np.ones(len(rows))))
    penalty = ridge * len(x) * np.append(np.var(x[:, :-1], axis=0), 0.0)
    solved = np.linalg.solve(x.T @ x + np.diag(penalty), x.T @ np.array(errors))
    return solved[:-1].T


class _LinearRays:
    """One head's frames as linear equations in the unknowns of learn_tracker_model: per frame
    and point, two rows (n, 2, 3) acting on p - L and their right-hand sides, in pixels."""

    def __init__(self, part, head, heads, camera, centre, rot):
        seen = np.all(np.isfinite(part.points[..., :2]), axis=(1, 2))
        points = part.points[seen, :, :2]
        matrices = part.rotations[np.flatnonzero(seen)].as_matrix()       # (T, 3, 3)
        translations = part.translations[seen]
        # the direction to the camera from the head's centre, in the model's axes
        to_camera = ShapeModel.camera_offsets(part.rotations[np.flatnonzero(seen)], translations,
                                              centre)
        features = ShapeModel.pose_features(to_camera @ rot.T)             # (T, F)
        which = np.zeros((len(points), heads))
        which[:, head] = 1.0
        self.unknowns = np.column_stack((which, part.weights[seen], features))   # (T, U)
        located = np.einsum("tij,nj->tni", matrices, part.neutral) + translations[:, None]
        depth = located[..., 2]                                           # (T, n)
        focal = np.array([camera.fx, camera.fy])
        offset = points - np.array([camera.cx, camera.cy])                # (T, n, 2)
        # the ray of pixel (u, v): f X_k - (u_k - c_k) X_z = 0 for X = R p + t, k = x, y
        self.rows = (focal[None, None, :, None] * matrices[:, None, :2, :]
                     - offset[..., None] * matrices[:, None, None, 2, :]) / depth[..., None, None]
        values = (offset * translations[:, None, None, 2] - focal * translations[:, None, :2]) \
            / depth[..., None]
        self.values = values - np.einsum("tnkj,nj->tnk", self.rows, part.neutral)
        self.weights = np.ones(depth.shape)                               # (T, n)

    def gram(self, solved, robust):
        """(n, 3U, 3U); with robust, the observations are first reweighed by their residuals
        under `solved` (n, U, 3)."""
        if robust:
            residual = self.residuals(solved)
            self.weights = tukey_weights(residual,
                                         TUKEY_CUTOFF * robust_sigma(residual, 0.5, axis=0))
        count, size = self.unknowns.shape
        pair = np.einsum("tu,tv->tuv", self.unknowns, self.unknowns).reshape(count, -1)
        outer = np.einsum("tnki,tnkj,tn->tnij", self.rows, self.rows, self.weights).reshape(count, -1)
        n = self.rows.shape[1]
        return (pair.T @ outer).reshape(size, size, n, 3, 3).transpose(2, 0, 3, 1, 4).reshape(
            n, 3 * size, 3 * size)

    def residuals(self, solved):
        """(T, n) each observation's distance in pixels from its ray under `solved` (n, U, 3)."""
        predicted = np.einsum("tu,nui->tni", self.unknowns, solved)
        return np.linalg.norm(np.einsum("tnkj,tnj->tnk", self.rows, predicted) - self.values, axis=2)

    def rhs(self):
        """(n, 3U) with the weights of the last gram()."""
        return np.einsum("tu,tnki,tnk,tn->nui", self.unknowns, self.rows, self.values,
                         self.weights).reshape(self.rows.shape[1], -1)


def write_tracker_model(locations, learned, path=data.TRACKER_MODEL_FILE):
    np.savez_compressed(path, format_version=np.int64(TRACKER_MODEL_VERSION),
                        library=np.str_(data.LIBRARY_FILE.name),
                        corners=locations.corners.astype(np.int32), bary=locations.bary,
                        **{key: np.asarray(value, dtype=np.float32) for key, value in learned.items()})


# -- run time ---------------------------------------------------------------------------------------

def read_tracker_locations(path=data.TRACKER_MODEL_FILE):
    """The shipped surface locations of the canonical face's points on the library's face."""
    stored = data.versioned_arrays(path, TRACKER_MODEL_VERSION, "tracker model", REMEDY)
    return SurfaceLocations(stored["corners"].astype(np.int64), stored["bary"].astype(np.float64))


def read_learned_model(path=data.TRACKER_MODEL_FILE):
    """The shipped model learnt from FaceMesh's points (learn_tracker_model's arrays)."""
    stored = data.versioned_arrays(path, TRACKER_MODEL_VERSION, "tracker model", REMEDY)
    return {key: stored[key].astype(np.float64) for key in LEARNED_ARRAYS}


@dataclass(frozen=True)
class TrackerModel:
    """The tracker's 3D shape model (canonical face + ICT expression modes) in the canonical
    face's units (cm) and axes."""
    shape_model: ShapeModel
    canonical: np.ndarray      # (468, 3) MediaPipe's canonical face
    depth_weight: float = 0.1  # how much FaceMesh's depth counts in the fit (ShapeFitter)
    eye_slide: EyeSlide = None   # the eyes' reading's slide with the head's turn, if learnt
    pose_bias: np.ndarray = None   # (3, K + F) the fit's learnt rotation bias (learn_pose_bias)
    expressions: np.ndarray = None   # (E, 468, 3) the library's expressions' located motion

    @classmethod
    def from_learned(cls, learned):
        """The model learnt from FaceMesh's points (learn_tracker_model): its mean and the
        points' slide with the head's turn; the modes are the expressions' located motion
        (FaceMesh's own, learnt too, moves its points 0.2-0.7 times as far: modes of that read
        the rendered takes worse, docs/method.md §11), seen by the fit SEEN_SHARE of the way
        towards FaceMesh's own. FaceMesh's depth is not read with it: the model says nothing of
        it. The eyes' slide (learn_eye_slide), when learnt, is measured about the points'
        centre."""
        canonical = data.canonical_face()
        located, seen = learned["deltas"], learned["seen_deltas"]
        model = ShapeModel.from_displacements(learned["mean"], located,
                                              triangles=canonical.triangles(),
                                              seen=located + SEEN_SHARE * (seen - located))
        return cls(replace(model, pose_offsets=learned["pose_offsets"],
                           pose_centre=learned["pose_centre"]), canonical.vertices, depth_weight=0.0,
                   eye_slide=None if learned.get("eye_pose_offsets") is None else
                   EyeSlide(learned["eye_pose_offsets"], learned["pose_centre"]),
                   pose_bias=learned.get("pose_bias"), expressions=located)

    def unbiased_rotation(self, fit):
        """A fit's rotation less its learnt bias (learn_pose_bias); the fit's own without one."""
        if self.pose_bias is None:
            return fit.rotation
        features = pose_bias_features(self.shape_model, fit.params, fit.rotation, fit.translation)
        return fit.rotation * Rotation.from_rotvec(-(self.pose_bias @ features))

    @classmethod
    def from_locations(cls, locations, library=None):
        library = library or load_library()
        canonical = data.canonical_face()
        model = expression_shape_model(canonical.vertices, locations.sample(library.mesh.vertices),
                                       locations.sample(library.deltas),
                                       triangles=canonical.triangles())
        return cls(model, canonical.vertices)


@functools.lru_cache(maxsize=1)
def load_tracker_model():
    """The bundled tracker model, built once per process from data/tracker_model.npz."""
    return TrackerModel.from_learned(read_learned_model())
