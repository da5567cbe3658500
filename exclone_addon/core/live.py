"""Live face tracking, one frame at a time: the whole of issue 5's pipeline behind one step().

Per frame: BlazeFace on the first frame and whenever tracking is lost, otherwise the region the
previous frame's landmarks give; FaceMesh's 468 points; the tracker's 3D shape model fitted to
them with head pose, warm-started from the previous frame (core.tracking); One Euro filters on
pose, shape and landmarks; neutral calibration over the first frames with a face; then, with an
avatar, its shape-key weights (core.retarget).

The tracker's shape model is the canonical face (MediaPipe's 468 points) with the bundled ICT
library's expressions sampled where those points lie on ICT's face. Finding them there is a
registration (about 5 s); its result, a surface location per point, ships in
data/tracker_model.npz (made by scripts/make_tracker_model.py), so loading the model costs
reading the library and a small PCA (about 0.4 s, once per process).
"""
import functools
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from . import data, face_models
from .errors import ExCloneError
from .library import load_library
from .mesh import MeshError, PolyMesh
from .retarget import (SurfaceLocations, WeightSolver, locate_canonical_face, map_blendshapes,
                       refine_take)
from .tracking import (Camera, OneEuroFilter, RotationFilter, ShapeFitter, ShapeModel,
                       calibrate_neutral, expression_shape_model)

TRACKER_MODEL_VERSION = 1
# The model's axes (canonical face: +Y up, looking along +Z, +X the subject's left) -> Blender's
# (+Z up, looking along -Y, +X the subject's left): a quarter turn about x.
MODEL_TO_BLENDER = Rotation.from_euler("x", 90, degrees=True)
# A region smaller than this many pixels cannot hold a face FaceMesh can read.
MIN_ROI_SIZE = 24.0
# The fit stops when no point moves by more than this (pixels): FaceMesh's own noise is several
# times larger. 0.05 instead of tracking's 1e-3 takes the fit from 4 to about 3 iterations with no
# change in test_live's figures at 3 decimals.
FIT_TOLERANCE_PX = 0.05
# The per-frame stages timed in FrameResult.stage_ms (calibration adds "calibrate" when it runs).
STAGES = ("detect", "landmarks", "fit", "weights")


# ---------------------------------------------------------------------------- tracker's model
def locate_tracker_landmarks(library=None, progress=None):
    """Where the canonical face's 468 points lie on the bundled ICT face's skin (a registration)."""
    library = library or load_library()
    triangles = library.mesh.triangles()
    start, stop = library.parts["face"]      # ICT's skin, as its README defines it
    skin = triangles[np.all((triangles >= start) & (triangles < stop), axis=1)]
    locations, _ = locate_canonical_face(data.canonical_face(), library.mesh, skin,
                                         progress=progress)
    return locations


def write_tracker_model(locations, path=data.TRACKER_MODEL_FILE):
    np.savez_compressed(path, format_version=np.int64(TRACKER_MODEL_VERSION),
                        library=np.str_(data.LIBRARY_FILE.name),
                        corners=locations.corners.astype(np.int32), bary=locations.bary)


def read_tracker_locations(path=data.TRACKER_MODEL_FILE):
    if not Path(path).is_file():
        raise ExCloneError(f"tracker model {path} is missing; run scripts/make_tracker_model.py")
    with np.load(path, allow_pickle=False) as data:
        if int(data["format_version"]) != TRACKER_MODEL_VERSION:
            raise ExCloneError(f"tracker model {path} has an old format; "
                               "run scripts/make_tracker_model.py")
        return SurfaceLocations(data["corners"].astype(np.int64), data["bary"].astype(np.float64))


@dataclass(frozen=True)
class TrackerModel:
    """The tracker's 3D shape model (canonical face + ICT expression modes) in the canonical
    face's units (cm) and axes."""
    shape_model: ShapeModel
    canonical: np.ndarray      # (468, 3) MediaPipe's canonical face

    @classmethod
    def from_locations(cls, locations, library=None):
        library = library or load_library()
        canonical = data.canonical_face().vertices
        model = expression_shape_model(canonical, locations.sample(library.mesh.vertices),
                                       locations.sample(library.deltas))
        return cls(model, canonical)


@functools.lru_cache(maxsize=1)
def load_tracker_model():
    """The bundled tracker model, built once per process from data/tracker_model.npz."""
    return TrackerModel.from_locations(read_tracker_locations())


