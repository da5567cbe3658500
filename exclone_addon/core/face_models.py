"""Face detection and 468-point face landmarks from MediaPipe's models, run by OpenCV's dnn module
(docs/method.md §10).

The three TFLite models come from the mediapipe 0.10.21 wheel (extracted by scripts/setup.sh into
exclone_addon/models/); mediapipe itself is never imported. Pre- and post-processing follow
MediaPipe's graphs (modules/face_detection/face_detection_short_range.pbtxt + face_detection.pbtxt,
modules/face_landmark/face_landmark_cpu.pbtxt, face_detection_front_detection_to_roi.pbtxt and
face_landmark_landmarks_to_roi.pbtxt):

- BlazeFace short range: the whole image letterboxed into 128x128 RGB in [-1, 1]; 896 SSD anchors
  (strides 8, 16, 16, 16, two anchors per layer, fixed size 1); 16 regressed values per anchor
  (box centre x, y, width, height, then six keypoints x, y) in pixels of the 128x128 input; a
  logit score per anchor; weighted non-maximum suppression at IoU 0.3.
- FaceMesh: a square, rotated region of interest warped to 192x192 RGB in [0, 1]; 1404 values
  (468 x, y, z in units of the 192-pixel crop) and one face-presence logit.
- Iris (modules/iris_landmark/iris_landmark_cpu.pbtxt, iris_landmark_left_and_right_cpu.pbtxt):
  per eye a square region 2.3 times the distance between FaceMesh's two corners of that eye,
  turned so that the corners are level, warped to 64x64 RGB in [0, 1]; the image-right eye is
  mirrored so that the model always sees an image-left eye (outer corner on the left). 213 values
  (71 eye-contour and brow points x, y, z) and 15 (5 iris points: centre first) in crop units.

Pixel coordinates everywhere are OpenCV's: the centre of pixel (column i, row j) is (i, j).
"""
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from . import data
from .errors import ExCloneError

DETECTOR_MODEL = "face_detection_short_range.tflite"
LANDMARK_MODEL = "face_landmark.tflite"
IRIS_MODEL = "iris_landmark.tflite"

DETECTOR_SIZE = 128
LANDMARK_SIZE = 192
NUM_LANDMARKS = 468
IRIS_SIZE = 64
NUM_EYE_CONTOUR = 71
NUM_IRIS = 5
# FaceMesh's corners of each eye, image-left eye (outer, inner) then image-right eye (inner,
# outer): left to right in an upright face, as MediaPipe's iris graph takes them.
EYE_CORNERS = ((33, 133), (362, 263))
# The eye region is the corner distance times this, square (MediaPipe's 2.3).
EYE_ROI_SCALE = 2.3
# MediaPipe's thresholds: detection score, NMS overlap, face presence (face_landmark_cpu.pbtxt).
MIN_DETECTION_SCORE = 0.5
NMS_IOU_THRESHOLD = 0.3
FACE_PRESENCE_THRESHOLD = 0.5
# The region of interest is the face box (or the landmarks' box) enlarged 1.5 times, square.
ROI_SCALE = 1.5
# The smallest region (side, pixels) that can hold a face FaceMesh can read; an image whose
# shorter side is smaller holds no face.
MIN_FACE_PIXELS = 24
# BlazeFace short range finds faces from about 1/8 to 3/5 of its input's side (16-80 of 128
# pixels, measured on the astronaut photograph: scores 0.74 at 1/8, 0.94 at 1/6). Smaller faces
# are looked for in square tiles, each level's tiles TILE_LEVEL_RATIO times smaller than the
# last's, overlapping by half (a face up to half a tile's side lies whole in one), down to tiles
# in which a face of SMALLEST_FACE_FRACTION of the image's shorter side fills FACE_IN_TILE (an
# 80-pixel face in a 1080p frame is found; 35 detector passes when there is no face).
TILE_LEVEL_RATIO = 2.0
SMALLEST_FACE_FRACTION = 1.0 / 16.0
FACE_IN_TILE = 1.0 / 6.0
# A face near the detector's smallest size is found with a low score and a wrong box (a
# 120-pixel face in a 1920-pixel frame: score 0.59, box 303 pixels wide); one level down it is
# found properly, so a level's detections count when one scores at least this.
TILE_MIN_SCORE = 0.75

