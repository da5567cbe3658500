"""core.face_models on a real photograph: skimage.data.astronaut() (public domain, 512x512).

Reference positions below were measured by hand on enlarged crops of the photograph (about +-2 px:
eye and mouth corners are a few pixels wide), independently of the models.
"""
import cv2
import numpy as np
import pytest
from skimage import data

from exclone_addon.core import face_models
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.face_models import (
    FACE_PRESENCE_THRESHOLD, IBUG68_FROM_MEDIAPIPE, FaceDetector, FaceLandmarker,
    non_max_suppression, roi_from_detection, roi_from_landmarks, ssd_anchor_centres)

# Hand-measured (x, y) pixels in astronaut(), by iBUG-68 index. "Image left" = the subject's right.
HAND_POINTS = {
    36: (192.5, 100.5),  # outer corner, image-left eye
    39: (211.0, 102.5),  # inner corner, image-left eye
    42: (236.5, 104.0),  # inner corner, image-right eye
    45: (258.0, 103.5),  # outer corner, image-right eye
    30: (224.0, 127.0),  # nose tip
    48: (203.5, 140.0),  # mouth corner, image left (smiling: the corner is a short crease)
    54: (244.5, 141.0),  # mouth corner, image right
}
HAND_IOD = float(np.hypot(258.0 - 192.5, 103.5 - 100.5))  # outer eye corners, 65.6 px
# The face: cheek to cheek at eye level, brows to chin.
HAND_FACE_BOX = (180.0, 90.0, 268.0, 177.0)
HAND_PUPILS = ((204.7, 100.8), (245.3, 103.0))  # image left, image right
INNER_51 = IBUG68_FROM_MEDIAPIPE[17:]  # brows, nose, eyes, lips: the points accuracy is judged on


@pytest.fixture(scope="module")
def detector():
    return FaceDetector()


@pytest.fixture(scope="module")
def landmarker():
    return FaceLandmarker()


@pytest.fixture(scope="module")
def astronaut():
    return cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2BGR)


def track(image, detector, landmarker):
    """What the tracker does on a first frame: detect, landmarks in the detection's region, then
    landmarks again in the region the first landmarks give (as on the next video frame)."""
    detections = detector.detect(image)
    assert len(detections) == 1, f"expected one face, found scores {[d.score for d in detections]}"
    first, score = landmarker.landmarks(image, roi_from_detection(detections[0]))
    assert score > FACE_PRESENCE_THRESHOLD
    roi = roi_from_landmarks(first)
    points, score = landmarker.landmarks(image, roi)
    assert score > FACE_PRESENCE_THRESHOLD
    return points, roi, detections[0]


def box_iou(a, b):
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    overlap = max(w, 0.0) * max(h, 0.0)
    return overlap / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - overlap)


def test_one_face_detected_around_the_face(detector, astronaut):
    detections = detector.detect(astronaut)
    assert len(detections) == 1
    face = detections[0]
    assert face.score > 0.5
    assert box_iou(face.box, HAND_FACE_BOX) > 0.7, face.box
    # BlazeFace's keypoints are coarse, but the eyes must be on the right eyes, in the right order.
    width = face.box[2] - face.box[0]
    for keypoint, pupil in zip(face.keypoints[:2], HAND_PUPILS):
        assert np.hypot(*(keypoint - pupil)) < 0.1 * width, (keypoint, pupil)
    nose_tip = face.keypoints[2]
    assert np.hypot(*(nose_tip - HAND_POINTS[30])) < 0.1 * width


def test_landmarks_on_the_hand_measured_points(detector, landmarker, astronaut):
    points, _, _ = track(astronaut, detector, landmarker)
    assert points.shape == (468, 3) and np.isfinite(points).all()
    ibug = points[IBUG68_FROM_MEDIAPIPE, :2]
    errors = {i: np.hypot(*(ibug[i] - xy)) / HAND_IOD for i, xy in HAND_POINTS.items()}
    assert max(errors.values()) < 0.06, {i: round(e, 3) for i, e in errors.items()}
    # The face's points stay on the face: a box a little larger than the detector's.
    assert (points[:, :2].min(axis=0) > (165, 60)).all() and (points[:, :2].max(axis=0) < (285, 190)).all()


def test_ibug68_mapping_is_in_ibug_order(detector, landmarker, astronaut):
    assert IBUG68_FROM_MEDIAPIPE.shape == (68,) and len(set(IBUG68_FROM_MEDIAPIPE.tolist())) == 68
    assert IBUG68_FROM_MEDIAPIPE.min() >= 0 and IBUG68_FROM_MEDIAPIPE.max() < 468
    points, _, _ = track(astronaut, detector, landmarker)
    x, y = points[IBUG68_FROM_MEDIAPIPE, 0], points[IBUG68_FROM_MEDIAPIPE, 1]
    assert (np.diff(y[0:9]) > 0).all() and (np.diff(y[8:17]) < 0).all(), "jaw: down to the chin, up"
    assert x[0:8].max() < x[8] < x[9:17].min(), "jaw: image-left side first, chin in the middle"
    assert (np.diff(x[17:22]) > 0).all() and (np.diff(x[22:27]) > 0).all(), "brows left to right"
    assert y[17:27].max() < y[36:48].min(), "brows above the eyes"
    assert (np.diff(y[27:31]) > 0).all(), "nose bridge runs down to the tip"
    assert (np.diff(x[31:36]) > 0).all() and y[31:36].min() > y[29], "nostrils under the nose"
    for eye in (slice(36, 42), slice(42, 48)):
        ex, ey = x[eye], y[eye]
        assert ex[0] < ex[1] < ex[2] < ex[3] and ex[3] > ex[4] > ex[5] > ex[0], "eye runs clockwise"
        assert ey[1] < ey[5] and ey[2] < ey[4], "upper lid above the lower lid"
    assert x[39] < x[42], "image-left eye first"
    outer, inner = slice(48, 60), slice(60, 68)
    assert x[48] < x[51] < x[54] and x[54] > x[57] > x[48], "outer lips clockwise from corner 48"
    assert x[60] < x[62] < x[64] and x[64] > x[66] > x[60], "inner lips clockwise from corner 60"
    assert y[51] < y[62] <= y[66] < y[57], "upper lip above the lower lip"
    assert y[outer].min() > y[33] and y[inner].min() > y[33], "mouth under the nose"


