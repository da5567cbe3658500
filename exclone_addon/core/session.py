"""Live face tracking, one frame at a time: the per-frame session behind one step().

Per frame: BlazeFace on the first frame and whenever tracking is lost (over tiles, so a small
face in a large frame is found), otherwise the region the previous frame's landmarks give. With
several faces in view the take follows one: the largest at first, then the same one (the face
found where it was last seen), never a bystander while it is briefly out of view; FaceMesh's 468 points and the iris model's eye points
(docs/method.md §10); the tracker's 3D
shape model fitted to them with head pose, warm-started from the previous frame, the actor's
neutral calibrated over the first frames with a face (core.tracking, §11); after calibration
the shape parameters refitted with the material points, image points on texture tracked by
optical flow (core.material_points, §11); One Euro filters on pose, shape and landmarks; then,
with an avatar, its shape-key weights (core.retarget, §12): the eye keys with the eyes' lids and
gaze (core.eyes) as further targets of the same bounded solve, the other keys from the face's
appearance (core.appearance: the face frontalised by the tracked pose, less the actor's
calibrated neutral face, read with the points' own weights by a map learnt from rendered faces;
its weights also take what the fit read of the expression as a turn off the head's pose), or
without it from the landmarks alone.
"""
import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from . import data, eyes, face_models, threads
from .appearance import (MOTION_SHARE, FaceFrontaliser, NeutralReading, load_appearance_map,
                         turn_between)
from .eyes import EyeGeometry
from .errors import ExCloneError
from .material_points import MaterialPoints
from .retarget import WeightSolver, map_blendshapes, refine_take
from .tracker_model import load_tracker_model
from .tracking import Camera, OneEuroFilter, RotationFilter, ShapeFitter, calibrate_neutral

# The model's axes (canonical face: +Y up, looking along +Z, +X the subject's left) -> Blender's
# (+Z up, looking along -Y, +X the subject's left): a quarter turn about x.
MODEL_TO_BLENDER = Rotation.from_euler("x", 90, degrees=True)
# The fit stops when no point moves by more than this (pixels): FaceMesh's own noise is several
# times larger. 0.05 instead of tracking's 1e-3 takes the fit from 4 to about 3 iterations with no
# change in test_live's figures at 3 decimals.
FIT_TOLERANCE_PX = 0.05
# A face lost for longer than this may be replaced by another one in view (the largest); until
# then only a face found where the followed one was last seen, or one about as wide (within this
# ratio: the actor back in view elsewhere, nearer or farther by up to 40%), is taken up: a face
# of another size is a bystander. (BlazeFace's box and FaceMesh's points are equally wide: 94.1
# and 94.0 pixels on the astronaut photograph.)
FOLLOW_GRACE_S = 1.0
SAME_WIDTH_RATIO = 1.4
# The iris model's crops of the eyes where the flow moved the frame before's FaceMesh points are
# used when each eye's corners lie within this share of the eye's width (corner to corner) of
# this frame's; otherwise the eyes are cropped again from this frame's points (after the early
# run: such a frame takes about one network run longer). The moved corners lie 1% of the width
# from this frame's (median; 3% at the 95th percentile) with the eyes open on the eye take, 2-15%
# in its blinks, where FaceMesh's corners drop as the lids close; the iris model reads a blink
# weaker from crops that did not follow them: the eye take's lowest blink peak 0.743 (this
# frame's crops) -> 0.689 at 0.1, 0.703 at 0.05, 0.740 at 0.04. At 0.04, 3-10% of the rendered
# takes' frames and none of bench_track's take are cropped again.
CROP_SHIFT = 0.04
# The per-frame stages timed in FrameResult.stage_ms (calibration adds "calibrate" when it runs):
# "eyes" reads the iris model's points and brings them frontal, "material" tracks the material
# points and fits them beside FaceMesh's (its flow, with the frame made grey, on the iris
# model's thread). The iris model's network runs on its own thread beside "landmarks" (or, when
# its crops are made again, beside "fit"): the stages add up to more than the step. "fit" is the
# step's own thread's part of the fit: its start from the frame before's fit is made on the iris
# thread while FaceMesh runs.
STAGES = ("detect", "landmarks", "iris", "fit", "material", "eyes", "appearance", "weights")