# BlazeFace keypoints, in the order the model outputs them. In an upright face the first eye is the
# one on the image's left (the subject's right eye).
DETECTION_KEYPOINTS = ("eye_image_left", "eye_image_right", "nose_tip", "mouth_centre",
                       "ear_image_left", "ear_image_right")

# FaceMesh points that define the ROI's rotation: the outer eye corners (image left, image right).
# MediaPipe uses 33 -> 133 (both corners of one eye); both eyes give a longer, steadier baseline.
ROI_ROTATION_POINTS = (33, 263)

# The 68 points of the iBUG 300-W annotation (0-based: jaw 0-16, brows 17-26, nose 27-35, eyes
# 36-47, outer lips 48-59, inner lips 60-67) as FaceMesh indices. From Peizhi Yan's published
# MediaPipe-to-dlib correspondence (github.com/PeizhiYan/Mediapipe_2_Dlib_Landmarks); where it
# averages two FaceMesh points (jaw 3, 4, 12; nose 27, 28) one of them is taken, keeping the jaw
# symmetric (132/361, 58/288 are mirror pairs). Checked by drawing it on a photograph.
IBUG68_FROM_MEDIAPIPE = np.array([
    127, 234, 93, 132, 58, 136, 150, 176, 152, 400, 379, 365, 288, 361, 323, 454, 356,  # jaw
    70, 63, 105, 66, 107,                                  # brow, image left (subject's right)
    336, 296, 334, 293, 300,                               # brow, image right
    168, 197, 5, 4,                                        # nose bridge down to the tip
    75, 97, 2, 326, 305,                                   # nostrils, image left to right
    33, 160, 158, 133, 153, 144,                           # eye, image left: outer corner first
    362, 385, 387, 263, 373, 380,                          # eye, image right: inner corner first
    61, 39, 37, 0, 267, 269, 291, 321, 314, 17, 84, 91,    # outer lips from the image-left corner
    78, 82, 13, 312, 308, 317, 14, 87,                     # inner lips from the image-left corner
], dtype=np.intp)
IBUG68_FROM_MEDIAPIPE.flags.writeable = False


@dataclass(frozen=True)
class FaceDetection:
    """One face found by the detector, in image pixels."""
    box: np.ndarray        # (4,) x_min, y_min, x_max, y_max
    score: float           # 0..1
    keypoints: np.ndarray  # (6, 2) x, y in DETECTION_KEYPOINTS order


@dataclass(frozen=True)
class FaceRoi:
    """A square region of the image, turned so that the face in it is upright.

    angle: radians from the image's x axis to the region's x axis, clockwise on screen (the image's
    y axis points down), i.e. the region's x axis is (cos angle, sin angle) in pixels.
    """
    centre: np.ndarray  # (2,) x, y in pixels
    size: float         # side length in pixels
    angle: float

    def crop_to_image(self, crop_size):
        """2x3 affine matrix taking pixel coordinates of a crop_size x crop_size crop to the image's."""
        k = self.size / crop_size
        c, s = np.cos(self.angle), np.sin(self.angle)
        linear = k * np.array([[c, -s], [s, c]])
        # Pixel centres sit half a pixel in from the edges of both the crop and the region.
        offset = self.centre + linear @ np.full(2, 0.5 - crop_size / 2.0)
        return np.hstack([linear, offset[:, None]])


def _load_net(name, models_dir):
    path = Path(models_dir) / name
    if not path.is_file():
        raise ExCloneError(f"face model {name} not found in {path.parent}; run scripts/setup.sh")
    try:
        net = cv2.dnn.readNetFromTFLite(str(path))
    except cv2.error as error:
        raise ExCloneError(f"face model {path} could not be loaded ({error.err}); "
                           "run scripts/setup.sh again") from None
    net.setPreferableBackend(cv2.dnn.DNN_BACKEND_OPENCV)
    net.setPreferableTarget(cv2.dnn.DNN_TARGET_CPU)
    return net