# ---------------------------------------------------------------------------- avatar
@dataclass
class AvatarRig:
    """The avatar's side: its shape keys sampled where the tracker's 468 points lie on it."""
    names: list
    neutral: np.ndarray        # (468, 3) the located points on the avatar's neutral
    deltas: np.ndarray         # (N, 468, 3) each shape key's displacement there
    locations: SurfaceLocations

    @classmethod
    def from_locations(cls, vertices, deltas, names, locations):
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
        return cls(list(names), neutral, sparse, locations)

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
        return cls.from_locations(vertices, deltas, names, locations)


# ---------------------------------------------------------------------------- session
class LandmarkFilter:
    """One Euro filtering of image landmarks in the face's own frame.

    Each frame's points are brought onto the first frame's by the least-squares 2D similarity
    (rotation, scale, shift) over all of them; the filter runs there and the result goes back by
    the same similarity. The similarity, an average over 468 points, hardly jitters and is not
    filtered, so moving the head costs no lag; what is filtered is the points' motion within the
    face: jitter at rest, expressions (which the speed adaptation lets through).
    """

    def __init__(self, min_cutoff=1.5, beta=0.05):
        self._filter = OneEuroFilter(min_cutoff, beta)
        self._reference = None

    def __call__(self, points, timestamp):
        points = np.asarray(points, dtype=np.float64)
        z = points[:, 0] + 1j * points[:, 1]
        if self._reference is None:
            self._reference = z - z.mean()
        # z ~ a * reference + b with complex a (rotation and scale), b (shift)
        centre = z.mean()
        a = np.vdot(self._reference, z - centre) / np.vdot(self._reference, self._reference).real
        local = (z - centre) / a
        local_points = np.column_stack((local.real, local.imag, points[:, 2:] / abs(a)))
        smooth = self._filter(local_points, timestamp)
        back = a * (smooth[:, 0] + 1j * smooth[:, 1]) + centre
        return np.column_stack((back.real, back.imag, smooth[:, 2:] * abs(a)))


@dataclass
class FrameResult:
    found: bool
    landmarks: np.ndarray = None      # (468, 3) image pixels x, y + FaceMesh z
    ibug68: np.ndarray = None         # (68, 2) iBUG 300-W order, image pixels
    rotation: Rotation = None         # model -> camera (OpenCV axes)
    translation: np.ndarray = None    # (3,) camera space, model units (cm)
    head_rotation: Rotation = None    # relative to the calibrated neutral, Blender axes
    weights: dict = None              # shape-key name -> 0..1
    stage_ms: dict = field(default_factory=dict)
    status: str = ""


@dataclass
class Take:
    """What a calibrated session with an avatar recorded: per-frame head-motion-free landmark
    displacements from the calibrated neutral, and their timestamps."""
    timestamps: list = field(default_factory=list)
    displacements: list = field(default_factory=list)