def _face_crop(gray, points):
    """(the grey image about a face's points, with a margin of a quarter of their box's size,
    its top-left corner (2,) in the image's pixels)."""
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    margin = 0.25 * (high - low)
    x0, y0 = np.maximum(np.floor(low - margin), 0).astype(int)
    x1, y1 = np.ceil(high + margin).astype(int) + 1
    return gray[y0:y1, x0:x1].copy(), np.array([x0, y0], dtype=np.float64)


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


def _crops_hold(moved, points):
    """Whether the eyes' crops from the points `moved` (n, 2; None: none) serve for FaceMesh's
    `points` (n, 2 or 3) of the frame (CROP_SHIFT)."""
    if moved is None:
        return False
    corners = np.array(face_models.EYE_CORNERS)
    widths = np.linalg.norm(points[corners[:, 1], :2] - points[corners[:, 0], :2], axis=1)
    shifts = np.linalg.norm(moved[corners] - points[corners, :2], axis=2)
    return bool(np.all(shifts <= CROP_SHIFT * widths[:, None]))


@dataclass
class FrameResult:
    found: bool
    landmarks: np.ndarray = None      # (468, 3) image pixels x, y + FaceMesh z
    ibug68: np.ndarray = None         # (68, 2) iBUG 300-W order, image pixels
    rotation: Rotation = None         # model -> camera (OpenCV axes)
    translation: np.ndarray = None    # (3,) camera space, model units (cm)
    head_rotation: Rotation = None    # relative to the calibrated neutral, Blender axes
    weights: dict = None              # shape-key name -> 0..1
    eyes: face_models.EyeLandmarks = None   # the iris model's points, image pixels
    stage_ms: dict = field(default_factory=dict)
    status: str = ""


@dataclass
class RecordedTake:
    """What a calibrated session with an avatar recorded: per-frame head-motion-free landmark
    displacements from the calibrated neutral, and their timestamps."""
    timestamps: list = field(default_factory=list)
    displacements: list = field(default_factory=list)


@dataclass
class _Pose:
    """One frame's pose and shape parameters as shown (filtered unless still images)."""
    rotation: Rotation
    translation: np.ndarray
    params: np.ndarray
    landmarks: np.ndarray