def checked_bgr(image_bgr, name="the image"):
    """The image as an array; ExCloneError unless it is 8-bit BGR (height, width, 3)."""
    image = np.asarray(image_bgr)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ExCloneError(f"{name} is not an 8-bit BGR image (height, width, 3) but "
                           f"{image.dtype} {image.shape}")
    return image


def checked_image(image_bgr, name="the image"):
    """checked_bgr, and big enough to hold a face; `name` says which image in the message."""
    image = checked_bgr(image_bgr, name)
    height, width = image.shape[:2]
    if min(height, width) < MIN_FACE_PIXELS:
        raise ExCloneError(f"{name} is {width}x{height} pixels; a face needs at least "
                           f"{MIN_FACE_PIXELS}x{MIN_FACE_PIXELS}")
    return image


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def ssd_anchor_centres():
    """(896, 2) anchor centres of BlazeFace short range, in pixels of the 128x128 input.

    MediaPipe's SsdAnchorsCalculator with num_layers 4, strides 8, 16, 16, 16, aspect ratio 1 plus
    one interpolated scale (two anchors per layer and cell), fixed anchor size: consecutive layers
    with the same stride share one grid, so the 16x16 grid has 2 anchors per cell and the 8x8 grid
    6; the order is row, column, anchor.
    """
    centres = []
    for stride, anchors_per_cell in ((8, 2), (16, 6)):
        cells = DETECTOR_SIZE // stride
        ys, xs = np.mgrid[0:cells, 0:cells]
        grid = (np.stack([xs.ravel(), ys.ravel()], axis=1) + 0.5) / cells
        centres.append(np.repeat(grid, anchors_per_cell, axis=0))
    return np.concatenate(centres) * DETECTOR_SIZE


def iou(box, boxes):
    """Intersection over union of a box (4,) with each of boxes (n, 4) (x_min, y_min, x_max,
    y_max): (n,)."""
    top_left = np.maximum(box[:2], boxes[:, :2])
    bottom_right = np.minimum(box[2:], boxes[:, 2:])
    overlap = np.prod(np.clip(bottom_right - top_left, 0.0, None), axis=1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1)
    return overlap / np.maximum(area + areas - overlap, 1e-12)


def non_max_suppression(boxes, scores, keypoints, iou_threshold=NMS_IOU_THRESHOLD, weighted=True):
    """Merges overlapping detections; returns FaceDetections by decreasing score.

    weighted (MediaPipe's choice for faces): each kept detection is the score-weighted mean of the
    best remaining one and all that overlap it by more than iou_threshold, which steadies the box
    from frame to frame; otherwise the overlapping ones are simply dropped.
    """
    order = np.argsort(-scores, kind="stable")
    boxes, scores, keypoints = boxes[order], scores[order], keypoints[order]
    remaining = np.arange(len(scores))
    detections = []
    while remaining.size:
        best = remaining[0]
        overlapping = iou(boxes[best], boxes[remaining]) > iou_threshold
        overlapping[0] = True  # a zero-area box does not overlap itself
        group = remaining[overlapping]
        if weighted:
            weights = scores[group] / scores[group].sum()
            box = weights @ boxes[group]
            points = np.tensordot(weights, keypoints[group], axes=1)
        else:
            box, points = boxes[best], keypoints[best]
        detections.append(FaceDetection(box=box, score=float(scores[best]), keypoints=points))
        remaining = remaining[~overlapping]
    return detections