class FaceTrackingSession:
    """One camera or clip's tracking state; step() does one frame's whole work.

    still_images: every frame is an unrelated photograph (detection on each, no warm start, no
    temporal filtering, camera intrinsics from each image's size unless given).
    """

    def __init__(self, avatar=None, camera=None, calibration_frames=30,
                 models_dir=data.MODELS_DIR, tracker_model=None, still_images=False):
        self.avatar = avatar
        self.camera = camera
        self._fixed_camera = camera is not None
        self.calibration_frames = int(calibration_frames)
        if self.calibration_frames < 1:
            raise ExCloneError("calibration needs at least one frame")
        self.still_images = bool(still_images)
        self.detector = face_models.FaceDetector(models_dir)
        self.landmarker = face_models.FaceLandmarker(models_dir)
        self.model = (tracker_model or load_tracker_model()).shape_model
        self._fitter = None           # the canonical model's fitter until calibrated
        self.neutral = None           # (468, 3) the actor's calibrated neutral (model space)
        self.neutral_rotation = None  # mean head pose over the calibration frames
        self.solver = None
        self.take = Take()
        self._roi = None
        self._previous_fit = None
        self._last = None             # the last FrameResult with a face
        self._pending = 0             # calibration frames still wanted (0: not calibrating)
        self._calibration_points = []
        self._reset_filters()
        self.calibrate()

    @property
    def calibrated(self):
        return self.neutral is not None

    def calibrate(self, frames=None):
        """(Re)start neutral calibration over the next `frames` frames with a face (default
        calibration_frames). Until it completes the previous calibration stays in use; a new
        calibration starts a new take."""
        self._pending = int(frames) if frames is not None else self.calibration_frames
        if self._pending < 1:
            raise ExCloneError("calibration needs at least one frame")
        self._calibration_points = []

    def _reset_filters(self):
        # Cut-offs in Hz at rest; beta raises them with speed (rad/s, cm/s, parameter units/s,
        # px/s). Rotation: 1 deg of jitter is halved at rest while a 45 deg/s turn lags about 2 deg
        # (measured on test_live's synthetic take).
        self._filters = {
            "rotation": RotationFilter(min_cutoff=1.0, beta=10.0),
            "translation": OneEuroFilter(min_cutoff=1.0, beta=2.0),
            "params": OneEuroFilter(min_cutoff=2.0, beta=5.0),
            "landmarks": LandmarkFilter(min_cutoff=1.5, beta=0.05),
        }

    def _use_image_size(self, width, height):
        """The default camera for this image size, unless one was given."""
        if self.camera is None or (self.still_images and not self._fixed_camera):
            camera = Camera.from_image_size(width, height)
            if camera != self.camera:
                self.camera = camera
                self._fitter = None
        if self._fitter is None:
            model = self.model if self.neutral is None else ShapeModel(
                self.neutral, self.model.modes, self.model.eigenvalues)
            self._fitter = ShapeFitter(model, self.camera, tolerance_px=FIT_TOLERANCE_PX)

    # -- image models
    def _find_face(self, image, stage_ms):
        """Landmarks and presence: from the previous region when tracking, else by detection."""
        if self._roi is not None and not self.still_images:
            start = time.perf_counter()
            points, presence = self.landmarker.landmarks(image, self._roi)
            stage_ms["landmarks"] += 1000 * (time.perf_counter() - start)
            if presence >= face_models.FACE_PRESENCE_THRESHOLD:
                return points, False
        start = time.perf_counter()
        detections = self.detector.detect(image)
        stage_ms["detect"] += 1000 * (time.perf_counter() - start)
        if not detections:
            return None, True
        start = time.perf_counter()
        points, presence = self.landmarker.landmarks(image, face_models.roi_from_detection(detections[0]))
        if presence >= face_models.FACE_PRESENCE_THRESHOLD:
            # the detector's box is coarse: a second pass in the region the landmarks give
            # (what the next video frame would use) places the points as tracking does
            again, again_presence = self.landmarker.landmarks(image, face_models.roi_from_landmarks(points))
            if again_presence >= face_models.FACE_PRESENCE_THRESHOLD:
                points = again
        stage_ms["landmarks"] += 1000 * (time.perf_counter() - start)
        if presence < face_models.FACE_PRESENCE_THRESHOLD:
            return None, True
        return points, True

    def step(self, image_bgr, timestamp):
        """One frame (8-bit BGR) at `timestamp` seconds -> FrameResult."""
        image = face_models._check_image(image_bgr)
        self._use_image_size(image.shape[1], image.shape[0])
        stage_ms = dict.fromkeys(STAGES, 0.0)
        points, detected = self._find_face(image, stage_ms)
        if points is None:
            return self._lost(stage_ms)
        roi = face_models.roi_from_landmarks(points)
        self._roi = roi if roi.size >= MIN_ROI_SIZE else None
        return self._track(points, timestamp, stage_ms, restart=detected)

    def step_landmarks(self, landmarks, timestamp, image_size=None):
        """One frame from given landmarks (468, 2 or 3) in pixels, past the image models (for
        landmarks from elsewhere and for tests); image_size (w, h) sets the default camera."""
        points = np.asarray(landmarks, dtype=np.float64)
        if points.ndim != 2 or points.shape[0] != face_models.NUM_LANDMARKS or points.shape[1] not in (2, 3):
            raise ExCloneError(f"expected ({face_models.NUM_LANDMARKS}, 2 or 3) landmarks, "
                               f"got {points.shape}")
        if points.shape[1] == 2:
            points = np.column_stack((points, np.zeros(len(points))))
        if image_size is None:
            if self.camera is None:
                raise ExCloneError("step_landmarks needs a camera or the image size")
            image_size = (2 * self.camera.cx, 2 * self.camera.cy)
        self._use_image_size(*image_size)
        stage_ms = dict.fromkeys(STAGES, 0.0)
        return self._track(points, timestamp, stage_ms, restart=self._previous_fit is None)

    def _lost(self, stage_ms):
        self._roi = None
        self._previous_fit = None
        last = self._last
        status = "no face in view: holding the last pose" if last else "no face in view"
        if last is None:
            return FrameResult(found=False, stage_ms=stage_ms, status=status)
        return FrameResult(found=False, rotation=last.rotation, translation=last.translation,
                           head_rotation=last.head_rotation, weights=last.weights,
                           stage_ms=stage_ms, status=status)

    # -- shape fit, calibration, weights
    def _track(self, points, timestamp, stage_ms, restart):
        if restart or self.still_images:
            self._reset_filters()
            if self.still_images:
                self._previous_fit = None
        start = time.perf_counter()
        fit = self._fitter.fit(points[:, :2], previous=self._previous_fit)
        self._previous_fit = fit
        stage_ms["fit"] = 1000 * (time.perf_counter() - start)

        if self._pending:
            self._calibration_points.append(points[:, :2].copy())
            if len(self._calibration_points) >= self._pending:
                start = time.perf_counter()
                self._finish_calibration()
                stage_ms["calibrate"] = 1000 * (time.perf_counter() - start)
                fit = self._previous_fit

        if self.still_images:
            rotation, translation, params, shown = fit.rotation, fit.translation, fit.params, points
        else:
            rotation = self._filters["rotation"](fit.rotation, timestamp)
            translation = self._filters["translation"](fit.translation, timestamp)
            params = self._filters["params"](fit.params, timestamp)
            shown = self._filters["landmarks"](points, timestamp)

        head_rotation = weights = None
        if self.calibrated:
            relative = self.neutral_rotation.inv() * rotation     # in the face's own axes
            head_rotation = MODEL_TO_BLENDER * relative * MODEL_TO_BLENDER.inv()
            if self.solver is not None:
                start = time.perf_counter()
                displacement = self._fitter.model.shape(params) - self.neutral
                values = self.solver.solve(displacement)
                stage_ms["weights"] = 1000 * (time.perf_counter() - start)
                weights = dict(zip(self.solver.names, values.tolist()))
                self.take.timestamps.append(float(timestamp))
                self.take.displacements.append(displacement)

        if self._pending:
            status = f"calibrating {len(self._calibration_points)}/{self._pending}: hold a neutral face"
        else:
            status = "tracking"
        result = FrameResult(found=True, landmarks=shown,
                             ibug68=shown[face_models.IBUG68_FROM_MEDIAPIPE, :2],
                             rotation=rotation, translation=translation,
                             head_rotation=head_rotation, weights=weights,
                             stage_ms=stage_ms, status=status)
        self._last = result
        return result

    def _finish_calibration(self):
        frames = np.array(self._calibration_points)
        generic = ShapeFitter(self.model, self.camera, tolerance_px=FIT_TOLERANCE_PX)
        neutral, fitter, fits = calibrate_neutral(generic, frames)
        self.neutral = neutral
        self._fitter = fitter
        self.neutral_rotation = Rotation.concatenate([f.rotation for f in fits]).mean()
        self._previous_fit = fits[-1]
        self._pending = 0
        self._calibration_points = []
        self.take = Take()
        self._reset_filters()
        if self.avatar is not None:
            mapped = map_blendshapes(self.avatar.neutral, self.avatar.deltas, neutral)
            self.solver = WeightSolver(mapped, self.avatar.names)

    def refine_take(self, closeness=1.0, iterations=20):
        """Jointly refine the blendshapes and the weights over the recorded take (Liu et al.);
        returns (timestamps (T,), weights (T, N), names)."""
        if self.solver is None:
            raise ExCloneError("nothing to refine: the session has no calibrated avatar")
        if not self.take.timestamps:
            raise ExCloneError("nothing to refine: no frame was recorded since calibration")
        refined = refine_take(self.solver, np.array(self.take.displacements), closeness, iterations)
        return np.array(self.take.timestamps), refined.weights, list(self.solver.names)