class FaceTrackingSession:
    """One camera or clip's tracking state; step() does one frame's whole work.

    still_images: every frame is an unrelated photograph (detection on each, no warm start, no
    temporal filtering, camera intrinsics from each image's size unless given). Otherwise the
    frames are a take from one camera and must all be one size.
    appearance: what the face's appearance is read with (docs/method.md §12): True, the bundled
    map (data/appearance_map.npz); an appearance.AppearanceMap; False, not read (the avatar's
    keys follow the points and the eyes alone).
    """

    def __init__(self, avatar=None, camera=None, calibration_frames=30,
                 models_dir=data.MODELS_DIR, tracker_model=None, still_images=False,
                 appearance=True):
        self.avatar = avatar            # a retarget.AvatarRig, or None
        self.camera = camera
        self._fixed_camera = camera is not None
        self.calibration_frames = int(calibration_frames)
        if self.calibration_frames < 1:
            raise ExCloneError("calibration needs at least one frame")
        self.still_images = bool(still_images)
        self.detector = face_models.FaceDetector(models_dir)
        self.landmarker = face_models.FaceLandmarker(models_dir)
        self.iris = face_models.IrisLandmarker(models_dir)
        # The iris model's network runs on a thread of its own beside FaceMesh and the shape fit
        # (OpenCV's forward pass releases the GIL): a step takes the longer of the two threads'
        # work, not their sum. Before it that thread does what needs only the frame before:
        # the material points' flow and the fit's start (ShapeFitter.start_from), while
        # FaceMesh runs on the step's thread. The reading of its outputs stays on the step's
        # thread, so the iris thread seldom waits for the GIL the fit holds (0.4 ms a step less
        # on bench_track's take).
        self._iris_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ExClone iris")
        tracker_model = tracker_model or load_tracker_model()
        self._tracker_model = tracker_model
        self.model = tracker_model.shape_model
        self._depth_weight = tracker_model.depth_weight
        self._eye_slide = tracker_model.eye_slide
        self._fitter = None           # the canonical model's fitter until calibrated
        self.neutral = None           # (468, 3) the actor's calibrated neutral (model space)
        self.neutral_rotation = None  # mean head pose over the calibration frames
        self.solver = None
        self.eye_neutral = None       # the actor's neutral eyes, frontal (eyes.EyeReading)
        self._eye_geometry = None
        self._eye_targets = None
        self._other_keys = None       # the keys the eyes' rows do not read (indices), if any
        self._other_solver = None     # and their solve from the landmarks or the appearance
        # the face's appearance (core.appearance): read each frame once calibrated from images;
        # the avatar's keys the eyes do not read follow it with `appearance`: True (the bundled
        # map), an appearance.AppearanceMap, or False (the points alone)
        self._frontaliser = FaceFrontaliser(self.model.mean)
        self._appearance = appearance
        self._appearance_map = None
        self._read_by_name = []       # (a key among the other keys, the map's columns): named alike
        self._neutral_reading = None  # the calibration frames' reading (NeutralReading)
        self.expression_reading = None   # this frame's reading less it (None: not read)
        # this frame's points' expression: the fit's shape less the actor's neutral (468, 3;
        # None before calibration)
        self.expression_displacement = None
        self._calibration_faces = []  # the calibration frames' faces: (grey crop, its corner)
        self._material = None         # the take's material points (after calibration, not stills)
        self._gray = None             # the frame being tracked, grey (None: landmarks given)
        self.take = RecordedTake()
        self._frame_size = None       # (width, height) of the take's first frame
        self._roi = None
        self._followed_box = None     # where the followed face was last seen (pixels)
        self._seen_at = None          # and when (seconds)
        self._previous_fit = None
        self._fit_before = None       # the fit of the frame before that (None: none to go on)
        self._face_points = None      # the frame before's FaceMesh points (None: no face)
        self._last = None             # the last FrameResult with a face
        self._pending = 0             # calibration frames still wanted (0: not calibrating)
        self._calibration_points = []
        self._calibration_eyes = []
        self._reset_filters()
        self.calibrate()

    @property
    def calibrated(self):
        return self.neutral is not None

    @property
    def material_points(self):
        """The take's material points (core.material_points; None before calibration, for still
        images and for given landmarks)."""
        return self._material

    def calibrate(self, frames=None):
        """(Re)start neutral calibration over the next `frames` frames with a face (default
        calibration_frames). Until it completes the previous calibration stays in use; a new
        calibration starts a new take."""
        self._pending = int(frames) if frames is not None else self.calibration_frames
        if self._pending < 1:
            raise ExCloneError("calibration needs at least one frame")
        self._calibration_points = []
        self._calibration_eyes = []
        self._calibration_faces = []

    def _reset_filters(self):
        # Cut-offs in Hz at rest; beta raises them with speed (rad/s, cm/s, parameter units/s,
        # px/s). Rotation: 4 Hz at rest, where the fit's error is mostly slow (an expression
        # read as a turn), so 1 Hz mostly added lag (rendered takes, docs/method.md §11).
        self._filters = {
            "rotation": RotationFilter(min_cutoff=4.0, beta=10.0),
            "translation": OneEuroFilter(min_cutoff=1.0, beta=2.0),
            "params": OneEuroFilter(min_cutoff=2.0, beta=5.0),
            "landmarks": LandmarkFilter(min_cutoff=1.5, beta=0.05),
            # the appearance map's weights (weight units/s): each frame's image brings its own
            # sensor noise into them, which the points' filters do not see (3 Hz at rest: a
            # webcam's take 0.910 -> 0.928, the clean takes within 0.003; docs/method.md §12)
            "appearance": OneEuroFilter(min_cutoff=3.0, beta=5.0),
        }

    def _use_image_size(self, width, height, name):
        """The camera for a frame of this size: the given one, else the default for the take's
        frame size (for still images, each image's own). The camera and the tracked region are
        in the take's pixels, so a frame of another size is an error naming it."""
        if self.still_images:
            if not self._fixed_camera:
                self._use_camera(Camera.from_image_size(width, height))
        elif self._frame_size is None:
            self._frame_size = (width, height)
            if self.camera is None:
                self._use_camera(Camera.from_image_size(width, height))
        elif (width, height) != self._frame_size:
            raise ExCloneError(f"{name} is {width}x{height} pixels but the take's first frame was "
                               f"{self._frame_size[0]}x{self._frame_size[1]}: a take's frames "
                               "must all be one size")
        if self._fitter is None:
            model = self.model if self.neutral is None else self.model.with_mean(self.neutral)
            self._fitter = ShapeFitter(model, self.camera, tolerance_px=FIT_TOLERANCE_PX,
                                       depth_weight=self._depth_weight)

    def _use_camera(self, camera):
        if camera != self.camera:
            self.camera = camera
            self._fitter = None

    # -- image models (docs/method.md §10)
    def _find_face(self, image, timestamp, stage_ms):
        """(Landmarks or None, whether they come from a detection): from the previous region
        when tracking, else from the followed face's detection."""
        if self._roi is not None and not self.still_images:
            start = time.perf_counter()
            points, presence = self.landmarker.landmarks(image, self._roi)
            stage_ms["landmarks"] += 1000 * (time.perf_counter() - start)
            if presence >= face_models.FACE_PRESENCE_THRESHOLD:
                return points, False
        start = time.perf_counter()
        detection = self._followed(self.detector.detect_any_size(image), timestamp)
        stage_ms["detect"] += 1000 * (time.perf_counter() - start)
        if detection is None:
            return None, True
        start = time.perf_counter()
        points, presence = self.landmarker.landmarks(image, face_models.roi_from_detection(detection))
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

    def _followed(self, detections, timestamp):
        """The detection to track: the one overlapping most where the followed face was last
        seen, else (within FOLLOW_GRACE_S of losing it) the one closest to its width if within
        SAME_WIDTH_RATIO; the largest when there is no face to follow or it is gone for longer;
        None otherwise."""
        if not detections:
            return None
        boxes = np.array([d.box for d in detections])
        widths = boxes[:, 2] - boxes[:, 0]
        if self._followed_box is not None and not self.still_images:
            overlaps = face_models.iou(self._followed_box, boxes)
            if overlaps.max() > 0.0:
                return detections[int(np.argmax(overlaps))]
            if timestamp - self._seen_at < FOLLOW_GRACE_S:
                followed_width = self._followed_box[2] - self._followed_box[0]
                ratios = np.maximum(widths / followed_width, followed_width / widths)
                best = int(np.argmin(ratios))
                return detections[best] if ratios[best] <= SAME_WIDTH_RATIO else None
        return detections[int(np.argmax(widths))]

    def step(self, image_bgr, timestamp, name="the frame"):
        """One frame (8-bit BGR) at `timestamp` seconds -> FrameResult. name: what an error
        message calls the frame (e.g. capture.Frame.name). A frame that is not an image, is too
        small to hold a face or differs in size from the take's first is an ExCloneError."""
        with threads.step_threads():
            return self._step(face_models.checked_image(image_bgr, name), timestamp, name)

    def _step(self, image, timestamp, name):
        self._use_image_size(image.shape[1], image.shape[0], name)
        stage_ms = dict.fromkeys(STAGES, 0.0)
        # on the iris model's thread while FaceMesh runs on this one: the material points' flow
        # (it needs only the frames; the frame made grey there too), then the iris network on
        # the eyes of the frame before's points moved as the flow saw the face move
        flow_run = early_iris = fit_start = None
        if self._material is not None and not self.still_images:
            flow_run = self._iris_thread.submit(self._timed_flow, image, self._face_points)
        # the fit's start from the frame before's fit (all of it but reading the points), also
        # there while FaceMesh runs
        if self._previous_fit is not None and not self.still_images:
            fit_start = self._iris_thread.submit(self._fitter.start_from, self._warm_start())
        if flow_run is not None and self._face_points is not None:
            early_iris = self._iris_thread.submit(self._early_iris, image, flow_run)
        points, detected = self._find_face(image, timestamp, stage_ms)
        self._face_points = points
        flow = None if flow_run is None else flow_run.result()
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if flow is None else flow[3]
        self._gray = None if self.still_images else gray
        if points is None:
            wait([run for run in (fit_start, early_iris) if run is not None])
            return self._lost(stage_ms)
        start = time.perf_counter()
        if detected or early_iris is None or not _crops_hold(flow[2], points):
            if early_iris is not None:
                early_iris.cancel()
            iris_run = self._iris_thread.submit(self._timed_iris, self.iris.input_blob(image, points),
                                                points)
        else:
            iris_run = early_iris
        stage_ms["iris"] = 1000 * (time.perf_counter() - start)
        try:
            self._followed_box, self._seen_at = face_models.landmarks_box(points), timestamp
            roi = face_models.roi_from_landmarks(points)
            self._roi = roi if roi.size >= face_models.MIN_FACE_PIXELS else None
            return self._track(points, timestamp, stage_ms, restart=detected, iris_run=iris_run,
                               flow=flow, fit_start=fit_start, gray=gray)
        finally:
            wait([iris_run])        # the network is free again when the step returns

    def _timed_flow(self, image, face_points):
        """On the iris thread: (the material points tracked into this frame, the milliseconds,
        where the frame before's FaceMesh points `face_points` (or None) moved to by the face's
        motion the flow saw (None when it saw none), the frame in grey)."""
        start = time.perf_counter()
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        tracked = self._material.track(gray)
        motion = self._material.motion
        moved = None
        if face_points is not None and motion is not None:
            moved = face_points[:, :2] @ motion[:, :2].T + motion[:, 2]
        return tracked, 1000 * (time.perf_counter() - start), moved, gray

    def _early_iris(self, image, flow_run):
        """On the iris thread after the flow (`flow_run`, done by then): _timed_iris on the
        eyes where the flow moved the frame before's points; None when it moved none."""
        moved = flow_run.result()[2]
        if moved is None:
            return None
        start = time.perf_counter()
        outputs = self.iris.run(self.iris.input_blob(image, moved))
        return outputs, 1000 * (time.perf_counter() - start), moved

    def _timed_iris(self, blob, points):
        """(The iris network's outputs, its milliseconds, the points whose eyes `blob` holds):
        on the iris thread."""
        start = time.perf_counter()
        outputs = self.iris.run(blob)
        return outputs, 1000 * (time.perf_counter() - start), points

    def step_landmarks(self, landmarks, timestamp, image_size=None):
        """One frame from given landmarks (468, 2 or 3) in pixels, past the image models (for
        landmarks from elsewhere and for tests); image_size (w, h) sets the default camera."""
        points = np.asarray(landmarks, dtype=np.float64)
        if points.ndim != 2 or points.shape[0] != face_models.NUM_LANDMARKS or points.shape[1] not in (2, 3):
            raise ExCloneError(f"expected ({face_models.NUM_LANDMARKS}, 2 or 3) landmarks, "
                               f"got {points.shape}")
        depth = points.shape[1] == 3
        if not depth:
            points = np.column_stack((points, np.zeros(len(points))))
        if image_size is None:
            if self.camera is None:
                raise ExCloneError("step_landmarks needs a camera or the image size")
            image_size = (2 * self.camera.cx, 2 * self.camera.cy)
        self._use_image_size(*image_size, name="the landmarks' image")
        stage_ms = dict.fromkeys(STAGES, 0.0)
        self._gray = None
        return self._track(points, timestamp, stage_ms, restart=self._previous_fit is None,
                           depth=depth)

    def _lost(self, stage_ms):
        self._roi = None
        self._previous_fit = self._fit_before = None
        self.expression_reading = self.expression_displacement = None
        last = self._last
        status = "no face in view: holding the last pose" if last else "no face in view"
        if last is None:
            return FrameResult(found=False, stage_ms=stage_ms, status=status)
        return FrameResult(found=False, rotation=last.rotation, translation=last.translation,
                           head_rotation=last.head_rotation, weights=last.weights,
                           stage_ms=stage_ms, status=status)

    # -- shape fit and calibration (docs/method.md §11), weights (§12)
    def _track(self, points, timestamp, stage_ms, restart, iris_run=None, depth=True,
               flow=None, fit_start=None, gray=None):
        """iris_run: a Future of _timed_iris or _early_iris (the iris network running beside
        FaceMesh or the fit), or None;
        flow: what _timed_flow returned (the material points tracked into this frame), or None;
        fit_start: a Future of the fit's start from _warm_start() (ShapeFitter.start_from), or
        None;
        gray: the frame in grey (None: landmarks given, no appearance to read)."""
        # the fit reads the points' relative depth (FaceMesh's z) too, when they have one
        observed = points if depth else points[:, :2]
        if restart or self.still_images:
            self._reset_filters()
            self._fit_before = None       # the face is found anew: no motion to go on
            if self.still_images:
                self._previous_fit = None
        start = time.perf_counter()
        # after a detection the fit starts from the last one without its motion (_fit_before)
        previous = self._warm_start() if restart or fit_start is None else fit_start.result()
        fit = self._fitter.fit(observed, previous=previous)
        self._fit_before, self._previous_fit = self._previous_fit, fit
        stage_ms["fit"] = 1000 * (time.perf_counter() - start)
        shown = fit       # its shape parameters from the material points' fit when there is one
        if self._material is not None and not self._pending:
            tracked = None
            if flow is not None:
                tracked, stage_ms["material"] = flow[:2]
            start = time.perf_counter()
            # after a detection the last frame's points are not this face's
            shown = self._material.fit(None if restart else tracked, fit)
            stage_ms["material"] += 1000 * (time.perf_counter() - start)
        # the reported turn less the fit's learnt bias (which FaceMesh's fit still places it by)
        shown = replace(shown, rotation=self._tracker_model.unbiased_rotation(fit))
        # the filters need only the fit: run while the iris model may still be running (on the
        # last calibration frame the calibration replaces the fit and restarts them: after it)
        pose = None if self._pending else self._shown_pose(shown, points, timestamp)
        eye_points = None
        if iris_run is not None:
            outputs, run_ms, crop_points = iris_run.result()
            start = time.perf_counter()
            eye_points = self.iris.read(outputs, crop_points)
            stage_ms["iris"] += run_ms + 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        reading = eyes.read_eyes(eye_points) if eye_points is not None else None
        if not self._pending and reading is not None and self.eye_neutral is not None:
            reading = self._eye_geometry.frontal(reading, fit.rotation, fit.translation,
                                                 self.eye_neutral.iris)
        stage_ms["eyes"] = 1000 * (time.perf_counter() - start)
        if self._pending:
            fit = self._calibration_frame(observed, reading, fit, stage_ms, gray)
            reading = None       # not brought frontal: the eyes' rows join from the next frame
            pose = self._shown_pose(replace(fit, rotation=self._tracker_model.unbiased_rotation(fit)),
                                    points, timestamp)
        self.expression_reading = self.expression_displacement = read = None
        if self.calibrated:
            start = time.perf_counter()
            self.expression_displacement = self._fitter.model.shape(pose.params) - self.neutral
            stage_ms["weights"] = 1000 * (time.perf_counter() - start)
        if gray is not None and self._neutral_reading is not None:
            start = time.perf_counter()
            self.expression_reading = (self._frontaliser.reading(
                gray, self._posed_neutral(pose.rotation, pose.translation))
                - self._neutral_reading.at(pose.rotation))
            if self._appearance_map is not None:
                read = self._appearance_map.weights(self.expression_reading,
                                                    self.expression_displacement,
                                                    turn_between(self.neutral_rotation,
                                                                 pose.rotation))
                if not self.still_images:
                    read = self._filters["appearance"](read, timestamp)
                # the turn less what the expression made the fit read into it
                pose = replace(pose, rotation=self._appearance_map.unbiased_turn(pose.rotation,
                                                                                 read))
            stage_ms["appearance"] = 1000 * (time.perf_counter() - start)
        head_rotation = weights = None
        if self.calibrated:
            relative = self.neutral_rotation.inv() * pose.rotation     # in the face's own axes
            head_rotation = MODEL_TO_BLENDER * relative * MODEL_TO_BLENDER.inv()
            if self.solver is not None:
                weights = self._weights(self.expression_displacement, reading, read, timestamp,
                                        stage_ms)
        if self._pending:
            status = f"calibrating {len(self._calibration_points)}/{self._pending}: hold a neutral face"
        else:
            status = "tracking"
        result = FrameResult(found=True, landmarks=pose.landmarks,
                             ibug68=pose.landmarks[face_models.IBUG68_FROM_MEDIAPIPE, :2],
                             rotation=pose.rotation, translation=pose.translation,
                             head_rotation=head_rotation, weights=weights, eyes=eye_points,
                             stage_ms=stage_ms, status=status)
        self._last = result
        return result

    def _warm_start(self):
        """Where this frame's fit starts: the frame before's fit, its pose moved on by the turn
        and shift since the frame before that. A head moving steadily is found in fewer
        iterations (bench_track's take: 2.2 instead of 3.0 a frame); with FaceMesh's jitter on
        the rendered takes the gain is small (moving 3.85 -> 3.70, turning 3.19 -> 3.13) and a
        still head takes a little more (2.78 -> 2.89)."""
        last, before = self._previous_fit, self._fit_before
        if last is None or before is None:
            return last
        return replace(last, rotation=last.rotation * before.rotation.inv() * last.rotation,
                       translation=2.0 * last.translation - before.translation)

    def _calibration_frame(self, points, reading, fit, stage_ms, gray):
        """Collects a calibration frame (its points, eye reading and the face in `gray`, if
        given); on the last one calibrates. Returns the frame's fit (refitted by the calibration
        when it ran)."""
        self._calibration_points.append(points.copy())
        self._calibration_eyes.append(reading)
        if gray is not None and self._appearance is not False:
            self._calibration_faces.append(_face_crop(gray, points))
        if len(self._calibration_points) < self._pending:
            return fit
        start = time.perf_counter()
        self._finish_calibration()
        stage_ms["calibrate"] = 1000 * (time.perf_counter() - start)
        return self._previous_fit

    def _shown_pose(self, fit, points, timestamp):
        if self.still_images:
            return _Pose(fit.rotation, fit.translation, fit.params, points)
        return _Pose(self._filters["rotation"](fit.rotation, timestamp),
                     self._filters["translation"](fit.translation, timestamp),
                     self._filters["params"](fit.params, timestamp),
                     self._filters["landmarks"](points, timestamp))

    def _posed_neutral(self, rotation, translation):
        """(468, 2) the actor's calibrated neutral posed so, in pixels."""
        return self.camera.project(rotation.apply(self.neutral) + translation)

    def _weights(self, displacement, reading, read, timestamp, stage_ms):
        """The avatar's shape-key weights for the points' displacement from the neutral, the
        eyes' frontal reading (the eyes' rows join the solve when both the reading and the
        eyes' neutral exist; after the calibration frame itself) and the appearance map's
        weights of its keys (None: not read); the frame is recorded."""
        start = time.perf_counter()
        values, recorded = self._solved(displacement, None if self._pending else reading, read)
        stage_ms["weights"] += 1000 * (time.perf_counter() - start)
        self.take.timestamps.append(float(timestamp))
        self.take.displacements.append(recorded)
        return dict(zip(self.solver.names, values.tolist()))

    def _solved(self, displacement, reading, read=None):
        """((N,) the avatar's weights, the displacement the take records) for a displacement
        from the neutral (468, 3), the eyes' frontal reading (None: no eyes' rows) and the
        appearance map's weights of its keys (None: not read)."""
        if reading is not None and self._eye_targets is not None:
            values = self.solver.solve(displacement, *self._eye_targets.rows(reading))
        else:
            values = self.solver.solve(displacement)
        if self._other_solver is None:
            return values, displacement
        # the keys the eyes do not read, from the landmarks alone: FaceMesh's points hardly
        # follow what the eye keys move about the eyes (the rings of points about the lids),
        # so with the eye keys' motion taken off them the brow keys answer its negative
        # (docs/method.md §12)
        from_points = self._other_solver.solve(displacement)
        if read is None:
            values[self._other_keys] = from_points
            return values, displacement
        # with the appearance: a key it reads by name takes its weight and the points' at its
        # share; the others follow its expression (its keys' motion) and the points' (at
        # MOTION_SHARE)
        share = self._appearance_map.share
        blended = (MOTION_SHARE * self._appearance_map.motion_of(read)
                   + (1.0 - MOTION_SHARE) * displacement)
        others = self._other_solver.solve(blended)
        for key, columns in self._read_by_name:
            others[key] = share * read[columns].mean() + (1.0 - share) * from_points[key]
        values[self._other_keys] = others
        return values, blended

    def _finish_calibration(self):
        frames = np.array(self._calibration_points)
        generic = ShapeFitter(self.model, self.camera, tolerance_px=FIT_TOLERANCE_PX,
                              depth_weight=self._depth_weight)
        neutral, fitter, fits = calibrate_neutral(generic, frames)
        self.neutral = neutral
        self._fitter = fitter
        rotations = Rotation.concatenate([self._tracker_model.unbiased_rotation(f) for f in fits])
        self.neutral_rotation = rotations.mean()
        self._previous_fit, self._fit_before = fits[-1], None
        self._material = None if self._gray is None else MaterialPoints(self._gray, fits[-1], fitter)
        self._calibrate_eyes(fits)
        self._calibrate_appearance(fits, rotations)
        self._pending = 0
        self._calibration_points = []
        self._calibration_eyes = []
        self._calibration_faces = []
        self.take = RecordedTake()
        self._reset_filters()
        if self.avatar is not None:
            mapped = map_blendshapes(self.avatar.neutral, self.avatar.deltas, neutral)
            self.solver = WeightSolver(mapped, self.avatar.names)
            self._eye_targets = None if self.eye_neutral is None else eyes.EyeTargets(
                self.avatar.names, self.eye_neutral, self.solver.scale, self.avatar.closures)
            self._appearance_map = None
            if self._neutral_reading is not None:     # read (appearance not False)
                self._appearance_map = (load_appearance_map() if self._appearance is True
                                        else self._appearance)
            read_by_eyes = (np.zeros(len(mapped), dtype=bool) if self._eye_targets is None
                            else self._eye_targets.keys)
            self._other_keys = self._other_solver = None
            self._read_by_name = []
            if read_by_eyes.any() or self._appearance_map is not None:
                self._other_keys = np.flatnonzero(~read_by_eyes)
            if self._other_keys is not None and len(self._other_keys):
                names = [self.avatar.names[j] for j in self._other_keys]
                self._other_solver = WeightSolver(mapped[self._other_keys], names,
                                                  scale=self.solver.scale)
                if self._appearance_map is not None:
                    self._read_by_name = self._appearance_map.keys_by_name(names)

    def _calibrate_appearance(self, fits, rotations):
        """The neutral face's reading as the head turns (appearance.NeutralReading) from the
        calibration frames' (none unless every frame was an image), each frontalised by its own
        fitted pose (rotations: the fits' unbiased turns, a Rotation of them)."""
        self._neutral_reading = None
        if self._calibration_faces and len(self._calibration_faces) == len(fits):
            readings = np.array([self._frontaliser.reading(
                crop, self._posed_neutral(rotation, fit.translation) - corner)
                for (crop, corner), fit, rotation in zip(self._calibration_faces, fits,
                                                         rotations)])
            self._neutral_reading = NeutralReading.fitted(readings, rotations,
                                                          self.neutral_rotation)

    def _calibrate_eyes(self, fits):
        """The eyes' neutral: the median of the calibration frames' readings, each brought
        frontal by its own fitted pose (none when the frames had no eye readings)."""
        self._eye_geometry = EyeGeometry(self.neutral, self.camera, self._eye_slide)
        frontal = [self._eye_geometry.frontal(reading, fit.rotation, fit.translation)
                   for reading, fit in zip(self._calibration_eyes, fits) if reading is not None]
        self.eye_neutral = eyes.neutral_reading(frontal) if frontal else None

    def refine_take(self, closeness=1.0, iterations=20):
        """Jointly refine the blendshapes and the weights over the recorded take (Liu et al.,
        docs/method.md §12); returns (timestamps (T,), weights (T, N), names)."""
        if self.solver is None:
            raise ExCloneError("nothing to refine: the session has no calibrated avatar")
        if not self.take.timestamps:
            raise ExCloneError("nothing to refine: no frame was recorded since calibration")
        refined = refine_take(self.solver, np.array(self.take.displacements), closeness, iterations)
        return np.array(self.take.timestamps), refined.weights, list(self.solver.names)