class FaceDetector:
    """BlazeFace short range: faces within about two metres of the camera. Loads the model once."""

    def __init__(self, models_dir=data.MODELS_DIR, min_score=MIN_DETECTION_SCORE, weighted_nms=True):
        self.net = _load_net(DETECTOR_MODEL, models_dir)
        self.min_score = min_score
        self.weighted_nms = weighted_nms
        self.anchors = ssd_anchor_centres()

    def detect(self, image_bgr):
        """Faces in an 8-bit BGR image, best first (an empty list when there is none)."""
        image = checked_image(image_bgr)
        return non_max_suppression(*self._raw(image), weighted=self.weighted_nms)

    def detect_any_size(self, image_bgr):
        """Faces down to SMALLEST_FACE_FRACTION of an 8-bit BGR image of any size (an 80-pixel
        face in a 1080p frame): the whole image, then ever smaller overlapping tiles, stopping at
        the first level that finds a face scoring TILE_MIN_SCORE (so the faces found are the
        largest ones); without one, whatever scored min_score. Best first; an empty list when
        there is none."""
        image = checked_image(image_bgr)
        height, width = image.shape[:2]
        levels = [[(image, (0, 0))]] + [
            [(image[y:y + side, x:x + side], (x, y)) for x, y in tile_corners(width, height, side)]
            for side in tile_sides(height, width)]
        weak = []
        for level in levels:
            boxes, scores, keypoints = (np.concatenate(parts) for parts in
                                        zip(*(self._raw(tile, offset) for tile, offset in level)))
            sure = scores >= max(self.min_score, TILE_MIN_SCORE)
            if sure.any():
                return non_max_suppression(boxes[sure], scores[sure], keypoints[sure],
                                           weighted=self.weighted_nms)
            weak.append((boxes, scores, keypoints))
        return non_max_suppression(*(np.concatenate(parts) for parts in zip(*weak)),
                                   weighted=self.weighted_nms)

    def _raw(self, image, offset=(0, 0)):
        """(boxes (n, 4), scores (n,), keypoints (n, 6, 2)) above min_score, before suppression,
        in pixels of the image the region `image` is cut from at `offset` (x, y)."""
        height, width = image.shape[:2]
        # Letterbox: keep the aspect ratio, pad with black around the centre (as MediaPipe does).
        scale = DETECTOR_SIZE / max(height, width)
        new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
        left, top = (DETECTOR_SIZE - new_w) // 2, (DETECTOR_SIZE - new_h) // 2
        resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
        tensor_image = cv2.copyMakeBorder(resized, top, DETECTOR_SIZE - new_h - top, left,
                                          DETECTOR_SIZE - new_w - left, cv2.BORDER_CONSTANT, value=0)
        blob = cv2.dnn.blobFromImage(tensor_image, 1.0 / 127.5, mean=(127.5, 127.5, 127.5), swapRB=True)
        self.net.setInput(blob)
        logits, regressors = self.net.forward(["classificators", "regressors"])
        scores = _sigmoid(np.clip(logits.reshape(-1).astype(np.float64), -100.0, 100.0))
        keep = scores >= self.min_score
        raw = regressors.reshape(-1, 16)[keep].astype(np.float64)
        anchors = self.anchors[keep]
        centres = raw[:, 0:2] + anchors
        half_sizes = raw[:, 2:4] / 2.0
        keypoints = raw[:, 4:16].reshape(-1, 6, 2) + anchors[:, None, :]
        # Back from the 128-pixel tensor (continuous coordinates) to image pixel centres.
        to_image_scale = np.array([width / new_w, height / new_h])
        shift = np.array([left, top])
        origin = np.asarray(offset, dtype=np.float64)
        boxes = np.hstack([(centres - half_sizes - shift) * to_image_scale + origin,
                           (centres + half_sizes - shift) * to_image_scale + origin]) - 0.5
        keypoints = (keypoints - shift) * to_image_scale + origin - 0.5
        return boxes, scores[keep], keypoints


def tile_sides(height, width):
    """The tile sides (pixels) detect_any_size looks in after the whole image, largest first."""
    smallest_face = max(MIN_FACE_PIXELS, SMALLEST_FACE_FRACTION * min(height, width))
    side = min(height, width, max(height, width) / TILE_LEVEL_RATIO)
    sides = []
    while side >= smallest_face / FACE_IN_TILE:
        sides.append(int(round(side)))
        side /= TILE_LEVEL_RATIO
    return sides


def tile_corners(width, height, side):
    """Top-left corners (x, y) of square tiles of `side` covering the image, overlapping by at
    least half a tile."""
    def starts(length):
        count = int(np.ceil(max(length - side, 0) / (side / 2.0))) + 1
        return np.round(np.linspace(0, length - side, count)).astype(int)
    return [(int(x), int(y)) for y in starts(height) for x in starts(width)]