# (shift x, shift y, rotation degrees counter-clockwise on screen, scale) about the image centre.
MOTIONS = [(37, -21, 0, 1.0), (0, 0, 15, 1.0), (0, 0, -20, 1.0), (0, 0, 0, 0.7), (0, 0, 0, 1.3),
           (25, 10, 12, 1.2), (-30, 40, -17, 0.8)]


@pytest.mark.parametrize("shift_x, shift_y, degrees, scale", MOTIONS)
def test_landmarks_follow_a_known_motion(detector, landmarker, astronaut, shift_x, shift_y, degrees, scale):
    reference, reference_roi, _ = track(astronaut, detector, landmarker)
    matrix = cv2.getRotationMatrix2D((256.0, 256.0), degrees, scale)
    matrix[:, 2] += (shift_x, shift_y)
    moved = cv2.warpAffine(astronaut, matrix, (512, 512), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    points, roi, _ = track(moved, detector, landmarker)
    expected = reference[:, :2] @ matrix[:, :2].T + matrix[:, 2]
    iod = scale * np.hypot(*(reference[263, :2] - reference[33, :2]))
    errors = np.hypot(*(points[:, :2] - expected).T) / iod
    assert errors[INNER_51].max() < 0.03, f"worst inner point {errors[INNER_51].max():.3f} IOD"
    assert errors.mean() < 0.015, f"mean {errors.mean():.4f} IOD"
    # The region turns with the face (angles are clockwise on screen, cv2's counter-clockwise).
    assert abs(np.degrees(roi.angle - reference_roi.angle) + degrees) < 2.0


def test_no_face_in_blank_or_noise_images(detector, landmarker, astronaut):
    _, roi, _ = track(astronaut, detector, landmarker)
    noise = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    for image in (np.zeros((480, 640, 3), np.uint8), np.full((480, 640, 3), 128, np.uint8), noise):
        assert detector.detect(image) == []
        _, presence = landmarker.landmarks(image, roi)
        assert presence < FACE_PRESENCE_THRESHOLD


def test_missing_or_broken_model_is_a_clear_error(tmp_path):
    with pytest.raises(ExCloneError, match="face_detection_short_range.tflite not found.*run scripts/setup.sh"):
        FaceDetector(models_dir=tmp_path)
    with pytest.raises(ExCloneError, match="face_landmark.tflite not found.*run scripts/setup.sh"):
        FaceLandmarker(models_dir=tmp_path)
    (tmp_path / face_models.LANDMARK_MODEL).write_text("not a model")
    with pytest.raises(ExCloneError, match="could not be loaded.*run scripts/setup.sh"):
        FaceLandmarker(models_dir=tmp_path)


def test_bad_image_is_a_clear_error(detector):
    with pytest.raises(ExCloneError, match="8-bit BGR image"):
        detector.detect(np.zeros((480, 640), np.uint8))
    with pytest.raises(ExCloneError, match="8-bit BGR image"):
        detector.detect(np.zeros((480, 640, 3), np.float32))
    with pytest.raises(ExCloneError, match="^the image is 1x1 pixels; a face needs at least 24x24$"):
        detector.detect(np.zeros((1, 1, 3), np.uint8))


def test_anchor_layout():
    anchors = ssd_anchor_centres()
    assert anchors.shape == (896, 2)
    # 16x16 grid (stride 8), two anchors per cell, row by row; then 8x8 (stride 16), six per cell.
    np.testing.assert_allclose(anchors[[0, 1, 2, 31, 32, 511]], [[4, 4], [4, 4], [12, 4], [124, 4],
                                                                  [4, 12], [124, 124]])
    np.testing.assert_allclose(anchors[[512, 517, 518, 895]], [[8, 8], [8, 8], [24, 8], [120, 120]])


def test_non_max_suppression_weighted_and_hard():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], float)
    scores = np.array([0.9, 0.6, 0.7])
    keypoints = np.zeros((3, 6, 2))
    keypoints[:, :, 0] = boxes[:, :1]
    weighted = non_max_suppression(boxes, scores, keypoints, weighted=True)
    assert [d.score for d in weighted] == [0.9, 0.7]
    np.testing.assert_allclose(weighted[0].box, [0.4, 0, 10.4, 10])  # (0.9 * 0 + 0.6 * 1) / 1.5
    np.testing.assert_allclose(weighted[0].keypoints[:, 0], 0.4)
    hard = non_max_suppression(boxes, scores, keypoints, weighted=False)
    np.testing.assert_allclose([d.box for d in hard], boxes[[0, 2]])