# ---------------------------------------------------------------------------- camera calibration
def calibrate_camera(images_bgr, pattern_size=(9, 6), square_size=1.0, min_views=3):
    """Pinhole intrinsics from views of a chessboard with pattern_size inner corners.

    Returns (tracking.Camera, RMS reprojection error in pixels). Lens distortion is estimated
    (k1, k2, p1, p2) so that it does not bias the focal length, but the tracker ignores it.
    """
    object_points = np.zeros((pattern_size[0] * pattern_size[1], 3), np.float32)
    object_points[:, :2] = np.mgrid[0:pattern_size[0], 0:pattern_size[1]].T.reshape(-1, 2) * square_size
    found_object, found_image, size = [], [], None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    for image in images_bgr:
        image = face_models._check_image(image)
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if size is None:
            size = grey.shape[::-1]
        elif grey.shape[::-1] != size:
            raise ExCloneError(f"calibration images differ in size: {size} and {grey.shape[::-1]}")
        ok, corners = cv2.findChessboardCorners(
            grey, pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            continue
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
        found_object.append(object_points)
        found_image.append(corners)
    if len(found_image) < min_views:
        raise ExCloneError(f"a {pattern_size[0]}x{pattern_size[1]} chessboard was found in "
                           f"{len(found_image)} of the images; at least {min_views} views are needed")
    flags = cv2.CALIB_FIX_K3
    rms, matrix, _, _, _ = cv2.calibrateCamera(found_object, found_image, size, None, None, flags=flags)
    return Camera(float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2])), float(rms)