def _square_roi(x_min, y_min, x_max, y_max, eye_from, eye_to):
    centre = np.array([(x_min + x_max) / 2.0, (y_min + y_max) / 2.0])
    direction = np.asarray(eye_to, float) - np.asarray(eye_from, float)
    angle = float(np.arctan2(direction[1], direction[0]))
    size = float(max(x_max - x_min, y_max - y_min)) * ROI_SCALE
    return FaceRoi(centre=centre, size=size, angle=angle)


def roi_from_detection(detection):
    """The landmark model's region for a detected face: its box enlarged 1.5 times, square,
    turned so that the eyes are level."""
    return _square_roi(*detection.box, detection.keypoints[0], detection.keypoints[1])


def landmarks_box(landmarks):
    """(4,) the box of (n, 2 or 3) landmarks: x_min, y_min, x_max, y_max."""
    points = np.asarray(landmarks, float)[:, :2]
    return np.concatenate([points.min(axis=0), points.max(axis=0)])


def roi_from_landmarks(landmarks):
    """The region for the next video frame from this frame's (468, 2 or 3) landmarks: their box
    enlarged 1.5 times (room for the head to move), square, turned so that the eyes are level."""
    points = np.asarray(landmarks, float)[:, :2]
    (x_min, y_min), (x_max, y_max) = points.min(axis=0), points.max(axis=0)
    return _square_roi(x_min, y_min, x_max, y_max, *points[list(ROI_ROTATION_POINTS)])


class FaceLandmarker:
    """FaceMesh: 468 face points in a region of interest. Loads the model once."""

    def __init__(self, models_dir=data.MODELS_DIR):
        self.net = _load_net(LANDMARK_MODEL, models_dir)
        self.output_names = self.net.getUnconnectedOutLayersNames()

    def crop(self, image_bgr, roi):
        """The 192x192 BGR image the model sees for this region (edges replicated outside the image)."""
        image = checked_image(image_bgr)
        return cv2.warpAffine(image, roi.crop_to_image(LANDMARK_SIZE), (LANDMARK_SIZE, LANDMARK_SIZE),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)

    def landmarks(self, image_bgr, roi):
        """(468, 3) landmarks and the face-presence score (0..1) for a region of an 8-bit BGR image.

        x, y are image pixels; z is depth relative to the face's centre, in pixels at the same
        scale, smaller towards the camera. A score below FACE_PRESENCE_THRESHOLD means there is no
        face in the region and the points are meaningless.
        """
        crop = self.crop(image_bgr, roi)
        blob = cv2.dnn.blobFromImage(crop, 1.0 / 255.0, swapRB=True)
        self.net.setInput(blob)
        raw_points, presence_logit = self._split_outputs(self.net.forward(self.output_names))
        points = raw_points.reshape(NUM_LANDMARKS, 3).astype(np.float64)
        # Model output is in continuous crop coordinates (0..192); shift to pixel centres first.
        matrix = roi.crop_to_image(LANDMARK_SIZE)
        xy = (points[:, :2] - 0.5) @ matrix[:, :2].T + matrix[:, 2]
        z = points[:, 2] * (roi.size / LANDMARK_SIZE)
        return np.column_stack([xy, z]), float(_sigmoid(presence_logit))

    @staticmethod
    def _split_outputs(outputs):
        # Told apart by size: OpenCV names the outputs after internal layers, not the model's.
        by_size = {out.size: out for out in outputs}
        if set(by_size) != {NUM_LANDMARKS * 3, 1}:
            raise ExCloneError(f"{LANDMARK_MODEL} is not the expected FaceMesh model "
                               f"(outputs of sizes {sorted(by_size)}); run scripts/setup.sh again")
        return by_size[NUM_LANDMARKS * 3].reshape(-1), float(by_size[1].reshape(-1)[0])


@dataclass(frozen=True)
class EyeLandmarks:
    """The iris model's points for both eyes, in image pixels; index 0 is the image-left eye (the
    subject's right), 1 the image-right eye. Contour point order is the model's, the same for
    both eyes: 0 outer corner, 1-7 lower lid outer to inner, 8 inner corner, 9-15 upper lid
    outer to inner, then two rings around the eye and the brow. Iris: centre, then four points on
    its rim."""
    contours: np.ndarray   # (2, 71, 2)
    irises: np.ndarray     # (2, 5, 2)


def eye_rois(landmarks):
    """The iris model's two regions (image-left eye, image-right eye) from FaceMesh's points."""
    points = np.asarray(landmarks, float)[:, :2]
    rois = []
    for start, end in EYE_CORNERS:
        a, b = points[start], points[end]
        direction = b - a
        rois.append(FaceRoi(centre=(a + b) / 2.0, size=float(np.hypot(*direction)) * EYE_ROI_SCALE,
                            angle=float(np.arctan2(direction[1], direction[0]))))
    return rois


def _mirrored(matrix, crop_size):
    """A crop->image affine matrix that reads the crop mirrored left to right (pixel centres)."""
    flip = np.array([[-1.0, 0.0, crop_size - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return matrix @ flip


class IrisLandmarker:
    """MediaPipe's iris model on both eyes of a face, in one batch. Loads the model once."""

    def __init__(self, models_dir=data.MODELS_DIR):
        self.net = _load_net(IRIS_MODEL, models_dir)
        # OpenCV's fusion of its layers makes this network slower, not faster (a batch of two
        # eyes 4.69 -> 4.34 ms without it on one thread, the outputs identical)
        self.net.enableFusion(False)
        self.output_names = self.net.getUnconnectedOutLayersNames()

    def _crop_matrices(self, landmarks):
        left, right = eye_rois(landmarks)
        return (left.crop_to_image(IRIS_SIZE),
                _mirrored(right.crop_to_image(IRIS_SIZE), IRIS_SIZE))

    def crops(self, image_bgr, landmarks):
        """The two 64x64 BGR eye images the model sees (the image-right eye mirrored)."""
        image = checked_bgr(image_bgr)
        return [cv2.warpAffine(image, matrix, (IRIS_SIZE, IRIS_SIZE),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)
                for matrix in self._crop_matrices(landmarks)]

    def eyes(self, image_bgr, landmarks):
        """EyeLandmarks for an 8-bit BGR image and FaceMesh's (468, 2 or 3) points in it."""
        return self.read(self.run(self.input_blob(image_bgr, landmarks)), landmarks)

    # eyes() in three parts, so that the network can run on another thread than the rest
    def input_blob(self, image_bgr, landmarks):
        """The network's input: both eyes' crops, one batch."""
        return cv2.dnn.blobFromImages(self.crops(image_bgr, landmarks), 1.0 / 255.0, swapRB=True)

    def run(self, blob):
        """The network's outputs for an input_blob."""
        self.net.setInput(blob)
        return self.net.forward(self.output_names)

    def read(self, outputs, landmarks):
        """EyeLandmarks from the network's outputs for the crops of these landmarks."""
        matrices = self._crop_matrices(landmarks)
        contours, irises = self._split_outputs(outputs)
        both = np.concatenate([contours, irises], axis=1)[..., :2].astype(np.float64)
        # continuous crop coordinates (0..64) -> pixel centres -> image pixels, per eye
        image_points = np.stack([(eye - 0.5) @ matrix[:, :2].T + matrix[:, 2]
                                 for eye, matrix in zip(both, matrices)])
        return EyeLandmarks(contours=image_points[:, :NUM_EYE_CONTOUR],
                            irises=image_points[:, NUM_EYE_CONTOUR:])

    @staticmethod
    def _split_outputs(outputs):
        # Told apart by size, as FaceMesh's; a batch of two eyes comes out as one row each
        by_size = {out.size: out for out in outputs}
        sizes = (2 * NUM_EYE_CONTOUR * 3, 2 * NUM_IRIS * 3)
        if set(by_size) != set(sizes):
            raise ExCloneError(f"{IRIS_MODEL} is not the expected iris model (outputs of sizes "
                               f"{sorted(by_size)} for two eyes); run scripts/setup.sh again")
        return (by_size[sizes[0]].reshape(2, NUM_EYE_CONTOUR, 3),
                by_size[sizes[1]].reshape(2, NUM_IRIS, 3))
